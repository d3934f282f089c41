"""Spatially varying stacks: a constant stack with some parameters driven by images.

A parameter is named by its path in the stack, ``base.<field>`` or ``coatings[i].<field>``
(coatings bottom to top), e.g. ``coatings[0].roughness`` for the clear coat's GGX alpha or
``base.albedo`` for a colour map. Images are numpy arrays in the parameter's own units, rows top
to bottom: (H, W) or (H, W, 1) for scalar fields; (H, W, 3) (or grey (H, W)) for RGB fields.
All driving images of one stack share one resolution.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..formula import LUMINANCE
from ..stack import VALID_RANGES, Stack, StackArrays
from .mip import resample_area

_PATH = re.compile(r"^(base|coatings\[(\d+)\])\.(\w+)$")
RGB_FIELDS = {"albedo", "eta", "k"}

# StackArrays attribute for each (layer kind, field).
_BASE_ATTR = {
    "albedo": "base_albedo",
    "roughness": "base_roughness",
    "eta": "base_eta",
    "k": "base_k",
    "ior": "base_ior",
}
_COAT_ATTR = {
    "roughness": "coat_roughness",
    "ior": "coat_ior",
    "albedo": "coat_albedo",
    "thickness": "coat_thickness",
    "g": "coat_g",
}


def parse_parameter_path(stack: Stack, path: str) -> tuple[str, int | None, str]:
    """('base' | 'coating', coating index or None, field) for a parameter path, or ValueError."""
    m = _PATH.match(path.strip())
    if not m:
        raise ValueError(f"parameter path {path!r} must look like 'base.albedo' or 'coatings[0].roughness'")
    name = m.group(3)
    if m.group(1) == "base":
        fields = [f for f in _BASE_ATTR if hasattr(stack.base, f)]
        if name not in fields:
            raise ValueError(f"{type(stack.base).__name__} base has no parameter {name!r}; it has {fields}")
        return "base", None, name
    i = int(m.group(2))
    if i >= len(stack.coatings):
        raise ValueError(
            f"{path!r}: the stack has {len(stack.coatings)} coating(s), so indices are 0..{len(stack.coatings) - 1}"
        )
    if name not in _COAT_ATTR:
        raise ValueError(f"a coating has no parameter {name!r}; it has {sorted(_COAT_ATTR)}")
    return "coating", i, name


def _as_channels(path: str, name: str, image) -> np.ndarray:
    """A map as (H, W, C) float64 of the channels ``name`` takes: 3 for a colour (a grey image repeated, an RGBA
    one's alpha left out), 1 for a number (a colour image's luminance, as Blender turns a colour into a number: a
    grey image saved as RGB, every JPEG, is its grey). Refuses what is not an image of numbers, naming the map."""
    a = np.asarray(image)
    if a.dtype.kind not in "iuf":  # a string (a file name where pixels were meant), bools, complex values
        raise ValueError(f"image for {path} must hold real numbers, got {a.dtype} values")
    img = a.astype(np.float64)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"image for {path} must be (H, W) or (H, W, C), got shape {np.shape(image)}")
    want = 3 if name in RGB_FIELDS else 1
    if img.shape[2] == want:
        return img
    if want == 3 and img.shape[2] == 1:
        return np.repeat(img, 3, axis=2)
    if img.shape[2] == 4:  # RGBA: alpha does not drive anything
        img = img[..., :3]
        if want == 3:
            return img
    if want == 1 and img.shape[2] == 3:
        return img @ np.array(LUMINANCE)[:, None]
    raise ValueError(
        f"image for {path} has {img.shape[2]} channel(s); {name} needs {want} (or 1 grey / 3 RGB / 4 RGBA)"
    )


@dataclass
class SpatialStack:
    """``stack`` with the parameters named in ``maps`` replaced per texel by images."""

    stack: Stack
    maps: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        checked: dict[str, np.ndarray] = {}
        shape = None
        for path, image in self.maps.items():
            _, _, name = parse_parameter_path(self.stack, path)
            img = _as_channels(path, name, image)
            if shape is not None and img.shape[:2] != shape:
                raise ValueError(
                    f"image for {path} is {img.shape[1]}x{img.shape[0]} but the other driving images are "
                    f"{shape[1]}x{shape[0]}: all images of one material must share a resolution"
                )
            shape = img.shape[:2]
            lo, hi = VALID_RANGES[name]
            bad = ~np.isfinite(img) | (img < lo) | (img > hi)
            if bad.any():
                y, x, _ = np.argwhere(bad)[0]
                raise ValueError(
                    f"image for {path}: {int(bad.any(axis=2).sum())} texel(s) outside the valid range "
                    f"[{lo}, {hi}], first at (x={x}, y={y}) = {img[y, x].tolist()}"
                )
            checked[path] = img
        self.maps = checked

    @property
    def resolution(self) -> tuple[int, int] | None:
        """(height, width) of the driving images, or None for a constant stack."""
        for img in self.maps.values():
            return img.shape[0], img.shape[1]
        return None

    def resolution_for_max_side(self, max_side: int) -> tuple[int, int]:
        """(height, width) with the images' aspect and the longer side at most ``max_side``
        (0 = the images' own resolution); never finer than the images."""
        h, w = self.resolution or (1, 1)
        if max_side <= 0 or max(h, w) <= max_side:
            return h, w
        scale = max_side / max(h, w)
        return max(1, round(h * scale)), max(1, round(w * scale))

    def stacks_at(self, uv: np.ndarray) -> StackArrays:
        """The stacks (N rows) of the texels at ``uv`` (N, 2), nearest texel of the images' resolution, with a
        latent texture's addressing (repeat, v = 0 at the bottom row): the per-hit stacks of reference mode."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not np.isfinite(uv).all():
            raise ValueError("uv must be finite")
        arrays = StackArrays.repeat(self.stack, len(uv))
        if self.resolution is None:
            return arrays
        h, w = self.resolution
        col = np.floor(uv[:, 0] * w).astype(np.int64) % w
        row = np.floor((1.0 - uv[:, 1]) * h).astype(np.int64) % h
        for path, img in self.maps.items():  # a loop over the driving images, each gathered at every hit
            self._assign(arrays, path, img[row, col])
        return arrays

    def top_range(self, name: str) -> tuple[float, float] | None:
        """(least, greatest) of the top interface's parameter ``name`` ("roughness": GGX alpha, or "ior") over the
        texels; None where the top layer has no such parameter (a diffuse base without coatings: no interface; a
        conductor's ior)."""
        top = f"coatings[{len(self.stack.coatings) - 1}].{name}" if self.stack.coatings else f"base.{name}"
        if top in self.maps:
            return float(self.maps[top].min()), float(self.maps[top].max())
        layer = self.stack.coatings[-1] if self.stack.coatings else self.stack.base
        value = getattr(layer, name, None)
        return None if value is None else (float(value), float(value))

    def _assign(self, arrays: StackArrays, path: str, values: np.ndarray) -> None:
        """Set the parameter ``path`` of every row of ``arrays`` from ``values`` (N, channels)."""
        kind, i, name = parse_parameter_path(self.stack, path)
        values = values.reshape(len(arrays), -1)
        if name not in RGB_FIELDS:
            values = values[:, 0]
        if kind == "base":
            getattr(arrays, _BASE_ATTR[name])[:] = values
        else:
            getattr(arrays, _COAT_ATTR[name])[:, i] = values

    def texels(self, resolution: tuple[int, int] | None = None) -> tuple[StackArrays, tuple[int, int]]:
        """One stack per texel (rows top to bottom) and the (height, width) used.

        The resolution defaults to the images' and may be lower (parameters are box-filtered
        down), never higher: a bake finer than its driving images only costs time.
        """
        native = self.resolution or (1, 1)
        h, w = resolution or native
        if h > native[0] or w > native[1] or h < 1 or w < 1:
            raise ValueError(
                f"bake resolution {w}x{h} must be between 1x1 and the driving images' {native[1]}x{native[0]}"
            )
        arrays = StackArrays.repeat(self.stack, h * w)
        for path, img in self.maps.items():
            self._assign(arrays, path, img if (h, w) == img.shape[:2] else resample_area(img, h, w))
        return arrays, (h, w)

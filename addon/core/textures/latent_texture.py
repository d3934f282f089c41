"""Latent textures: per-texel latent codes (3 x 32) plus the two sampling-proxy channels.

Channel layout (DESIGN section 3): ``z.R.00 .. z.R.31, z.G.00 .. z.B.31, proxy.sigma, proxy.w``,
98 channels in all. Stored as a tiled, mip-mapped, half-float OpenEXR through OpenImageIO.
OpenImageIO ships inside Blender and the bpy wheel; inside Blender's Python (or after
``bpy.utils.expose_bundled_modules()``) it is importable as ``OpenImageIO``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .mip import build_mip_chain, trilinear_lookup

LATENT_DIM = 32
CHANNELS = 3
LATENT_CHANNELS = [f"z.{c}.{i:02d}" for c in "RGB" for i in range(LATENT_DIM)]
PROXY_CHANNELS = ["proxy.sigma", "proxy.w"]
CHANNEL_NAMES = LATENT_CHANNELS + PROXY_CHANNELS
TILE = 64


def oiio_module():
    """The OpenImageIO module: importable inside Blender; with the bpy wheel it lies in the
    wheel's bundled site-packages, which is found here without importing bpy."""
    try:
        import OpenImageIO as oiio  # noqa: N813

        return oiio
    except ImportError:
        pass
    import importlib.util
    import sys

    spec = importlib.util.find_spec("bpy")
    roots = list(spec.submodule_search_locations or []) if spec is not None else []
    for root in roots:
        for site in sorted(Path(root).glob("*/python/lib/python3*/site-packages")):
            if (site / "OpenImageIO").is_dir():
                sys.path.append(str(site))
                try:
                    import OpenImageIO as oiio  # noqa: N813

                    return oiio
                except ImportError:
                    sys.path.remove(str(site))
    raise RuntimeError(
        "OpenImageIO is not importable: it ships with Blender and the bpy wheel (pip install bpy); "
        "latent textures and EXR output need it"
    )


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Any image OpenImageIO reads (PNG, EXR, TIFF, JPEG, ...) as (H, W, C) float32, rows top to bottom.

    Values are the file's raw values (8/16-bit integers normalised to [0, 1]); no colour
    transform is applied, since a driving image holds parameter values, not colours to display.
    """
    oiio = oiio_module()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"cannot read {path} as an image: {oiio.geterror()}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise ValueError(f"cannot read pixels of {path}: {inp.geterror()}")
        return np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    finally:
        inp.close()


@dataclass
class LatentTexture:
    """A mip chain of (H, W, 98) latent texels; ``levels[0]`` is the finest."""

    levels: list[np.ndarray]
    metadata: dict = field(default_factory=dict)

    @classmethod
    def from_texels(cls, texels: np.ndarray, metadata: dict | None = None) -> "LatentTexture":
        """Build the mip chain (box filter in latent space) from (H, W, 98) base texels."""
        texels = np.asarray(texels, dtype=np.float32)
        if texels.ndim != 3 or texels.shape[2] != len(CHANNEL_NAMES):
            raise ValueError(
                f"latent texels must have shape (H, W, {len(CHANNEL_NAMES)}), got {texels.shape}"
            )
        if not np.isfinite(texels).all():
            raise ValueError("latent texels must be finite")
        return cls(build_mip_chain(texels), dict(metadata or {}))

    @property
    def width(self) -> int:
        return self.levels[0].shape[1]

    @property
    def height(self) -> int:
        return self.levels[0].shape[0]

    def lookup(self, uv: np.ndarray, footprint) -> tuple[np.ndarray, np.ndarray]:
        """Latents (N, 3, 32) and proxy parameters (N, 2) at uv with a footprint in uv units."""
        v = trilinear_lookup(self.levels, uv, footprint)
        z = v[:, : CHANNELS * LATENT_DIM].reshape(-1, CHANNELS, LATENT_DIM)
        return z, v[:, CHANNELS * LATENT_DIM :]

    def write_exr(self, path: str | os.PathLike) -> None:
        """Write a tiled, mip-mapped, half-float EXR; written to a temporary name, then renamed."""
        oiio = oiio_module()
        path = Path(path)
        tmp = path.with_name(path.name + ".partial.exr")
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise RuntimeError(f"cannot create an EXR writer for {path}: {oiio.geterror()}")
        try:
            for i, level in enumerate(self.levels):
                h, w, c = level.shape
                spec = oiio.ImageSpec(w, h, c, "half")
                spec.channelnames = tuple(CHANNEL_NAMES)
                spec.tile_width = TILE
                spec.tile_height = TILE
                spec.attribute("compression", "zip")
                for key, value in self.metadata.items():
                    spec.attribute(f"nlm:{key}", str(value))
                mode = "Create" if i == 0 else "AppendMIPLevel"
                if i == 0:
                    spec.attribute("textureformat", "Plain Texture")  # tells the EXR writer: MIPMAP_LEVELS
                    spec.attribute("openexr:levelmode", 1)
                    spec.attribute("openexr:roundingmode", 0)  # ROUND_DOWN
                if not out.open(str(tmp), spec, mode):
                    raise RuntimeError(f"cannot write {path}: {out.geterror()}")
                if not out.write_image(np.ascontiguousarray(level, dtype=np.float32)):
                    raise RuntimeError(f"cannot write level {i} of {path}: {out.geterror()}")
        except BaseException:
            out.close()
            tmp.unlink(missing_ok=True)
            raise
        out.close()
        tmp.replace(path)

    @classmethod
    def read_exr(cls, path: str | os.PathLike) -> "LatentTexture":
        """Read a latent texture EXR written by :meth:`write_exr` (all mip levels)."""
        oiio = oiio_module()
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"latent texture not found: {path}")
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise ValueError(f"cannot read {path} as an image: {oiio.geterror()}")
        try:
            spec = inp.spec()
            names = list(spec.channelnames)
            # OpenEXR stores channels sorted by name: map them back to the layout by name.
            if sorted(names) != sorted(CHANNEL_NAMES):
                raise ValueError(
                    f"{path} is not a latent texture: expected {len(CHANNEL_NAMES)} channels "
                    f"{CHANNEL_NAMES[0]} .. {CHANNEL_NAMES[-1]}, got {len(names)}: {names[:4]}..."
                )
            metadata = {
                a.name[4:]: a.value for a in spec.extra_attribs if a.name.startswith("nlm:")
            }
            order = [names.index(n) for n in CHANNEL_NAMES]
            levels = []
            level = 0
            while inp.seek_subimage(0, level):
                pixels = inp.read_image(0, level, 0, len(CHANNEL_NAMES), "float")
                if pixels is None:
                    raise ValueError(f"cannot read mip level {level} of {path}: {inp.geterror()}")
                lspec = inp.spec_dimensions(0, level)
                arr = np.asarray(pixels, dtype=np.float32).reshape(
                    lspec.height, lspec.width, len(CHANNEL_NAMES))
                levels.append(np.ascontiguousarray(arr[..., order]))
                level += 1
        finally:
            inp.close()
        return cls(levels, metadata)

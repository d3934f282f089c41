"""The film: per-pixel running sums, so the mean and its standard error are always at hand."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .. import kernels

_NO_ROWS = np.empty(0, np.int64)


class Film:
    """Accumulates one radiance sample per pixel per pass. Rows run top to bottom.

    Per pixel it keeps 84 bytes (0.70 GB at 3840 x 2160): the radiance's sum and sum of squares in float64 (the
    standard error subtracts them, and float32 would lose a low-variance pixel's variance to rounding), the
    sample count in int32, and the first hits' features in float32: the sums of albedo and normal, which guide a
    denoiser (their means over 4,096 samples stay within 2e-6 of float64's), and of coverage, the share of camera
    rays that met a surface, the alpha of a transparent film; and the depth, the nearest of the pixel's samples. It
    kept 112 bytes, all float64: a 3840 x 2160 render of two samples peaked at 1.50 GB.

    ``transparent`` (the render's ``RenderSettings.transparent``): :meth:`rgba`'s alpha is the coverage, and the
    sky the camera rays meet was left out of the radiance (Blender's Film > Transparent); else alpha is 1.
    """

    FEATURES = 8  # albedo (3), normal (3), depth, coverage
    DEPTH = 6  # the features' column of the depth, which the film keeps the least of, not the sum
    NO_DEPTH = 1e10  # the depth where no camera ray met a surface, as Cycles' Z pass writes it

    def __init__(self, width: int, height: int):
        self.width, self.height = int(width), int(height)
        self.sum = np.zeros((self.height * self.width, 3))
        self.sum_sq = np.zeros((self.height * self.width, 3))
        self.count = np.zeros(self.height * self.width, dtype=np.int32)
        self.passes = 0
        self.transparent = False
        # What a denoiser is guided by, from each path's first hit: albedo, shading normal, depth; and coverage.
        self.feature_sum = np.zeros((self.height * self.width, self.FEATURES), dtype=np.float32)
        self.feature_sum[:, self.DEPTH] = self.NO_DEPTH

    def add(self, pixels: np.ndarray | slice, radiance: np.ndarray, features: np.ndarray | None = None) -> None:
        """Add radiance (N, 3) to ``pixels``: (N,) flat indices, each at most once per call, or a slice of
        N consecutive pixels (a whole render's chunks). ``features`` (N, 8): first-hit albedo (3), world shading
        normal (3), depth (1, of which the film keeps the least) and whether the camera ray met a surface (1). One
        compiled pass (``kernels.film_add``): numpy's adds on views and the depth's least took 3% of a render, on
        the thread that hands the chunks out."""
        radiance = kernels.float64_rows(radiance)
        if isinstance(pixels, slice):
            first, rows = int(pixels.start or 0), _NO_ROWS
            if len(radiance) != len(range(*pixels.indices(len(self.count)))) or pixels.step not in (None, 1):
                raise ValueError(f"a slice of {len(radiance)} consecutive pixels must go with {len(radiance)} rows")
        else:
            first, rows = 0, np.ascontiguousarray(pixels, dtype=np.int64)
            if len(rows) != len(radiance):
                raise ValueError(f"{len(rows)} pixels for {len(radiance)} rows of radiance")
            if len(rows) and (rows.min() < 0 or rows.max() >= len(self.count)):
                raise IndexError(f"pixels must lie in [0, {len(self.count)}), got {rows.min()}..{rows.max()}")
        feats = _NO_FEATURES if features is None else kernels.float64_rows(features)
        kernels.film_add(self.sum, self.sum_sq, self.count, self.feature_sum, first, rows, radiance, feats, self.DEPTH)

    # each feature's columns of ``feature_sum``
    _COLUMNS = {"albedo": slice(0, 3), "normal": slice(3, 6), "depth": slice(6, 7), "coverage": slice(7, 8)}

    def features(self, names=("albedo", "normal", "depth", "coverage")) -> dict[str, np.ndarray]:
        """Per-pixel means of the first hits' features, (H, W, C) float32 each, row 0 at the top:
        ``albedo`` (3, clipped to [0, 1]: a denoiser's albedo guide), ``normal`` (3, world space, not renormalised:
        :func:`camera_normals` turns it into Cycles' Denoising Normal),
        ``depth`` (1, as Cycles' Z measures it: the distance along the camera's axis to the nearest surface the
        pixel's camera rays met, :data:`NO_DEPTH` where they met none; the nearest, not a mean, so that a pixel on
        an edge reads one surface's depth, not a depth between the two where nothing is. Cycles keeps its first
        sample's: on an edge, either surface's, or none, by chance) and ``coverage`` (1, the share of the
        pixel's camera rays that met a surface). Only those ``names`` asks for, each from its own columns in float32
        (all eight divided in float64 held 3.1 GB more at 8K, on every F12, passes or none)."""
        inverse = (1.0 / np.maximum(self.count, 1).astype(np.float32))[:, None]
        out = {}
        for name in names:
            columns = self.feature_sum[:, self._COLUMNS[name]]
            f = columns.copy() if name == "depth" else columns * inverse
            f = f.reshape(self.height, self.width, -1)
            out[name] = np.clip(f, 0.0, 1.0, out=f) if name in ("albedo", "coverage") else f
        return out

    def mean(self) -> np.ndarray:
        """(H, W, 3) float32 per-pixel mean (0 where no sample yet)."""
        c = np.maximum(self.count, 1)[:, None]
        return (self.sum / c).reshape(self.height, self.width, 3).astype(np.float32)

    def stderr(self) -> np.ndarray:
        """(H, W, 3) standard error of the per-pixel mean (inf with fewer than 2 samples)."""
        c = self.count[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            var = (self.sum_sq - self.sum * self.sum / c) / (c - 1)
            se = np.sqrt(np.maximum(var, 0.0) / c)
        se = np.where(c >= 2, se, np.inf)
        return se.reshape(self.height, self.width, 3)

    def rgba(self) -> np.ndarray:
        """(H, W, 4) float32 mean, premultiplied as Blender's render results are: alpha 1, or the coverage for a
        transparent film (whose radiance holds no sky seen directly)."""
        img = self.mean()
        if self.transparent:
            alpha = self.features(("coverage",))["coverage"]
        else:
            alpha = np.ones(img.shape[:2] + (1,), np.float32)
        return np.concatenate([img, alpha], axis=2)


_NO_FEATURES = np.empty((0, Film.FEATURES))  # ``Film.add``'s features where none are given


def camera_normals(normals: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
    """World-space ``normals`` (..., 3) in a camera's frame as Cycles writes its Denoising Normal pass: by the
    inverse of the camera's rotation (``camera_to_world``'s 3 x 3, orthonormalised first: a scaled camera object
    turns them, not stretches them), in Cycles' camera axes: Blender's camera axes (x right, y up) with z negated,
    pointing away from the camera (Cycles' camera looks down its +z), so that a surface facing the camera reads
    z < 0. Float32."""
    u, _, vt = np.linalg.svd(np.asarray(camera_to_world, dtype=np.float64)[:3, :3])
    to_camera = (u @ vt) * np.array([1.0, 1.0, -1.0])  # columns: the camera's axes in world space, z negated
    return (np.asarray(normals, dtype=np.float64) @ to_camera).astype(np.float32)


def to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear RGB -> display sRGB in [0, 1] (the standard piecewise transfer curve, clipped)."""
    x = np.clip(np.nan_to_num(linear, nan=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _write_oiio(path: Path, pixels: np.ndarray, pixel_type: str, straight_alpha: bool = False) -> None:
    """Write (H, W, C) ``pixels`` through OpenImageIO (shipped with Blender and the bpy wheel; the
    format follows the file name), published as the textures' files are: a temporary name unique to
    this process, flushed and renamed over ``path`` in one step, removed on any failure. A folder that is not
    there yet is made (as Blender's F12 makes its output's)."""
    from ..textures.files import publishing
    from ..textures.latent_texture import oiio_module

    oiio = oiio_module()
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], getattr(oiio, pixel_type))
    if straight_alpha:  # the pixels' colour is not multiplied by their alpha: written as they are
        spec.attribute("oiio:UnassociatedAlpha", 1)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RuntimeError(f"cannot write {path}: cannot make its folder ({e})") from e
    with publishing(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise RuntimeError(f"cannot write {path}: {oiio.geterror() or 'OpenImageIO gave no reason'}")
        try:
            if not out.write_image(np.ascontiguousarray(pixels)):
                raise RuntimeError(f"cannot write {path}: {out.geterror()}")
        finally:
            out.close()
            del out  # the file is whole once its writer is gone (``LatentTexture.write_exr``), before the rename


def write_png(path: str | os.PathLike, linear: np.ndarray, exposure: float = 1.0) -> None:
    """8-bit sRGB PNG of a linear (H, W, 3) image, through OpenImageIO (Blender ships no Pillow). A (H, W, 4) image
    is premultiplied, as the film's (``Film.rgba``): it is written RGBA with straight alpha, as Blender writes a
    PNG (a transparent film's background transparent, its edges their own colour)."""
    linear = np.asarray(linear)
    rgb = linear[:, :, :3] * exposure
    if linear.shape[2] < 4:
        _write_oiio(Path(path), (to_srgb(rgb) * 255 + 0.5).astype(np.uint8), "UINT8")
        return
    alpha = np.clip(linear[:, :, 3:4], 0.0, 1.0)
    straight = np.where(alpha > 0.0, rgb / np.maximum(alpha, 1e-12), 0.0)
    img = np.concatenate([to_srgb(straight), alpha], axis=2)
    _write_oiio(Path(path), (img * 255 + 0.5).astype(np.uint8), "UINT8", straight_alpha=True)


def write_exr(path: str | os.PathLike, linear: np.ndarray) -> None:
    """Float RGB(A) OpenEXR through OpenImageIO (shipped with Blender and the bpy wheel)."""
    _write_oiio(Path(path), np.asarray(linear, dtype=np.float32), "FLOAT")


def from_srgb(encoded: np.ndarray) -> np.ndarray:
    """Display sRGB in [0, 1] -> linear RGB (the inverse of :func:`to_srgb`)."""
    x = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))

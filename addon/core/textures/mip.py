"""Mip chains in latent space and their trilinear, footprint-driven lookup.

Level sizes follow OpenEXR's round-down rule (``max(1, n // 2)`` per axis down to 1 x 1), so a
chain maps one-to-one onto the levels of a mip-mapped EXR. Each level is the *area-weighted box
filter* of the level below: for even sizes the mean of 2 x 2 blocks; for odd sizes each output
texel averages the input texels it covers, with fractional weights at the borders.
"""

from __future__ import annotations

import numpy as np


def box_weights(n: int, m: int | None = None) -> np.ndarray:
    """(m, n) matrix averaging n texels into m (default max(1, n // 2)) by area (rows sum to 1)."""
    m = max(1, n // 2) if m is None else m
    if not 1 <= m <= n:
        raise ValueError(f"box filter reduces {n} texels to between 1 and {n}, got {m}")
    edges = np.arange(m + 1) * (n / m)
    lo, hi = edges[:-1, None], edges[1:, None]
    j = np.arange(n)[None, :]
    overlap = np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0.0, None)
    return overlap / (n / m)


def downsample(level: np.ndarray) -> np.ndarray:
    """Box-filter one (H, W, C) level to the next one."""
    h, w = level.shape[:2]
    if h % 2 == 0 and w % 2 == 0:  # 2 x 2 means: the same sums as resample_area's taps, no gathers
        rows = 0.5 * (level[0::2] + level[1::2])
        return 0.5 * (rows[:, 0::2] + rows[:, 1::2])
    return resample_area(level, max(1, h // 2), max(1, w // 2))


def _reduce_rows(image: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``weights @ image`` along axis 0, using that each output row mixes only a few input rows."""
    taps = int((weights > 0).sum(axis=1).max())
    first = np.argmax(weights > 0, axis=1)
    out = np.zeros((weights.shape[0],) + image.shape[1:], dtype=image.dtype)
    rows = np.arange(weights.shape[0])
    for k in range(taps):  # a loop over filter taps (2 or 3 for a mip level), not texels
        src = np.minimum(first + k, weights.shape[1] - 1)
        wk = weights[rows, src] * (first + k < weights.shape[1])
        out += wk.astype(image.dtype).reshape((-1,) + (1,) * (image.ndim - 1)) * image[src]
    return out


def resample_area(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-weighted box reduction of an (H, W, C) image to (height, width), each at most H, W."""
    h, w, _ = image.shape
    tmp = _reduce_rows(image, box_weights(h, height))
    return _reduce_rows(tmp.transpose(1, 0, 2), box_weights(w, width)).transpose(1, 0, 2)


def build_mip_chain(base: np.ndarray) -> list[np.ndarray]:
    """All levels from ``base`` (H, W, C) down to 1 x 1, as float32 arrays."""
    if base.ndim != 3 or base.shape[0] < 1 or base.shape[1] < 1:
        raise ValueError(f"a mip chain needs an (H, W, C) array, got shape {base.shape}")
    levels = [np.ascontiguousarray(base, dtype=np.float32)]
    while levels[-1].shape[0] > 1 or levels[-1].shape[1] > 1:
        # float32: the texture is stored as half floats; contiguous, so a lookup's flat view is no copy
        levels.append(np.ascontiguousarray(downsample(levels[-1])))
    return levels


def _bilinear(level: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup (N, C) float32 with repeat addressing; uv (N, 2) with v = 0 at the bottom row.

    The four taps are gathered as rows of the level flattened to (H * W, C) and blended with float32
    weights: the texture is stored as half floats, so float64 arithmetic would only double the
    memory traffic of the renderer's widest arrays (98 channels per hit for a latent texture)."""
    h, w, c = level.shape
    flat = level.reshape(h * w, c)  # a view: the chain's levels are contiguous (build_mip_chain)
    x = uv[:, 0] * w - 0.5
    y = (1.0 - uv[:, 1]) * h - 0.5  # row 0 is the top of the image
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1 = (x0 + 1) % w
    r0 = y0 * w
    r1 = ((y0 + 1) % h) * w
    gx = 1.0 - fx
    out = flat.take(r0 + x0, axis=0).astype(np.float32, copy=False)
    out *= gx
    out += flat.take(r0 + x1, axis=0) * fx
    out *= 1.0 - fy
    bottom = flat.take(r1 + x0, axis=0).astype(np.float32, copy=False)
    bottom *= gx
    bottom += flat.take(r1 + x1, axis=0) * fx
    bottom *= fy
    out += bottom
    return out


def mip_level_for_footprint(footprint: np.ndarray, width: int, height: int, n_levels: int) -> np.ndarray:
    """Continuous mip level for a footprint given in uv units (the ray cone's width on the surface)."""
    texels = np.maximum(np.asarray(footprint, dtype=np.float64) * max(width, height), 1e-12)
    return np.clip(np.log2(texels), 0.0, n_levels - 1)


def trilinear_lookup(levels: list[np.ndarray], uv: np.ndarray, footprint: np.ndarray | float) -> np.ndarray:
    """Trilinear lookup (N, C) at uv (N, 2) with footprint (N,) or scalar in uv units.

    The level is log2 of the footprint in texels of level 0; the two nearest levels are looked
    up bilinearly and blended. Non-finite uv or footprints raise ``ValueError``.
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must have shape (N, 2), got {uv.shape}")
    fp = np.broadcast_to(np.asarray(footprint, dtype=np.float64), (uv.shape[0],))
    if not (np.isfinite(uv).all() and np.isfinite(fp).all()):
        raise ValueError("uv and footprint must be finite")
    h, w, c = levels[0].shape
    lod = mip_level_for_footprint(fp, w, h, len(levels))
    lo = np.floor(lod).astype(np.int64)
    t = (lod - lo).astype(np.float32)[:, None]
    if len(lo) == 0:
        return np.zeros((0, c), dtype=np.float32)
    if (lo == lo[0]).all():  # one pair of levels for every row: no gather and scatter of rows
        return _blend(levels, int(lo[0]), uv, t)
    out = np.empty((uv.shape[0], c), dtype=np.float32)
    for k in np.unique(lo):  # a loop over mip levels, not texels
        sel = np.flatnonzero(lo == k)
        out[sel] = _blend(levels, int(k), uv[sel], t[sel])
    return out


def _blend(levels: list[np.ndarray], k: int, uv: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Level ``k`` and the next one (the last level: itself) looked up at uv, mixed by ``t`` (N, 1)."""
    a = _bilinear(levels[k], uv)
    if k + 1 >= len(levels):
        return a
    a *= 1.0 - t
    a += _bilinear(levels[k + 1], uv) * t
    return a

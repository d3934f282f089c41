"""Mip chains in latent space and their trilinear, footprint-driven lookup.

Level sizes follow OpenEXR's round-down rule (``max(1, n // 2)`` per axis down to 1 x 1), so a
chain maps one-to-one onto the levels of a mip-mapped EXR. Each level is the *area-weighted box
filter* of the level below: for even sizes the mean of 2 x 2 blocks; for odd sizes each output
texel averages the input texels it covers, with fractional weights at the borders.
"""

from __future__ import annotations

import math

import numpy as np

from .. import kernels

HALF_MAX = 65504.0  # the largest finite half float: a latent texture's texels are halves
# The largest float32 that rounds to a finite half (to HALF_MAX). A mean of halves is one, but float32's rounding of
# the mean can step a little past HALF_MAX: the mip levels round it back.
HALF_ROUNDS_FINITE = float(np.nextafter(np.float32(65520.0), np.float32(0.0)))


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


def downsample(level: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Box-filter one (H, W, C) level to the next one, into ``out`` when given (a mip chain's next level: for even
    sizes no level-sized temporary, where a bake's base level can take gigabytes)."""
    h, w = level.shape[:2]
    if h % 2 or w % 2:
        small = resample_area(level, max(1, h // 2), max(1, w // 2))
        if out is None:
            return small
        out[...] = small
        return out
    if out is None:
        out = np.empty((h // 2, w // 2) + level.shape[2:], dtype=level.dtype if level.dtype.kind == "f" else np.float64)
    # 2 x 2 means, the same sums as resample_area's taps, no gathers: 0.5 * (0.5 (a + b) + 0.5 (c + d)), a and b
    # the left column of each block, c and d the right one
    np.add(level[0::2, 0::2], level[1::2, 0::2], out=out)
    out *= 0.5
    right = np.add(level[0::2, 1::2], level[1::2, 1::2], dtype=out.dtype)
    right *= 0.5
    out += right
    out *= 0.5
    return out


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


class MipChain(list):
    """The levels of a mip chain (finest first, each (H, W, C) float32, or float16) as views into one flat
    buffer, which the compiled lookup reads: ``flat``, each level's ``offsets`` into it, ``heights`` and
    ``widths``. Writing into a level writes into the buffer.

    A latent texture is held in half floats, as its file stores it, whether baked (``textures.bake``) or read
    (``LatentTexture.read_exr``): the values the file holds, in half the memory (1.1 GB for 2048 x 2048 x 100
    channels with its levels), which the lookup converts as it reads them. Each level is computed in float32 from
    the level above as held, a band of rows at a time (:meth:`fill`), and rounded to half once."""

    DTYPES = (np.float32, np.float16)

    def __init__(self, levels, dtype=np.float32):
        levels = [np.asarray(level) for level in levels]
        if not levels or any(level.ndim != 3 for level in levels):
            raise ValueError("a mip chain needs one or more (H, W, C) levels")
        if len({level.shape[2] for level in levels}) != 1:
            raise ValueError(f"the levels of a mip chain need one channel count, got {[lv.shape for lv in levels]}")
        self._allocate([level.shape for level in levels], dtype)
        for view, level in zip(self, levels, strict=True):
            view[...] = level

    def _allocate(self, shapes, dtype=np.float32) -> None:
        if np.dtype(dtype) not in [np.dtype(d) for d in self.DTYPES]:
            raise ValueError(f"a mip chain holds float32 or float16 texels, got {np.dtype(dtype)}")
        sizes = [int(np.prod(shape)) for shape in shapes]
        self.flat = np.empty(sum(sizes), dtype=dtype)
        self.offsets = np.concatenate([[0], np.cumsum(sizes[:-1])]).astype(np.int64)
        self.heights = np.array([shape[0] for shape in shapes], dtype=np.int64)
        self.widths = np.array([shape[1] for shape in shapes], dtype=np.int64)
        views = [
            self.flat[start : start + size].reshape(shape)
            for start, size, shape in zip(self.offsets, sizes, shapes, strict=True)
        ]
        super().__init__(views)

    @property
    def dtype(self) -> np.dtype:
        return self.flat.dtype

    @property
    def kernel_flat(self) -> np.ndarray:
        """``flat`` as the compiled lookup takes it: float32, or half floats as their bit patterns (uint16)."""
        return self.flat.view(np.uint16) if self.flat.dtype == np.float16 else self.flat

    @classmethod
    def empty(cls, height: int, width: int, channels: int, dtype=np.float32) -> "MipChain":
        """An uninitialised chain for an (height, width, channels) base: every level down to 1 x 1 (round-down
        sizes), of ``dtype`` (float32 or float16). Write the base into ``chain[0]``, then :meth:`fill`."""
        if height < 1 or width < 1 or channels < 1:
            raise ValueError(f"a mip chain needs a base of at least 1 x 1 x 1, got {height} x {width} x {channels}")
        shapes = [(height, width, channels)]
        while shapes[-1][0] > 1 or shapes[-1][1] > 1:
            shapes.append((max(1, shapes[-1][0] // 2), max(1, shapes[-1][1] // 2), channels))
        chain = cls.__new__(cls)
        chain._allocate(shapes, dtype)
        return chain

    def write_texels(self, start: int, values: np.ndarray) -> None:
        """Rows ``start`` .. ``start + len(values)`` of the base level's texels (row-major, (H * W, C) as
        flattened) from ``values`` (N, C), rounded to the chain's type. ValueError, before anything is written, for
        rows outside the base level, values of another shape, or a value a half-float chain cannot hold
        (non-finite, or beyond the largest half, 65504)."""
        values = np.asarray(values)
        h, w, c = self[0].shape
        if values.ndim != 2 or values.shape[1] != c:
            raise ValueError(f"texels are written as (N, {c}) rows, got shape {values.shape}")
        if not 0 <= start <= start + len(values) <= h * w:
            raise ValueError(f"texels {start} .. {start + len(values)} are outside the base level's {h * w} texels")
        store_texels(values, self.flat[start * c : (start + len(values)) * c].reshape(len(values), c), "latent texels")

    def fill(self) -> "MipChain":
        """Every level from the one above it, in place; returns the chain. Each is box-filtered (``downsample``,
        ``resample_area``) in float32 a band of rows at a time (``BAND_BYTES`` of the level above), then stored
        in the chain's type: a half-float chain needs no float32 copy of a level."""
        for k in range(1, len(self)):
            _downsample_in_bands(self[k - 1], self[k])
        return self


def first_row_beyond_half(values: np.ndarray, limit: float = HALF_MAX) -> int:
    """The first row (along the first axis) of ``values`` holding one that is not finite or beyond +-``limit``, -1
    for none. Half floats and float32 are tested by a compiled loop (``kernels.first_row_beyond``: numpy's
    ``np.abs(values) <= limit`` over half floats took 2.4 ns a value here, in software, the loop 0.15); other types
    by numpy."""
    values = np.asarray(values)
    if values.size == 0:
        return -1
    rows = values.reshape(len(values), -1) if values.ndim else values.reshape(1, 1)
    if rows.dtype == np.float16:
        return int(kernels.first_row_beyond(rows.view(np.uint16), limit))
    if rows.dtype == np.float32:
        return int(kernels.first_row_beyond(rows, limit))
    bad = ~(np.abs(rows) <= limit).all(axis=1)  # nan fails it
    return int(np.argmax(bad)) if bad.any() else -1


def check_half_range(values: np.ndarray, what: str, limit: float = HALF_MAX) -> None:
    """ValueError naming ``what`` unless every value is finite and fits a half float (a latent texture's type):
    within +-``limit`` (HALF_MAX, or :data:`HALF_ROUNDS_FINITE` for values rounded to the nearest half)."""
    values = np.asarray(values)
    row = first_row_beyond_half(values, limit)
    if row >= 0:
        first = np.ravel(values[row] if values.ndim else values)
        bad = first[~(np.abs(first.astype(np.float64)) <= limit)][0]
        raise ValueError(
            f"{what} must be finite and within the half-float range [-{HALF_MAX:g}, {HALF_MAX:g}] their texture is "
            f"stored in, got {bad:.9g}"
        )


def float32_texels(values: np.ndarray) -> np.ndarray:
    """``values`` as float32 (no copy when they are already). Half floats are converted by a compiled loop
    (``kernels.halves_to_float32``, the CPU's conversion where it has one): numpy converts them in software, 2.3 ns
    a value here against 0.2. Elsewhere the loop converts in integer operations, exact for finite halves but
    turning an inf or nan finite: texels are finite (a value beyond the half range is refused before it is
    stored), and a texture's file is checked as it is read."""
    if values.dtype != np.float16:
        return np.asarray(values, dtype=np.float32)
    values = np.ascontiguousarray(values)
    out = np.empty(values.shape, dtype=np.float32)
    kernels.halves_to_float32(values.view(np.uint16).reshape(-1), out.reshape(-1))
    return out


def store_texels(values: np.ndarray, out: np.ndarray, what: str, limit: float = HALF_MAX) -> None:
    """``out[...] = values`` in ``out``'s type (float32, or float16: then :func:`check_half_range`'s ValueError
    naming ``what``, with nothing written, for a value beyond ``limit``). float32 values go into a (N, C)
    half-float ``out`` by a compiled loop that also checks them (``kernels.float32_to_halves``, where the CPU
    converts half floats), rounded as numpy rounds them: numpy's check and conversion took 3.5 ns a value here, the
    loop 0.35."""
    if out.dtype != np.float16:
        out[...] = values
        return
    values = np.asarray(values)
    if kernels.NATIVE_HALF and values.dtype == np.float32 and values.shape == out.shape and out.ndim == 2:
        if kernels.float32_to_halves(values, limit, out.view(np.uint16)) < 0:
            return
    check_half_range(values, what, limit)  # raises for what the loop found, naming the value
    out[...] = values


BAND_BYTES = 64 << 20  # the float32 rows of a level that :meth:`MipChain.fill` reduces at once


def _downsample_in_bands(level: np.ndarray, out: np.ndarray) -> None:
    """``out`` = the next level of ``level`` (``downsample``'s values: the same sums, a band of output rows at a
    time, each from the input rows it covers converted to float32)."""
    (h, w), (m, n) = level.shape[:2], out.shape[:2]
    even = h % 2 == 0 and w % 2 == 0
    row_weights = None if even else box_weights(h, m)
    col_weights = None if even else box_weights(w, n)
    step = max(1, BAND_BYTES // max(1, 2 * level[0].size * 4))  # output rows per band: about two input rows each
    for a in range(0, m, step):  # a loop over bands of rows, not texels
        b = min(m, a + step)
        band = out[a:b]
        if even:
            src = float32_texels(level[2 * a : 2 * b])
            if out.dtype == np.float32:
                downsample(src, out=band)
                continue
            reduced = downsample(src)
        else:
            weights = row_weights[a:b]
            covered = np.flatnonzero(weights.any(axis=0))
            lo, hi = int(covered[0]), int(covered[-1]) + 1
            rows = _reduce_rows(float32_texels(level[lo:hi]), weights[:, lo:hi])
            reduced = _reduce_rows(rows.transpose(1, 0, 2), col_weights).transpose(1, 0, 2)
        texels = band.view()
        texels.shape = (-1, band.shape[-1])  # whole rows of a level: a view (a shape needing a copy raises)
        store_texels(
            np.ascontiguousarray(reduced).reshape(texels.shape), texels, "a mip level's texels", HALF_ROUNDS_FINITE
        )


def build_mip_chain(base: np.ndarray, dtype=np.float32) -> MipChain:
    """All levels from ``base`` (H, W, C) down to 1 x 1, in one :class:`MipChain` of ``dtype`` (float32, or
    float16: ValueError for a value a half cannot hold)."""
    if base.ndim != 3 or base.shape[0] < 1 or base.shape[1] < 1:
        raise ValueError(f"a mip chain needs an (H, W, C) array, got shape {base.shape}")
    chain = MipChain.empty(*base.shape, dtype=dtype)
    chain.write_texels(0, base.reshape(-1, base.shape[2]))
    return chain.fill()


def mip_level_for_footprint(footprint: np.ndarray, width: int, height: int, n_levels: int) -> np.ndarray:
    """Continuous mip level for a footprint given in uv units (the ray cone's width on the surface): log2 of the
    footprint in texels of level 0, a texel's side taken as the geometric mean of its two, sqrt(1 / (W H)) in uv
    (as the footprint's uv scale is the geometric mean of the triangle's: ``integrator.uv_scale``). The longer side
    alone made every texture of aspect a : 1 half a level per doubling of a too coarse (a 2 : 1 one seen at one
    texel a pixel looked up level 0.5)."""
    texels = np.maximum(np.asarray(footprint, dtype=np.float64) * math.sqrt(width * height), 1e-12)
    return np.clip(np.log2(texels), 0.0, n_levels - 1)


def trilinear_lookup(
    levels: list[np.ndarray],
    uv: np.ndarray,
    footprint: np.ndarray | float,
    n_levels: int | None = None,
    split: int | None = None,
    pick_seed: int | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Trilinear lookup (N, C) float32 at uv (N, 2) (v = 0 at the bottom row, repeat addressing) with
    footprint (N,) or scalar in uv units, on the first ``n_levels`` levels (default all: a coarser footprint
    stays on the last of them). With ``split``: two C-contiguous arrays, the first ``split`` channels (N, split)
    and the others (N, C - split), written by the same pass. With ``pick_seed`` (an integer >= 0): each row one
    texel, picked with the probability of its weight in the lookup (stochastic filtering, ``kernels.trilinear``),
    the same texels for the same seed.

    The level is log2 of the footprint in texels of level 0; the two nearest levels are looked up
    bilinearly and blended, in float32 (the texture is stored as half floats: float64 arithmetic would
    only double the memory traffic of the renderer's widest arrays, 100 channels per hit for a latent
    texture), in one compiled pass over the rows (``kernels.trilinear``; a half-float chain is converted as it is
    read, exactly). ``levels`` is best a
    :class:`MipChain` (what :func:`build_mip_chain` returns): any other list is packed on every call.
    Non-finite uv or footprints raise ``ValueError``.
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must have shape (N, 2), got {uv.shape}")
    fp = np.broadcast_to(np.asarray(footprint, dtype=np.float64), (uv.shape[0],))
    if not (np.isfinite(uv).all() and np.isfinite(fp).all()):
        raise ValueError("uv and footprint must be finite")
    chain = levels if isinstance(levels, MipChain) else MipChain(levels)
    h, w, c = chain[0].shape
    usable = len(chain) if n_levels is None else max(1, min(int(n_levels), len(chain)))
    lod = mip_level_for_footprint(fp, w, h, usable)
    first = c if split is None else int(split)
    if not 0 <= first <= c:
        raise ValueError(f"split must be in [0, {c}] (the texture's channels), got {split}")
    out = np.empty((uv.shape[0], first), dtype=np.float32)  # every row written by the loop
    rest = np.empty((uv.shape[0], c - first), dtype=np.float32)
    seed = -1 if pick_seed is None else int(pick_seed) % (1 << 63)
    kernels.trilinear(chain.kernel_flat, chain.offsets, chain.heights, chain.widths, c, uv, lod, out, rest, seed)
    return out if split is None else (out, rest)

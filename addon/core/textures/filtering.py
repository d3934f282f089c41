"""How far a latent texture may be filtered in latent space: the mip levels whose averaged latents decode
to the average of what their texels decode to.

A mip level holds the box-filtered *latents* of the level below (``mip.downsample``), and the renderer
decodes the level a ray's footprint asks for. Averaging latents is averaging the BRDFs only where the
averaged texels are alike: the demo's varnished tiles (a glossy coat on the light tiles, a rough one on the
dark tiles and the grout) rendered 9-13% too dark seen at 80-90 degrees, where the footprint reaches the
levels that mix tile and grout, and within 1% looked up on the finest level only
(docs/texture_calibration.md). Filtering after shading (decoding each texel a ray meets and letting the
pixel's samples average them, as reference mode does) has no such bias, only the noise of the texture's
detail, which the samples of a pixel average out.

So the bake measures the chain (:func:`filterable_levels`): at each level, 2 x 2 blocks of the level below (the crop
of at most :data:`CROP` texels a side whose blocks vary the most) are decoded at :data:`PAIRS` of directions texel
by texel and averaged, and compared with the decoding of their averaged latent; and each level is compared with the
base level's own texels, decoded and averaged over the blocks of it that it holds (a crop of at most
:data:`BASE_CROP` base texels a side, :func:`base_errors`): a step of 1.9% from each level to the next passed the
first test at every level, and the coarse levels of a texture of multi-scale noise were 2.1-4.6% off their texels.
The first level whose error, either one, exceeds :data:`TOLERANCE` of the mean value at some pair of directions
(:func:`relative_error`) ends the usable chain; the texture records how many levels the renderer may use
(``filter_levels`` in its metadata; ``LatentTexture.lookup`` clamps the level of detail to them), and finer
footprints than that are left to the pixel's samples.
"""

from __future__ import annotations

import numpy as np

from ..rows import distinct_rows
from .mip import downsample, float32_texels

TOLERANCE = 0.02  # mean |decoded average latent - average decoded| over the mean decoded value, at the worst pair
CROP = 128  # texels a side of the block of each level that is measured
BASE_CROP = 256  # base texels a side that the levels are compared with (down to the level of 1 x 1 there)
SEED = 0
# The least mean decoded value (f cos) an error is relative to, at a pair of directions: a Lambertian of about 3%
# albedo (as ``quality.ERROR_FLOOR``). Below it the error is absolute: a pair that leaves a texture all but black
# does not decide its levels by a ratio of two tiny numbers.
VALUE_FLOOR = 0.01


def relative_error(got: np.ndarray, want: np.ndarray) -> float:
    """The error of decoded values ``got`` against ``want`` (..., P x 3: :func:`decoded`'s, texels' rows and
    columns first): at each of the P pairs of directions the mean |got - want| over the mean |want| (at least
    :data:`VALUE_FLOOR`), the worst pair's. Pooled over the pairs instead, the grazing mirror pairs decided: their
    exact top lobe (the same for every texel, f cos up to 2) held 70% of the values and next to none of the error,
    and levels 8-10% off at the other pairs measured 1.6%."""
    p = len(PAIRS[0])
    diff = np.abs(got - want).reshape(-1, p, 3).mean(axis=(0, 2))
    scale = np.abs(want).reshape(-1, p, 3).mean(axis=(0, 2))
    return float((diff / np.maximum(scale, VALUE_FLOOR)).max())


VARIANCE_BAND = 64  # rows of texels whose blocks' variance is worked out at once (a 2,048-wide level: 52 MB)


def block_variance(level: np.ndarray, step=None) -> np.ndarray:
    """(H // 2, W // 2): each 2 x 2 block's variance of its texels, summed over the channels, of ``level`` (H, W, C),
    a band of :data:`VARIANCE_BAND` rows at a time in float32 (the whole level in float64 held 7 GB more at 2,048
    texels a side); ``step()`` (optional) between bands, which may raise to stop."""
    h, w = level.shape[:2]
    eh, ew = h - h % 2, w - w % 2
    out = np.zeros((eh // 2, ew // 2))
    for top in range(0, eh, VARIANCE_BAND):  # a loop over bands of rows, each vectorised
        if step is not None:
            step()
        x = float32_texels(level[top : min(top + VARIANCE_BAND, eh), :ew])
        blocks = x.reshape(x.shape[0] // 2, 2, ew // 2, 2, -1)
        mean = blocks.mean(axis=(1, 3))
        out[top // 2 : top // 2 + len(mean)] = ((blocks * blocks).mean(axis=(1, 3)) - mean * mean).sum(axis=2)
    return out


def most_varied_corner(level: np.ndarray, ch: int, cw: int, align: int, variance=None) -> tuple[int, int]:
    """The (row, column) of the ``ch`` x ``cw`` window of ``level`` (H, W, C), its corner on a multiple of ``align``,
    whose 2 x 2 blocks vary the most (the sum over the window of :func:`block_variance`, given as ``variance`` when
    already worked out): where averaging latents is tested hardest. A seeded crop missed a patch of fine detail
    elsewhere, and a texture with 256 x 256 of checkers in a corner of 1,024 passed 4 levels, one of which rendered
    12-32% dark."""
    h, w = level.shape[:2]
    if (ch >= h and cw >= w) or h < 2 or w < 2:  # the whole level, or a strip one texel wide: no 2 x 2 blocks
        return 0, 0
    variance = block_variance(level) if variance is None else variance
    v = np.pad(variance, ((0, 1), (0, 1)))
    table = np.zeros((v.shape[0] + 1, v.shape[1] + 1))  # summed-area table over the blocks
    table[1:, 1:] = v.cumsum(axis=0).cumsum(axis=1)
    bh, bw, step = max(1, ch // 2), max(1, cw // 2), max(1, align // 2)
    ys = np.arange(0, max(1, (h - ch) // 2 + 1), step)
    xs = np.arange(0, max(1, (w - cw) // 2 + 1), step)
    y1, x1 = np.minimum(ys + bh, v.shape[0]), np.minimum(xs + bw, v.shape[1])
    sums = table[y1][:, x1] - table[ys][:, x1] - table[y1][:, xs] + table[ys][:, xs]
    iy, ix = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return 2 * int(ys[iy]), 2 * int(xs[ix])


def _pairs() -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo) unit directions (P, 3) each: the viewer at 0, 45, 70, 80 and 86 degrees, each with the light
    at its mirror direction, at the normal, and at 60 degrees on the viewer's side (backscatter)."""
    wi, wo = [], []
    for view in np.radians([0.0, 45.0, 70.0, 80.0, 86.0]):
        o = np.array([np.sin(view), 0.0, np.cos(view)])
        for light in (
            np.array([-o[0], 0.0, o[2]]),  # the mirror direction
            np.array([0.0, 0.0, 1.0]),
            np.array([np.sin(np.radians(60.0)), 0.0, np.cos(np.radians(60.0))]),
        ):
            wi.append(light)
            wo.append(o)
    return np.array(wi), np.array(wo)


PAIRS = _pairs()


def decoded(models, texels: np.ndarray) -> np.ndarray:
    """f cos(theta_i) (N, P, 3) of texels (N, 100: latents, proxy, top coating) at :data:`PAIRS`, as the
    renderer evaluates them (top lobe included, no calibration); each distinct texel decoded once (a crop of a
    painted or tiled texture holds a few, where it has thousands of texels)."""
    first, inverse = distinct_rows(texels)
    if len(first) < len(texels):
        return decoded(models, texels[first])[inverse]
    wi, wo = PAIRS
    n, p = len(texels), len(wi)
    z = np.repeat(texels[:, :96].reshape(n, 3, 32), p, axis=0)
    top = np.repeat(texels[:, 98:100].astype(np.float64), p, axis=0)
    f = models.eval_brdf(z, np.tile(wi, (n, 1)), np.tile(wo, (n, 1)), top, unit=True)
    return (np.asarray(f, dtype=np.float64) * np.tile(wi[:, 2], n)[:, None]).reshape(n, p, 3)


def level_error(models, level: np.ndarray, seed: int = SEED, variance=None) -> float:
    """|decode(2 x 2 averaged latents) - average of the decoded 2 x 2 texels| (:func:`relative_error`), on the
    crop of ``level`` (H, W, 100) of at most :data:`CROP` texels a side whose blocks vary the most
    (:func:`most_varied_corner`), the larger of two: the blocks the next level averages, and the blocks one texel
    over, which a bilinear tap between two of those blends (repeat addressing). ``seed`` is kept for callers; the
    crop is chosen, not drawn."""
    h, w = level.shape[:2]
    ch, cw = max(1, min(CROP, h - h % 2)), max(1, min(CROP, w - w % 2))
    y0, x0 = most_varied_corner(level, ch, cw, 2, variance)
    errors = []
    for shift in (0, 1):  # a loop over the two alignments of the blocks
        rows = (y0 + shift + np.arange(ch)) % h
        cols = (x0 + shift + np.arange(cw)) % w
        crop = float32_texels(level[np.ix_(rows, cols)])
        averaged = downsample(crop)  # the latents of the blocks, averaged
        each = decoded(models, crop.reshape(-1, crop.shape[2])).reshape(ch, cw, -1)
        want = downsample(each)  # the texels' decoded values averaged the same way
        got = decoded(models, averaged.reshape(-1, crop.shape[2])).reshape(want.shape)
        errors.append(relative_error(got, want))
    return max(errors)


def base_errors(models, levels, seed: int = SEED, variance=None) -> list[float]:
    """Each level k >= 1 against the base level's texels: |decode(level k's latents) - the average of the decoded
    base texels each of them holds| (:func:`relative_error`), on the crop of at most :data:`BASE_CROP` base texels a
    side whose blocks vary the most (aligned to the blocks of the coarsest level it reaches) and the crop of every
    level over it; for
    the levels the crop reaches down to 1 x 1 there (log2 :data:`BASE_CROP` of them at most), where their texels are
    2 x 2 blocks of the level below's (even sizes); the others are not measured here."""
    base = levels[0]
    h, w = base.shape[:2]
    reach = 0  # levels whose texels are whole 2 x 2 blocks down from a crop of base texels
    while reach + 1 < len(levels) and levels[reach].shape[0] % 2 == 0 and levels[reach].shape[1] % 2 == 0:
        if (1 << (reach + 1)) > BASE_CROP:
            break
        reach += 1
    if reach == 0:
        return []
    block = 1 << reach
    ch, cw = min(BASE_CROP, h) // block * block, min(BASE_CROP, w) // block * block
    y0, x0 = most_varied_corner(base, ch, cw, block, variance)
    crop = float32_texels(base[y0 : y0 + ch, x0 : x0 + cw])
    want = decoded(models, crop.reshape(-1, crop.shape[2])).reshape(ch, cw, -1)
    errors = []
    for k in range(1, reach + 1):  # a loop over the levels the crop reaches
        want = downsample(want)  # the base texels' decoded values, averaged over level k's texels
        s = 1 << k
        mine = float32_texels(levels[k][y0 // s : (y0 + ch) // s, x0 // s : (x0 + cw) // s])
        got = decoded(models, mine.reshape(-1, mine.shape[2])).reshape(want.shape)
        errors.append(relative_error(got, want))
    return errors


def filterable_levels(models, levels, tolerance: float = TOLERANCE, step=None) -> tuple[int, list[float]]:
    """How many levels of the chain ``levels`` (finest first) decode like the average of their texels, and
    each measured level's error (the larger of :func:`level_error`, against the level below, and
    :func:`base_errors`, against the base texels, where it reaches), in order until the first one over
    ``tolerance``. ``step()`` (optional) before each level (about a second each), which may raise to stop."""
    if len(levels) < 2:
        return len(levels), []
    if step is not None:
        step()
    # the base level's blocks' variances, worked out once for both measurements (a band at a time, heard by step)
    base_variance = block_variance(levels[0], step) if min(levels[0].shape[:2]) >= 2 else None
    against_base = base_errors(models, levels, SEED, base_variance)
    errors = []
    for k in range(1, len(levels)):  # a loop over mip levels, each one batch of decodes
        if step is not None:
            step()
        variance = base_variance if k == 1 else None
        error = level_error(models, levels[k - 1], SEED + k, variance)
        errors.append(max(error, against_base[k - 1]) if k <= len(against_base) else error)
        if errors[-1] > tolerance:
            return k, errors
    return len(levels), errors

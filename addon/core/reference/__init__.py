"""Position-free Monte Carlo layered BSDF (Guo, Hasan, Zhao 2018): the ground truth.

Public API (directions are (N, 3) unit vectors in the local frame, normal +z, both pointing
away from the surface; results are float64):

- ``eval_brdf(stack, wi, wo, walks=64, seed=0) -> (f, stderr)``, both (N, 3): f(wi, wo)
  without the cosine, estimated by ``walks`` independent random walks per pair
  (unidirectional, next-event estimation toward ``wi`` with MIS; see :mod:`.walk`), and the
  standard error of that mean. Delta components (the mirror reflection of a smooth top
  interface) are not part of f. Pairs with ``wi`` or ``wo`` below the horizon give 0.
- ``eval_brdf_many(stack, wi, wo, walks=64, seed=0)``: the amortised form, ``wi`` (N, M, 3):
  one walk from ``wo[n]`` serves all M incident directions (lobe images, training data).
- ``sample(stack, wo, rng, with_flags=False) -> (wi, weight[, specular])``: one analog walk
  per row; ``weight`` = f cos / pdf in expectation (0 for absorbed walks), ``specular`` True
  where every event was a delta event (paths ``eval_brdf`` cannot represent).
- ``albedo(stack, wo, samples=4096, seed=0) -> (albedo, stderr)``, both (N, 3): directional
  albedo (all paths, delta ones included) as the mean of ``samples`` analog walks.

Backends: every function takes ``backend=None | "numpy" | "torch" | "cupy"`` and ``device``
(``"cpu"``, ``"cuda"``, ``"cuda:N"``). With a backend, the inputs are moved to that array library,
the walks run there (the same source as on numpy, see :mod:`addon.core.xp`) and the results come
back as numpy arrays. Without one, the walks run in the library of the inputs (numpy in, numpy
out). ``seed``/``rng`` may also be an :class:`addon.core.xp.Rng` (e.g. a ``HostRng`` that feeds
every backend the same numbers).

``stack`` is a :class:`~addon.core.stack.Stack` (the same stack for every row) or a
:class:`~addon.core.stack.StackArrays` with one row (shared) or N rows (one stack per
direction pair: a batch of different stacks with the same number of coatings; build it with
:func:`pack_stacks`).

The model: coating j is a rough dielectric interface over a homogeneous slab; interface j has
the relative index ``ior_j / ior_{j+1}`` (air above the top one); the base lies inside the
lowest coating's medium and its optical constants are taken relative to that medium
(``eta / n_0``, ``k / n_0``, ``ior / n_0``). Interfaces scatter once (single-scattering
microfacet model): a rough interface loses the energy of multiple microfacet bounces, so a
white base under an alpha = 0.3 coat has an albedo well below 1. That is the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import xp as xpmod
from ..bsdf.base import as_directions
from ..stack import Stack, StackArrays, validate
from ..xp import Rng, namespace, to_numpy
from .walk import CHUNK_WALKS, MAX_DEPTH, Layers, run_walks

__all__ = ["eval_brdf", "eval_brdf_many", "sample", "albedo", "pack_stacks", "MAX_DEPTH", "ESTIMATOR_VERSION"]

# What eval_brdf estimates, as a number that caches of its results key on: a change of its expectation (not of its
# noise) raises it. 2: the light that delta events bring to a vertex under smooth interfaces (``.walk``). 3: the same
# under rough interfaces, MIS-weighted, and Russian roulette relative to a smooth top's forced entry: the expectation
# was the same, but no practical walk count reached it (a milky coat over a mirror under a glossy top read 6-26%
# dark, a grazing view through a smooth coat 23% dark, each with tight error bars).
ESTIMATOR_VERSION = 3


def pack_stacks(stacks) -> StackArrays:
    """Many stacks with the same number of coatings as one struct of arrays (one row each)."""
    if isinstance(stacks, Stack):
        stacks = [stacks]
    return StackArrays.from_stacks(list(stacks))


def _layers_and_rows(stack, n: int, xp=np) -> tuple[Layers, np.ndarray]:
    if isinstance(stack, Stack):
        sa = StackArrays.from_stacks([stack])
    elif isinstance(stack, StackArrays):
        sa = stack
    else:
        raise ValueError(f"stack must be a Stack or StackArrays, got {type(stack).__name__}")
    validate(sa)
    if len(sa) == 1:
        return Layers.from_arrays(sa).to(xp), xp.zeros(n, dtype=xp.int64)
    if len(sa) != n:
        raise ValueError(f"StackArrays has {len(sa)} rows but there are {n} directions; give 1 or {n} stacks")
    return Layers.from_arrays(sa).to(xp), xp.arange(n)


def _count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _rng(rng, xp=np) -> Rng:
    if isinstance(rng, Rng):
        return rng
    if isinstance(rng, np.random.Generator):
        return Rng(xp, rng)
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return Rng(xp, int(rng))
    raise ValueError(f"rng must be a numpy Generator or an integer seed, got {type(rng).__name__}")


def _backend(backend, device, *arrays):
    """``(xp, out)``: the namespace to run in and the conversion of the results."""
    if backend is None:
        if device is not None:
            raise ValueError(f"device={device!r} needs a backend ('numpy', 'torch' or 'cupy')")
        return namespace(*arrays), lambda a: a
    return xpmod.get(backend, device), to_numpy


def _accumulate(sums, sq, pair, est) -> None:
    """Add per-walk estimates to their pair's sums; ``pair`` is sorted (walks are pair-major)."""
    xp = namespace(est)
    if xp is not np:
        xpmod.index_add(xp, sums, pair, est)
        xpmod.index_add(xp, sq, pair, est * est)
        return
    starts = np.flatnonzero(np.r_[True, pair[1:] != pair[:-1]])
    idx = pair[starts]
    sums[idx] += np.add.reduceat(est, starts, axis=0)
    sq[idx] += np.add.reduceat(est * est, starts, axis=0)


def _finish(sums, sq, k: int):
    xp = namespace(sums)
    mean = sums / k
    if k < 2:
        return mean, xp.full_like(mean, xp.inf)
    var = xp.maximum(sq / k - mean * mean, 0.0) * (k / (k - 1))
    return mean, xp.sqrt(var / k)


def eval_brdf(stack, wi, wo, walks: int = 64, seed: int = 0, backend=None, device=None):
    """f(wi, wo) (N, 3) without the cosine and its standard error (N, 3).

    Each pair gets ``walks`` independent walks; with ``walks == 1`` the standard error is
    infinite (unknown). Raises ValueError on malformed or non-finite directions, bad stack
    parameters or a non-positive walk count. ``backend``/``device``: see the module docstring.
    """
    wi = as_directions(wi, "wi")
    wo = as_directions(wo, "wo")
    if wi.shape[0] != wo.shape[0]:
        raise ValueError(f"wi has {wi.shape[0]} rows but wo has {wo.shape[0]}")
    xp, out = _backend(backend, device, wi, wo)
    f, se = _eval(stack, xp.asarray(wi)[:, None, :], xp.asarray(wo), walks, seed, xp)
    return out(f[:, 0]), out(se[:, 0])


def eval_brdf_many(stack, wi, wo, walks: int = 64, seed: int = 0, backend=None, device=None):
    """Amortised estimator: f(wi[n, j], wo[n]) for M incident directions per outgoing one.

    ``wi`` is (N, M, 3), ``wo`` (N, 3); returns f and its standard error, (N, M, 3) each. Every
    walk from ``wo[n]`` connects each of its vertices to all M incident directions (one
    pre-sampled chain each), so the walk is paid once for M values. The M estimates of one
    ``n`` are correlated (same walks); each one is unbiased with the stated standard error.
    For a lobe image (fixed incident direction, many outgoing ones) use reciprocity,
    f(wi, wo) = f(wo, wi): pass the grid as ``wi`` and the incident direction as ``wo``.
    """
    xin = namespace(wi)
    try:
        a = xin.asarray(wi, dtype=xin.float64)
    except (TypeError, ValueError):
        raise ValueError(f"wi must be an (N, M, 3) array of directions, got {type(wi).__name__}") from None
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"wi must have shape (N, M, 3), got {tuple(a.shape)}")
    n, m = a.shape[0], a.shape[1]
    if m < 1:
        raise ValueError("wi must hold at least one direction per row (M >= 1)")
    flat = as_directions(a.reshape(-1, 3), "wi").reshape(n, m, 3)
    wo = as_directions(wo, "wo")
    if wo.shape[0] != n:
        raise ValueError(f"wi has {n} rows but wo has {wo.shape[0]}")
    xp, out = _backend(backend, device, flat, wo)
    f, se = _eval(stack, xp.asarray(flat), xp.asarray(wo), walks, seed, xp)
    return out(f), out(se)


def _eval(stack, wi, wo, walks, seed, xp=np):
    k = _count(walks, "walks")
    n, m = wi.shape[0], wi.shape[1]
    lay, prow = _layers_and_rows(stack, n, xp)
    rng = _rng(seed, xp)
    sums = xp.zeros((n, m, 3))
    sq = xp.zeros((n, m, 3))
    total = n * k
    step = max(1, CHUNK_WALKS // m)
    for r0 in range(0, total, step):
        r = xp.arange(r0, min(total, r0 + step))
        pair = r // k
        est = run_walks(lay, prow[pair], wo[pair], wi[pair], rng, nee=True)
        _accumulate(sums, sq, pair, est)
    above = ((wi[:, :, 2] > 0.0) & (wo[:, None, 2] > 0.0))[:, :, None]
    f, se = _finish(sums, sq, k)
    return xp.where(above, f, 0.0), xp.where(above, se, 0.0)


def sample(stack, wo, rng, with_flags: bool = False, backend=None, device=None):
    """One analog walk per row of ``wo``: ``(wi, weight)`` or ``(wi, weight, specular)``.

    ``weight`` (N, 3) is an unbiased estimate of f(wi, wo) cos(wi) / pdf(wi); absorbed walks
    and ``wo`` below the horizon give weight 0 (and wi = +z). ``rng`` is a numpy Generator or
    an integer seed (or an :class:`addon.core.xp.Rng`).
    """
    wo = as_directions(wo, "wo")
    n = wo.shape[0]
    xp, out = _backend(backend, device, wo)
    wo = xp.asarray(wo)
    lay, prow = _layers_and_rows(stack, n, xp)
    g = _rng(rng, xp)
    out_wi = xp.zeros((n, 3))
    out_w = xp.zeros((n, 3))
    out_s = xp.zeros(n, dtype=bool)
    for r0 in range(0, n, CHUNK_WALKS):
        sl = slice(r0, min(n, r0 + CHUNK_WALKS))
        out_wi[sl], out_w[sl], out_s[sl] = run_walks(lay, prow[sl], wo[sl], None, g, nee=False)
    return (out(out_wi), out(out_w), out(out_s)) if with_flags else (out(out_wi), out(out_w))


def albedo(stack, wo, samples: int = 4096, seed: int = 0, backend=None, device=None):
    """Directional albedo (N, 3) seen from ``wo`` (all paths) and its standard error (N, 3)."""
    wo = as_directions(wo, "wo")
    k = _count(samples, "samples")
    n = wo.shape[0]
    xp, out = _backend(backend, device, wo)
    wo = xp.asarray(wo)
    lay, prow = _layers_and_rows(stack, n, xp)
    rng = _rng(seed, xp)
    sums = xp.zeros((n, 3))
    sq = xp.zeros((n, 3))
    total = n * k
    for r0 in range(0, total, CHUNK_WALKS):
        r = xp.arange(r0, min(total, r0 + CHUNK_WALKS))
        pair = r // k
        _, w, _ = run_walks(lay, prow[pair], wo[pair], None, rng, nee=False)
        _accumulate(sums, sq, pair, w)
    f, se = _finish(sums, sq, k)
    return out(f), out(se)


@dataclass(frozen=True)
class AlbedoParts:
    """The directional albedo seen from N directions, whole and in parts, each with its standard error:
    ``albedo`` (N, 3), all paths; ``below_top`` (N, 3), every path but a first reflection at the top
    interface (the light that entered the stack: what a remainder decoder holds; for a coating-free
    stack, all of it); ``by_exit`` and ``below_top_by_exit`` (N, B, 3), the two split over the B weights
    ``exit_bins`` gives each exit direction (weights summing to 1 split them whole)."""

    albedo: np.ndarray
    albedo_stderr: np.ndarray
    below_top: np.ndarray
    below_top_stderr: np.ndarray
    by_exit: np.ndarray | None = None
    by_exit_stderr: np.ndarray | None = None
    below_top_by_exit: np.ndarray | None = None
    below_top_by_exit_stderr: np.ndarray | None = None


def albedo_parts(
    stack, wo, samples: int = 4096, seed: int = 0, exit_bins=None, step=None, bins: int | None = None
) -> AlbedoParts:
    """:class:`AlbedoParts` of ``stack`` seen from ``wo`` (N, 3), from ``samples`` analog walks each (the
    same walks for every part). ``exit_bins``: a function of the walks' exit directions (m, 3) giving
    their (m, B) bin weights, for ``by_exit``; with ``bins`` = B given, their sparse form instead: the bins
    (m, J) each walk falls in, J of the B and distinct within a walk, and their weights (m, J) (the same
    numbers; a walk's binning then costs J columns, not B). The first reflections at the top interface carry the
    walks' largest noise under a bright coat; ``below_top`` is free of it. ``step()`` (optional) is called
    before each event of the walks; raising there stops them."""
    wo = as_directions(wo, "wo")
    k = _count(samples, "samples")
    n = wo.shape[0]
    lay, prow = _layers_and_rows(stack, n)
    rng = _rng(seed)
    sums, sq = np.zeros((n, 3)), np.zeros((n, 3))
    below, below_sq = np.zeros((n, 3)), np.zeros((n, 3))
    binned = binned_sq = None
    total = n * k
    for r0 in range(0, total, CHUNK_WALKS):
        pair = np.arange(r0, min(total, r0 + CHUNK_WALKS)) // k
        first = []
        wi, w, _ = run_walks(lay, prow[pair], wo[pair], None, rng, nee=False, first_exits=first, step=step)
        _accumulate(sums, sq, pair, w)
        w_below = np.where(first[0][:, None], 0.0, w)
        _accumulate(below, below_sq, pair, w_below)
        if exit_bins is not None and bins is not None:
            if binned is None:
                binned, binned_sq = np.zeros((n, 6 * bins)), np.zeros((n, 6 * bins))
            _accumulate_cells(binned, binned_sq, pair, *exit_bins(wi), np.stack([w, w_below]), bins)
        elif exit_bins is not None:
            b = np.asarray(exit_bins(wi), dtype=np.float64)
            est = np.concatenate([b[:, :, None] * w[:, None, :], b[:, :, None] * w_below[:, None, :]], axis=1)
            est = est.reshape(len(pair), -1)
            if binned is None:
                binned, binned_sq = np.zeros((n, est.shape[1])), np.zeros((n, est.shape[1]))
            _accumulate(binned, binned_sq, pair, est)
    f, se = _finish(sums, sq, k)
    f_below, se_below = _finish(below, below_sq, k)
    if binned is None:
        return AlbedoParts(f, se, f_below, se_below)
    f_bins, se_bins = (np.split(a.reshape(n, -1, 3), 2, axis=1) for a in _finish(binned, binned_sq, k))
    return AlbedoParts(f, se, f_below, se_below, f_bins[0], se_bins[0], f_bins[1], se_bins[1])


def _accumulate_cells(sums, sq, pair, cells, weights, parts, bins: int) -> None:
    """:func:`_accumulate` of the walks' binned parts from their sparse bins: ``parts`` (A, m, 3), A weights per
    walk (the whole, the light below the top), each split over its ``cells`` (m, J) (distinct within a walk) with
    ``weights`` (m, J), into ``sums`` and ``sq`` (N, A * bins * 3), laid out as the dense path's (part, bin,
    channel). One walk's estimate in a bin is one of its products (its cells are distinct), so its square is that
    product's."""
    a = len(parts)
    cells = np.asarray(cells, dtype=np.int64)
    est = np.asarray(weights, dtype=np.float64)[None, :, :, None] * parts[:, :, None, :]  # (A, m, J, 3)
    row = (pair[None, :] * a + np.arange(a)[:, None]) * bins  # (A, m): the first bin of each walk's row and part
    index = ((row[:, :, None] + cells[None]) * 3)[..., None] + np.arange(3)
    size = sums.size
    sums.reshape(-1)[:] += np.bincount(index.reshape(-1), est.reshape(-1), size)
    sq.reshape(-1)[:] += np.bincount(index.reshape(-1), np.square(est).reshape(-1), size)

"""The exact top coat of the remainder design: the first reflection at a stack's top interface.

    top = top_coats(arrays)                   # (N, 2) float64: alpha, ior of each stack's top coating
    f = eval_top(top, wi, wo)                 # (N,) f of that reflection, 1/sr, no cosine
    wi, pdf = sample_top(top, wo, u)          # GGX visible-normal samples of it
    s = top_share(top, wo)                    # the share of samples a material gives it

A layered stack's BRDF is the sum of the light reflected at its top interface, a rough dielectric
lobe (GGX, Fresnel) that is known in closed form, and the rest: the light that entered the coat. A
decoder of the *remainder* design (its card says ``"remainder": true``) holds only the rest;
``ModelSet.eval_brdf`` adds this lobe for it, and the renderer's sampler mixes exact samples of it with
the proxy. The lobe is ``RoughDielectric(alpha, ior, reflection_only=True)`` with the top coating's
roughness and index, the reference walk's own top event (``addon.core.reference.walk``), so it is the
reference's first reflection exactly; the training targets of such a decoder are each stack's
reference BRDF minus this lobe (``onnx_export.remainder``).

The light that entered the coat crossed the top interface twice, in along ``wi`` and out along ``wo``, so
near the horizon, where the interface reflects nearly everything, the remainder falls to 0 with its
transmission. A decoder whose card also says ``"top_transmission": true`` holds the remainder divided by
that factor, ``remainder_scale(top, wi, wo) = T(cos theta_i) T(cos theta_o)``, with ``T`` the share of
the light the top interface lets into the coat in the reference walk's own interface model
(``transmission``: 1 - F at the macro normal for a smooth coat; for a rough one more near grazing, where
tilted microfacets let light in). The factor is a structural prior that makes the decoded remainder fall
towards grazing as the reference's does and is reciprocal, and the network learns a function without
that steep fall.

A stack without coatings has no top lobe (its base is the whole BRDF): its row is :data:`NO_TOP`, an
index-matched interface, which reflects nothing. A smooth top interface reflects a delta lobe, which is
not part of f either (0 here, as in ``RoughDielectric``). The lobe's alpha is the one the decoder was trained
with (clamped to the trained range, ``stack.clamp_to_trained``), its ior the coating's own (:func:`top_coats`).
"""

from __future__ import annotations

import functools
import threading

import numpy as np

from .. import kernels
from ..bsdf import ggx
from ..bsdf.base import SMOOTH_ALPHA
from ..bsdf.dielectric import INDEX_MATCHED_TOL, RoughDielectric
from ..bsdf.frame import dot, reflect, refract
from ..bsdf.fresnel import fresnel_dielectric
from ..stack import Stack, StackArrays, clamp_to_trained
from .top_formulas import TOP_SHARE_RANGE, TOP_SHARE_REST, top_share_cos  # noqa: F401 (TOP_SHARE_*: this module's API)

# (alpha, ior) of a stack without coatings: index-matched, no reflection
NO_TOP = (0.0, 1.0)
# no top coat at all, as the compiled loops take coatings (``kernels.decoded_brdf``): no rows
NO_TOP_ROWS = np.zeros((0, 2))


def top_coats(arrays: StackArrays) -> np.ndarray:
    """(N, 2) float64 ``alpha, ior`` of each stack's top coating as the renderer adds its lobe: the alpha in the
    trained range (the value the decoder saw; a smooth coat's delta reflection is not part of f), the ior the
    stack's own, outside the trained 1.05-2 too. The calibration of the remainder cannot take away light that the
    exact lobe adds, nor add light where the remainder is dark: at the trained bounds, an index-matched coat over
    a black base glowed at grazing (0.15 at 87 degrees for 0), and an opaque coat of ior 3 rendered 0.56 of its
    reflection. :data:`NO_TOP` for stacks without coatings."""
    if not isinstance(arrays, StackArrays):
        raise ValueError(f"top_coats needs StackArrays, got {type(arrays).__name__}")
    out = np.tile(np.asarray(NO_TOP, dtype=np.float64), (len(arrays), 1))
    if arrays.n_coatings == 0 or len(arrays) == 0:
        return out
    fixed, _notes = clamp_to_trained(arrays)  # encode_arrays warns about the clamp once
    out[:, 0] = np.asarray(fixed.coat_roughness, dtype=np.float64)[:, -1]
    out[:, 1] = np.asarray(arrays.coat_ior, dtype=np.float64)[:, -1]
    return out


# What the keys of work made with a material's top lobe (calibrations, bakes) add where the top coating's ior is
# outside the trained range: the lobe takes that ior, where it took the trained bound before.
OWN_TOP_IOR = "-top-ior-own"


def ior_outside_trained(arrays: StackArrays) -> np.ndarray:
    """(N,) bool: the stacks whose top coating's ior lies outside the trained range (their top lobe takes it as it
    is, :func:`top_coats`)."""
    if arrays.n_coatings == 0 or len(arrays) == 0:
        return np.zeros(len(arrays), dtype=bool)
    return outside_trained_ior(np.asarray(arrays.coat_ior, dtype=np.float64)[:, -1])


def outside_trained_ior(ior) -> np.ndarray:
    """Whether each of these iors lies outside the trained range (``stack.TRAINED_RANGES``)."""
    from ..stack import TRAINED_RANGES

    lo, hi = TRAINED_RANGES["ior"]
    ior = np.asarray(ior, dtype=np.float64)
    return (ior < lo) | (ior > hi)


def top_coat(stack: Stack) -> np.ndarray:
    """(2,) ``alpha, ior`` of one stack's top coating (see :func:`top_coats`)."""
    if not isinstance(stack, Stack):
        raise ValueError(f"top_coat needs a Stack, got {type(stack).__name__}")
    return top_coats(StackArrays.from_stacks([stack]))[0]


def as_top(top, n: int) -> np.ndarray:
    """``top`` as (n, 2) float64 rows: one (2,) pair for every row, or (n, 2) per row; checked."""
    t = _checked(top, n)
    return np.broadcast_to(t, (n, 2)) if t.shape == (2,) else t


def _checked(top, n: int) -> np.ndarray:
    """``top`` as float64, (2,) (one pair for every row: every function here then works on scalars) or
    (n, 2); finite, alpha >= 0 and ior > 0, else ValueError."""
    if np.iscomplexobj(top):
        raise ValueError("top must be real (alpha, ior) pairs, got complex values")
    t = np.asarray(top, dtype=np.float64)
    if t.shape != (2,) and t.shape != (n, 2):
        raise ValueError(f"top must have shape (2,) or ({n}, 2) (alpha, ior per row), got {t.shape}")
    if not np.all(np.isfinite(t)) or (t[..., 0] < 0).any() or (t[..., 1] <= 0).any():
        raise ValueError("top must hold finite alpha >= 0 and ior > 0")
    return t


def has_top(top: np.ndarray) -> np.ndarray:
    """(N,) bool: rows whose interface reflects (not index-matched)."""
    return np.abs(top[:, 1] - 1.0) >= INDEX_MATCHED_TOL


def _unit(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, dtype=np.float64)
    n = np.sqrt(dot(w, w))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((n > 0)[:, None], w / np.where(n > 0, n, 1.0)[:, None], 0.0)


def _lobe(top: np.ndarray) -> RoughDielectric:
    return RoughDielectric(top[..., 0], top[..., 1], reflection_only=True)


def eval_top(top, wi, wo, unit: bool = False) -> np.ndarray:
    """(N,) float64 f of the top interface's reflection at directions ``wi``, ``wo`` (N, 3), any
    length (normalised here unless ``unit``; zero-length or below-horizon rows give 0)."""
    if not unit:
        wi, wo = _unit(wi), _unit(wo)
    return eval_pdf_top(top, wi, wo)[0]


def pdf_top(top, wi, wo) -> np.ndarray:
    """(N,) solid-angle density of :func:`sample_top` choosing ``wi`` given ``wo`` (unit, local frame)."""
    return eval_pdf_top(top, wi, wo)[1]


def eval_pdf_top(top, wi, wo) -> tuple[np.ndarray, np.ndarray]:
    """:func:`eval_top` and :func:`pdf_top` of unit directions together (one half vector, Fresnel term and
    microfacet density for both): the renderer's query, which needs f and the sampling density at once,
    in one compiled pass (``kernels.top_lobe_eval_pdf``, the same formula as ``RoughDielectric``)."""
    return kernels.top_lobe_eval_pdf(kernels.float64_rows(wi), kernels.float64_rows(wo), top_table(top, len(wi)))


def top_table(top, n: int) -> np.ndarray:
    """``top`` checked as the compiled loops take it: (1, 2) for one pair shared by ``n`` rows, else (n, 2);
    contiguous, writable float64 (one type, so the loops are compiled once)."""
    return np.require(_checked(top, n).reshape(-1, 2), np.float64, ["C", "W"])


def sample_top(top, wo, u) -> tuple[np.ndarray, np.ndarray]:
    """Incident directions (N, 3) of the top lobe seen from ``wo`` (unit, local frame), by its GGX
    visible normals, with their density (N,) (0 where no sample: no top, a smooth top, a sample below
    the horizon); ``u`` (N, 2) uniform in [0, 1)."""
    t = _checked(top, len(wo))
    wi, ok = sample_top_directions(t, wo, u)
    wi = np.where(ok[:, None], wi, np.array([0.0, 0.0, 1.0]))
    return wi, np.where(ok, pdf_top(t, wi, wo), 0.0)


def sample_top_directions(top, wo, u) -> tuple[np.ndarray, np.ndarray]:
    """The directions of :func:`sample_top` (the mirror of ``wo`` about a visible normal of the interface's
    GGX distribution, as ``RoughDielectric.sample`` reflects) and whether each is a sample (a rough top, both
    directions above the horizon); without their density, for a caller that evaluates it with the lobe."""
    t = _checked(top, len(wo))
    rough = has_top(t.reshape(-1, 2)) & (t.reshape(-1, 2)[:, 0] >= SMOOTH_ALPHA)
    m = ggx.sample_visible_normal(wo, t[..., 0], u)
    wi = reflect(wo, m)
    return wi, rough & (wo[:, 2] > 0) & (wi[:, 2] > 0)


# The grid of the top interface's transmittance table (transmission): outgoing cosines denser towards
# grazing, roughness (geometric: the table changes fastest for smooth coats) over the trained range (the top lobe's
# alpha is clamped to it) and index over the valid range (stack.VALID_RANGES: the top lobe keeps the coating's own),
# evenly by 0.1.
TRANSMITTANCE_COS = 1e-3 + (1.0 - 1e-3) * np.linspace(0.0, 1.0, 33) ** 2
TRANSMITTANCE_ALPHA = np.geomspace(0.01, 1.0, 21)
TRANSMITTANCE_IOR = np.linspace(1.0, 4.0, 31)
TRANSMITTANCE_STRATA = 16  # 16 x 16 stratified visible normals per cell: the estimator varies little


@functools.lru_cache(maxsize=1)
def transmittance_table() -> np.ndarray:
    """(cos, alpha, ior) table of the share of the light arriving from ``cos`` that the top interface lets
    into the coat, in the reference walk's interface model (``RoughDielectric``: GGX visible normals,
    Fresnel, height-correlated Smith): the mean of (1 - F) G2 / G1 over refracted visible-normal samples,
    at stratified midpoints, deterministic; made once per process (about a second, by the add-on's warm-up)."""
    k = TRANSMITTANCE_STRATA
    g = (np.arange(k) + 0.5) / k
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    c = TRANSMITTANCE_COS
    n_c, n_a, n_u = len(c), len(TRANSMITTANCE_ALPHA), len(u)
    wo = np.repeat(np.stack([np.sqrt(1.0 - c * c), np.zeros_like(c), c], axis=1), n_a * n_u, axis=0)
    alpha = np.repeat(np.tile(TRANSMITTANCE_ALPHA, n_c), n_u)
    m = ggx.sample_visible_normal(wo, alpha, np.tile(u, (n_c * n_a, 1)))
    out = np.empty((n_c, n_a, len(TRANSMITTANCE_IOR)))
    for j, ior in enumerate(TRANSMITTANCE_IOR):  # a loop over the 31 table slices, each one vectorised pass
        eta = np.full(len(wo), ior)
        wt, ok = refract(wo, m, eta)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (1.0 - fresnel_dielectric(dot(wo, m), eta)) * ggx.smith_g2(wt, wo, alpha) / ggx.smith_g1(wo, alpha)
        t = np.where(ok & (wt[:, 2] < 0.0) & np.isfinite(t), t, 0.0)
        out[:, :, j] = t.reshape(n_c, n_a, n_u).mean(axis=2)
    return out


def transmission(top, cos) -> np.ndarray:
    """(N,) the share of the light arriving from cosine ``cos`` (N,) that the top coatings ``top`` (N, 2), or
    one pair (2,) for all rows, let into the coat (trilinear in :func:`transmittance_table`, one compiled pass:
    ``kernels.transmission_rows``): 1 without a top interface (NO_TOP), 0 at and below the horizon."""
    c = kernels.float64_rows(cos).reshape(-1)
    return kernels.transmission_rows(top_table(top, len(c)), c, *transmittance_grids())


_GRIDS_LOCK = threading.Lock()


def transmittance_grids() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The table and its cosine, alpha and ior grids as the compiled loops take them (contiguous float64), made once
    a process: a render that needs them while the add-on's warm-up makes them waits for it, where both had made the
    table at once (1.2 s alone, 2-4 s side by side, right after Blender starts)."""
    with _GRIDS_LOCK:
        return _transmittance_grids()


@functools.lru_cache(maxsize=1)
def _transmittance_grids() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return tuple(
        kernels.float64_rows(a)
        for a in (transmittance_table(), TRANSMITTANCE_COS, TRANSMITTANCE_ALPHA, TRANSMITTANCE_IOR)
    )


def remainder_scale(top, wi, wo, unit: bool = False) -> np.ndarray:
    """(N,) the structural factor T(cos theta_i) T(cos theta_o) of a ``top_transmission`` decoder's
    remainder (module docstring); directions of any length (normalised here unless ``unit``)."""
    if not unit:
        wi, wo = _unit(wi), _unit(wo)
    return transmission(top, wi[:, 2]) * transmission(top, wo[:, 2])


def top_share(top, wo) -> np.ndarray:
    """(N,) probability that the renderer samples the top lobe at outgoing ``wo`` (0 without one)."""
    t = _checked(top, len(wo))
    if t.ndim == 1:
        t = t[None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return top_share_cos(np.asarray(wo)[:, 2], t[:, 0], t[:, 1])


def own_tops(arrays: StackArrays) -> np.ndarray:
    """(N, 2) float64 ``alpha, ior`` of each stack's own top coating, as the stack gives it (not clamped to the
    trained ranges: the interface the reference walks); :data:`NO_TOP` for stacks without coatings."""
    out = np.tile(np.asarray(NO_TOP, dtype=np.float64), (len(arrays), 1))
    if arrays.n_coatings and len(arrays):
        out[:, 0] = np.asarray(arrays.coat_roughness, dtype=np.float64)[:, -1]
        out[:, 1] = np.asarray(arrays.coat_ior, dtype=np.float64)[:, -1]
    return out


def interface_reflection(top, cosines, exit_bins, samples: int = 8192, seed: int = 0):
    """What the top interface ``top`` (2,) reflects at its first event, seen from outgoing ``cosines`` (A,): its
    albedo (A,) and that albedo split by exit direction, ``exit_bins(wi)`` (m, B) weights, (A, B). A smooth
    interface's delta reflection counts (Fresnel at each cosine, exit at the mirror direction), unlike
    :func:`top_albedo`'s, which is f's alone: this is the reference's first reflection at the top (what its
    ``below_top`` leaves out). Index-matched: nothing."""
    t = as_top(top, 1)
    c = np.atleast_1d(np.asarray(cosines, dtype=np.float64))
    wo = np.stack([np.sqrt(np.maximum(1 - c * c, 0)), np.zeros_like(c), c], axis=1)
    bins = np.asarray(exit_bins(wo))
    if not has_top(t)[0]:
        return np.zeros(len(c)), np.zeros((len(c), bins.shape[1]))
    if t[0, 0] < SMOOTH_ALPHA:
        f = fresnel_dielectric(c, np.full(len(c), t[0, 1]))
        mirror = wo * np.array([-1.0, -1.0, 1.0])
        return f, f[:, None] * np.asarray(exit_bins(mirror))
    wo = np.repeat(wo, samples, axis=0)
    u = np.random.default_rng(seed).random((len(wo), 2))
    s = _lobe(np.broadcast_to(t, (len(wo), 2))).sample(wo, np.zeros(len(wo)), u, check=False)
    w = s.weight[:, 0]
    split = (w[:, None] * np.asarray(exit_bins(s.wi))).reshape(len(c), samples, -1).mean(axis=1)
    return w.reshape(len(c), samples).mean(axis=1), split


def top_albedo(top, cosines, samples: int = 8192, seed: int = 0) -> np.ndarray:
    """(A,) directional albedo of one top lobe ``top`` (2,) at outgoing ``cosines`` (A,), by its own
    importance samples (weight F G2 / G1 per sample)."""
    t = as_top(top, 1)
    c = np.atleast_1d(np.asarray(cosines, dtype=np.float64))
    if not has_top(t)[0] or t[0, 0] < SMOOTH_ALPHA:
        return np.zeros(len(c))
    wo = np.repeat(np.stack([np.sqrt(np.maximum(1 - c * c, 0)), np.zeros_like(c), c], axis=1), samples, axis=0)
    u = np.random.default_rng(seed).random((len(wo), 2))
    s = _lobe(np.broadcast_to(t, (len(wo), 2))).sample(wo, np.zeros(len(wo)), u, check=False)
    return s.weight[:, 0].reshape(len(c), samples).mean(axis=1)

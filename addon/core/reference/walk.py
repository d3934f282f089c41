"""The position-free random walk through a layer stack (Guo et al. 2018), vectorised.

Geometry of the model (all in the local frame, normal +z, light and viewer above):

- coatings are numbered bottom to top ``0 .. C-1``; coating ``j`` is a rough dielectric
  *interface j* over *slab j*, a homogeneous medium of refractive index ``n_j = ior_j``,
  optical thickness ``tau_j`` (extinction 1 per unit depth), single-scattering albedo
  ``a_j`` (RGB) and a Henyey-Greenstein phase of asymmetry ``g_j``;
- above the top interface is air: "slab C" with ``n_C = 1`` and no medium;
- interface ``j`` separates slab ``j`` (below) from slab ``j + 1`` (above): its relative
  index, the ``ior`` of :class:`~addon.core.bsdf.RoughDielectric`, is ``n_j / n_{j+1}``;
- the base lies at the floor of slab 0, inside the medium of index ``n_0`` (1 without
  coatings). **Convention:** the base's parameters are relative to vacuum (as measured
  optical constants are) and the walk applies them relative to the medium around the base:
  a conductor uses ``(eta + i k) / n_0``, a dielectric base ``ior / n_0``. A Lambertian base
  has no index. (pbrt-v4 and Guo et al. use the base as given; for a conductor under a
  lacquer the two differ, and ours is the physical one.)

A walk starts above the top interface travelling along ``-wo``. Each iteration is one event:
a free flight in the current slab (the depth is sampled with the exponential distribution
of extinction 1 along ``|w.z|``; absorbing-only slabs attenuate deterministically) that ends
either in a medium scattering (throughput times the RGB albedo, new direction from the phase
function) or at a boundary, where the interface or base BSDF is sampled in RADIANCE mode.
The steps are the methods of :class:`_RandomWalk`: ``free_flight``, ``medium_events``,
``surface_event`` and, with NEE, ``connect`` (with the MIS weights ``_splits_above`` /
``_splits_below``); the light chains are :class:`Chains`.
A walk ends when it crosses the top interface upward, when a sample fails, or by Russian
roulette (after ``RR_START`` events, a walk whose throughput of basic radiance, beta n^2 in a
slab of index n, is below 1/4 survives with that probability and carries the lost weight;
the throughput is taken relative to the probability of the walk's forced entry through a smooth
top, 1 - F(wo), a factor of everything the walk brings: at a grazing wo it is 4e-4, and roulette
on the absolute throughput ended nearly every walk there): unbiased, and no walk is cut at a
fixed depth. A white, non-absorbing medium keeps beta n^2 = 1, so such walks run until they
leave the stack (tens of thousands of events in the thickest coats); ``MAX_DEPTH`` is a safety
cap far beyond any walk measured at the thickest valid coat, and a walk it cuts raises a ``RuntimeWarning``.

**Estimator of f(wi, wo)** (``nee=True``): unidirectional with next-event estimation and MIS,
as pbrt-v4's ``LayeredBxDF``, generalised to any number of coatings:

- before the walk, a *chain* of directions is sampled from ``wi`` downward through every
  interface, in IMPORTANCE mode, by transmission: ``d_C = -wi``, and ``d_k`` is sampled from
  interface ``k`` given ``-d_{k+1}`` (a smooth interface is forced to refract, weighted by
  its transmittance). Its weight is ``W_k = W_{k+1} Tr(slab k+1 along d_{k+1}) weight_k``.
  The chain is a light subpath whose vertices are the rough interfaces it crosses.
- every non-delta vertex of the walk (medium scattering in slab s, or a surface at the floor
  of slab s: the base is the floor of slab 0, interface k of slab k + 1) connects to the
  chain direction ``d_s``: ``beta f(-d_s, -w) Tr(to the top of slab s) W_s`` (for a medium
  vertex ``beta a p(-d_s, -w) Tr W_s / |d_s.z|``, as pbrt).
- A light path ends with a *straight run*: a vertex v, then straight up through interfaces,
  the rough ones x_1 .. x_R being vertices (transmission), then out along wi. Every split of
  that run between walk and chain makes it: the connection at v (chain through x_1..x_R),
  at x_1 (the walk sampled v -> x_1), ..., at x_R (the walk sampled everything; the chain is
  just wi: pbrt's "exit" strategy). They are combined with the power heuristic over **all**
  splits, computed from the same densities in every place: for each segment, the walk's
  density ``r`` (RADIANCE, sampled at its lower end) and the chain's ``q`` (IMPORTANCE,
  sampled at its upper end), both per unit ``n^2 |cos| d(omega)`` so that they compare across
  smooth refractions (etendue). The walk carries ``A = sum over lower splits of
  (p_u / p_t)^2`` along its run, the chain ``B`` for the splits above; the weight is
  ``1 / (1 + A + B)``. With one rough interface this is pbrt's two-strategy MIS with the
  *matching* density ``pdf_exit(d | wi, IMPORTANCE)`` (pbrt weighs the exit strategy with the
  reverse density ``pdf_exit(wi | -w)``, which biases rough coats by 2.5-10%).
  A run starts at every non-delta vertex (in any direction) and goes on through delta events,
  reflections included, to the next non-delta vertex: the light that delta events carry between a
  vertex and the first rough interface above it is also joined at the vertex in closed form (the
  three routes below), so the connection at that interface, where the run reaches it from below,
  gets the split weights of the run. A path the chain cannot make (before the walk's first
  non-delta vertex) gets its splits from the first rough vertex on.
- a medium vertex also receives the light that delta events bring back to it after the chain
  brought it into the vertex's slab: reflected up by a delta floor (a smooth base, a smooth interface
  and what lies below it) and back and forth between that and the smooth interfaces above, up to the
  first rough one (``_RandomWalk._delta_routes``). Under smooth interfaces only no split of the walk
  makes these paths (weight 1): without them a milky smooth coat over a smooth gold base evaluated
  6-24% dark (by channel) against the analog walk. Under a rough interface the walk makes them too,
  by connecting at it, but that connection evaluates the interface's transmission at a direction the
  phase function chose: under a glossy top (alpha 0.002) it almost never scored and the coat read
  6-26% dark (by channel) with tight error bars, so the two are weighted with the power heuristic.
- a rough interface vertex also receives the light that the chain brings through that interface into
  the slab under it and a delta floor reflects back up to it (``_RandomWalk._floor_routes``), against
  the walk's connection at the interface after the vertex sampled the way down: for a glossy
  interface both are lobes a few thousandths of a radian wide, each evaluated at a direction the other
  chose, and with the two each lobe's peak is sampled by its own strategy.
- the chain's weight also holds the light that smooth interfaces reflect back and forth before it
  passes them, between each pair of smooth interfaces up to the first rough one
  (``_RandomWalk._entry_reflections``); without it, three smooth coats under a dense top (ior 1.95)
  evaluated 1.1% dark, and a rough coat under two smooth ones 12% dark.
- still missing: a strategy for a path that reflects at a rough interface between the chain's entry
  and a vertex (the chain only transmits). Under a glossy interface such paths, which pass it three
  times or reflect inside it before reaching a medium vertex, are made only by connections that
  evaluate its narrow lobe: heavy-tailed (docs/reference.md, Not done).

The per-walk estimate is the sum of the connections; ``f`` is its mean over walks and the
standard error is the sample standard deviation over walks / sqrt(walks).

**Analog walk** (``nee=False``): no connections; a walk that crosses the top interface
upward is a sample ``wi = w`` with weight ``beta`` (its expectation is
``f(wi, wo) cos(wi) / pdf``), with a flag telling whether every event was a delta event.
"""

from __future__ import annotations

import warnings
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np

from ..bsdf import (
    IMPORTANCE,
    RADIANCE,
    SMOOTH_ALPHA,
    HenyeyGreenstein,
    Lambertian,
    RoughConductor,
    RoughDielectric,
)
from ..bsdf.dielectric import is_smooth
from ..bsdf.fresnel import fresnel_conductor, fresnel_dielectric
from ..stack import BASE_KINDS, StackArrays, validate
from ..xp import Rng, namespace

# Safety cap on events per walk, never reached in practice. Over a white base under a smooth
# coat of thickness 100 (the valid maximum), the longest of 1000 walks took 57 000 events (ior
# 1.5, g 0; 0.1% still inside at 50 000, decaying as exp(-n / 12 000)) and the longest of 100
# took 290 000 (ior 4, g -0.99, the slowest corner of the valid range; 2% still inside at
# 100 000, decaying as exp(-n / 95 000)): extrapolated, about 1e-11 of the energy reaches this
# cap there (docs/reference_furnace.md). Walks still alive here are cut with a RuntimeWarning.
MAX_DEPTH = 1 << 21
RR_START = 3
CHUNK_WALKS = 1 << 17
_JUST_BELOW_ONE = float(np.nextafter(1.0, 0.0))
# The density of the chain's sample used in the MIS weight of the walk's own splits:
# "matching" (the chain's own density, unbiased) or "pbrt_reverse" (pbrt-v4's exit.PDF(-w, wi),
# which biases rough coats; an ablation for the tests and the benchmark only).
EXIT_DENSITY = "matching"

_DIFFUSE, _CONDUCTOR, _DIELECTRIC = (BASE_KINDS.index(k) for k in ("Diffuse", "Conductor", "Dielectric"))


# ------------------------------------------------------------------------------------ layers


@dataclass
class Layers:
    """Per-stack (row) arrays the walk gathers from; built once by :meth:`from_arrays`."""

    C: int
    n: np.ndarray  # (P, C+1) refractive index of slab j; n[:, C] = 1 (air)
    eta: np.ndarray  # (P, C) relative index of interface j: n_j / n_{j+1}
    alpha: np.ndarray  # (P, C)
    tau: np.ndarray  # (P, C+1) optical thickness; tau[:, C] = 0
    albedo: np.ndarray  # (P, C, 3)
    g: np.ndarray  # (P, C)
    scatter: np.ndarray  # (P, C+1) bool: slab has a scattering medium
    smooth: np.ndarray  # (P, C) bool: interface j is a delta interface
    base_kind: np.ndarray  # (P,)
    base_albedo: np.ndarray  # (P, 3)
    base_alpha: np.ndarray  # (P,)
    base_eta: np.ndarray  # (P, 3) relative to n_0
    base_k: np.ndarray  # (P, 3) relative to n_0
    base_ior: np.ndarray  # (P,) relative to n_0
    xp: object = np  # the array namespace of the fields

    @classmethod
    def from_arrays(cls, sa: StackArrays) -> "Layers":
        validate(sa)
        P, C = len(sa), sa.n_coatings
        n = np.ones((P, C + 1))
        n[:, :C] = sa.coat_ior
        eta = n[:, :C] / n[:, 1:]
        alpha = np.asarray(sa.coat_roughness, dtype=np.float64)
        tau = np.zeros((P, C + 1))
        tau[:, :C] = sa.coat_thickness
        albedo = np.asarray(sa.coat_albedo, dtype=np.float64).reshape(P, C, 3)
        scatter = np.zeros((P, C + 1), dtype=bool)
        scatter[:, :C] = (tau[:, :C] > 0.0) & (albedo.max(axis=2, initial=0.0) > 0.0)
        # RoughDielectric's own rule (``is_smooth``): an interface index-matched within INDEX_MATCHED_TOL is a delta
        # transmission too. With ``eta == 1.0`` exactly here, an interface within the tolerance but not at 1 (a coat
        # of float32 1.45 under one of 1.45) was rough to the walk and delta to the BSDF: its MIS weights no longer
        # summed to one (eval 1-9% low, 44% at a near-mirror pair over gold).
        smooth = is_smooth(alpha, eta)
        n0 = n[:, 0]
        return cls(
            C=C,
            n=n,
            eta=eta,
            alpha=alpha,
            tau=tau,
            albedo=albedo,
            g=np.asarray(sa.coat_g, dtype=np.float64),
            scatter=scatter,
            smooth=smooth,
            base_kind=np.asarray(sa.base_kind, dtype=np.int64),
            base_albedo=np.asarray(sa.base_albedo, dtype=np.float64),
            base_alpha=np.asarray(sa.base_roughness, dtype=np.float64),
            base_eta=np.asarray(sa.base_eta, dtype=np.float64) / n0[:, None],
            base_k=np.asarray(sa.base_k, dtype=np.float64) / n0[:, None],
            base_ior=np.asarray(sa.base_ior, dtype=np.float64) / n0,
        )

    def to(self, xp) -> "Layers":
        """The same layers with every array in the namespace ``xp`` (itself if already there)."""
        if xp is self.xp:
            return self
        fields = {k: (v if k == "C" else xp.asarray(v)) for k, v in self.__dict__.items() if k != "xp"}
        return Layers(**fields, xp=xp)


def _base_bsdf(lay: Layers, kind: int, pr):
    if kind == _DIFFUSE:
        return Lambertian(lay.base_albedo[pr])
    if kind == _CONDUCTOR:
        return RoughConductor(lay.base_alpha[pr], lay.base_eta[pr], lay.base_k[pr])
    return RoughDielectric(lay.base_alpha[pr], lay.base_ior[pr], reflection_only=True)


def _base_smooth(lay: Layers, pr):
    kind = lay.base_kind[pr]
    return (kind != _DIFFUSE) & (
        (lay.base_alpha[pr] < SMOOTH_ALPHA) | ((kind == _DIELECTRIC) & is_smooth(lay.base_alpha[pr], lay.base_ior[pr]))
    )


def _delta_below(lay: Layers, pr, slab, cos):
    """The delta reflectance (m, 3) of what lies below slab ``slab`` (m,) of stack rows ``pr``, for light travelling
    down in that slab at ``|cos|`` (m,): the light that comes back up into the slab by delta events alone (a
    smooth base's mirror reflection, a smooth interface's reflection, and through a smooth interface the delta
    reflectance of what lies below it, with the inter-reflections between the two and the extinction of the slab
    between, exp(-2 tau / |cos|) per round trip). A rough surface or a medium scattering on the way is a vertex of
    the walk, not a delta event: that light is not part of it."""
    xp = lay.xp
    out = xp.zeros((pr.shape[0], 3))
    at_base = xp.flatnonzero((slab == 0) & _base_smooth(lay, pr))
    if at_base.shape[0]:
        p, c = pr[at_base], cos[at_base]
        conductor = lay.base_kind[p] == _CONDUCTOR
        r_cond = fresnel_conductor(c, lay.base_eta[p], lay.base_k[p])
        r_diel = fresnel_dielectric(c, lay.base_ior[p])[:, None]
        out[at_base] = xp.where(conductor[:, None], r_cond, r_diel)
    inside = xp.flatnonzero(slab > 0)
    if inside.shape[0]:
        inside = inside[lay.smooth[pr[inside], slab[inside] - 1]]
    if inside.shape[0] == 0:
        return out
    p, k, c = pr[inside], slab[inside] - 1, cos[inside]
    e = lay.eta[p, k]  # interface k, seen from slab k + 1 above it
    r = xp.repeat(fresnel_dielectric(c, e)[:, None], 3, axis=1)
    sin2_t = (1.0 - c * c) / (e * e)
    cos_t = xp.sqrt(xp.clip(1.0 - sin2_t, 0.0, 1.0))
    through = xp.flatnonzero(sin2_t < 1.0)  # the rest is total internal reflection: r = 1
    if through.shape[0]:
        pt, kt, ct = p[through], k[through], cos_t[through]
        r[through] = _with_beyond(r[through], _delta_below(lay, pt, kt, ct) * _tr(2.0 * lay.tau[pt, kt], ct)[:, None])
    out[inside] = r
    return out


def _delta_above(lay: Layers, pr, slab, cos):
    """The delta reflectance (m, 3) of the smooth interfaces above slab ``slab`` (m,) of stack rows ``pr`` for light
    travelling up in that slab at ``|cos|`` (m,): interface ``slab`` from below, and through it the delta reflectance
    of what lies above it, with the inter-reflections between the two and the extinction of the slab between (as
    :func:`_delta_below`, upward), up to the first rough interface: a rough interface reflects nothing by delta
    events (its light is a vertex of the walk), so it and everything above it count 0."""
    xp = lay.xp
    p, c = pr, cos
    e = 1.0 / lay.eta[p, slab]  # interface ``slab``, seen from below: n_{slab + 1} / n_slab
    smooth = lay.smooth[p, slab]
    r = xp.repeat(xp.where(smooth, fresnel_dielectric(c, e), 0.0)[:, None], 3, axis=1)
    sin2_t = (1.0 - c * c) / (e * e)
    # into a slab with a smooth interface above it
    through = xp.flatnonzero(smooth & (sin2_t < 1.0) & (slab + 1 < lay.C))
    if through.shape[0]:
        through = through[lay.smooth[p[through], slab[through] + 1]]
    if through.shape[0]:
        pt, st = p[through], slab[through] + 1
        ct = xp.sqrt(xp.clip(1.0 - sin2_t[through], 0.0, 1.0))
        r[through] = _with_beyond(r[through], _delta_above(lay, pt, st, ct) * _tr(2.0 * lay.tau[pt, st], ct)[:, None])
    return r


def _delta_floors(lay: Layers):
    """(P, C + 1) bool: what lies below slab s (the base for s = 0, else interface s - 1 and what lies below it) may
    reflect light back up by delta events alone, where :func:`_delta_below` is not 0: a smooth base, or a smooth
    interface that reflects (its relative index is not exactly 1) or lets the light through to such a floor."""
    xp = lay.xp
    floors = [_base_smooth(lay, xp.arange(lay.n.shape[0]))]
    for s in range(1, lay.C + 1):
        floors.append(lay.smooth[:, s - 1] & ((lay.eta[:, s - 1] != 1.0) | floors[-1]))
    return xp.stack(floors, axis=1)


def _with_beyond(r, beyond):
    """The delta reflectance of a smooth interface of reflectance ``r`` (m, 3) with ``beyond`` (m, 3) behind it: what
    lies past the interface reflects back, extinction of the slab between included, any number of times (the
    adding of two layers for delta events: the interface transmits 1 - r each way)."""
    xp = namespace(r, beyond)
    with xp.errstate(divide="ignore", invalid="ignore"):
        return r + (1.0 - r) ** 2 * beyond / (1.0 - r * beyond)


def _tr(tau, cos):
    xp = namespace(tau, cos)
    with xp.errstate(divide="ignore", over="ignore"):
        return xp.where(tau > 0.0, xp.exp(-tau / xp.abs(cos)), 1.0)


# ------------------------------------------------------------------------------------ chain


@dataclass
class Chains:
    """Light chains sampled from incident directions down through every interface.

    Per chain and slab s (0..C), arrays of shape (m, C+1, ...) (or (m, M, C+1, ...) once
    :meth:`per_walk` has grouped the M chains of each walk):

    - ``direction`` (.., 3): d_s, pointing down into slab s (d_C = -wi);
    - ``weight`` (.., 3): W_s, 0 where the chain did not reach slab s;
    - ``density``: the chain's density of its segment in slab s, sampled at the first rough
      interface above it, per unit n^2 |cos| solid angle (comparable across smooth refractions);
    - ``splits_above``: the sum of squared density ratios of the connection splits above that
      interface (``B`` of the module docstring);
    - ``rough_above`` (bool): a rough interface lies above slab s.
    """

    direction: object
    weight: object
    density: object
    splits_above: object
    rough_above: object

    def per_walk(self, m: int, M: int) -> "Chains":
        """The chains of ``m * M`` rows grouped as (m walks, M incident directions)."""
        fields = {k: v.reshape((m, M) + tuple(v.shape[1:])) for k, v in self.__dict__.items()}
        return Chains(**fields)


def _sample_chain(lay: Layers, pr, wi, rng: Rng) -> Chains:
    """The light chain from ``wi`` (m, 3) for stack rows ``pr`` down through every interface
    (IMPORTANCE mode, transmission); see :class:`Chains`."""
    xp = lay.xp
    m, C = pr.shape[0], lay.C
    ch = Chains(
        direction=xp.zeros((m, C + 1, 3)),
        weight=xp.zeros((m, C + 1, 3)),
        density=xp.ones((m, C + 1)),
        splits_above=xp.zeros((m, C + 1)),
        rough_above=xp.zeros((m, C + 1), dtype=bool),
    )
    ch.direction[:, C] = -wi
    ch.weight[:, C] = 1.0
    for k in range(C - 1, -1, -1):
        # slab k inherits the first rough interface above slab k + 1 unless interface k is rough
        ch.density[:, k] = ch.density[:, k + 1]
        ch.splits_above[:, k] = ch.splits_above[:, k + 1]
        ch.rough_above[:, k] = ch.rough_above[:, k + 1]
        reached = xp.flatnonzero(xp.max(ch.weight[:, k + 1], axis=1) > 0.0)
        if reached.shape[0]:
            _chain_through_interface(lay, pr, k, reached, ch, rng)
    return ch


def _chain_through_interface(lay: Layers, pr, k: int, act, ch: Chains, rng: Rng) -> None:
    """Refract the chains ``act`` from slab k + 1 down through interface k into slab k."""
    xp = lay.xp
    p = pr[act]
    u = rng.random((act.shape[0], 3))
    # A smooth interface is forced to transmit (u_lobe just below 1 picks the refraction
    # unless it is total internal reflection), weighted by the probability of that event
    # (the delta sample's pdf), instead of killing the chain with probability F.
    smooth = lay.smooth[p, k]
    u[smooth, 0] = _JUST_BELOW_ONE
    up = -ch.direction[act, k + 1]
    iface = RoughDielectric(lay.alpha[p, k], lay.eta[p, k])
    bs = iface.sample(up, u[:, 0], u[:, 1:], IMPORTANCE, check=False)
    ok = bs.valid & bs.transmission & (bs.wi[:, 2] < 0.0)
    weight = bs.weight * xp.where(smooth & bs.delta, bs.pdf, 1.0)[:, None]
    ch.direction[act, k] = xp.where(ok[:, None], bs.wi, 0.0)
    tr = _tr(lay.tau[p, k + 1], ch.direction[act, k + 1, 2])
    ch.weight[act, k] = xp.where(ok[:, None], ch.weight[act, k + 1] * tr[:, None] * weight, 0.0)
    rough = xp.flatnonzero(ok & ~smooth)
    if rough.shape[0] == 0:
        return
    # interface k is the first rough one above slab k: the densities of the segment below it
    a, pa = act[rough], p[rough]
    dk, dup = ch.direction[a, k], ch.direction[a, k + 1]
    q = bs.pdf[rough] / (lay.n[pa, k] ** 2 * xp.abs(dk[:, 2]))
    # the walk's density of the segment above this interface (arriving along -d_k)
    rw = iface.take(rough).pdf(-dup, dk, RADIANCE, check=False) / (lay.n[pa, k + 1] ** 2 * xp.abs(dup[:, 2]))
    above = ch.rough_above[a, k + 1]
    with xp.errstate(divide="ignore", invalid="ignore"):
        ratio = xp.where(above, (rw / ch.density[a, k + 1]) ** 2 * (1.0 + ch.splits_above[a, k + 1]), 0.0)
    ch.density[a, k] = q
    ch.splits_above[a, k] = xp.where(xp.isfinite(ratio), ratio, xp.inf)
    ch.rough_above[a, k] = True


# ------------------------------------------------------------------------------------ walk


class _Walks:
    """The live walks (one row each), compacted after every event.

    ``walk``: the walk's index in the output; ``row``: its stack row; ``slab``: the slab it is in
    (C: above the top interface); ``height``: its optical height above the slab's floor;
    ``direction``: its direction of travel; ``throughput``: beta (RGB). For the MIS weights of
    the straight upward run that may end the path (see the module docstring):
    ``straight_run`` (only delta events since the last non-delta vertex: its light may be joined there in closed
    form, so a connection where the run reaches a rough interface from below has the run's split weights),
    ``run_density`` (the walk's density ``r`` of its current segment, sampled at its lower end)
    and ``run_splits`` (``A``: the sum of squared density ratios of the splits below).
    ``any_nondelta``: some event of the walk was not a delta event.
    """

    FIELDS = (
        "walk",
        "row",
        "slab",
        "height",
        "direction",
        "throughput",
        "run_splits",
        "run_density",
        "straight_run",
        "any_nondelta",
        "entry",
    )

    def __init__(self, **fields):
        for k, v in fields.items():
            setattr(self, k, v)

    def __len__(self) -> int:
        return self.walk.shape[0]

    def keep(self, mask) -> None:
        for f in self.FIELDS:
            setattr(self, f, getattr(self, f)[mask])


class _PhaseVertex:
    """Medium-scattering vertices, as the connection sees them: f = p (the phase function),
    and the same as density in either mode."""

    in_medium = True

    def __init__(self, phase: HenyeyGreenstein):
        self.phase = phase

    def f(self, a, wi, wo):
        return self.phase.take(a).eval(wi, wo, check=False)

    def pdf(self, a, wi, wo, mode):
        return self.phase.take(a).eval(wi, wo, check=False)


class _SurfaceVertex:
    """Non-delta surface vertices (rough interface or base), as the connection sees them."""

    in_medium = False

    def __init__(self, bsdf):
        self.bsdf = bsdf

    def f(self, a, wi, wo):
        return self.bsdf.take(a).eval(wi, wo, RADIANCE, check=False)

    def pdf(self, a, wi, wo, mode):
        return self.bsdf.take(a).pdf(wi, wo, mode, check=False)


@dataclass
class _Surface:
    """Walks hitting one kind of surface in this event: ``rows`` (into the live walks), the
    surface's ``bsdf`` per row, whether it is ``smooth`` (a delta BSDF), ``from_below`` (an
    interface hit from below), ``interface`` (its index k per row; None for the base) and
    ``chain_slab``: the slab above the surface, whose chain direction a connection uses."""

    rows: object
    bsdf: object
    smooth: object
    from_below: object
    interface: object
    chain_slab: object


@dataclass
class _Link:
    """Connections of one ``connect`` call, one per (vertex, incident direction) whose chain
    reached the vertex's slab: ``a`` the vertex (index into the call's rows), ``rows`` its live
    walk, ``walk`` and ``chain`` where the estimate goes, ``slab`` the chain's slab and ``d``
    its direction there (pointing down)."""

    a: object
    rows: object
    walk: object
    chain: object
    slab: object
    d: object

    def take(self, idx) -> "_Link":
        return _Link(**{k: v[idx] for k, v in self.__dict__.items()})


class _RandomWalk:
    """One batch of walks through the layers: the event loop of :func:`run_walks`."""

    def __init__(self, lay: Layers, pr, wo, wi, rng: Rng, nee: bool):
        xp = self.xp = lay.xp
        self.lay, self.rng, self.nee = lay, rng, nee
        m, C = pr.shape[0], lay.C
        self.C = C
        self.M = 1 if wi is None else wi.shape[1]
        self.estimate = xp.zeros((m, self.M, 3))
        self.exit_direction = xp.zeros((m, 3))
        self.exit_direction[:, 2] = 1.0
        self.exit_weight = xp.zeros((m, 3))
        self.exit_specular = xp.zeros(m, dtype=bool)
        self.exit_first = xp.zeros(m, dtype=bool)  # left at the first event (reflected by the top interface)
        self.depth = 0
        if nee:
            self.delta_floor = _delta_floors(lay)
            self.chains = _sample_chain(lay, xp.repeat(pr, self.M), wi.reshape(-1, 3), rng).per_walk(m, self.M)
        self.walks = _Walks(
            walk=xp.arange(m),
            row=xp.copy(pr),
            slab=xp.full(m, C),
            height=xp.zeros(m),
            direction=-xp.copy(wo),
            throughput=xp.ones((m, 3)),
            run_splits=xp.zeros(m),
            run_density=xp.ones(m),
            straight_run=xp.zeros(m, dtype=bool),
            any_nondelta=xp.zeros(m, dtype=bool),
            entry=xp.ones(m),
        )
        # a walk must see the stack from above
        self.walks.keep(wo[:, 2] > 0.0)

    def run(self, alive_per_event: list | None = None, step=None):
        """The event loop: after the first events Russian roulette, then a free flight that
        ends in a medium or a surface event, until every walk has left the stack or ended.
        ``step()`` (optional) is called before each event; it stops the walks by raising."""
        xp = self.xp
        for depth in range(MAX_DEPTH):
            self.depth = depth
            if len(self.walks) == 0:
                break
            if step is not None:
                step()
            if depth > RR_START:
                self.roulette()
                if len(self.walks) == 0:
                    break
            scattered, upward = self.free_flight()
            dead = xp.zeros(len(self.walks), dtype=bool)
            self.medium_events(xp.flatnonzero(scattered), dead)
            self.surface_events(~scattered, upward, dead)
            self.walks.keep(~dead)
            if alive_per_event is not None:
                alive_per_event.append(len(self.walks))
        if len(self.walks):
            self._warn_cut()
        if self.nee:
            return self.estimate
        return self.exit_direction, self.exit_weight, self.exit_specular

    def _warn_cut(self) -> None:
        """Walks still inside at the safety cap are cut: say so, it biases the estimate."""
        lost = float(self.xp.max(self.walks.throughput))
        warnings.warn(
            f"{len(self.walks)} reference walks were still inside the stack after MAX_DEPTH = {MAX_DEPTH} events "
            f"and were cut (throughput up to {lost:.3g} lost): the estimate is biased low; no valid stack is known "
            "to need that many",
            RuntimeWarning,
            stacklevel=4,
        )

    def roulette(self) -> None:
        """Russian roulette: a walk of low throughput ends with probability 1 - max(beta n^2),
        the survivors carry the lost weight (pbrt's rule on the throughput of basic radiance
        L / n^2, which refraction conserves: entering a dense coat, 1 / n^2 is no loss)."""
        xp, lay, w = self.xp, self.lay, self.walks
        bmax = xp.max(w.throughput, axis=1) * lay.n[w.row, w.slab] ** 2 / w.entry
        q = xp.where(bmax < 0.25, xp.maximum(0.0, 1.0 - bmax), 0.0)
        u = self.rng.random(bmax.shape[0])
        alive = u >= q
        w.throughput /= xp.where(alive, 1.0 - q, 1.0)[:, None]
        w.keep(alive & (bmax > 0.0))

    def free_flight(self):
        """Fly through the current slab: a scattering medium stops the walk at an
        exponentially distributed optical depth (extinction 1 along |cos|) unless it reaches a
        boundary first; an absorbing-only slab attenuates the throughput all the way across.
        Returns (scattered in the medium, travelling upward), per live walk."""
        xp, lay, w = self.xp, self.lay, self.walks
        inside = w.slab < self.C
        up = w.direction[:, 2] > 0.0
        tau = lay.tau[w.row, w.slab]
        scattered = xp.zeros(len(w), dtype=bool)
        in_medium = xp.flatnonzero(inside & lay.scatter[w.row, w.slab])
        if in_medium.shape[0]:
            wz = xp.abs(w.direction[in_medium, 2])
            dist = -xp.log1p(-self.rng.random(in_medium.shape[0])) * wz
            zp = w.height[in_medium] + xp.where(up[in_medium], dist, -dist)
            hit = (zp > 0.0) & (zp < tau[in_medium])
            scattered[in_medium[hit]] = True
            w.height[in_medium[hit]] = zp[hit]
        absorbing = xp.flatnonzero(inside & ~lay.scatter[w.row, w.slab] & (tau > 0.0))
        if absorbing.shape[0]:
            dist = xp.where(up[absorbing], tau[absorbing] - w.height[absorbing], w.height[absorbing])
            w.throughput[absorbing] *= _tr(dist, w.direction[absorbing, 2])[:, None]
        return scattered, up

    def medium_events(self, rows, dead) -> None:
        """Scatter in the medium: connect to the light, then the albedo scales the throughput
        and the phase function gives the new direction."""
        if rows.shape[0] == 0:
            return
        xp, lay, w = self.xp, self.lay, self.walks
        p, s = w.row[rows], w.slab[rows]
        phase = HenyeyGreenstein(lay.g[p, s])
        if self.nee:
            self.connect(rows, xp.copy(s), _PhaseVertex(phase), xp.zeros(rows.shape[0], dtype=bool))
        wnew, pdf = phase.sample(-w.direction[rows], self.rng.random((rows.shape[0], 2)), check=False)
        w.throughput[rows] *= lay.albedo[p, s]
        w.direction[rows] = wnew
        # a medium vertex starts a new run, sampled by the phase function (up, or down to a delta floor that may
        # send it up: ``_delta_routes`` is its split at the vertex)
        w.run_splits[rows] = 0.0
        w.run_density[rows] = pdf / (lay.n[p, s] ** 2 * xp.abs(wnew[:, 2]))
        w.straight_run[rows] = True
        w.any_nondelta[rows] = True
        dead[rows] = (wnew[:, 2] == 0.0) | ~(pdf > 0.0)

    def _surfaces(self, at_surface, upward) -> list[_Surface]:
        """The walks at a boundary this event, grouped by surface: interfaces, then each base kind."""
        xp, lay, w, C = self.xp, self.lay, self.walks, self.C
        groups = []
        at_interface = xp.flatnonzero(at_surface & ((upward & (w.slab < C)) | (~upward & (w.slab > 0))))
        if at_interface.shape[0]:
            p = w.row[at_interface]
            k = xp.where(upward, w.slab, w.slab - 1)[at_interface]
            groups.append(
                _Surface(
                    at_interface,
                    RoughDielectric(lay.alpha[p, k], lay.eta[p, k]),
                    lay.smooth[p, k],
                    upward[at_interface],
                    k,
                    k + 1,
                )
            )
        at_base = xp.flatnonzero(at_surface & ~upward & (w.slab == 0))
        for kind in range(len(BASE_KINDS)):
            rows = at_base[lay.base_kind[w.row[at_base]] == kind]
            if rows.shape[0]:
                p = w.row[rows]
                groups.append(
                    _Surface(
                        rows,
                        _base_bsdf(lay, kind, p),
                        _base_smooth(lay, p),
                        xp.zeros(rows.shape[0], dtype=bool),
                        None,
                        xp.zeros(rows.shape[0], dtype=xp.int64),
                    )
                )
        return groups

    def surface_events(self, at_surface, upward, dead) -> None:
        """Reflect or refract at the boundary the flight reached (an interface from either side,
        or the base); walks that leave through the top interface end there."""
        if not self.xp.any(at_surface):
            return
        for surface in self._surfaces(at_surface, upward):
            dead[surface.rows] = self.surface_event(surface, upward)
        self.exit(at_surface, dead)

    def surface_event(self, srf: _Surface, upward):
        """Connect to the light from a rough surface, then sample the surface's BSDF in
        RADIANCE mode for the new direction. Returns the rows whose sample failed."""
        xp, lay, w, C, rows = self.xp, self.lay, self.walks, self.C, srf.rows
        if self.nee:
            rough = xp.flatnonzero(~srf.smooth)
            if rough.shape[0]:
                self.connect(
                    rows[rough], srf.chain_slab[rough], _SurfaceVertex(srf.bsdf.take(rough)), srf.from_below[rough]
                )
        u = self.rng.random((rows.shape[0], 3))
        forced = xp.zeros(rows.shape[0], dtype=bool)
        if self.nee and srf.interface is not None:
            # f has no delta part: a smooth top interface hit from above (entering) must
            # transmit and one hit from below must reflect for the walk to contribute;
            # force that event and weight it by its probability (pbrt's
            # transmission-only / reflection-only sampling of the interfaces).
            forced = srf.smooth & (srf.interface == C - 1)
            u[forced, 0] = xp.where(upward[rows[forced]], 0.0, _JUST_BELOW_ONE)
        bs_wo = -w.direction[rows]
        bs = srf.bsdf.sample(bs_wo, u[:, 0], u[:, 1:], RADIANCE, check=False)
        wnew = bs.wi
        ok = bs.valid & (wnew[:, 2] != 0.0)
        w.throughput[rows] *= bs.weight * xp.where(forced & bs.delta, bs.pdf, 1.0)[:, None]
        # the forced entry's probability scales everything the walk brings: Russian roulette leaves it out
        w.entry[rows] *= xp.where(forced & bs.delta & ~srf.from_below, bs.pdf, 1.0)
        w.direction[rows] = wnew
        goes_up = wnew[:, 2] > 0.0
        if srf.interface is None:
            slab = xp.zeros(rows.shape[0], dtype=xp.int64)
        else:
            slab = xp.where(goes_up, srf.interface + 1, srf.interface)
        w.slab[rows] = slab
        w.height[rows] = xp.where(goes_up, 0.0, lay.tau[w.row[rows], xp.minimum(slab, C)])
        nondelta = ~bs.delta
        if self.nee:
            self.continue_run(srf, bs_wo, bs, slab, goes_up, nondelta)
        # a non-delta event starts a run (up: a straight run; down: to a delta floor, ``_floor_routes``), which goes
        # on through delta events: its split at that vertex is a closed form (``_delta_routes``, ``_floor_routes``,
        # ``_entry_reflections``) wherever it reaches a rough interface from below
        w.straight_run[rows] |= nondelta
        w.any_nondelta[rows] |= nondelta
        return ~ok

    def continue_run(self, srf: _Surface, bs_wo, bs, slab, goes_up, nondelta) -> None:
        """Bookkeeping of the straight upward run for the connection weights: a non-delta
        event restarts the run with the density ``r`` of its sample; a rough interface crossed
        upward on a straight run adds to ``A`` the split in which the chain made the segment
        below it."""
        xp, lay, w, rows = self.xp, self.lay, self.walks, srf.rows
        wnew = bs.wi
        p = w.row[rows]
        with xp.errstate(divide="ignore", invalid="ignore"):
            r_new = bs.pdf / (lay.n[p, slab] ** 2 * xp.abs(wnew[:, 2]))
        a_new = xp.zeros(rows.shape[0])
        cont = xp.flatnonzero(nondelta & srf.from_below & goes_up & w.straight_run[rows])
        if cont.shape[0]:
            w_in = -bs_wo[cont]
            q = srf.bsdf.take(cont).pdf(-w_in, wnew[cont], IMPORTANCE, check=False) / (
                lay.n[p[cont], srf.interface[cont]] ** 2 * xp.abs(w_in[:, 2])
            )
            with xp.errstate(divide="ignore", invalid="ignore", over="ignore"):
                a_new[cont] = (q / w.run_density[rows[cont]]) ** 2 * (1.0 + w.run_splits[rows[cont]])
        w.run_splits[rows] = xp.where(nondelta, xp.nan_to_num(a_new, nan=xp.inf), w.run_splits[rows])
        w.run_density[rows] = xp.where(nondelta, r_new, w.run_density[rows])

    # ---------------------------------------------------------------- connection

    def connect(self, rows, chain_slab, vertex, from_below) -> None:
        """Next-event estimation: join the vertices ``rows`` (live walks) to the light chains'
        directions in ``chain_slab`` (the slab above each vertex), one connection per incident
        direction, through the interfaces above (the chain's weight) with the MIS weight of
        every split of the path. ``from_below``: the vertex is a rough interface reached from
        below (on the connected path it transmits upward, continuing the walk's straight run)."""
        xp, lay, w = self.xp, self.lay, self.walks
        if not vertex.in_medium:
            self._floor_routes(rows, chain_slab, vertex)
        link, chain_weight = self._links(rows, chain_slab, xp.arange(rows.shape[0]))
        if link is None:
            return
        p = w.row[link.rows]
        w_in = w.direction[link.rows]
        dz = xp.abs(link.d[:, 2])
        self._entry_reflections(link, p, chain_weight)
        f = vertex.f(link.a, -link.d, -w_in)
        splits_above = self._splits_above(link, vertex, p, w_in, dz)
        splits_below = self._splits_below(link, vertex, p, w_in, from_below)
        with xp.errstate(invalid="ignore"):
            mis = 1.0 / (1.0 + xp.nan_to_num(splits_below, nan=xp.inf) + xp.nan_to_num(splits_above, nan=xp.inf))
        if vertex.in_medium:
            tr = _tr(lay.tau[p, link.slab] - w.height[link.rows], dz)
            c = w.throughput[link.rows] * lay.albedo[p, w.slab[link.rows]] * (f * tr / dz)[:, None] * chain_weight
            self._delta_routes(link, vertex, p, w_in, dz, f, chain_weight, mis)
        else:
            tr = _tr(lay.tau[p, link.slab], dz)
            c = w.throughput[link.rows] * f * tr[:, None] * chain_weight
        self.estimate[link.walk, link.chain] += c * mis[:, None]

    def _links(self, rows, chain_slab, vertices):
        """``(link, chain_weight)``: the :class:`_Link` of the vertices ``vertices`` (indices into ``rows``) to every
        chain's direction in their slab ``chain_slab[vertex]``, where the chain reached it, and the chain's weight
        there; ``(None, None)`` if none did."""
        xp, w, ch, M = self.xp, self.walks, self.chains, self.M
        vertex_of = xp.repeat(vertices, M)
        chain = xp.tile(xp.arange(M), vertices.shape[0])
        walk = w.walk[rows][vertex_of]
        slab = chain_slab[vertex_of]
        chain_weight = ch.weight[walk, chain, slab]
        sel = xp.flatnonzero(xp.max(chain_weight, axis=1) > 0.0)
        if sel.shape[0] == 0:
            return None, None
        a = vertex_of[sel]
        link = _Link(
            a=a, rows=rows[a], walk=walk[sel], chain=chain[sel], slab=slab[sel], d=ch.direction[walk, chain, slab][sel]
        )
        return link, chain_weight[sel]

    def _entry_reflections(self, link: "_Link", p, chain_weight) -> None:
        """The chain's weight into the vertex's slab with the light that smooth interfaces above reflect back and forth
        before it enters (in place). The chain refracts straight down through each; light that interface k reflects
        up goes back down from what lies above it up to the first rough interface (:func:`_delta_above`), so the light
        that passes interface k is 1 / (1 - R_k R_above(k + 1) T(2 tau_{k+1})) times the straight passage's, at the
        chain's direction in slab k + 1, wherever interfaces k and k + 1 are smooth, whatever lies between k and the
        vertex. Every split of a path below a rough interface under k carries the same factor. Where a rough interface
        lies above k, the walk makes these paths too (its run goes on through delta events to the rough interface,
        whose connection then has the split weights of the run), so the MIS weights hold every strategy. (Applied
        only under smooth interfaces all the way down to the vertex, three coats with a rough one under two smooth
        ones read 0.88 of the analog walk.)"""
        xp, lay, ch, C = self.xp, self.lay, self.chains, self.C
        for k in range(C - 1):  # interface k under slab k + 1, for the vertices in slab k or below
            at = xp.flatnonzero((link.slab <= k) & lay.smooth[p, k] & lay.smooth[p, k + 1])
            if at.shape[0] == 0:
                continue
            pk = p[at]
            c = xp.abs(ch.direction[link.walk[at], link.chain[at], k + 1][:, 2])
            r = fresnel_dielectric(c, lay.eta[pk, k])[:, None]
            back = r * _delta_above(lay, pk, xp.full(at.shape[0], k + 1), c) * _tr(2.0 * lay.tau[pk, k + 1], c)[:, None]
            with xp.errstate(divide="ignore", invalid="ignore"):
                chain_weight[at] = chain_weight[at] / (1.0 - back)

    def _delta_routes(self, link: "_Link", vertex, p, w_in, dz, f, chain_weight, mis) -> None:
        """The light that reaches a medium vertex by delta events after the chain brought it into the vertex's slab:
        reflected back up by what lies below (:func:`_delta_below`), and between that and the interfaces above (up to
        the first rough one), any number of times. With R_b the reflectance below, R_t the delta reflectance of what
        lies above from below (:func:`_delta_above`), T(x) the extinction over optical length x along the chain's
        direction in the slab and h the vertex's height above the floor of a slab of thickness tau, the light arrives
        travelling down with T(tau - h) / (1 - q) (the connection holds its first term) and travelling up with
        R_b T(tau + h) / (1 - q), q = R_b R_t T(2 tau); the chain's weight holds the light's passage into the slab
        (:meth:`_entry_reflections`).

        Under smooth interfaces only no other strategy makes these paths (after the vertex they hold no rough vertex
        to connect at), so they have weight 1. Under a rough interface the walk makes them too: the vertex samples
        the direction, delta events bring it to the first rough interface above, which connects (the walk's run goes
        on through delta events, :meth:`surface_event`). That connection evaluates the interface's transmission at a
        direction the phase function chose: where the interface is nearly smooth it almost never scores (a milky coat
        over a mirror under an alpha-0.002 top read 23% dark in red, with tight error bars). So both are weighted with
        the power heuristic over every split, as a straight run is: the terms arriving down share the connection's
        direction and weight ``mis``; the term arriving up has the split of the vertex sampling the mirrored one."""
        xp, lay, w = self.xp, self.lay, self.walks
        sel = xp.flatnonzero(self.delta_floor[p, link.slab])
        if sel.shape[0] == 0:
            return
        ps, slab, c = p[sel], link.slab[sel], dz[sel]
        below = _delta_below(lay, ps, slab, c)
        hit = xp.flatnonzero(xp.max(below, axis=1) > 0.0)
        if hit.shape[0] == 0:
            return
        sel, ps, slab, c, below = sel[hit], ps[hit], slab[hit], c[hit], below[hit]
        rows = link.rows[sel]
        tau, h = lay.tau[ps, slab], w.height[rows]
        r_top = _delta_above(lay, ps, slab, c)
        q = below * r_top * _tr(2.0 * tau, c)[:, None]
        d_up = link.d[sel] * xp.asarray([1.0, 1.0, -1.0])
        f_up = vertex.f(link.a[sel], -d_up, -w_in[sel])  # the phase function: its own density
        mis_up = self._route_weight(link.walk[sel], link.chain[sel], slab, f_up, ps, c)
        with xp.errstate(divide="ignore", invalid="ignore"):
            # arriving down: the terms after the connection's first
            down = (f[sel] * _tr(tau - h, c) * mis[sel])[:, None] * (q / (1.0 - q))
            up = (f_up * _tr(tau + h, c) * mis_up)[:, None] * below / (1.0 - q)
            add = w.throughput[rows] * lay.albedo[ps, slab] * (down + up) / c[:, None] * chain_weight[sel]
        self.estimate[link.walk[sel], link.chain[sel]] += xp.where(xp.isfinite(add), add, 0.0)

    def _floor_routes(self, rows, chain_slab, vertex) -> None:
        """The light that reaches a rough interface vertex from below by delta events: the chain brings it through the
        interface into the slab under it, whose floor reflects it back up by delta events (:func:`_delta_below`) to
        the vertex (transmitted up to a walk above it, reflected down to a walk below it). The walk makes these paths
        too: the vertex samples the direction down, delta events bring it back to the interface, which connects.
        Where the interface is nearly smooth both are lobes a few thousandths of a radian wide, each evaluated at a
        direction the other chose (a clear alpha-0.04 coat over a mirror read 16-40% dark by channel, with tight error
        bars at 300 000 walks, at a pair away from the mirror direction); weighted with the power heuristic, each
        lobe's peak is sampled by its own strategy. (The base has no floor: none.)"""
        xp, lay, w = self.xp, self.lay, self.walks
        floor = chain_slab - 1  # the slab under an interface vertex; -1 for the base
        vertices = xp.flatnonzero((floor >= 0) & self.delta_floor[w.row[rows], xp.maximum(floor, 0)])
        if vertices.shape[0] == 0:
            return
        link, chain_weight = self._links(rows, floor, vertices)
        if link is None:
            return
        p = w.row[link.rows]
        c = xp.abs(link.d[:, 2])
        below = _delta_below(lay, p, link.slab, c)
        hit = xp.flatnonzero(xp.max(below, axis=1) > 0.0)
        if hit.shape[0] == 0:
            return
        link, chain_weight, p, c, below = link.take(hit), chain_weight[hit], p[hit], c[hit], below[hit]
        self._entry_reflections(link, p, chain_weight)
        w_in = w.direction[link.rows]
        d_up = link.d * xp.asarray([1.0, 1.0, -1.0])
        f, pdf = vertex.bsdf.take(link.a).eval_pdf(-d_up, -w_in, RADIANCE, check=False)  # a grey interface
        mis = self._route_weight(link.walk, link.chain, link.slab, pdf, p, c)
        tr = _tr(2.0 * lay.tau[p, link.slab], c)
        with xp.errstate(invalid="ignore"):
            add = w.throughput[link.rows] * (f * tr * mis)[:, None] * below * chain_weight
        self.estimate[link.walk, link.chain] += xp.where(xp.isfinite(add), add, 0.0)

    def _route_weight(self, walk, chain, slab, pdf, p, cos):
        """The MIS weight 1 / (1 + B) of a closed-form route that brings the chain's light in slab ``slab`` to a vertex
        whose density of sampling the route's first direction is ``pdf`` (solid angle; ``cos`` its |cos|): ``B``
        (as :meth:`_splits_above`) holds the splits in which the walk made the route and connected at the first rough
        interface above, or further up; 1 where none lies above (no split of the walk makes the route)."""
        xp, lay, ch = self.xp, self.lay, self.chains
        at = (walk, chain, slab)
        with xp.errstate(divide="ignore", invalid="ignore", over="ignore"):
            r = pdf / (lay.n[p, slab] ** 2 * cos)
            b = xp.where(ch.rough_above[at], (r / ch.density[at]) ** 2 * (1.0 + ch.splits_above[at]), 0.0)
            return 1.0 / (1.0 + xp.nan_to_num(b, nan=xp.inf))

    def _splits_above(self, link: "_Link", vertex, p, w_in, dz):
        """``B``: the splits in which the chain's lower segments were made by the walk instead
        (the walk's density over the chain's, squared, at the first rough interface above)."""
        xp, lay, ch = self.xp, self.lay, self.chains
        out = xp.zeros(link.a.shape[0])
        hr = xp.flatnonzero(ch.rough_above[link.walk, link.chain, link.slab])
        if hr.shape[0]:
            d = link.d[hr]
            r = vertex.pdf(link.a[hr], -d, -w_in[hr], RADIANCE) / (lay.n[p[hr], link.slab[hr]] ** 2 * dz[hr])
            at = (link.walk[hr], link.chain[hr], link.slab[hr])
            with xp.errstate(divide="ignore", invalid="ignore"):
                out[hr] = (r / ch.density[at]) ** 2 * (1.0 + ch.splits_above[at])
        return out

    def _splits_below(self, link: "_Link", vertex, p, w_in, from_below):
        """``A``: the splits in which the chain made the walk's straight run below this vertex
        (the chain's density over the walk's, squared, for the segment below it)."""
        xp, lay, w = self.xp, self.lay, self.walks
        out = xp.zeros(link.a.shape[0])
        sx = xp.flatnonzero(from_below[link.a] & w.straight_run[link.rows])
        if sx.shape[0]:
            k = link.slab[sx] - 1
            if EXIT_DENSITY == "matching":
                q = vertex.pdf(link.a[sx], -w_in[sx], -link.d[sx], IMPORTANCE)
            else:  # pbrt-v4's reverse density: biased, kept only to measure the bias
                q = vertex.pdf(link.a[sx], -link.d[sx], -w_in[sx], RADIANCE)
            q = q / (lay.n[p[sx], k] ** 2 * xp.abs(w_in[sx, 2]))
            run = link.rows[sx]
            with xp.errstate(divide="ignore", invalid="ignore"):
                out[sx] = (q / w.run_density[run]) ** 2 * (1.0 + w.run_splits[run])
        return out

    # ---------------------------------------------------------------- exit

    def exit(self, at_surface, dead) -> None:
        """Walks above the top interface have left the stack: in the analog walk each is a
        sample (direction, weight, specular flag); with NEE their light was connected already."""
        w = self.walks
        exits = self.xp.flatnonzero(at_surface & ~dead & (w.slab == self.C))
        if exits.shape[0] == 0:
            return
        if not self.nee:
            wid = w.walk[exits]
            self.exit_direction[wid] = w.direction[exits]
            self.exit_weight[wid] = w.throughput[exits]
            self.exit_specular[wid] = ~w.any_nondelta[exits]
            self.exit_first[wid] = self.depth == 0
        dead[exits] = True


# The check the walks call before each event when their caller passes none (``run_walks``' ``step``): set by
# ``stopping`` on the thread that walks, so that a render's Esc or a decoder choice's stop is heard inside a
# reference estimate, however deep in the calls (a thick scattering coat's walks took minutes between two checks).
_STOP: ContextVar = ContextVar("walk_stop", default=None)


@contextmanager
def stopping(check):
    """Within the block, on this thread, the walks call ``check()`` (None: nothing) before each event; it stops
    them by raising."""
    token = _STOP.set(check)
    try:
        yield
    finally:
        _STOP.reset(token)


def run_walks(
    lay: Layers,
    pr,
    wo,
    wi,
    rng: Rng,
    nee: bool,
    alive_per_event: list | None = None,
    first_exits: list | None = None,
    step=None,
):
    """Walk ``len(pr)`` independent walks, walk ``r`` for stack row ``pr[r]`` seen from ``wo[r]``.

    With ``nee`` (``wi`` of shape (m, M, 3) given): returns the per-walk estimates of
    f(wi[r, j], wo[r]) (m, M, 3): one walk serves the M incident directions, each with its
    own chain.
    Without: returns ``(wi, weight, specular)`` of the analog walk (weight 0 for absorbed walks).
    Arrays (``lay``, ``pr``, ``wo``, ``wi``) are in the namespace ``lay.xp``; ``rng`` draws there.
    ``alive_per_event``: a list that receives the number of walks still inside after each event
    (for measuring walk lengths).
    ``first_exits`` (analog walk): a list that receives the (m,) flags of the walks that left at their first
    event: with coatings, those the top interface reflected, the paths of the exact top lobe.
    ``step()`` (optional) is called before each event; raising there stops the walks. Without one, the check
    ``stopping`` set on this thread is (a render's Esc, a decoder choice's).
    """
    walk = _RandomWalk(lay, pr, wo, wi, rng, nee)
    out = walk.run(alive_per_event, step if step is not None else _STOP.get())
    if first_exits is not None:
        first_exits.append(walk.exit_first & (walk.C > 0))
    return out

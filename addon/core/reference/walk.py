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
Crossing the top interface upward ends the walk. Russian roulette after 3 events keeps
walks of any length unbiased; ``MAX_DEPTH`` only bounds pathological walks.

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
  A delta reflection or a downward direction ends a run; a path the chain cannot make (the
  run starts after a delta event) gets its splits from the first rough vertex on.

The per-walk estimate is the sum of the connections; ``f`` is its mean over walks and the
standard error is the sample standard deviation over walks / sqrt(walks).

**Analog walk** (``nee=False``): no connections; a walk that crosses the top interface
upward is a sample ``wi = w`` with weight ``beta`` (its expectation is
``f(wi, wo) cos(wi) / pdf``), with a flag telling whether every event was a delta event.
"""

from __future__ import annotations

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
from ..stack import BASE_KINDS, VALID_RANGES, StackArrays
from ..xp import Rng, namespace

MAX_DEPTH = 256
RR_START = 3
CHUNK_WALKS = 1 << 17
_JUST_BELOW_ONE = float(np.nextafter(1.0, 0.0))
# The density of the chain's sample used in the MIS weight of the walk's own splits:
# "matching" (the chain's own density, unbiased) or "pbrt_reverse" (pbrt-v4's exit.PDF(-w, wi),
# which biases rough coats; an ablation for the tests and the benchmark only).
EXIT_DENSITY = "matching"

_DIFFUSE, _CONDUCTOR, _DIELECTRIC = (BASE_KINDS.index(k) for k in ("Diffuse", "Conductor", "Dielectric"))


# ------------------------------------------------------------------------------------ layers


def validate_arrays(sa: StackArrays) -> None:
    """Raise ValueError if any field of ``sa`` is malformed, not finite or outside VALID_RANGES."""
    if not isinstance(sa, StackArrays):
        raise ValueError(f"expected a Stack or StackArrays, got {type(sa).__name__}")
    n = len(sa)
    c = sa.n_coatings
    shapes = {
        "base_kind": (n,), "base_albedo": (n, 3), "base_roughness": (n,), "base_eta": (n, 3),
        "base_k": (n, 3), "base_ior": (n,), "coat_roughness": (n, c), "coat_ior": (n, c),
        "coat_albedo": (n, c, 3), "coat_thickness": (n, c), "coat_g": (n, c),
    }
    ranges = {
        "base_albedo": "albedo", "base_roughness": "roughness", "base_eta": "eta", "base_k": "k",
        "base_ior": "ior", "coat_roughness": "roughness", "coat_ior": "ior", "coat_albedo": "albedo",
        "coat_thickness": "thickness", "coat_g": "g",
    }
    for name, shape in shapes.items():
        a = np.asarray(getattr(sa, name))
        if a.shape != shape:
            raise ValueError(f"StackArrays.{name} must have shape {shape}, got {a.shape}")
    kind = np.asarray(sa.base_kind)
    if np.any((kind < 0) | (kind >= len(BASE_KINDS))):
        raise ValueError(f"StackArrays.base_kind must index {BASE_KINDS}, got values {np.unique(kind).tolist()}")
    for name, key in ranges.items():
        a = np.asarray(getattr(sa, name), dtype=np.float64)
        lo, hi = VALID_RANGES[key]
        bad = ~np.isfinite(a) | (a < lo) | (a > hi)
        if np.any(bad):
            where = tuple(int(i[0]) for i in np.nonzero(bad))
            raise ValueError(
                f"StackArrays.{name}{list(where)} = {a[where]!r} is outside the valid range [{lo}, {hi}]"
            )


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
        validate_arrays(sa)
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
        # RoughDielectric treats an index-matched interface as a delta transmission too.
        smooth = (alpha < SMOOTH_ALPHA) | (eta == 1.0)
        n0 = n[:, 0]
        return cls(
            C=C, n=n, eta=eta, alpha=alpha, tau=tau, albedo=albedo, g=np.asarray(sa.coat_g, dtype=np.float64),
            scatter=scatter, smooth=smooth,
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
        (lay.base_alpha[pr] < SMOOTH_ALPHA) | ((kind == _DIELECTRIC) & (lay.base_ior[pr] == 1.0))
    )


def _tr(tau, cos):
    xp = namespace(tau, cos)
    with xp.errstate(divide="ignore", over="ignore"):
        return xp.where(tau > 0.0, xp.exp(-tau / xp.abs(cos)), 1.0)


# ------------------------------------------------------------------------------------ chain


def _sample_chain(lay: Layers, pr, wi, rng: Rng):
    """The light chain from ``wi`` down through every interface (IMPORTANCE mode, transmission).

    Returns, per chain and slab s (0..C):
    ``D`` (m, C+1, 3) the direction d_s pointing down into slab s (d_C = -wi);
    ``W`` (m, C+1, 3) its weight (0 where the chain did not reach slab s);
    ``Q`` (m, C+1) the chain's density of the segment in slab s, sampled at the first rough
    interface above it, per unit n^2 |cos| solid angle (comparable across smooth refractions);
    ``B`` (m, C+1) the sum of squared density ratios of the connection splits above that
    interface (see :func:`run_walks`); ``HR`` (m, C+1) bool: a rough interface lies above slab s.
    """
    xp = lay.xp
    m, C = pr.shape[0], lay.C
    D = xp.zeros((m, C + 1, 3))
    W = xp.zeros((m, C + 1, 3))
    Q = xp.ones((m, C + 1))
    B = xp.zeros((m, C + 1))
    HR = xp.zeros((m, C + 1), dtype=bool)
    D[:, C] = -wi
    W[:, C] = 1.0
    for k in range(C - 1, -1, -1):
        # slab k inherits the first rough interface above slab k + 1 unless interface k is rough
        Q[:, k], B[:, k], HR[:, k] = Q[:, k + 1], B[:, k + 1], HR[:, k + 1]
        act = xp.flatnonzero(xp.max(W[:, k + 1], axis=1) > 0.0)
        if act.shape[0] == 0:
            continue
        p = pr[act]
        u = rng.random((act.shape[0], 3))
        # A smooth interface is forced to transmit (u_lobe just below 1 picks the refraction
        # unless it is total internal reflection), weighted by the probability of that event
        # (the delta sample's pdf), instead of killing the chain with probability F.
        smooth = lay.smooth[p, k]
        u[smooth, 0] = _JUST_BELOW_ONE
        up = -D[act, k + 1]
        iface = RoughDielectric(lay.alpha[p, k], lay.eta[p, k])
        bs = iface.sample(up, u[:, 0], u[:, 1:], IMPORTANCE, check=False)
        ok = bs.valid & bs.transmission & (bs.wi[:, 2] < 0.0)
        weight = bs.weight * xp.where(smooth & bs.delta, bs.pdf, 1.0)[:, None]
        D[act, k] = xp.where(ok[:, None], bs.wi, 0.0)
        tr = _tr(lay.tau[p, k + 1], D[act, k + 1, 2])
        W[act, k] = xp.where(ok[:, None], W[act, k + 1] * tr[:, None] * weight, 0.0)
        r_ = xp.flatnonzero(ok & ~smooth)
        if r_.shape[0]:
            a, pa = act[r_], p[r_]
            dk, dup = D[a, k], D[a, k + 1]
            q = bs.pdf[r_] / (lay.n[pa, k] ** 2 * xp.abs(dk[:, 2]))
            # the walk's density of the segment above this interface (arriving along -d_k)
            rw = iface.take(r_).pdf(-dup, dk, RADIANCE, check=False) / (lay.n[pa, k + 1] ** 2 * xp.abs(dup[:, 2]))
            above = HR[a, k + 1]
            with xp.errstate(divide="ignore", invalid="ignore"):
                ratio = xp.where(above, (rw / Q[a, k + 1]) ** 2 * (1.0 + B[a, k + 1]), 0.0)
            Q[a, k] = q
            B[a, k] = xp.where(xp.isfinite(ratio), ratio, xp.inf)
            HR[a, k] = True
    return D, W, Q, B, HR


# ------------------------------------------------------------------------------------ walk


class _State:
    """Live walks, compacted every event."""

    FIELDS = ("wid", "pr", "s", "z", "w", "beta", "run_a", "run_r", "straight", "nondelta")

    def __init__(self, **kw):
        for k, v in kw.items():
            setattr(self, k, v)

    def keep(self, mask) -> None:
        for f in self.FIELDS:
            setattr(self, f, getattr(self, f)[mask])


def run_walks(lay: Layers, pr, wo, wi, rng: Rng, nee: bool):
    """Walk ``len(pr)`` independent walks, walk ``r`` for stack row ``pr[r]`` seen from ``wo[r]``.

    With ``nee`` (``wi`` of shape (m, M, 3) given): returns the per-walk estimates of
    f(wi[r, j], wo[r]) (m, M, 3): one walk serves the M incident directions, each with its
    own chain.
    Without: returns ``(wi, weight, specular)`` of the analog walk (weight 0 for absorbed walks).
    Arrays (``lay``, ``pr``, ``wo``, ``wi``) are in the namespace ``lay.xp``; ``rng`` draws there.
    """
    xp = lay.xp
    m, C = pr.shape[0], lay.C
    M = 1 if wi is None else wi.shape[1]
    acc = xp.zeros((m, M, 3))
    out_wi = xp.zeros((m, 3))
    out_wi[:, 2] = 1.0
    out_w = xp.zeros((m, 3))
    out_spec = xp.zeros(m, dtype=bool)
    if nee:
        D, W, Q, Bc, HR = _sample_chain(lay, xp.repeat(pr, M), wi.reshape(-1, 3), rng)
        D = D.reshape(m, M, C + 1, 3)
        W = W.reshape(m, M, C + 1, 3)
        Q, Bc, HR = Q.reshape(m, M, C + 1), Bc.reshape(m, M, C + 1), HR.reshape(m, M, C + 1)
    st = _State(
        wid=xp.arange(m), pr=xp.copy(pr), s=xp.full(m, C), z=xp.zeros(m), w=-xp.copy(wo), beta=xp.ones((m, 3)),
        run_a=xp.zeros(m), run_r=xp.ones(m), straight=xp.zeros(m, dtype=bool),
        nondelta=xp.zeros(m, dtype=bool),
    )
    # a walk must see the stack from above
    st.keep(wo[:, 2] > 0.0)

    def connect(ix, s_nee, f_fn, pdf_fn, medium, suffix):
        """NEE from vertices ``ix`` (indices into st) to the chain directions of slab s_nee,
        for each of the M incident directions of the walk. ``suffix``: the vertex is a rough
        interface reached from below (it transmits upward on the connected path)."""
        rep = xp.repeat(xp.arange(ix.shape[0]), M)
        mm = xp.tile(xp.arange(M), ix.shape[0])
        wid = st.wid[ix][rep]
        sn = s_nee[rep]
        d = D[wid, mm, sn]
        Wc = W[wid, mm, sn]
        sel = xp.flatnonzero(xp.max(Wc, axis=1) > 0.0)
        if sel.shape[0] == 0:
            return
        a = rep[sel]  # row of the vertex within ``ix`` (what f_fn / pdf_fn index)
        wid, mm, sn, d, Wc = wid[sel], mm[sel], sn[sel], d[sel], Wc[sel]
        ixa = ix[a]
        p = st.pr[ixa]
        w_in = st.w[ixa]
        dz = xp.abs(d[:, 2])
        f = f_fn(a, -d, -w_in)
        if medium:
            tr = _tr(lay.tau[p, sn] - st.z[ixa], dz)
            c = st.beta[ixa] * lay.albedo[p, st.s[ixa]] * (f * tr / dz)[:, None] * Wc
        else:
            tr = _tr(lay.tau[p, sn], dz)
            c = st.beta[ixa] * f * tr[:, None] * Wc
        # splits above: the chain could also have been the walk for its lower segments
        Bw = xp.zeros(sel.shape[0])
        hr = xp.flatnonzero(HR[wid, mm, sn])
        if hr.shape[0]:
            r = pdf_fn(a[hr], -d[hr], -w_in[hr], RADIANCE) / (lay.n[p[hr], sn[hr]] ** 2 * dz[hr])
            with xp.errstate(divide="ignore", invalid="ignore"):
                Bw[hr] = (r / Q[wid[hr], mm[hr], sn[hr]]) ** 2 * (1.0 + Bc[wid[hr], mm[hr], sn[hr]])
        # splits below: the walk's straight run could also have been the chain
        Aw = xp.zeros(sel.shape[0])
        sx = xp.flatnonzero(suffix[a] & st.straight[ixa])
        if sx.shape[0]:
            k = sn[sx] - 1
            if EXIT_DENSITY == "matching":
                q = pdf_fn(a[sx], -w_in[sx], -d[sx], IMPORTANCE)
            else:  # pbrt-v4's reverse density: biased, kept only to measure the bias
                q = pdf_fn(a[sx], -d[sx], -w_in[sx], RADIANCE)
            q = q / (lay.n[p[sx], k] ** 2 * xp.abs(w_in[sx, 2]))
            with xp.errstate(divide="ignore", invalid="ignore"):
                Aw[sx] = (q / st.run_r[ixa[sx]]) ** 2 * (1.0 + st.run_a[ixa[sx]])
        with xp.errstate(invalid="ignore"):
            wt = 1.0 / (1.0 + xp.nan_to_num(Aw, nan=xp.inf) + xp.nan_to_num(Bw, nan=xp.inf))
        acc[wid, mm] += c * wt[:, None]

    for depth in range(MAX_DEPTH):
        if st.wid.shape[0] == 0:
            break
        # Russian roulette
        if depth > RR_START:
            bmax = xp.max(st.beta, axis=1)
            q = xp.where(bmax < 0.25, xp.maximum(0.0, 1.0 - bmax), 0.0)
            u = rng.random(bmax.shape[0])
            alive = u >= q
            st.beta /= xp.where(alive, 1.0 - q, 1.0)[:, None]
            st.keep(alive & (bmax > 0.0))
            if st.wid.shape[0] == 0:
                break

        # ---- free flight in the current slab
        inside = st.s < C
        up = st.w[:, 2] > 0.0
        tau = lay.tau[st.pr, st.s]
        scat = xp.zeros(st.wid.shape[0], dtype=bool)
        sc_rows = xp.flatnonzero(inside & lay.scatter[st.pr, st.s])
        if sc_rows.shape[0]:
            wz = xp.abs(st.w[sc_rows, 2])
            dist = -xp.log1p(-rng.random(sc_rows.shape[0])) * wz
            zp = st.z[sc_rows] + xp.where(up[sc_rows], dist, -dist)
            hit = (zp > 0.0) & (zp < tau[sc_rows])
            scat[sc_rows[hit]] = True
            st.z[sc_rows[hit]] = zp[hit]
        ab_rows = xp.flatnonzero(inside & ~lay.scatter[st.pr, st.s] & (tau > 0.0))
        if ab_rows.shape[0]:
            dist = xp.where(up[ab_rows], tau[ab_rows] - st.z[ab_rows], st.z[ab_rows])
            st.beta[ab_rows] *= _tr(dist, st.w[ab_rows, 2])[:, None]
        dead = xp.zeros(st.wid.shape[0], dtype=bool)

        # ---- medium scattering
        ms = xp.flatnonzero(scat)
        if ms.shape[0]:
            p, s = st.pr[ms], st.s[ms]
            phase = HenyeyGreenstein(lay.g[p, s])
            if nee:
                def f_ph(a, wi_, wo_):
                    return phase.take(a).eval(wi_, wo_, check=False)

                def pdf_ph(a, wi_, wo_, mode):
                    return phase.take(a).eval(wi_, wo_, check=False)

                connect(ms, xp.copy(s), f_ph, pdf_ph, True, xp.zeros(ms.shape[0], dtype=bool))
            wnew, pdf = phase.sample(-st.w[ms], rng.random((ms.shape[0], 2)), check=False)
            st.beta[ms] *= lay.albedo[p, s]
            st.w[ms] = wnew
            st.run_a[ms] = 0.0
            st.run_r[ms] = pdf / (lay.n[p, s] ** 2 * xp.abs(wnew[:, 2]))
            st.straight[ms] = wnew[:, 2] > 0.0
            st.nondelta[ms] = True
            dead[ms] = (wnew[:, 2] == 0.0) | ~(pdf > 0.0)

        # ---- surface events: interface k hit from either side, or the base
        srf = ~scat
        if xp.any(srf):
            new_s = xp.copy(st.s)
            k = xp.where(up, st.s, st.s - 1)
            base_rows = xp.flatnonzero(srf & ~up & (st.s == 0))
            if_rows = xp.flatnonzero(srf & ((up & (st.s < C)) | (~up & (st.s > 0))))
            groups = []
            if if_rows.shape[0]:
                p, kk = st.pr[if_rows], k[if_rows]
                groups.append((if_rows, RoughDielectric(lay.alpha[p, kk], lay.eta[p, kk]), kk + 1,
                               lay.smooth[p, kk], up[if_rows], kk))
            for kind in range(len(BASE_KINDS)):
                rows = base_rows[lay.base_kind[st.pr[base_rows]] == kind]
                if rows.shape[0]:
                    p = st.pr[rows]
                    groups.append((rows, _base_bsdf(lay, kind, p), xp.zeros(rows.shape[0], dtype=xp.int64),
                                   _base_smooth(lay, p), xp.zeros(rows.shape[0], dtype=bool), None))
            for rows, bsdf, s_nee, smooth, from_below, kk in groups:
                if nee:
                    nd = xp.flatnonzero(~smooth)
                    if nd.shape[0]:
                        sub = bsdf.take(nd)

                        def f_s(a, wi_, wo_, sub=sub):
                            return sub.take(a).eval(wi_, wo_, RADIANCE, check=False)

                        def pdf_s(a, wi_, wo_, mode, sub=sub):
                            return sub.take(a).pdf(wi_, wo_, mode, check=False)

                        connect(rows[nd], s_nee[nd], f_s, pdf_s, False, from_below[nd])
                u = rng.random((rows.shape[0], 3))
                forced = xp.zeros(rows.shape[0], dtype=bool)
                if nee and kk is not None:
                    # f has no delta part: a smooth top interface hit from above (entering) must
                    # transmit and one hit from below must reflect for the walk to contribute;
                    # force that event and weight it by its probability (pbrt's
                    # transmission-only / reflection-only sampling of the interfaces).
                    forced = smooth & (kk == C - 1)
                    u[forced, 0] = xp.where(up[rows[forced]], 0.0, _JUST_BELOW_ONE)
                bs_wo = -st.w[rows]
                bs = bsdf.sample(bs_wo, u[:, 0], u[:, 1:], RADIANCE, check=False)
                wnew = bs.wi
                ok = bs.valid & (wnew[:, 2] != 0.0)
                st.beta[rows] *= bs.weight * xp.where(forced & bs.delta, bs.pdf, 1.0)[:, None]
                st.w[rows] = wnew
                upn = wnew[:, 2] > 0.0
                if kk is None:
                    sn = xp.zeros(rows.shape[0], dtype=xp.int64)
                else:
                    sn = xp.where(upn, kk + 1, kk)
                new_s[rows] = sn
                st.z[rows] = xp.where(upn, 0.0, lay.tau[st.pr[rows], xp.minimum(sn, C)])
                nd_ev = ~bs.delta
                if nee:
                    # bookkeeping of the straight upward run for the connection weights
                    pr_r = st.pr[rows]
                    with xp.errstate(divide="ignore", invalid="ignore"):
                        r_new = bs.pdf / (lay.n[pr_r, sn] ** 2 * xp.abs(wnew[:, 2]))
                    a_new = xp.zeros(rows.shape[0])
                    cont = xp.flatnonzero(nd_ev & from_below & upn & st.straight[rows])
                    if cont.shape[0]:
                        w_in = -bs_wo[cont]
                        q = bsdf.take(cont).pdf(-w_in, wnew[cont], IMPORTANCE, check=False) / (
                            lay.n[pr_r[cont], kk[cont]] ** 2 * xp.abs(w_in[:, 2]))
                        with xp.errstate(divide="ignore", invalid="ignore", over="ignore"):
                            a_new[cont] = (q / st.run_r[rows[cont]]) ** 2 * (1.0 + st.run_a[rows[cont]])
                    st.run_a[rows] = xp.where(nd_ev, xp.nan_to_num(a_new, nan=xp.inf), st.run_a[rows])
                    st.run_r[rows] = xp.where(nd_ev, r_new, st.run_r[rows])
                st.straight[rows] = xp.where(nd_ev, upn, st.straight[rows] & bs.transmission)
                st.nondelta[rows] |= nd_ev
                dead[rows] = ~ok
            st.s = new_s
            exits = xp.flatnonzero(srf & ~dead & (st.s == C))
            if exits.shape[0]:
                if not nee:
                    wid = st.wid[exits]
                    out_wi[wid] = st.w[exits]
                    out_w[wid] = st.beta[exits]
                    out_spec[wid] = ~st.nondelta[exits]
                dead[exits] = True
        st.keep(~dead)

    if nee:
        return acc
    return out_wi, out_w, out_spec

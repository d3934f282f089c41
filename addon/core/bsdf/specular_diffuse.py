"""The opaque part of Cycles' Principled BSDF: a GGX dielectric reflection over a Lambertian base, mixed with a GGX
conductor by Metallic.

Cycles builds its Principled BSDF (``svm_node_closure_bsdf``, Blender 4.x/5.x) as closures weighted so:

    f = m S_metal(mu_o) f_metal + (1 - m) (S_spec(mu_o) f_spec + (1 - S_spec(mu_o) E(mu_o)) base / pi)

- ``f_spec`` is the reflection of a rough dielectric interface (:class:`RoughDielectric` with
  ``reflection_only``) at the index that Specular IOR Level sets (:func:`specular_ior`);
- the diffuse base under it is weighted by one minus the specular layer's directional albedo S E at the view
  direction (Cycles' ``closure_layering_weight``; the albedo scaling of Kulla and Conty, "Revisiting Physically
  Based Shading at Imageworks", SIGGRAPH 2017), so that the pair never reflects more than it receives;
- ``f_metal`` is a :class:`RoughConductor` whose normal-incidence reflectance is the base colour
  (``stack.k_from_f0``: eta 1 and the k that gives that F0; Cycles uses Schlick's curve from the same F0, with
  the same normal-incidence value and a rise to 1 at grazing);
- S is Cycles' Multiscatter GGX (its Principled BSDF's default), the light a single-scattering microfacet model
  loses between facets given back (:func:`multiscatter_scale`). Without it a rough metal came out darker than
  Cycles': a Metallic 1 base 0.8 roughness 0.5 sphere 0.918 of Cycles' object pixels, worst block 6.3% of the
  brightest; with it 1.003 and 1.4% (the dielectric's own S is at most about 1.02 at roughness 0.6: its F is
  small).

E(mu, alpha, ior) comes from a table (:func:`dielectric_albedo`) of the reflection's own sample weights,
integrated by a fixed midpoint rule over the visible normals, written once to ``ggx_dielectric_albedo.npz``
beside this module by ``python -c "from addon.core.bsdf.specular_diffuse import write_albedo_table as w; w()"``
from the repository root (about 90 s on one core; deterministic).

Sampling is a mixture: the GGX visible-normal reflection (shared by the dielectric and the conductor: both reflect
about the same microfacets) with a probability from the two lobes' albedos at wo, else a cosine-weighted direction;
the pdf is the mixture's, and a sample's weight is the whole f times the cosine over that pdf.

Each of these is written once, as a formula (``addon.core.formula``): what the view sets (:func:`principled_view`:
the multiple-scattering factors, the diffuse base's weight, the lobe probability), f with the sampler's pdf
(:func:`principled_eval`, over ``ggx.reflection_terms`` and the two Fresnel terms) and a sample
(:func:`principled_sample`). :class:`SpecularDiffuse` runs them on columns; the renderer runs them on scalars in one
compiled pass a bounce (``kernels.principled_shade``), the table read at the view cosine from a curve made once for
the material's alpha and index (:func:`albedo_curve`, :func:`curve_at`, which the numpy lookup of one alpha and index
reads too).

The surface is opaque and two-sided, as Cycles shades a Principled BSDF without transmission: a view from below is
mirrored above (both directions' z negated) and light never crosses it.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from ..formula import clip, formula, maximum, node_below, where
from ..stack import k_from_f0
from . import ggx
from .base import BSDF, RADIANCE, SMOOTH_ALPHA, BSDFSample, as_param, rows
from .dielectric import INDEX_MATCHED_TOL, rough_dielectric_sample
from .frame import reflected
from .fresnel import fresnel_conductor_cos, fresnel_dielectric_cos
from .lambert import lambert_f, lambert_pdf, lambert_sample

TABLE_PATH = Path(__file__).with_name("ggx_dielectric_albedo.npz")
# the table's nodes: the view cosine mu, artist roughness r = sqrt(alpha) and z = (ior - 1) / (ior + 1) (the square
# root of the normal-incidence reflectance, Cycles' own axis for its tables), each evenly spaced on [0, 1]
TABLE_SHAPE = (32, 32, 32)  # (z, r, mu)
TABLE_QUADRATURE = 128  # midpoints a side of the (u0, u1) square of visible-normal samples: 16,384 a cell
GRAZING_MU = 1e-3  # the cosine the mu = 0 nodes are evaluated at (at 0 the view sees no facet)


def specular_ior(ior, level):
    """The index of Cycles' Principled specular layer for its IOR and Specular IOR Level (``svm_node_closure_bsdf``,
    "Apply IOR adjustment"): the level scales the normal-incidence reflectance F0 = ((n - 1) / (n + 1))^2 by
    2 x level (0.5 leaves it as it is), and the layer reflects as the interface of the index that has that F0,
    turned below 1 where the IOR is. Level 0 gives index 1: no specular layer. An F0 of 1 or more is held just
    below 1 (an index of about 4,000). Numbers or arrays; returns float64."""
    ior = np.maximum(np.asarray(ior, dtype=np.float64), 1e-5)
    level = np.maximum(np.asarray(level, dtype=np.float64), 0.0)
    f0 = np.minimum(((ior - 1.0) / (ior + 1.0)) ** 2 * 2.0 * level, 0.999)
    root = np.sqrt(f0)
    eta = (1.0 + root) / (1.0 - root)
    out = np.where(ior < 1.0, 1.0 / eta, eta)
    return float(out) if out.ndim == 0 else out


def build_albedo_table(shape=TABLE_SHAPE, quadrature: int = TABLE_QUADRATURE) -> np.ndarray:
    """E[z, r, mu]: the directional albedo of :class:`RoughDielectric`'s reflection (``reflection_only``) seen at
    cosine mu, for GGX alpha r^2 and index (1 + z) / (1 - z) (z = 1: a perfect mirror's Fresnel, 1), as the mean of
    its own sample weights (F G2 / G1 for visible normals, the delta mirror's F where alpha < SMOOTH_ALPHA) over
    the midpoints of a ``quadrature`` x ``quadrature`` grid of random numbers: deterministic, and within about 1e-3
    of the integral."""
    n_z, n_r, n_mu = shape
    mu = np.linspace(0.0, 1.0, n_mu)
    mu[0] = GRAZING_MU
    alpha = np.linspace(0.0, 1.0, n_r) ** 2
    z = np.linspace(0.0, 1.0, n_z)
    with np.errstate(divide="ignore"):
        ior = (1.0 + z) / (1.0 - z)  # z = 1: infinite, whose Fresnel reflectance is 1
    u = (np.arange(quadrature) + 0.5) / quadrature
    u0, u1 = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
    ox, oz = np.sqrt(1.0 - mu * mu)[:, None], mu[:, None]
    table = np.empty(shape)
    for i in range(n_z):
        for j in range(n_r):  # a (mu, sample) slab at a time: 0.5 M rows
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                *_, weight, _, _, _, valid = rough_dielectric_sample(
                    ox, 0.0 * ox, oz, alpha[j], ior[i], 0.0 * u0, u0, u1, True, True
                )
            table[i, j] = np.where(valid & np.isfinite(weight), weight, 0.0).mean(axis=1)
    return table


@functools.cache
def albedo_table() -> np.ndarray:
    """The stored E[z, r, mu] (:func:`build_albedo_table`), read once."""
    with np.load(TABLE_PATH) as data:
        table = np.asarray(data["albedo"], dtype=np.float64)
    if table.shape != TABLE_SHAPE:
        raise ValueError(
            f"{TABLE_PATH.name} holds a table of shape {table.shape}, not {TABLE_SHAPE}: write it again "
            "(specular_diffuse.write_albedo_table)"
        )
    return table


def dielectric_albedo(mu, alpha, ior) -> np.ndarray:
    """The directional albedo E (N,) of :class:`RoughDielectric`'s reflection over black seen at cosine ``mu``
    (N,) (|mu| used), GGX ``alpha`` and index ``ior`` >= 1 (scalars or (N,)): the stored table interpolated
    linearly in mu, sqrt(alpha) and (ior - 1) / (ior + 1). Within 3e-3 of the integral for mu >= 0.1 (the
    quadrature and the interpolation), within 1e-2 nearer grazing."""
    ior = np.asarray(ior, dtype=np.float64)
    return _lookup((ior - 1.0) / (ior + 1.0), alpha, mu)


def ggx_albedo(mu, alpha) -> np.ndarray:
    """The directional albedo (N,) of the GGX reflection with Fresnel 1 (height-correlated Smith): the share of
    light that leaves the microfacets after one bounce, the table's z = 1 slice."""
    return _lookup(1.0, alpha, mu)


@functools.cache
def _ggx_average_nodes() -> np.ndarray:
    """The cosine-weighted average 2 * integral of E1(mu) mu over mu of :func:`ggx_albedo` at each roughness node,
    by the trapezoid rule over the table's mu nodes."""
    mu = np.linspace(0.0, 1.0, TABLE_SHAPE[2])
    e1 = albedo_table()[-1]
    return np.sum(0.5 * np.diff(mu) * (e1[:, 1:] * mu[1:] + e1[:, :-1] * mu[:-1]), axis=1) * 2.0


def ggx_average(alpha) -> np.ndarray:
    """E1_avg: the cosine-weighted average of :func:`ggx_albedo` over view cosines at GGX ``alpha`` (a number or
    (N,)), linear in sqrt(alpha) between the table's roughness nodes."""
    return curve_at(_ggx_average_nodes(), np.sqrt(np.asarray(alpha, dtype=np.float64)))


def multiscatter_scale(mu, alpha, fresnel_average) -> np.ndarray:
    """What Cycles' Multiscatter GGX (``microfacet_ggx_preserve_energy``, the default of its Principled BSDF)
    multiplies a single-scattering GGX reflection by, seen at cosine ``mu`` (N,): :func:`multiscatter_factor` of
    the single-scattering albedo with Fresnel 1 there (:func:`ggx_albedo`), its cosine-weighted mean
    (:func:`ggx_average`) and ``fresnel_average`` (N,) or (N, 3). Returns (N,) or (N, 3) as ``fresnel_average``."""
    mu = np.abs(np.asarray(mu, dtype=np.float64))
    e1 = ggx_albedo(mu, alpha)
    e1_avg = np.broadcast_to(ggx_average(alpha), e1.shape)
    f_avg = np.asarray(fresnel_average, dtype=np.float64)
    if f_avg.ndim == 2:
        e1_avg, e1 = e1_avg[:, None], e1[:, None]
    return multiscatter_factor(e1, e1_avg, f_avg)


def fresnel_dielectric_average(ior) -> np.ndarray:
    """A smooth dielectric's albedo under uniform light: the cosine-weighted hemispherical average of its exact
    Fresnel reflectance, 2 * integral of F(mu) mu over mu in [0, 1], by 64-point Gauss-Legendre quadrature (about
    0.092 at n = 1.5). ``ior`` a number or (N,); returns float64 of its shape."""
    mu, w = np.polynomial.legendre.leggauss(64)
    mu, w = 0.5 * (mu + 1.0), 0.5 * w
    ior = np.asarray(ior, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = fresnel_dielectric_cos(mu, ior[..., None])
    return 2.0 * np.sum(w * mu * f, axis=-1)


def schlick_average(f0) -> np.ndarray:
    """:func:`schlick_mean` of ``f0`` (a number or an array), float64."""
    return schlick_mean(np.asarray(f0, dtype=np.float64))


def albedo_curve(z, alpha) -> np.ndarray:
    """The table (:func:`albedo_table`) at one (z, sqrt(alpha)), bilinearly, as a curve over its mu nodes
    (``TABLE_SHAPE[2]``,): what :func:`curve_at` reads at a view cosine, for a material whose z and alpha are one
    (a tenth of the time of eight lookups a row)."""
    table = albedo_table()
    curve = np.zeros(TABLE_SHAPE[2])
    for zi, wz in _linear_weights(float(z), TABLE_SHAPE[0]):
        for ri, wr in _linear_weights(float(np.sqrt(alpha)), TABLE_SHAPE[1]):
            curve += wz * wr * table[zi, ri]
    return curve


def _lookup(z, alpha, mu) -> np.ndarray:
    """The table (:func:`albedo_table`) at (z, sqrt(alpha), |mu|), trilinearly; (N,) as ``mu``. A material's one z
    and alpha are read once, into a curve over mu (:func:`albedo_curve`, :func:`curve_at`: the renderer's compiled
    loop reads the same curve)."""
    mu = np.abs(np.asarray(mu, dtype=np.float64))
    coords = [np.asarray(z, dtype=np.float64), np.sqrt(np.asarray(alpha, dtype=np.float64)), mu]
    if coords[0].size == 1 and coords[1].size == 1:
        return curve_at(albedo_curve(coords[0].ravel()[0], np.asarray(alpha).ravel()[0]), mu)
    table = albedo_table()
    lo, frac = [], []
    for c, n in zip(coords, TABLE_SHAPE, strict=True):
        x = np.clip(np.broadcast_to(c, mu.shape), 0.0, 1.0) * (n - 1)
        i = np.minimum(x.astype(np.int64), n - 2)
        lo.append(i)
        frac.append(x - i)
    out = np.zeros(mu.shape)
    for corner in range(8):  # the eight nodes around each query, weighted trilinearly
        bits = [(corner >> axis) & 1 for axis in range(3)]
        weight = np.ones(mu.shape)
        for b, f in zip(bits, frac, strict=True):
            weight = weight * (f if b else 1.0 - f)
        out += weight * table[lo[0] + bits[0], lo[1] + bits[1], lo[2] + bits[2]]
    return out


def _linear_weights(c: float, n: int) -> list[tuple[int, float]]:
    """The two nodes of an axis of ``n`` nodes evenly spaced on [0, 1] around ``c`` (clipped), with their linear
    interpolation weights."""
    x = min(max(c, 0.0), 1.0) * (n - 1)
    i = min(int(x), n - 2)
    return [(i, 1.0 - (x - i)), (i + 1, x - i)]


# --- the formulas (addon.core.formula): SpecularDiffuse runs them on columns, kernels.principled_shade on scalars ---


@formula
def curve_at(curve, x):
    """The piecewise-linear function through ``curve``'s values at nodes evenly spaced on [0, 1], at |x| (held to
    [0, 1]): a table's curve (:func:`albedo_curve`) at a view cosine, or the roughness nodes of E1_avg."""
    last = curve.shape[0] - 1
    t = clip(abs(x), 0.0, 1.0) * last
    i = node_below(t, last - 1)
    t = t - i
    return curve[i] * (1.0 - t) + curve[i + 1] * t


@formula
def multiscatter_factor(e1, e1_avg, f_avg):
    """Cycles' Multiscatter GGX factor on a single-scattering reflection (:func:`multiscatter_scale`): 1 + F_ms
    (1 - E1) / E1, E1 the single-scattering albedo with Fresnel 1 at the view, so that a white surface reflects all
    light, and F_ms = F_avg E1_avg / (1 - F_avg (1 - E1_avg)) the Fresnel of the light that bounces more than once
    (Kulla and Conty 2017, appendix; F_avg the Fresnel's cosine-weighted average, E1_avg E1's)."""
    return 1.0 + f_avg * e1_avg / (1.0 - f_avg * (1.0 - e1_avg)) * ((1.0 - e1) / maximum(e1, 1e-6))


@formula
def schlick_mean(f0):
    """The cosine-weighted average of Schlick's Fresnel F0 + (1 - F0)(1 - mu)^5: F0 + (1 - F0) / 21, the average
    Cycles' metal compensates its multiple scattering with (its Fresnel is Schlick's from the base colour)."""
    return f0 + (1.0 - f0) / 21.0


@formula
def lobe_probability(spec_albedo, colour, metallic):
    """The chance that a sample reflects about a visible microfacet, from the lobes' albedos at wo: the dielectric's
    E S (with multiple scattering) and the metal's F0 (``colour``, the mean of the base's channels in [0, 1])
    against the diffuse base's (1 - E S) colour."""
    glossy = (1.0 - metallic) * spec_albedo + metallic * colour
    diffuse = (1.0 - metallic) * (1.0 - spec_albedo) * colour
    total = glossy + diffuse
    return where(total > 0.0, glossy / total, 0.5)


@formula
def lobe_mixture_pdf(p, p_glossy, iz, oz):
    """The sampler's density: the visible-normal reflection's ``p_glossy`` with probability ``p``, else the
    cosine-weighted direction's."""
    return p * p_glossy + (1.0 - p) * lambert_pdf(iz, oz)


@formula
def principled_view(e, e1, e1_avg, f_avg, metallic, b0, b1, b2, metal):
    """What the view sets, from the table at its cosine (the layer's albedo E, the GGX albedo E1) and the
    material's E1_avg, Fresnel average, metallic and base colour: (S_spec, 1 - E S_spec the diffuse base's weight,
    the metal's S per channel (S_spec without ``metal``: unused), the lobe probability). ``metal``: whether any
    row is metallic (a bool for every row)."""
    spec_scale = multiscatter_factor(e1, e1_avg, f_avg)
    spec_albedo = e * spec_scale
    c0, c1, c2 = clip(b0, 0.0, 1.0), clip(b1, 0.0, 1.0), clip(b2, 0.0, 1.0)
    p = lobe_probability(spec_albedo, (c0 + c1 + c2) / 3.0, metallic)
    s0 = s1 = s2 = spec_scale
    if metal:
        s0 = multiscatter_factor(e1, e1_avg, schlick_mean(c0))
        s1 = multiscatter_factor(e1, e1_avg, schlick_mean(c1))
        s2 = multiscatter_factor(e1, e1_avg, schlick_mean(c2))
    return spec_scale, 1.0 - spec_albedo, s0, s1, s2, p


@formula
def principled_eval(
    ix, iy, iz, ox, oy, oz, alpha, ior, metallic, b0, b1, b2, k0, k1, k2, spec_scale, diffuse, s0, s1, s2, p, metal
):
    """(f R, G, B, the sampler's pdf) of :class:`SpecularDiffuse` at wi, wo (components; wo above the surface) with
    what its view sets (:func:`principled_view`: S_spec, the diffuse weight, the metal's S, the lobe probability p)
    and the metal's k per channel (``stack.k_from_f0`` of the base; read only with ``metal``)."""
    dg, p_glossy, dwo = ggx.reflection_terms(ix, iy, iz, ox, oy, oz, alpha)
    spec = where(abs(ior - 1.0) < INDEX_MATCHED_TOL, 0.0, dg * fresnel_dielectric_cos(dwo, ior)) * spec_scale
    dielectric = 1.0 - metallic
    f0 = dielectric * (spec + lambert_f(iz, oz, b0) * diffuse)
    f1 = dielectric * (spec + lambert_f(iz, oz, b1) * diffuse)
    f2 = dielectric * (spec + lambert_f(iz, oz, b2) * diffuse)
    if metal:  # the conductor of F0 = base (eta 1), about the same facets
        f0 = f0 + metallic * (dg * fresnel_conductor_cos(dwo, 1.0, k0) * s0)
        f1 = f1 + metallic * (dg * fresnel_conductor_cos(dwo, 1.0, k1) * s1)
        f2 = f2 + metallic * (dg * fresnel_conductor_cos(dwo, 1.0, k2) * s2)
    return f0, f1, f2, lobe_mixture_pdf(p, p_glossy, iz, oz)


@formula
def principled_sample(
    ox, oy, oz, u_lobe, u0, u1, alpha, ior, metallic, b0, b1, b2, k0, k1, k2, spec_scale, diffuse, s0, s1, s2, p, metal
):
    """(x, y, z, weight R, G, B, pdf, delta, valid): one sample of :class:`SpecularDiffuse` seen from wo above the
    surface (the arguments of :func:`principled_eval`), before ``BSDFSample.build``'s checks: the mirror of wo
    about a visible normal (the geometric normal where alpha < SMOOTH_ALPHA: a delta event of weight the
    dielectric's and the metal's Fresnel over its chance p) with probability p, else a cosine-weighted direction,
    both from the same numbers; weight f |cos| / pdf, pdf the mixture's."""
    glossy = u_lobe < p
    smooth = alpha < SMOOTH_ALPHA
    mx, my, mz = ggx.visible_normal(ox, oy, oz, maximum(alpha, ggx.MIN_ALPHA), u0, u1)
    mx, my, mz = where(smooth, 0.0, mx), where(smooth, 0.0, my), where(smooth, 1.0, mz)
    rx, ry, rz = reflected(ox, oy, oz, mx, my, mz)
    dx, dy, dz, _, ok_diffuse = lambert_sample(oz, u0, u1)
    ix, iy, iz = where(glossy, rx, dx), where(glossy, ry, dy), where(glossy, rz, dz)
    f0, f1, f2, pdf = principled_eval(
        ix, iy, iz, ox, oy, oz, alpha, ior, metallic, b0, b1, b2, k0, k1, k2, spec_scale, diffuse, s0, s1, s2, p, metal
    )
    c = abs(iz)
    delta = glossy & smooth
    mirror = (1.0 - metallic) * fresnel_dielectric_cos(oz, ior)
    m0 = m1 = m2 = mirror
    if metal:
        m0 = mirror + metallic * fresnel_conductor_cos(oz, 1.0, k0)
        m1 = mirror + metallic * fresnel_conductor_cos(oz, 1.0, k1)
        m2 = mirror + metallic * fresnel_conductor_cos(oz, 1.0, k2)
    w0 = where(delta, m0 / p, f0 * c / pdf)
    w1 = where(delta, m1 / p, f1 * c / pdf)
    w2 = where(delta, m2 / p, f2 * c / pdf)
    valid = (oz > 0.0) & (iz > 0.0) & (glossy | ok_diffuse)
    return ix, iy, iz, w0, w1, w2, where(delta, p, pdf), delta, valid


class SpecularDiffuse(BSDF):
    """Cycles' Principled BSDF without transmission, coat, sheen, subsurface or tints (module docstring).

    ``base`` RGB (N, 3) or (3,), >= 0 (above 1 allowed, as Cycles renders a base colour); ``alpha`` GGX alpha;
    ``ior`` >= 1 the specular layer's index after Specular IOR Level (:func:`specular_ior`; 1: no layer);
    ``metallic`` in [0, 1]. ``fresnel_average`` is derived: the layer's :func:`fresnel_dielectric_average`, kept
    per stored row of ``ior`` (64 Fresnel evaluations each: per hit, they took most of the time of a bounce).

    ``eval``, ``pdf`` and ``sample`` run the formulas above on columns; the renderer runs the same formulas in one
    compiled pass a bounce (``kernels.principled_shade``, with :meth:`shading_arrays`).
    """

    _params = ("base", "alpha", "ior", "metallic", "fresnel_average")

    def __init__(self, base, alpha, ior, metallic=0.0):
        self.base = as_param(base, "SpecularDiffuse.base", lo=0.0, rgb=True)
        self.alpha = as_param(alpha, "SpecularDiffuse.alpha", lo=0.0)
        self.ior = as_param(ior, "SpecularDiffuse.ior", lo=1.0)
        self.metallic = as_param(metallic, "SpecularDiffuse.metallic", lo=0.0, hi=1.0)
        self.fresnel_average = fresnel_dielectric_average(self.ior)
        self._lobes = None  # shading_arrays' (lobes, curves), made at first use
        self._k = None  # k_from_f0 of a shared base, made at first use

    def with_base(self, base: np.ndarray) -> "SpecularDiffuse":
        """This BSDF over per-row base colours (N, 3) that are float64, finite and non-negative by construction (the
        renderer's texture lookups, ``kernels.tinted_albedo``): the other parameters and what is made from them
        kept, without ``as_param``'s checks, which cost passes over every hit of every bounce."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        out.base, out._k = base, None
        return out

    def shading_arrays(self) -> tuple | None:
        """What ``kernels.principled_shade`` reads: (base (1 or N, 3), k (1 or N, 3): the metal's
        ``stack.k_from_f0`` of the base (zeros without a metal), lobes (alpha, ior, metallic, Fresnel average,
        E1_avg), the layer's albedo curve over mu, E1's), float64 and contiguous; None where alpha, ior or metallic
        vary by row (then :class:`~addon.core.render.shading.ShadeByParts` answers from eval, pdf, sample)."""
        if any(getattr(self, p).shape[0] != 1 for p in ("alpha", "ior", "metallic")):
            return None
        if self._lobes is None:
            alpha, ior, metallic = float(self.alpha[0]), float(self.ior[0]), float(self.metallic[0])
            avg = float(ggx_average(np.asarray(alpha)))
            lobes = np.array([alpha, ior, metallic, float(self.fresnel_average[0]), avg])
            self._lobes = lobes, albedo_curve((ior - 1.0) / (ior + 1.0), alpha), albedo_curve(1.0, alpha)
        base = np.require(self.base, np.float64, ["C"])
        k = self._k
        if k is None or len(base) != 1:
            k = np.ascontiguousarray(k_from_f0(base)) if self.metallic[0] > 0.0 else np.zeros((1, 3))
            if len(base) == 1:
                self._k = k
        return (base, k, *self._lobes)

    def _rows(self, n):
        """(base, alpha, ior, metallic, fresnel_average) for a batch of ``n`` rows: a per-row parameter checked to
        have them, a shared one left at its one row, which numpy broadcasts (and :func:`_lookup` reads once)."""
        return tuple(v if v.shape[0] == 1 else rows(v, n, p) for p in self._params for v in [getattr(self, p)])

    @staticmethod
    def _lobe_arguments(mu, base, alpha, ior, metallic, fresnel_average):
        """The material's arguments to :func:`principled_eval` and :func:`principled_sample` after the directions,
        on columns, at view cosines ``mu`` (N,)."""
        metal = bool(np.any(metallic > 0.0))
        view = principled_view(
            dielectric_albedo(mu, alpha, ior), ggx_albedo(mu, alpha), ggx_average(alpha), fresnel_average,
            metallic, base[:, 0], base[:, 1], base[:, 2], metal,
        )  # fmt: skip
        k = k_from_f0(base) if metal else np.zeros((1, 3))
        return (alpha, ior, metallic, base[:, 0], base[:, 1], base[:, 2], k[:, 0], k[:, 1], k[:, 2], *view, metal)

    # --- the interface ------------------------------------------------------------------------------------------

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, _ = self._inputs(wi, wo, mode, check)
        wi, wo = _above(wi, wo)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            args = self._lobe_arguments(wo[:, 2], *self._rows(len(wi)))
            f0, f1, f2, _ = principled_eval(*wi.T, *wo.T, *args)
        return np.stack(np.broadcast_arrays(f0, f1, f2), axis=-1)

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, _ = self._inputs(wi, wo, mode, check)
        wi, wo = _above(wi, wo)
        params = self._rows(len(wi))
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            p = self._lobe_arguments(wo[:, 2], *params)[-2]
            _, p_glossy, _ = ggx.reflection_terms(*wi.T, *wo.T, params[1])
            return lobe_mixture_pdf(p, p_glossy, wi[:, 2], wo[:, 2])

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u, _ = self._sample_inputs(wo, u_lobe, u, mode, check)
        below = wo[:, 2] < 0.0
        wo = _mirrored(wo, below)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            args = self._lobe_arguments(wo[:, 2], *self._rows(len(wo)))
            x, y, z, w0, w1, w2, pdf, delta, valid = principled_sample(*wo.T, u_lobe, u[:, 0], u[:, 1], *args)
        wi = np.stack([x, y, z], axis=-1)
        weight = np.stack(np.broadcast_arrays(w0, w1, w2), axis=-1)
        false = np.zeros(len(wo), dtype=bool)
        return BSDFSample.build(_mirrored(wi, below), weight, pdf, delta, false, valid)


def _mirrored(w, rows_below):
    """``w`` with z negated on ``rows_below``."""
    return np.where(rows_below[:, None], w * np.array([1.0, 1.0, -1.0]), w)


def _above(wi, wo):
    """(wi, wo) with both mirrored where wo lies below the surface: the surface is two-sided and opaque."""
    below = wo[:, 2] < 0.0
    return _mirrored(wi, below), _mirrored(wo, below)


def write_albedo_table(path: Path = TABLE_PATH) -> None:
    """Build the table (:func:`build_albedo_table`) and store it, float32, at ``path``."""
    np.savez_compressed(path, albedo=build_albedo_table().astype(np.float32))

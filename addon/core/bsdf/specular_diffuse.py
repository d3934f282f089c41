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

The surface is opaque and two-sided, as Cycles shades a Principled BSDF without transmission: a view from below is
mirrored above (both directions' z negated) and light never crosses it.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from ..stack import k_from_f0
from . import ggx
from .base import BSDF, RADIANCE, SMOOTH_ALPHA, BSDFSample, as_param, rows
from .conductor import RoughConductor
from .dielectric import rough_dielectric_eval_pdf, rough_dielectric_sample
from .frame import reflected
from .fresnel import fresnel_conductor, fresnel_dielectric_cos
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


def multiscatter_scale(mu, alpha, fresnel_average) -> np.ndarray:
    """What Cycles' Multiscatter GGX (``microfacet_ggx_preserve_energy``, the default of its Principled BSDF)
    multiplies a single-scattering GGX reflection by, seen at cosine ``mu`` (N,): 1 + F_ms (1 - E1) / E1, E1 the
    single-scattering albedo with Fresnel 1 (:func:`ggx_albedo`), so that a white surface reflects all light, and
    F_ms = F_avg E1_avg / (1 - F_avg (1 - E1_avg)) the Fresnel of the light that bounces more than once (Kulla and
    Conty 2017, appendix; F_avg ``fresnel_average`` (N,) or (N, 3), E1_avg the cosine-weighted mean of E1).
    Returns (N,) or (N, 3) as ``fresnel_average``."""
    mu = np.abs(np.asarray(mu, dtype=np.float64))
    e1 = ggx_albedo(mu, alpha)
    r = np.clip(np.sqrt(np.broadcast_to(np.asarray(alpha, dtype=np.float64), mu.shape)), 0.0, 1.0)
    e1_avg = np.interp(r, np.linspace(0.0, 1.0, TABLE_SHAPE[1]), _ggx_average_nodes())
    f_avg = np.asarray(fresnel_average, dtype=np.float64)
    extra = (1.0 - e1) / np.maximum(e1, 1e-6)
    if f_avg.ndim == 2:
        e1_avg, extra = e1_avg[:, None], extra[:, None]
    return 1.0 + f_avg * e1_avg / (1.0 - f_avg * (1.0 - e1_avg)) * extra


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
    """The cosine-weighted average of Schlick's Fresnel F0 + (1 - F0)(1 - mu)^5: F0 + (1 - F0) / 21, the average
    Cycles' metal compensates its multiple scattering with (its Fresnel is Schlick's from the base colour)."""
    f0 = np.asarray(f0, dtype=np.float64)
    return f0 + (1.0 - f0) / 21.0


def _lookup(z, alpha, mu) -> np.ndarray:
    """The table (:func:`albedo_table`) at (z, sqrt(alpha), |mu|), trilinearly; (N,) as ``mu``. A material's one z
    and alpha are read once, into a curve over mu (a tenth of the time of eight lookups a row)."""
    table = albedo_table()
    mu = np.abs(np.asarray(mu, dtype=np.float64))
    coords = [np.asarray(z, dtype=np.float64), np.sqrt(np.asarray(alpha, dtype=np.float64)), mu]
    if coords[0].size == 1 and coords[1].size == 1:
        curve = np.zeros(TABLE_SHAPE[2])
        for zi, wz in _linear_weights(float(coords[0].ravel()[0]), TABLE_SHAPE[0]):
            for ri, wr in _linear_weights(float(coords[1].ravel()[0]), TABLE_SHAPE[1]):
                curve += wz * wr * table[zi, ri]
        return np.interp(mu, np.linspace(0.0, 1.0, TABLE_SHAPE[2]), curve)
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


class SpecularDiffuse(BSDF):
    """Cycles' Principled BSDF without transmission, coat, sheen, subsurface or tints (module docstring).

    ``base`` RGB (N, 3) or (3,), >= 0 (above 1 allowed, as Cycles renders a base colour); ``alpha`` GGX alpha;
    ``ior`` >= 1 the specular layer's index after Specular IOR Level (:func:`specular_ior`; 1: no layer);
    ``metallic`` in [0, 1]. ``fresnel_average`` is derived: the layer's :func:`fresnel_dielectric_average`, kept
    per stored row of ``ior`` (64 Fresnel evaluations each: per hit, they took most of the time of a bounce).
    """

    _params = ("base", "alpha", "ior", "metallic", "fresnel_average")

    def __init__(self, base, alpha, ior, metallic=0.0):
        self.base = as_param(base, "SpecularDiffuse.base", lo=0.0, rgb=True)
        self.alpha = as_param(alpha, "SpecularDiffuse.alpha", lo=0.0)
        self.ior = as_param(ior, "SpecularDiffuse.ior", lo=1.0)
        self.metallic = as_param(metallic, "SpecularDiffuse.metallic", lo=0.0, hi=1.0)
        self.fresnel_average = fresnel_dielectric_average(self.ior)

    def _rows(self, n):
        """(base, alpha, ior, metallic, fresnel_average) for a batch of ``n`` rows: a per-row parameter checked to
        have them, a shared one left at its one row, which numpy broadcasts (and :func:`_lookup` reads once)."""
        return tuple(v if v.shape[0] == 1 else rows(v, n, p) for p in self._params for v in [getattr(self, p)])

    # --- the lobes -----------------------------------------------------------------------------------------------

    def _f(self, wi, wo, base, alpha, ior, metallic, fresnel_average):
        """(f (N, 3), the glossy lobe's pdf (N,)) at upper-hemisphere wo (rough parts only: a delta mirror adds
        nothing here)."""
        f_spec, _ = rough_dielectric_eval_pdf(
            wi[:, 0], wi[:, 1], wi[:, 2], wo[:, 0], wo[:, 1], wo[:, 2], alpha, ior, True, True
        )  # index-matched rows (ior 1) give 0: no layer
        spec_scale = multiscatter_scale(wo[:, 2], alpha, fresnel_average)
        spec_albedo = dielectric_albedo(wo[:, 2], alpha, ior) * spec_scale
        diffuse = lambert_f(wi[:, 2:3], wo[:, 2:3], base) * (1.0 - spec_albedo)[:, None]
        f = (1.0 - metallic)[:, None] * ((f_spec * spec_scale)[:, None] + diffuse)
        pdf_glossy = RoughConductor(alpha, 1.0, 0.0).pdf(wi, wo, check=False)  # the same facets, whatever the index
        if np.any(metallic > 0.0):
            metal = RoughConductor(alpha, 1.0, k_from_f0(base)).eval(wi, wo, check=False)
            metal = metal * multiscatter_scale(wo[:, 2], alpha, schlick_average(np.clip(base, 0.0, 1.0)))
            f = f + metallic[:, None] * metal
        return f, pdf_glossy

    @staticmethod
    def _glossy_probability(mu, base, alpha, ior, metallic, fresnel_average):
        """The chance (N,) that a sample reflects about a visible microfacet, from the lobes' albedos at wo: the
        dielectric's E (with multiple scattering) and the metal's F0 (its mean over the channels) against the
        diffuse base's (1 - E) base."""
        e = dielectric_albedo(mu, alpha, ior) * multiscatter_scale(mu, alpha, fresnel_average)
        colour = np.clip(base, 0.0, 1.0).mean(axis=1)
        glossy = (1.0 - metallic) * e + metallic * colour
        diffuse = (1.0 - metallic) * (1.0 - e) * colour
        total = glossy + diffuse
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(total > 0.0, glossy / total, 0.5)

    # --- the interface ------------------------------------------------------------------------------------------

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, _ = self._inputs(wi, wo, mode, check)
        wi, wo = _above(wi, wo)
        with np.errstate(invalid="ignore", divide="ignore"):
            return self._f(wi, wo, *self._rows(len(wi)))[0]

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, _ = self._inputs(wi, wo, mode, check)
        wi, wo = _above(wi, wo)
        params = self._rows(len(wi))
        p = self._glossy_probability(wo[:, 2], *params)
        alpha = params[1]
        with np.errstate(invalid="ignore", divide="ignore"):
            glossy = RoughConductor(alpha, 1.0, 0.0).pdf(wi, wo, check=False)
        return p * glossy + (1.0 - p) * lambert_pdf(wi[:, 2], wo[:, 2])

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u, _ = self._sample_inputs(wo, u_lobe, u, mode, check)
        below = wo[:, 2] < 0.0
        wo = _mirrored(wo, below)
        n = len(wo)
        params = self._rows(n)
        base, alpha, ior, metallic, _ = params
        p = self._glossy_probability(wo[:, 2], *params)
        glossy = u_lobe < p
        # both candidates from the same numbers: a visible-normal reflection and a cosine-weighted direction
        with np.errstate(invalid="ignore", divide="ignore"):
            mx, my, mz = ggx.visible_normal(wo[:, 0], wo[:, 1], wo[:, 2], np.maximum(alpha, ggx.MIN_ALPHA), *u.T)
            smooth = alpha < SMOOTH_ALPHA  # the mirror about the geometric normal
            mx, my, mz = np.where(smooth, 0.0, mx), np.where(smooth, 0.0, my), np.where(smooth, 1.0, mz)
            rx, ry, rz = reflected(wo[:, 0], wo[:, 1], wo[:, 2], mx, my, mz)
            dx, dy, dz, _, ok_diffuse = lambert_sample(wo[:, 2], u[:, 0], u[:, 1])
        wi = np.where(glossy[:, None], np.stack([rx, ry, rz], axis=-1), np.stack([dx, dy, dz], axis=-1))
        delta = glossy & smooth
        with np.errstate(invalid="ignore", divide="ignore"):
            f, pdf_glossy = self._f(wi, wo, *params)
            pdf = p * pdf_glossy + (1.0 - p) * lambert_pdf(wi[:, 2], wo[:, 2])
            weight = f * np.abs(wi[:, 2:3]) / pdf[:, None]
            if np.any(delta):  # a smooth surface's mirror: the dielectric's and the metal's Fresnel over its chance
                mirror = (1.0 - metallic) * fresnel_dielectric_cos(wo[:, 2], ior)
                mirror = mirror[:, None] + metallic[:, None] * fresnel_conductor(wo[:, 2], 1.0, k_from_f0(base))
                weight = np.where(delta[:, None], mirror / p[:, None], weight)
        pdf = np.where(delta, p, pdf)
        valid = (wo[:, 2] > 0.0) & (wi[:, 2] > 0.0) & np.where(glossy, True, ok_diffuse)
        false = np.zeros(n, dtype=bool)
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

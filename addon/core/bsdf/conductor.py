"""Rough conductor: GGX microfacets, height-correlated Smith G2, complex Fresnel."""

from __future__ import annotations

import numpy as np

from . import ggx
from .base import BSDF, RADIANCE, SMOOTH_ALPHA, BSDFSample, as_param, rows
from .frame import dot, reflect
from .fresnel import fresnel_conductor


def _half_vector(wi, wo, xp):
    """The reflection half vector normalize(wi + wo) turned to face +z, and where it exists."""
    h = wi + wo
    h *= xp.where(h[:, 2] < 0.0, -1.0, 1.0)[:, None]
    hn = xp.sqrt(dot(h, h))
    with xp.errstate(invalid="ignore", divide="ignore"):
        m = h / hn[:, None]
    return m, hn > 0.0


class RoughConductor(BSDF):
    """Microfacet conductor (Cook-Torrance with GGX; pbrt-v4 ``ConductorBxDF``).

    f(wi, wo) = D(m) G2(wi, wo) F(|wo.m|) / (4 |cos wi| |cos wo|), m = normalize(wi + wo)
    facing +z, for wi and wo on the same side (either side; a conductor is usually seen from
    outside). Reciprocal in both modes. Sampling uses visible normals from wo, so the sample
    weight is F G2 / G1(wo). ``alpha < SMOOTH_ALPHA`` is a delta mirror with weight F.
    ``eta`` and ``k`` are RGB (complex index eta + i k relative to the outside medium).
    """

    _params = ("alpha", "eta", "k")

    def __init__(self, alpha, eta, k):
        self.alpha = as_param(alpha, "RoughConductor.alpha", lo=0.0)
        self.eta = as_param(eta, "RoughConductor.eta", lo=0.0, lo_open=True, rgb=True)
        self.k = as_param(k, "RoughConductor.k", lo=0.0, rgb=True)

    def _rows(self, n, xp):
        return rows(self.alpha, n, "alpha", xp), rows(self.eta, n, "eta", xp), rows(self.k, n, "k", xp)

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        n = wi.shape[0]
        alpha, eta, k = self._rows(n, xp)
        ci, co = wi[:, 2], wo[:, 2]
        m, has_half = _half_vector(wi, wo, xp)
        ok = (ci * co > 0.0) & has_half & (alpha >= SMOOTH_ALPHA)
        with xp.errstate(invalid="ignore", divide="ignore"):
            dwo = xp.abs(dot(wo, m))
            f = (ggx.ndf(m, alpha) * ggx.smith_g2(wi, wo, alpha) / (4.0 * xp.abs(ci * co)))[:, None]
            f = f * fresnel_conductor(dwo, eta, k)
        return xp.where(ok[:, None] & xp.isfinite(f), f, 0.0)

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        n = wi.shape[0]
        alpha = rows(self.alpha, n, "alpha", xp)
        m, has_half = _half_vector(wi, wo, xp)
        ok = (wi[:, 2] * wo[:, 2] > 0.0) & has_half & (alpha >= SMOOTH_ALPHA)
        with xp.errstate(invalid="ignore", divide="ignore"):
            p = ggx.pdf_visible_normal(wo, m, alpha) / (4.0 * xp.abs(dot(wo, m)))
        return xp.where(ok & xp.isfinite(p), p, 0.0)

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u, xp = self._sample_inputs(wo, u_lobe, u, mode, check)
        n = wo.shape[0]
        alpha, eta, k = self._rows(n, xp)
        smooth = alpha < SMOOTH_ALPHA
        m = ggx.sample_visible_normal(wo, alpha, u)
        m = xp.where(smooth[:, None], xp.asarray([0.0, 0.0, 1.0]), m)
        wi = reflect(wo, m)
        dwo = xp.abs(dot(wo, m))
        F = fresnel_conductor(dwo, eta, k)
        with xp.errstate(invalid="ignore", divide="ignore"):
            rough_w = ggx.smith_g2(wi, wo, alpha) / ggx.smith_g1(wo, alpha)
            rough_pdf = ggx.pdf_visible_normal(wo, m, alpha) / (4.0 * dwo)
        weight = F * xp.where(smooth, 1.0, rough_w)[:, None]
        pdf = xp.where(smooth, 1.0, rough_pdf)
        valid = wi[:, 2] * wo[:, 2] > 0.0
        false = xp.zeros(n, dtype=bool)
        return BSDFSample.build(wi, weight, pdf, xp.copy(smooth), false, valid)

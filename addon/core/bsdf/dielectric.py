"""Rough dielectric interface: GGX reflection and transmission (Walter et al. 2007; pbrt-v4
``DielectricBxDF``), with the height-correlated Smith G2."""

from __future__ import annotations

import numpy as np

from . import ggx
from .base import BSDF, RADIANCE, SMOOTH_ALPHA, BSDFSample, as_param, rows
from .frame import dot, reflect, refract
from .fresnel import fresnel_dielectric

# |ior - 1| below this is index-matched: Fresnel reflectance is < 1e-15 there, and the
# generalised half vector of rough transmission loses all precision to cancellation.
INDEX_MATCHED_TOL = 1e-7


class RoughDielectric(BSDF):
    """The interface between the outside (index 1, +z side) and a medium of relative index
    ``ior`` (-z side), lit and seen from either side.

    ``ior`` is the relative index n_below / n_above; any positive finite value is allowed
    (< 1 for an interface between two media where the lower one is optically thinner);
    ``ior == 1`` (to within ``INDEX_MATCHED_TOL``) is index-matched: a delta transmission
    with weight ~1 whatever alpha.

    With m the generalised half vector facing +z (m ~ wi etap + wo, etap = ior when wo is
    above, 1/ior below, 1 for reflection), F = Fresnel(wo.m):

    - reflection:   f = D(m) G2 F / (4 |cos wi cos wo|)
    - transmission: f = D(m) G2 (1 - F) |wi.m wo.m| / (|cos wi cos wo| (wi.m + wo.m / etap)^2),
      divided by etap^2 in RADIANCE mode (radiance is compressed into the denser medium) and
      not in IMPORTANCE mode.

    Reciprocity: reflection is reciprocal; for transmission in RADIANCE mode
    f(wi, wo) / n_o^2 = f(wo, wi) / n_i^2 with n_i, n_o the indices on wi's and wo's sides
    (Veach 1997, section 5.2; pbrt-v4 section 9.5.2), and IMPORTANCE mode is RADIANCE mode
    with the arguments swapped: f_importance(wi, wo) = f_radiance(wo, wi).
    ``sample`` chooses reflection with probability F(wo.m) (Fresnel-weighted lobe choice),
    so the weight of a rough sample is G2 / G1(wo) (times 1/etap^2 for radiance transmission).

    ``reflection_only=True`` is a dielectric over black: the transmitted energy is lost,
    ``eval``/``pdf`` of transmission are 0 and ``sample`` only reflects (weight F G2 / G1).

    ``alpha < SMOOTH_ALPHA`` (or an index-matched ``ior``) gives delta lobes: eval/pdf are 0, ``sample``
    returns the mirror (weight 1; F for ``reflection_only``) with pdf F, or the refracted
    direction (weight 1/etap^2 in RADIANCE mode, 1 in IMPORTANCE) with pdf 1 - F.
    """

    _params = ("alpha", "ior")

    def __init__(self, alpha, ior, reflection_only: bool = False):
        self.alpha = as_param(alpha, "RoughDielectric.alpha", lo=0.0)
        self.ior = as_param(ior, "RoughDielectric.ior", lo=0.0, lo_open=True)
        self.reflection_only = bool(reflection_only)

    def _rows(self, n, xp):
        alpha = rows(self.alpha, n, "alpha", xp)
        ior = rows(self.ior, n, "ior", xp)
        return alpha, ior, (alpha < SMOOTH_ALPHA) | (xp.abs(ior - 1.0) < INDEX_MATCHED_TOL)

    def _half(self, wi, wo, ior, xp):
        """Generalised half vector m (facing +z), etap, reflect flag and the row mask where
        the microfacet configuration is possible (pbrt-v4 DielectricBxDF::f)."""
        ci, co = wi[:, 2], wo[:, 2]
        refl = ci * co > 0.0
        etap = xp.where(refl, 1.0, xp.where(co > 0.0, ior, 1.0 / ior))
        h = wi * etap[:, None] + wo
        h *= xp.where(h[:, 2] < 0.0, -1.0, 1.0)[:, None]
        hn = xp.sqrt(dot(h, h))
        with xp.errstate(invalid="ignore", divide="ignore"):
            m = h / hn[:, None]
        dwi, dwo = dot(wi, m), dot(wo, m)
        ok = (ci != 0.0) & (co != 0.0) & (hn > 0.0) & (dwi * ci > 0.0) & (dwo * co > 0.0)
        return m, etap, refl, ok, dwi, dwo

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        f, _ = self._eval_pdf(wi, wo, mode, xp, want_pdf=False)
        return xp.repeat(f[:, None], 3, axis=1)

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        return self._eval_pdf(wi, wo, mode, xp, want_f=False)[1]

    def eval_pdf(self, wi, wo, mode=RADIANCE, check=True) -> tuple[np.ndarray, np.ndarray]:
        """``eval`` (as (N,): the interface is grey) and ``pdf`` together, from one half vector, Fresnel
        term and microfacet density: what a caller that needs both (MIS) pays once."""
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        return self._eval_pdf(wi, wo, mode, xp)

    def _eval_pdf(self, wi, wo, mode, xp, want_f=True, want_pdf=True):
        """(f (N,) or None, pdf (N,) or None): the one implementation of both (class docstring)."""
        n = wi.shape[0]
        alpha, ior, smooth = self._rows(n, xp)
        m, etap, refl, ok, dwi, dwo = self._half(wi, wo, ior, xp)
        ci, co = wi[:, 2], wo[:, 2]
        live = ok & ~smooth
        f = p = None
        with xp.errstate(invalid="ignore", divide="ignore"):
            F = fresnel_dielectric(dwo, ior)
            d = ggx.ndf(m, alpha)
            if want_f:
                dg = d * ggx.smith_g2(wi, wo, alpha)
                f = dg * F / xp.abs(4.0 * ci * co)
                if not self.reflection_only:
                    denom = (dwi + dwo / etap) ** 2 * ci * co
                    ft = dg * (1.0 - F) * xp.abs(dwi * dwo / denom)
                    if mode == RADIANCE:
                        ft = ft / (etap * etap)
                    f = xp.where(refl, f, ft)
                f = xp.where(live & refl if self.reflection_only else live, f, 0.0)
                f = xp.where(xp.isfinite(f), f, 0.0)
            if want_pdf:
                pvis = ggx.pdf_visible_normal(wo, m, alpha, d=d)
                p = pvis / (4.0 * xp.abs(dwo))  # reflection_only: R / (R + T) = 1
                if not self.reflection_only:
                    pt = pvis * xp.abs(dwi) / (dwi + dwo / etap) ** 2
                    p = xp.where(refl, p * F, pt * (1.0 - F))
                p = xp.where(live & refl if self.reflection_only else live, p, 0.0)
                p = xp.where(xp.isfinite(p), p, 0.0)
        return f, p

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u, xp = self._sample_inputs(wo, u_lobe, u, mode, check)
        n = wo.shape[0]
        alpha, ior, smooth = self._rows(n, xp)
        # smooth rows use the geometric normal; rough rows a visible microfacet normal
        m = ggx.sample_visible_normal(wo, alpha, u)
        m = xp.where(smooth[:, None], xp.asarray([0.0, 0.0, 1.0]), m)
        dwo = dot(wo, m)
        R = fresnel_dielectric(dwo, ior)
        T = xp.zeros_like(R) if self.reflection_only else 1.0 - R
        with xp.errstate(invalid="ignore", divide="ignore"):
            p_refl = R / (R + T)
        choose_r = u_lobe < p_refl

        wr = reflect(wo, m)
        wt, tir_free = refract(wo, m, ior)
        etap = xp.where(dwo > 0.0, ior, 1.0 / ior)
        wi = xp.where(choose_r[:, None], wr, wt)
        dwi = dot(wi, m)
        ci, co = wi[:, 2], wo[:, 2]
        valid = xp.where(choose_r, ci * co > 0.0, tir_free & (ci * co < 0.0)) & (co != 0.0)

        scale_t = 1.0 / (etap * etap) if mode == RADIANCE else xp.ones(n)
        with xp.errstate(invalid="ignore", divide="ignore"):
            pvis = ggx.pdf_visible_normal(wo, m, alpha)
            pdf_r = pvis / (4.0 * xp.abs(dwo)) * p_refl
            pdf_t = pvis * xp.abs(dwi) / (dwi + dwo / etap) ** 2 * (1.0 - p_refl)
            g = ggx.smith_g2(wi, wo, alpha) / ggx.smith_g1(wo, alpha)
        # both lobes have f |cos| / pdf = (R + T) g (times the radiance scale for transmission)
        lobe_w = (R + T) * xp.where(choose_r, 1.0, scale_t)
        weight = lobe_w * xp.where(smooth, 1.0, g)
        pdf = xp.where(smooth, xp.where(choose_r, p_refl, 1.0 - p_refl), xp.where(choose_r, pdf_r, pdf_t))
        weight = xp.repeat(weight[:, None], 3, axis=1)
        return BSDFSample.build(wi, weight, pdf, xp.copy(smooth), ~choose_r, valid)

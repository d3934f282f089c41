"""Rough dielectric interface: GGX reflection and transmission (Walter et al. 2007; pbrt-v4
``DielectricBxDF``), with the height-correlated Smith G2."""

from __future__ import annotations

import numpy as np

from ..formula import formula, isfinite, maximum, negate, sqrt, where
from . import ggx
from .base import BSDF, RADIANCE, SMOOTH_ALPHA, BSDFSample, as_param, rows
from .frame import reflected, refracted
from .fresnel import fresnel_dielectric_cos

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
        return rows(self.alpha, n, "alpha", xp), rows(self.ior, n, "ior", xp)

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        f, _ = self._eval_pdf(wi, wo, mode, xp)
        return xp.repeat(f[:, None], 3, axis=1)

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        return self._eval_pdf(wi, wo, mode, xp)[1]

    def eval_pdf(self, wi, wo, mode=RADIANCE, check=True) -> tuple[np.ndarray, np.ndarray]:
        """``eval`` (as (N,): the interface is grey) and ``pdf`` together, from one half vector, Fresnel
        term and microfacet density: what a caller that needs both (MIS) pays once."""
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        return self._eval_pdf(wi, wo, mode, xp)

    def _eval_pdf(self, wi, wo, mode, xp):
        alpha, ior = self._rows(wi.shape[0], xp)
        with xp.errstate(invalid="ignore", divide="ignore"):
            return rough_dielectric_eval_pdf(
                wi[:, 0], wi[:, 1], wi[:, 2], wo[:, 0], wo[:, 1], wo[:, 2],
                alpha, ior, mode == RADIANCE, self.reflection_only,
            )  # fmt: skip

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u, xp = self._sample_inputs(wo, u_lobe, u, mode, check)
        alpha, ior = self._rows(wo.shape[0], xp)
        with xp.errstate(invalid="ignore", divide="ignore"):
            x, y, z, weight, pdf, delta, reflected, valid = rough_dielectric_sample(
                wo[:, 0], wo[:, 1], wo[:, 2], alpha, ior, u_lobe, u[:, 0], u[:, 1],
                mode == RADIANCE, self.reflection_only,
            )  # fmt: skip
        wi = xp.stack([x, y, z], axis=-1)
        weight = xp.repeat(weight[:, None], 3, axis=1)
        return BSDFSample.build(wi, weight, pdf, delta, negate(reflected), valid)


@formula
def is_smooth(alpha, ior):
    """Rows of delta lobes: a smooth interface or an index-matched one (class docstring)."""
    return (alpha < SMOOTH_ALPHA) | (abs(ior - 1.0) < INDEX_MATCHED_TOL)


@formula(inline=True)
def rough_dielectric_eval_pdf(ix, iy, iz, ox, oy, oz, alpha, ior, radiance, reflection_only):
    """(f, pdf) of :class:`RoughDielectric` at wi, wo (components) for one interface (alpha, ior):
    the one implementation of both (class docstring); ``radiance``: RADIANCE mode, else IMPORTANCE.

    The generalised half vector m (facing +z) of pbrt-v4's ``DielectricBxDF::f``: m ~ wi etap + wo, with
    etap = 1 for reflection, ior when wo is above, 1 / ior below."""
    refl = iz * oz > 0.0
    etap = where(refl, 1.0, where(oz > 0.0, ior, 1.0 / ior))
    hx, hy, hz = ix * etap + ox, iy * etap + oy, iz * etap + oz
    s = where(hz < 0.0, -1.0, 1.0)
    hn = sqrt(hx * hx + hy * hy + hz * hz)
    mx, my, mz = hx * s / hn, hy * s / hn, hz * s / hn
    dwi = ix * mx + iy * my + iz * mz
    dwo = ox * mx + oy * my + oz * mz
    ok = (iz != 0.0) & (oz != 0.0) & (hn > 0.0) & (dwi * iz > 0.0) & (dwo * oz > 0.0)
    live = ok & negate(is_smooth(alpha, ior))
    a = maximum(alpha, ggx.MIN_ALPHA)
    F = fresnel_dielectric_cos(dwo, ior)
    d = ggx.ndf_cos(mz, a)
    dg = d * ggx.g2_cos(iz, oz, a)
    f = dg * F / abs(4.0 * iz * oz)
    pvis = ggx.visible_normal_pdf(oz, dwo, d, a)
    p = pvis / (4.0 * abs(dwo))  # reflection_only: R / (R + T) = 1
    if reflection_only:
        live = live & refl
    else:
        half = dwi + dwo / etap
        ft = dg * (1.0 - F) * abs(dwi * dwo / (half * half * iz * oz))
        if radiance:
            ft = ft / (etap * etap)
        f = where(refl, f, ft)
        p = where(refl, p * F, pvis * abs(dwi) / (half * half) * (1.0 - F))
    f = where(live, f, 0.0)
    p = where(live, p, 0.0)
    return where(isfinite(f), f, 0.0), where(isfinite(p), p, 0.0)


@formula
def rough_dielectric_sample(ox, oy, oz, alpha, ior, u_lobe, u0, u1, radiance, reflection_only):
    """(wix, wiy, wiz, weight, pdf, delta, reflected, valid): one sample of :class:`RoughDielectric` seen
    from wo (components), before :meth:`BSDFSample.build`'s checks. Smooth rows use the geometric normal,
    rough rows a visible microfacet normal; reflection is chosen with probability R / (R + T) (T = 0 for
    ``reflection_only``), so both lobes have f |cos| / pdf = (R + T) G2 / G1 (times 1 / etap^2 for radiance
    transmission)."""
    smooth = is_smooth(alpha, ior)
    a = maximum(alpha, ggx.MIN_ALPHA)
    mx, my, mz = ggx.visible_normal(ox, oy, oz, a, u0, u1)
    mx, my, mz = where(smooth, 0.0, mx), where(smooth, 0.0, my), where(smooth, 1.0, mz)
    dwo = ox * mx + oy * my + oz * mz
    R = fresnel_dielectric_cos(dwo, ior)
    T = R * 0.0 if reflection_only else 1.0 - R
    p_refl = R / (R + T)
    choose_r = u_lobe < p_refl
    tx, ty, tz, tir_free = refracted(ox, oy, oz, mx, my, mz, ior)
    rx, ry, rz = reflected(ox, oy, oz, mx, my, mz)
    ix, iy, iz = where(choose_r, rx, tx), where(choose_r, ry, ty), where(choose_r, rz, tz)
    dwi = ix * mx + iy * my + iz * mz
    valid = where(choose_r, iz * oz > 0.0, tir_free & (iz * oz < 0.0)) & (oz != 0.0)
    etap = where(dwo > 0.0, ior, 1.0 / ior)
    scale_t = 1.0 / (etap * etap) if radiance else etap * 0.0 + 1.0
    pvis = ggx.visible_normal_pdf(oz, dwo, ggx.ndf_cos(mz, a), a)
    half = dwi + dwo / etap
    pdf_r = pvis / (4.0 * abs(dwo)) * p_refl
    pdf_t = pvis * abs(dwi) / (half * half) * (1.0 - p_refl)
    g = ggx.g2_cos(iz, oz, a) / ggx.g1_cos(oz, a)
    weight = (R + T) * where(choose_r, 1.0, scale_t) * where(smooth, 1.0, g)
    pdf = where(smooth, where(choose_r, p_refl, 1.0 - p_refl), where(choose_r, pdf_r, pdf_t))
    return ix, iy, iz, weight, pdf, smooth, choose_r, valid

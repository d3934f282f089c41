"""Trowbridge-Reitz (GGX) microfacet distribution, isotropic, in the local frame (normal +z).

Masking is Smith's with the height-correlated G2 of pbrt-v4 (Heitz 2014): Mitsuba 3 uses the
separable G1(wi) G1(wo) instead. Visible normals are sampled with the spherical caps of
Dupuy & Benyoub 2023 ("Sampling Visible GGX Normals with Spherical Caps").

Each quantity is one :func:`~addon.core.formula.formula` over cosines and components (``*_cos``,
``visible_normal``), which the renderer's compiled loops call with scalars; the functions over
direction arrays (``ndf``, ``smith_g2``, ...) apply those formulas to columns.

``alpha`` is clamped to >= ``MIN_ALPHA`` so that near-specular lobes stay finite; callers that
want a true delta lobe test ``alpha < SMOOTH_ALPHA`` themselves (see ``base.py``).
"""

from __future__ import annotations

import math

import numpy as np

from ..formula import clip, formula, isfinite, maximum, sqrt, turn_cos_sin, where
from ..xp import namespace
from .base import SMOOTH_ALPHA
from .frame import dot

MIN_ALPHA = 1e-4


def _alpha(alpha, xp=np) -> np.ndarray:
    return xp.maximum(xp.asarray(alpha, dtype=xp.float64), MIN_ALPHA)


# --- the formulas (cosines and components; alpha already clamped) ---------------------------------


@formula
def ndf_cos(mz, alpha):
    """D(m) from m's cosine (see :func:`ndf`)."""
    a2 = alpha * alpha
    d = mz * mz * (a2 - 1.0) + 1.0
    return where(mz > 0.0, a2 / (math.pi * d * d), 0.0)


@formula
def lambda_cos(wz, alpha):
    """Smith's Lambda from w's cosine (see :func:`smith_lambda`)."""
    a2 = alpha * alpha
    c2 = wz * wz
    x = a2 * (1.0 - c2) / c2
    lam = x / (2.0 * (1.0 + sqrt(1.0 + x)))
    return where(c2 > 0.0, lam, math.inf)


@formula
def g1_cos(wz, alpha):
    return 1.0 / (1.0 + lambda_cos(wz, alpha))


@formula
def g2_cos(iz, oz, alpha):
    return 1.0 / (1.0 + lambda_cos(iz, alpha) + lambda_cos(oz, alpha))


@formula
def visible_normal(wx, wy, wz, alpha, u0, u1):
    """(mx, my, mz): a visible normal from w for uniforms (u0, u1) (see :func:`sample_visible_normal`)."""
    sign = where(wz < 0.0, -1.0, 1.0)
    # stretch the (upper-hemisphere) view direction to the unit-roughness configuration
    sx = wx * sign * alpha
    sy = wy * sign * alpha
    sz = abs(wz)
    inv = 1.0 / sqrt(sx * sx + sy * sy + sz * sz)
    sx, sy, sz = sx * inv, sy * inv, sz * inv
    # sample the spherical cap z in (-sz, 1]
    cos_phi, sin_phi = turn_cos_sin(u0)  # the azimuth 2 pi u0
    z = (1.0 - u1) * (1.0 + sz) - sz
    sin_t = sqrt(clip(1.0 - z * z, 0.0, 1.0))
    mx = (sin_t * cos_phi + sx) * alpha
    my = (sin_t * sin_phi + sy) * alpha
    mz = maximum(z + sz, 0.0)
    n = sqrt(mx * mx + my * my + mz * mz)
    ok = n > 0.0
    return where(ok, mx / n, 0.0), where(ok, my / n, 0.0), where(ok, mz / n, 1.0)


@formula
def visible_normal_pdf(wz, w_dot_m, d, alpha):
    """Density of :func:`visible_normal` from w's cosine, w.m and D(m) (see :func:`pdf_visible_normal`)."""
    sign = where(wz < 0.0, -1.0, 1.0)
    p = g1_cos(wz, alpha) * maximum(0.0, sign * w_dot_m) * d / abs(wz)
    return where((wz != 0.0) & isfinite(p), p, 0.0)


@formula
def reflection_terms(ix, iy, iz, ox, oy, oz, alpha):
    """(dg, pdf, wo.m) of the GGX reflection at wi, wo (components) about their half vector m (facing +z), for any
    Fresnel term F: f = dg F with dg = D(m) G2 / (4 |cos wi cos wo|); ``pdf`` the density of reflecting wo about a
    visible normal (``visible_normal``); both 0 (and finite) unless wi and wo lie on one side, m exists and alpha
    >= SMOOTH_ALPHA (a delta mirror below). ``alpha`` as given: clamped to MIN_ALPHA here. The microfacet part of
    ``RoughConductor`` (its f over F, its pdf) and of the reflection of ``rough_dielectric_eval_pdf``."""
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    s = where(hz < 0.0, -1.0, 1.0)
    hn = sqrt(hx * hx + hy * hy + hz * hz)
    mx, my, mz = hx * s / hn, hy * s / hn, hz * s / hn
    dwo = ox * mx + oy * my + oz * mz
    a = maximum(alpha, MIN_ALPHA)
    d = ndf_cos(mz, a)
    dg = d * g2_cos(iz, oz, a) / (4.0 * abs(iz * oz))
    p = visible_normal_pdf(oz, dwo, d, a) / (4.0 * abs(dwo))
    ok = (iz * oz > 0.0) & (hn > 0.0) & (alpha >= SMOOTH_ALPHA)
    return where(ok & isfinite(dg), dg, 0.0), where(ok & isfinite(p), p, 0.0), abs(dwo)


# --- over direction arrays ---------------------------------------------------------------------


def ndf(m: np.ndarray, alpha) -> np.ndarray:
    """D(m) in 1/sr (projected-area normalised: integral of D(m) cos(m) dm = 1); 0 for m.z <= 0."""
    xp = namespace(m, alpha)
    return ndf_cos(m[..., 2], _alpha(alpha, xp))


def smith_lambda(w: np.ndarray, alpha) -> np.ndarray:
    """Smith's Lambda(w) = (sqrt(1 + alpha^2 tan^2) - 1) / 2; infinite at grazing w.

    Written as a^2 t^2 / (2 (1 + sqrt(1 + a^2 t^2))) to avoid cancellation at small alpha.
    Depends on |cos w| only, so directions below the surface are mirrored.
    """
    xp = namespace(w, alpha)
    with xp.errstate(divide="ignore", invalid="ignore"):
        return lambda_cos(w[..., 2], _alpha(alpha, xp))


def smith_g1(w: np.ndarray, alpha) -> np.ndarray:
    """Smith masking G1(w) = 1 / (1 + Lambda(w)) (0 at grazing)."""
    return 1.0 / (1.0 + smith_lambda(w, alpha))


def smith_g2(wi: np.ndarray, wo: np.ndarray, alpha) -> np.ndarray:
    """Height-correlated masking-shadowing G2 = 1 / (1 + Lambda(wi) + Lambda(wo)) (pbrt-v4)."""
    return 1.0 / (1.0 + smith_lambda(wi, alpha) + smith_lambda(wo, alpha))


def sample_visible_normal(w: np.ndarray, alpha, u: np.ndarray) -> np.ndarray:
    """Sample a microfacet normal m (m.z > 0) from the normals visible from ``w``.

    Density :func:`pdf_visible_normal`. ``w`` below the surface is mirrored to +z first
    (the distribution is symmetric), so m always faces +z. ``u`` is (N, 2) in [0, 1).
    """
    xp = namespace(w, alpha, u)
    with xp.errstate(invalid="ignore", divide="ignore"):
        m = visible_normal(w[..., 0], w[..., 1], w[..., 2], _alpha(alpha, xp), u[..., 0], u[..., 1])
    return xp.stack(m, axis=-1)


def pdf_visible_normal(w: np.ndarray, m: np.ndarray, alpha, d=None) -> np.ndarray:
    """Density of :func:`sample_visible_normal`: G1(w) max(0, w'.m) D(m) / |cos w|, with w' = w
    mirrored to the upper hemisphere (so for w below the surface the facing test is -w.m > 0).
    ``d``: D(m) when the caller has it already (:func:`ndf`)."""
    xp = namespace(w, m, alpha)
    a = _alpha(alpha, xp)
    with xp.errstate(invalid="ignore", divide="ignore"):
        return visible_normal_pdf(w[..., 2], dot(w, m), ndf_cos(m[..., 2], a) if d is None else d, a)

"""Trowbridge-Reitz (GGX) microfacet distribution, isotropic, in the local frame (normal +z).

Masking is Smith's with the height-correlated G2 of pbrt-v4 (Heitz 2014): Mitsuba 3 uses the
separable G1(wi) G1(wo) instead. Visible normals are sampled with the spherical caps of
Dupuy & Benyoub 2023 ("Sampling Visible GGX Normals with Spherical Caps").

``alpha`` is clamped to >= ``MIN_ALPHA`` so that near-specular lobes stay finite; callers that
want a true delta lobe test ``alpha < SMOOTH_ALPHA`` themselves (see ``base.py``).
"""

from __future__ import annotations

import numpy as np

from ..xp import namespace
from .frame import dot

MIN_ALPHA = 1e-4


def _alpha(alpha, xp=np) -> np.ndarray:
    return xp.maximum(xp.asarray(alpha, dtype=xp.float64), MIN_ALPHA)


def ndf(m: np.ndarray, alpha) -> np.ndarray:
    """D(m) in 1/sr (projected-area normalised: integral of D(m) cos(m) dm = 1); 0 for m.z <= 0."""
    xp = namespace(m, alpha)
    a2 = _alpha(alpha, xp) ** 2
    c2 = m[..., 2] ** 2
    d = c2 * (a2 - 1.0) + 1.0
    return xp.where(m[..., 2] > 0.0, a2 / (xp.pi * d * d), 0.0)


def smith_lambda(w: np.ndarray, alpha) -> np.ndarray:
    """Smith's Lambda(w) = (sqrt(1 + alpha^2 tan^2) - 1) / 2; infinite at grazing w.

    Written as a^2 t^2 / (2 (1 + sqrt(1 + a^2 t^2))) to avoid cancellation at small alpha.
    Depends on |cos w| only, so directions below the surface are mirrored.
    """
    xp = namespace(w, alpha)
    a2 = _alpha(alpha, xp) ** 2
    c2 = w[..., 2] ** 2
    with xp.errstate(divide="ignore", invalid="ignore"):
        x = a2 * (1.0 - c2) / c2
        lam = x / (2.0 * (1.0 + xp.sqrt(1.0 + x)))
    return xp.where(c2 > 0.0, lam, xp.inf)


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
    a = _alpha(alpha, xp)
    sign = xp.where(w[..., 2] < 0.0, -1.0, 1.0)
    # stretch the (upper-hemisphere) view direction to the unit-roughness configuration
    wx = w[..., 0] * sign * a
    wy = w[..., 1] * sign * a
    wz = xp.abs(w[..., 2])
    inv = 1.0 / xp.sqrt(wx * wx + wy * wy + wz * wz)
    wx, wy, wz = wx * inv, wy * inv, wz * inv
    # sample the spherical cap z in (-wz, 1]
    phi = 2.0 * xp.pi * u[..., 0]
    z = (1.0 - u[..., 1]) * (1.0 + wz) - wz
    sin_t = xp.sqrt(xp.clip(1.0 - z * z, 0.0, 1.0))
    hx = sin_t * xp.cos(phi) + wx
    hy = sin_t * xp.sin(phi) + wy
    hz = z + wz
    m = xp.stack([hx * a, hy * a, xp.maximum(hz, 0.0)], axis=-1)
    n = xp.sqrt(dot(m, m))[..., None]
    with xp.errstate(invalid="ignore", divide="ignore"):
        m = m / n
    return xp.where(n > 0.0, m, xp.asarray([0.0, 0.0, 1.0]))


def pdf_visible_normal(w: np.ndarray, m: np.ndarray, alpha, d=None) -> np.ndarray:
    """Density of :func:`sample_visible_normal`: G1(w) max(0, w'.m) D(m) / |cos w|, with w' = w
    mirrored to the upper hemisphere (so for w below the surface the facing test is -w.m > 0).
    ``d``: D(m) when the caller has it already (:func:`ndf`)."""
    xp = namespace(w, m, alpha)
    cz = w[..., 2]
    sign = xp.where(cz < 0.0, -1.0, 1.0)
    wm = xp.maximum(0.0, sign * dot(w, m))
    with xp.errstate(invalid="ignore", divide="ignore"):
        p = smith_g1(w, alpha) * wm * (ndf(m, alpha) if d is None else d) / xp.abs(cz)
    return xp.where((cz != 0.0) & xp.isfinite(p), p, 0.0)

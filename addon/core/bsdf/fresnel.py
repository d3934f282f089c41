"""Fresnel reflectance: exact unpolarised dielectric and complex conductor (pbrt-v4, section 9.3)."""

from __future__ import annotations

import numpy as np

from ..formula import clip, formula, isfinite, maximum, sqrt, where
from ..xp import namespace


@formula
def fresnel_dielectric_cos(cos_i, eta):
    """The formula of :func:`fresnel_dielectric` (one cosine, one relative index)."""
    c = clip(cos_i, -1.0, 1.0)
    e = where(c < 0.0, 1.0 / eta, eta)
    c = abs(c)
    sin2_t = (1.0 - c * c) / (e * e)
    cos_t = sqrt(maximum(0.0, 1.0 - sin2_t))
    r_parl = (e * c - cos_t) / (e * c + cos_t)
    r_perp = (c - e * cos_t) / (c + e * cos_t)
    r = 0.5 * (r_parl * r_parl + r_perp * r_perp)
    return where(sin2_t >= 1.0, 1.0, where(isfinite(r), r, 1.0))


def fresnel_dielectric(cos_i, eta) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric interface (pbrt-v4 ``FrDielectric``).

    ``eta`` = n_t / n_i is the relative index for light arriving on the side the normal points
    to. ``cos_i < 0`` means arriving from the other side: then ``eta`` is inverted. Total
    internal reflection gives 1. Shapes broadcast; returns float64.
    """
    xp = namespace(cos_i, eta)
    with xp.errstate(invalid="ignore", divide="ignore"):
        return fresnel_dielectric_cos(xp.asarray(cos_i, dtype=xp.float64), xp.asarray(eta, dtype=xp.float64))


@formula
def fresnel_conductor_cos(cos_i, eta, k):
    """The formula of :func:`fresnel_conductor` (one cosine, clamped to [0, 1]; one channel's eta and k)."""
    c = clip(cos_i, 0.0, 1.0)
    cos2 = c * c
    sin2 = 1.0 - cos2
    eta2, k2 = eta * eta, k * k
    t0 = eta2 - k2 - sin2
    a2b2 = sqrt(t0 * t0 + 4.0 * eta2 * k2)  # a^2 + b^2 = |n^2 - sin^2|
    t1 = a2b2 + cos2
    a = sqrt(maximum(0.0, 0.5 * (a2b2 + t0)))
    t2 = 2.0 * c * a
    t3 = cos2 * a2b2 + sin2 * sin2
    t4 = t2 * sin2
    rs = (t1 - t2) / (t1 + t2)
    rp = rs * (t3 - t4) / (t3 + t4)
    r = 0.5 * (rs + rp)
    return where(isfinite(r), clip(r, 0.0, 1.0), 1.0)


def fresnel_conductor(cos_i, eta, k) -> np.ndarray:
    """Fresnel reflectance of a conductor with complex index ``eta + i k``.

    The exact unpolarised reflectance of pbrt-v4 ``FrComplex``, (|r_parl|^2 + |r_perp|^2) / 2,
    written in real arithmetic (pbrt-v3 ``FrConductor``, Mitsuba's ``fresnel_conductor``) because
    complex numpy is about ten times slower. ``cos_i`` of shape (N,) is clamped to [0, 1] (a
    conductor is seen from outside only); ``eta`` and ``k`` are RGB ``(N, 3)`` or ``(3,)``.
    Returns ``(N, 3)`` float64 in [0, 1].
    """
    xp = namespace(cos_i, eta, k)
    c = xp.asarray(cos_i, dtype=xp.float64)[..., None]
    with xp.errstate(invalid="ignore", divide="ignore"):
        return fresnel_conductor_cos(c, xp.asarray(eta, dtype=xp.float64), xp.asarray(k, dtype=xp.float64))

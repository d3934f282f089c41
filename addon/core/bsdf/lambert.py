"""Lambertian diffuse reflection."""

from __future__ import annotations

import math

import numpy as np

from ..formula import formula, maximum, quarter_cos_sin, sqrt, where
from ..xp import namespace
from .base import BSDF, RADIANCE, BSDFSample, as_param, rows


@formula
def concentric_disk(u0, u1):
    """(x, y): the point of the unit disk where Shirley and Chiu's concentric map takes the uniforms (u0, u1),
    evenly in area: the square's ring of half-width |r| to the disk's circle of radius |r|."""
    ox = 2.0 * u0 - 1.0
    oy = 2.0 * u1 - 1.0
    use_x = abs(ox) > abs(oy)
    r = where(use_x, ox, oy)
    # the angle from the nearer axis, within pi / 4 of it (the centre: 0)
    t = where(use_x, (math.pi / 4.0) * (oy / ox), (math.pi / 4.0) * (ox / oy))
    c, s = quarter_cos_sin(where((ox == 0.0) & (oy == 0.0), 0.0, t))
    return r * where(use_x, c, s), r * where(use_x, s, c)


@formula
def cosine_direction(u0, u1):
    """(x, y, z): the formula of :func:`sample_cosine_hemisphere` for one pair of uniforms."""
    x, y = concentric_disk(u0, u1)
    return x, y, sqrt(maximum(0.0, 1.0 - x * x - y * y))


def sample_cosine_hemisphere(u: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions on the upper hemisphere (Malley's method on a concentric
    disk, Shirley & Chiu 1997); density cos(theta) / pi. ``u`` (N, 2) -> (N, 3)."""
    xp = namespace(u)
    with xp.errstate(divide="ignore", invalid="ignore"):
        return xp.stack(cosine_direction(u[:, 0], u[:, 1]), axis=-1)


class Lambertian(BSDF):
    """f = albedo / pi for wi and wo on the same side of the surface (either side), else 0.

    Reciprocal; the mode does not matter. Sampling is cosine-weighted on wo's side, so the
    sample weight is the albedo.
    """

    _params = ("albedo",)

    def __init__(self, albedo):
        self.albedo = as_param(albedo, "Lambertian.albedo", lo=0.0, hi=1.0, rgb=True)

    @classmethod
    def of_valid_rows(cls, albedo: np.ndarray) -> "Lambertian":
        """A Lambertian over per-row albedos (N, 3) that are float64, finite and non-negative by construction
        (the renderer's texture lookups, and a Blender colour above 1, which Cycles renders as it is): the same
        object as ``Lambertian(albedo)`` without its checks (which hold an albedo to [0, 1], a physical surface's
        range), which cost several passes over every hit of every bounce."""
        out = object.__new__(cls)
        out.albedo = albedo
        return out

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        albedo = rows(self.albedo, wi.shape[0], "albedo", xp)
        return lambert_f(wi[:, 2:3], wo[:, 2:3], albedo)

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        return lambert_pdf(wi[:, 2], wo[:, 2])

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u, xp = self._sample_inputs(wo, u_lobe, u, mode, check)
        n = wo.shape[0]
        with xp.errstate(divide="ignore", invalid="ignore"):
            x, y, z, pdf, valid = lambert_sample(wo[:, 2], u[:, 0], u[:, 1])
        weight = xp.array(rows(self.albedo, n, "albedo", xp), dtype=xp.float64)
        false = xp.zeros(n, dtype=bool)
        return BSDFSample.build(xp.stack([x, y, z], axis=-1), weight, pdf, false, false, valid)


@formula
def lambert_f(iz, oz, albedo):
    """f = albedo / pi for wi and wo on the same side (their cosines iz, oz), else 0."""
    return where(iz * oz > 0.0, albedo / math.pi, 0.0)


@formula
def lambert_pdf(iz, oz):
    """The density of :func:`lambert_sample` at a direction of cosine iz, given oz."""
    return where(iz * oz > 0.0, abs(iz) / math.pi, 0.0)


@formula
def lambert_sample(oz, u0, u1):
    """(x, y, z, pdf, valid): a cosine-weighted direction on wo's side (wo's cosine oz); the weight is the
    albedo."""
    x, y, z = cosine_direction(u0, u1)
    z = z * where(oz < 0.0, -1.0, 1.0)
    return x, y, z, abs(z) / math.pi, (oz != 0.0) & (z != 0.0)

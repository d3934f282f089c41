"""Lambertian diffuse reflection."""

from __future__ import annotations

import numpy as np

from ..xp import namespace
from .base import BSDF, RADIANCE, BSDFSample, as_param, rows


def sample_cosine_hemisphere(u: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions on the upper hemisphere (Malley's method on a concentric
    disk, Shirley & Chiu 1997); density cos(theta) / pi. ``u`` (N, 2) -> (N, 3)."""
    xp = namespace(u)
    ox = 2.0 * u[:, 0] - 1.0
    oy = 2.0 * u[:, 1] - 1.0
    use_x = xp.abs(ox) > xp.abs(oy)
    with xp.errstate(divide="ignore", invalid="ignore"):
        r = xp.where(use_x, ox, oy)
        theta = xp.where(use_x, (xp.pi / 4.0) * (oy / ox), xp.pi / 2.0 - (xp.pi / 4.0) * (ox / oy))
    theta = xp.where((ox == 0.0) & (oy == 0.0), 0.0, theta)
    x = r * xp.cos(theta)
    y = r * xp.sin(theta)
    z = xp.sqrt(xp.maximum(0.0, 1.0 - x * x - y * y))
    return xp.stack([x, y, z], axis=-1)


class Lambertian(BSDF):
    """f = albedo / pi for wi and wo on the same side of the surface (either side), else 0.

    Reciprocal; the mode does not matter. Sampling is cosine-weighted on wo's side, so the
    sample weight is the albedo.
    """

    _params = ("albedo",)

    def __init__(self, albedo):
        self.albedo = as_param(albedo, "Lambertian.albedo", lo=0.0, hi=1.0, rgb=True)

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        n = wi.shape[0]
        ok = (wi[:, 2] * wo[:, 2] > 0.0)[:, None]
        return xp.where(ok, rows(self.albedo, n, "albedo", xp) / xp.pi, 0.0)

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo, xp = self._inputs(wi, wo, mode, check)
        ok = wi[:, 2] * wo[:, 2] > 0.0
        return xp.where(ok, xp.abs(wi[:, 2]) / xp.pi, 0.0)

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u, xp = self._sample_inputs(wo, u_lobe, u, mode, check)
        n = wo.shape[0]
        wi = sample_cosine_hemisphere(u)
        wi[:, 2] *= xp.where(wo[:, 2] < 0.0, -1.0, 1.0)
        pdf = xp.abs(wi[:, 2]) / xp.pi
        valid = (wo[:, 2] != 0.0) & (wi[:, 2] != 0.0)
        weight = xp.array(rows(self.albedo, n, "albedo", xp), dtype=xp.float64)
        false = xp.zeros(n, dtype=bool)
        return BSDFSample.build(wi, weight, pdf, false, false, valid)

"""Lambertian diffuse reflection."""

from __future__ import annotations

import numpy as np

from .base import BSDF, RADIANCE, BSDFSample, as_param, rows


def sample_cosine_hemisphere(u: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions on the upper hemisphere (Malley's method on a concentric
    disk, Shirley & Chiu 1997); density cos(theta) / pi. ``u`` (N, 2) -> (N, 3)."""
    ox = 2.0 * u[:, 0] - 1.0
    oy = 2.0 * u[:, 1] - 1.0
    use_x = np.abs(ox) > np.abs(oy)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(use_x, ox, oy)
        theta = np.where(use_x, (np.pi / 4.0) * (oy / ox), np.pi / 2.0 - (np.pi / 4.0) * (ox / oy))
    theta = np.where((ox == 0.0) & (oy == 0.0), 0.0, theta)
    x = r * np.cos(theta)
    y = r * np.sin(theta)
    z = np.sqrt(np.maximum(0.0, 1.0 - x * x - y * y))
    return np.stack([x, y, z], axis=-1)


class Lambertian(BSDF):
    """f = albedo / pi for wi and wo on the same side of the surface (either side), else 0.

    Reciprocal; the mode does not matter. Sampling is cosine-weighted on wo's side, so the
    sample weight is the albedo.
    """

    _params = ("albedo",)

    def __init__(self, albedo):
        self.albedo = as_param(albedo, "Lambertian.albedo", lo=0.0, hi=1.0, rgb=True)

    def eval(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo = self._inputs(wi, wo, mode, check)
        n = wi.shape[0]
        ok = (wi[:, 2] * wo[:, 2] > 0.0)[:, None]
        return np.where(ok, rows(self.albedo, n, "albedo") / np.pi, 0.0)

    def pdf(self, wi, wo, mode=RADIANCE, check=True) -> np.ndarray:
        wi, wo = self._inputs(wi, wo, mode, check)
        ok = wi[:, 2] * wo[:, 2] > 0.0
        return np.where(ok, np.abs(wi[:, 2]) / np.pi, 0.0)

    def sample(self, wo, u_lobe, u, mode=RADIANCE, check=True) -> BSDFSample:
        wo, u_lobe, u = self._sample_inputs(wo, u_lobe, u, mode, check)
        n = wo.shape[0]
        wi = sample_cosine_hemisphere(u)
        wi[:, 2] *= np.where(wo[:, 2] < 0.0, -1.0, 1.0)
        pdf = np.abs(wi[:, 2]) / np.pi
        valid = (wo[:, 2] != 0.0) & (wi[:, 2] != 0.0)
        weight = np.array(rows(self.albedo, n, "albedo"), dtype=np.float64)
        false = np.zeros(n, dtype=bool)
        return BSDFSample.build(wi, weight, pdf, false, false, valid)

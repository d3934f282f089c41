"""Henyey-Greenstein phase function (pbrt-v4 convention)."""

from __future__ import annotations

import numpy as np

from .base import as_directions, as_param, as_uniform, rows, same_rows
from .frame import coordinate_system, to_world


class HenyeyGreenstein:
    """p(wi, wo) = (1 - g^2) / (4 pi (1 + g^2 + 2 g cos)^(3/2)), cos = wi.wo, in 1/sr.

    Both directions point away from the scattering point, so ``g > 0`` (forward scattering)
    concentrates wi around -wo. Symmetric in (wi, wo); sampling is exact, so eval == pdf.
    ``g`` is a scalar or per-row (N,) array in (-1, 1).
    """

    _params = ("g",)

    def __init__(self, g):
        self.g = as_param(g, "HenyeyGreenstein.g", lo=-1.0, hi=1.0, lo_open=True)
        if np.any(self.g >= 1.0):
            raise ValueError(f"HenyeyGreenstein.g = {self.g.max()} is outside the valid range (-1, 1)")

    def take(self, index) -> "HenyeyGreenstein":
        out = object.__new__(HenyeyGreenstein)
        out.g = self.g if self.g.shape[0] == 1 else self.g[index]
        return out

    @staticmethod
    def _value(cos, g):
        denom = 1.0 + g * g + 2.0 * g * cos
        return (1.0 - g * g) / (4.0 * np.pi * denom * np.sqrt(np.maximum(denom, 1e-300)))

    def eval(self, wi, wo, check=True) -> np.ndarray:
        wi = as_directions(wi, "wi", check)
        wo = as_directions(wo, "wo", check)
        n = same_rows("wi", wi, "wo", wo)
        cos = np.clip(np.einsum("ij,ij->i", wi, wo), -1.0, 1.0)
        return self._value(cos, rows(self.g, n, "g"))

    pdf = eval

    def sample(self, wo, u, check=True) -> tuple[np.ndarray, np.ndarray]:
        """wi with density p(wi, wo); returns ``(wi (N, 3), pdf (N,))``. ``u`` (N, 2) in [0, 1)."""
        wo = as_directions(wo, "wo", check)
        n = wo.shape[0]
        u = as_uniform(u, "u", n, 2, check)
        g = rows(self.g, n, "g")
        iso = np.abs(g) < 1e-3
        gs = np.where(iso, 0.5, g)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = (1.0 - gs * gs) / (1.0 + gs - 2.0 * gs * u[:, 0])
            cos_hg = -(1.0 + gs * gs - s * s) / (2.0 * gs)
        cos = np.clip(np.where(iso, 1.0 - 2.0 * u[:, 0], cos_hg), -1.0, 1.0)
        sin = np.sqrt(np.maximum(0.0, 1.0 - cos * cos))
        phi = 2.0 * np.pi * u[:, 1]
        local = np.stack([sin * np.cos(phi), sin * np.sin(phi), cos], axis=-1)
        s_, t_ = coordinate_system(wo)
        wi = to_world(local, s_, t_, wo)
        return wi, self._value(cos, g)

"""Henyey-Greenstein phase function (pbrt-v4 convention)."""

from __future__ import annotations

import numpy as np

from ..xp import namespace
from .base import as_directions, as_param, as_uniform, rows, same_rows
from .frame import coordinate_system, dot, to_world


class HenyeyGreenstein:
    """p(wi, wo) = (1 - g^2) / (4 pi (1 + g^2 + 2 g cos)^(3/2)), cos = wi.wo, in 1/sr.

    Both directions point away from the scattering point, so ``g > 0`` (forward scattering)
    concentrates wi around -wo. Symmetric in (wi, wo); sampling is exact, so eval == pdf.
    ``g`` is a scalar or per-row (N,) array in (-1, 1).
    """

    _params = ("g",)

    def __init__(self, g):
        self.g = as_param(g, "HenyeyGreenstein.g", lo=-1.0, hi=1.0, lo_open=True)
        xp = namespace(self.g)
        if xp.any(self.g >= 1.0):
            raise ValueError(f"HenyeyGreenstein.g = {float(xp.max(self.g))} is outside the valid range (-1, 1)")

    def take(self, index) -> "HenyeyGreenstein":
        out = object.__new__(HenyeyGreenstein)
        out.g = self.g if self.g.shape[0] == 1 else self.g[index]
        return out

    @staticmethod
    def _value(cos, g):
        xp = namespace(cos, g)
        denom = 1.0 + g * g + 2.0 * g * cos
        return (1.0 - g * g) / (4.0 * xp.pi * denom * xp.sqrt(xp.maximum(denom, 1e-300)))

    def eval(self, wi, wo, check=True) -> np.ndarray:
        xp = namespace(wi, wo, self.g)
        wi = as_directions(wi, "wi", check, xp)
        wo = as_directions(wo, "wo", check, xp)
        n = same_rows("wi", wi, "wo", wo)
        cos = xp.clip(dot(wi, wo), -1.0, 1.0)
        return self._value(cos, rows(self.g, n, "g", xp))

    pdf = eval

    def sample(self, wo, u, check=True) -> tuple[np.ndarray, np.ndarray]:
        """wi with density p(wi, wo); returns ``(wi (N, 3), pdf (N,))``. ``u`` (N, 2) in [0, 1)."""
        xp = namespace(wo, u, self.g)
        wo = as_directions(wo, "wo", check, xp)
        n = wo.shape[0]
        u = as_uniform(u, "u", n, 2, check, xp)
        g = rows(self.g, n, "g", xp)
        iso = xp.abs(g) < 1e-3
        gs = xp.where(iso, 0.5, g)
        with xp.errstate(invalid="ignore", divide="ignore"):
            s = (1.0 - gs * gs) / (1.0 + gs - 2.0 * gs * u[:, 0])
            cos_hg = -(1.0 + gs * gs - s * s) / (2.0 * gs)
        cos = xp.clip(xp.where(iso, 1.0 - 2.0 * u[:, 0], cos_hg), -1.0, 1.0)
        sin = xp.sqrt(xp.maximum(0.0, 1.0 - cos * cos))
        phi = 2.0 * xp.pi * u[:, 1]
        local = xp.stack([sin * xp.cos(phi), sin * xp.sin(phi), cos], axis=-1)
        s_, t_ = coordinate_system(wo)
        wi = to_world(local, s_, t_, wo)
        return wi, self._value(cos, g)

"""The sampling proxy of Neural Layered BRDFs (supplement section 1.2), exact.

pdf(wi | wo) = (1 - w) * p_gauss(wi | wo) + w * cos(theta_i) / pi

``p_gauss`` places the half vector h = normalize(wi + wo) by an isotropic 2D Gaussian of
standard deviation ``sigma`` over its projection (h_x, h_y) onto the unit disk, truncated to the
disk and renormalised. Densities change variables twice:

- projected disk -> half-vector solid angle: dA = cos(theta_h) d(omega_h), so
  p(omega_h) = p_disk(h_x, h_y) * cos(theta_h);
- half vector -> incident direction (reflection): p(wi) = p(omega_h) / (4 |wo . h|).

Both ``sigma`` and ``w`` are per-material (per-texel) numbers predicted once by the sampling
network, so sampling costs no network evaluation. Directions are in the local frame (+z normal).
"""

from __future__ import annotations

import numpy as np

from .. import kernels

SIGMA_MIN = 1e-3


def guess(stack) -> tuple[float, float]:
    """Proxy (sigma, w) from the stack's top interface until the sampling network provides them.

    sigma follows the top roughness (the half-vector spread), w the chance of a diffuse-like
    lobe. Any values keep the render unbiased (the proxy pdf is exact); they only shape noise.
    """
    top = stack.coatings[-1] if stack.coatings else stack.base
    alpha = float(getattr(top, "roughness", 1.0))
    diffuse_below = not hasattr(stack.base, "roughness") or stack.base.roughness > 0.3
    return max(alpha, 0.02), (0.5 if diffuse_below or stack.coatings else 0.1)


def material_params(models, z, stack) -> tuple[float, float]:
    """A material's proxy (sigma, w): the sampling network's for latent ``z`` (3, 32) where ``models`` has one,
    else :func:`guess` from ``stack``."""
    if models.has("sampling"):
        sigma, w = models.proxy_params(z)[0]
        return float(sigma), float(w)
    return guess(stack)


def params(sigma, w, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Proxy parameters (shared or (n,)) as (n,) float64 rows, sigma floored at SIGMA_MIN and w in [0, 1];
    ValueError unless finite."""
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n,))
    m = np.broadcast_to(np.asarray(w, dtype=np.float64), (n,))
    if not (np.isfinite(s).all() and np.isfinite(m).all()):
        raise ValueError("proxy parameters sigma and w must be finite")
    return np.maximum(s, SIGMA_MIN), np.clip(m, 0.0, 1.0)


def _rows(a, name: str) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got {a.shape}")
    return a


def pdf(wo: np.ndarray, wi: np.ndarray, sigma, w) -> np.ndarray:
    """Solid-angle density (N,) of :func:`sample` choosing ``wi`` given ``wo``; 0 below the horizon.
    One compiled pass over the rows (``kernels.proxy_pdf``)."""
    wo, wi = _rows(wo, "wo"), _rows(wi, "wi")
    if wi.shape != wo.shape:
        raise ValueError(f"wo and wi must have the same shape, got {wo.shape} and {wi.shape}")
    s, m = params(sigma, w, wo.shape[0])
    return kernels.proxy_pdf(wo, wi, s, m)


def sample(wo: np.ndarray, sigma, w, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample wi (N, 3) with its density (N,); ``u`` (N, 3) uniform in [0, 1).

    ``u[:, 0]`` picks the lobe, ``u[:, 1:]`` place the direction. Samples that fall below
    the horizon (possible for the Gaussian lobe at grazing ``wo``) come back with pdf 0.
    """
    wi = sample_directions(wo, sigma, w, u)
    return wi, pdf(wo, wi, sigma, w)


def sample_directions(wo: np.ndarray, sigma, w, u: np.ndarray) -> np.ndarray:
    """The directions of :func:`sample` without their density (for a caller that evaluates :func:`pdf`
    on them together with other directions): ``kernels.proxy_directions``, where the lobes are."""
    wo = _rows(wo, "wo")
    u = np.ascontiguousarray(u, dtype=np.float64)
    if u.shape != (wo.shape[0], 3):
        raise ValueError(f"wo must be (N, 3) and u (N, 3), got {wo.shape} and {u.shape}")
    s, m = params(sigma, w, wo.shape[0])
    return kernels.proxy_directions(wo, s, m, u)

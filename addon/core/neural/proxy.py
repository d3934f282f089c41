"""The sampling proxy of Neural Layered BRDFs (supplement section 1.2), exact in numpy.

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

SIGMA_MIN = 1e-3
INV_PI = 1.0 / np.pi


def _params(sigma, w, n: int) -> tuple[np.ndarray, np.ndarray]:
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n,))
    m = np.broadcast_to(np.asarray(w, dtype=np.float64), (n,))
    if not (np.isfinite(s).all() and np.isfinite(m).all()):
        raise ValueError("proxy parameters sigma and w must be finite")
    return np.maximum(s, SIGMA_MIN), np.clip(m, 0.0, 1.0)


def _disk_mass(sigma: np.ndarray) -> np.ndarray:
    """Mass of the isotropic 2D Gaussian inside the unit disk: 1 - exp(-1 / (2 sigma^2))."""
    return -np.expm1(-0.5 / (sigma * sigma))


def pdf(wo: np.ndarray, wi: np.ndarray, sigma, w) -> np.ndarray:
    """Solid-angle density (N,) of :func:`sample` choosing ``wi`` given ``wo``; 0 below the horizon."""
    wo = np.asarray(wo, dtype=np.float64)
    wi = np.asarray(wi, dtype=np.float64)
    s, m = _params(sigma, w, wo.shape[0])
    up = (wo[:, 2] > 0) & (wi[:, 2] > 0)
    h = wi + wo
    hn = np.linalg.norm(h, axis=1, keepdims=True)
    h = h / np.maximum(hn, 1e-12)
    r2 = h[:, 0] ** 2 + h[:, 1] ** 2
    p_disk = np.exp(-0.5 * r2 / (s * s)) / (2.0 * np.pi * s * s * _disk_mass(s))
    p_h = p_disk * np.maximum(h[:, 2], 0.0)
    wo_h = np.abs(np.sum(wo * h, axis=1))
    p_gauss = np.where(wo_h > 1e-9, p_h / (4.0 * np.maximum(wo_h, 1e-9)), 0.0)
    p = (1.0 - m) * p_gauss + m * np.maximum(wi[:, 2], 0.0) * INV_PI
    return np.where(up, p, 0.0)


def sample(wo: np.ndarray, sigma, w, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample wi (N, 3) with its density (N,); ``u`` (N, 3) uniform in [0, 1).

    ``u[:, 0]`` picks the lobe, ``u[:, 1:]`` place the direction. Samples that fall below
    the horizon (possible for the Gaussian lobe at grazing ``wo``) come back with pdf 0.
    """
    wi = sample_directions(wo, sigma, w, u)
    return wi, pdf(wo, wi, sigma, w)


def sample_directions(wo: np.ndarray, sigma, w, u: np.ndarray) -> np.ndarray:
    """The directions of :func:`sample` without their density (for a caller that evaluates :func:`pdf`
    on them together with other directions)."""
    wo = np.asarray(wo, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if wo.ndim != 2 or wo.shape[1] != 3 or u.shape != (wo.shape[0], 3):
        raise ValueError(f"wo must be (N, 3) and u (N, 3), got {wo.shape} and {u.shape}")
    n = wo.shape[0]
    s, m = _params(sigma, w, n)
    phi = 2.0 * np.pi * u[:, 2]
    # Gaussian lobe: truncated Rayleigh radius in the projected disk, then mirror wo about h.
    r = s * np.sqrt(-2.0 * np.log1p(-u[:, 1] * _disk_mass(s)))
    r = np.minimum(r, 1.0)
    h = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - r * r, 0.0))], axis=1)
    wi_g = 2.0 * np.sum(wo * h, axis=1, keepdims=True) * h - wo
    # Cosine lobe (Malley's method).
    rc = np.sqrt(u[:, 1])
    wi_c = np.stack([rc * np.cos(phi), rc * np.sin(phi), np.sqrt(np.maximum(1.0 - u[:, 1], 0.0))], axis=1)
    wi = np.where((u[:, 0] < m)[:, None], wi_c, wi_g)
    wi /= np.maximum(np.linalg.norm(wi, axis=1, keepdims=True), 1e-12)
    return wi

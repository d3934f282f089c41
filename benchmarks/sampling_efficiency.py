"""Sampling efficiency of the proxy: the variance of one-bounce estimates under a smooth sky.

The measurement behind the "sampling efficiency" figures of ``benchmarks/bench_layering.py`` and
``docs/sampling.md``, and what ``tests/core/test_sampling.py`` checks: for a material's BRDF and a
sampling strategy (the proxy with the sampling network's (sigma, w), cosine, or GGX visible normals of
the top interface), the mean and variance of the one-sample estimate of the light reflected from
:func:`sky_radiance`. Not part of the renderer.
"""

from __future__ import annotations

import numpy as np

from addon.core.neural import proxy

SUN = np.array([0.35, 0.2, 0.915]) / np.linalg.norm([0.35, 0.2, 0.915])


def sky_radiance(w: np.ndarray) -> np.ndarray:
    """A smooth analytic environment (N,): dim sky, brighter horizon, a broad bright sun glow.

    The test light of the sampling-efficiency measurements: smooth, so that the variance measured
    is the BRDF sampling's, not that of a point-like light (the renderer's NEE handles those).
    """
    w = np.asarray(w, dtype=np.float64)
    glow = np.maximum(w @ SUN, 0.0) ** 16
    return 0.4 + 0.6 * (1.0 - np.clip(w[:, 2], 0.0, 1.0)) + 12.0 * glow


def one_bounce_variance(brdf, wo: np.ndarray, sampler, n: int, seed: int = 0, env=sky_radiance):
    """Mean and variance (W,) of the one-sample estimate of L_o(wo) = int L(wi) f(wi, wo) cos(theta_i) dwi.

    ``brdf(wi, wo) -> (N, 3)`` (the mean of the channels is used), ``wo`` (W, 3) outgoing
    directions, ``sampler(wo (N, 3), u (N, 3)) -> (wi, pdf)`` a sampling strategy; ``n`` samples per
    outgoing direction. Samples with pdf 0 or below the horizon contribute 0.
    """
    wo = np.asarray(wo, dtype=np.float64)
    m = wo.shape[0]
    rng = np.random.default_rng(seed)
    wo_r = np.repeat(wo, n, axis=0)
    wi, pdf = sampler(wo_r, rng.random((m * n, 3)))
    wi = np.asarray(wi, dtype=np.float64)
    ok = (pdf > 0) & np.all(np.isfinite(wi), axis=1) & (wi[:, 2] > 0)
    wi = np.where(ok[:, None], wi, np.array([0.0, 0.0, 1.0]))
    f = np.asarray(brdf(wi, wo_r), dtype=np.float64).mean(axis=1)
    est = np.where(ok, env(wi) * f * wi[:, 2] / np.where(ok, pdf, 1.0), 0.0).reshape(m, n)
    return est.mean(axis=1), est.var(axis=1, ddof=1)


def proxy_sampler(sigma: float, w: float):
    """The proxy with fixed (sigma, w) as a ``one_bounce_variance`` sampler."""
    return lambda wo, u: proxy.sample(wo, sigma, w, u)


def material_sampler(models, sigma: float, w: float, top=None):
    """The renderer's sampler of a neural material as a ``one_bounce_variance`` sampler: the proxy, mixed
    with exact samples of the top lobe for a remainder decoder (``render.neural_material``)."""
    from addon.core.render.neural_material import _BoundNeural

    bound = _BoundNeural(models, np.zeros((3, 32), np.float32), np.float64(sigma), np.float64(w), top=top)
    return lambda wo, u: bound.sample_direction(wo, u[:, 0], u[:, 1:])


def cosine_sampler():
    """Cosine-weighted hemisphere sampling (the proxy with w = 1)."""
    return lambda wo, u: proxy.sample(wo, 1.0, 1.0, u)


def ggx_sampler(alpha: float):
    """Visible-normal sampling of a GGX lobe of roughness ``alpha`` (e.g. the top coating's interface)."""
    from addon.core.bsdf.conductor import RoughConductor

    bsdf = RoughConductor(alpha, np.ones(3), np.ones(3))

    def sample(wo, u):
        s = bsdf.sample(wo, u[:, 0], u[:, 1:], check=False)
        return s.wi, np.where(s.valid, s.pdf, 0.0)

    return sample

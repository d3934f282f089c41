"""The sampling network at run time: latent z (3, 32) -> proxy parameters (sigma, w), ONNX Runtime.

The proxy pdf (``proxy.py``) is (1 - w) Gaussian over the projected half vector (standard deviation
sigma) + w cosine lobe. The network ``sampling_<size>.onnx`` (input ``z`` (B, 3, 32), outputs
``sigma`` (B,), ``w`` (B,)) was trained by minimising KL(target || proxy) where the target is the
decoder's BRDF (mean of R, G, B) times cos(theta_i), normalised per outgoing direction (see
``onnx_export/sampling_net.py``). The parameters are computed once per material (or texel) and
stored beside the latent (``proxy.sigma``, ``proxy.w`` channels), so sampling needs no inference.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import proxy
from .runtime import LATENT, MODEL_DIR, SIZES
from .session import ChunkedSession


class SamplingModel:
    """``sampling_<size>.onnx`` as an ONNX Runtime session."""

    def __init__(self, size: str, threads: int = 2, model_dir: Path | str | None = None):
        if size not in SIZES:
            raise ValueError(f"unknown decoder size {size!r}; sizes are {list(SIZES)}")
        self.size = size
        self.path = (Path(model_dir) if model_dir is not None else MODEL_DIR) / f"sampling_{size}.onnx"
        self._session = ChunkedSession(self.path, threads)
        card = self.path.with_suffix(".json")
        self.card = json.loads(card.read_text()) if card.exists() else {}

    def proxy_params(self, z) -> np.ndarray:
        """(N, 2) float32 (sigma, w) of latents z (N, 3, 32) or (3, 32) (-> (1, 2))."""
        z = np.asarray(z, dtype=np.float32)
        if z.shape == (3, LATENT):
            z = z[None]
        if z.ndim != 3 or z.shape[1:] != (3, LATENT):
            raise ValueError(f"z must have shape (N, 3, {LATENT}) or (3, {LATENT}), got {z.shape}")
        if not np.all(np.isfinite(z)):
            raise ValueError("z must be finite (the latent holds NaN or Inf)")
        sig, w = self._session.run(["sigma", "w"], {"z": z})
        out = np.stack([sig, w], axis=1).astype(np.float32)
        out[:, 0] = np.maximum(out[:, 0], proxy.SIGMA_MIN)
        out[:, 1] = np.clip(out[:, 1], 0.0, 1.0)
        return out


_CACHE: dict[tuple[str, int], SamplingModel] = {}


def load_sampling(size: str, threads: int = 2) -> SamplingModel:
    key = (size, int(threads))
    if key not in _CACHE:
        _CACHE[key] = SamplingModel(size, threads)
    return _CACHE[key]


# ----------------------------------------------------------------------------- sampling efficiency

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


def cosine_sampler():
    """Cosine-weighted hemisphere sampling (the proxy with w = 1)."""
    return lambda wo, u: proxy.sample(wo, 1.0, 1.0, u)


def ggx_sampler(alpha: float):
    """Visible-normal sampling of a GGX lobe of roughness ``alpha`` (e.g. the top coating's interface)."""
    from ..bsdf.conductor import RoughConductor

    bsdf = RoughConductor(alpha, np.ones(3), np.ones(3))

    def sample(wo, u):
        s = bsdf.sample(wo, u[:, 0], u[:, 1:], check=False)
        return s.wi, np.where(s.valid, s.pdf, 0.0)

    return sample

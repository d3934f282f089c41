"""Neural layered materials in the renderer: decoder evaluation and proxy sampling.

A :class:`NeuralMaterial` holds one latent (3, 32) or a latent texture (per-hit latents and proxy
parameters looked up at the hit's uv with its ray footprint). ``eval`` runs the ONNX decoder
(``addon.core.neural``); sampling uses the paper's proxy (``addon.core.neural.proxy``: a Gaussian
over the projected half vector plus a cosine lobe) whose pdf is exact, so MIS with next-event
estimation stays unbiased whatever the proxy's parameters are.

Such a material only proposes directions (``sample_direction``) and evaluates the decoder for
those directions together with the next-event directions (``shade``, from
``addon.core.render.shading.ShadeByProposal``), so each neural material costs one ONNX batch per
bounce.
"""

from __future__ import annotations

import numpy as np

from ..stack import Stack
from .shading import ShadeByProposal, finish_sample

DEFAULT_SIZE = "tiny"


def proxy_guess(stack: Stack) -> tuple[float, float]:
    """Proxy (sigma, w) from the stack's top interface until the sampling network provides them.

    sigma follows the top roughness (the half-vector spread), w the chance of a diffuse-like
    lobe. Any values keep the render unbiased (the proxy pdf is exact); they only shape noise.
    """
    top = stack.coatings[-1] if stack.coatings else stack.base
    alpha = float(getattr(top, "roughness", 1.0))
    diffuse_below = not hasattr(stack.base, "roughness") or stack.base.roughness > 0.3
    return max(alpha, 0.02), (0.5 if diffuse_below or stack.coatings else 0.1)


class _BoundNeural(ShadeByProposal):
    def __init__(self, models, z, sigma, w):
        self.models, self.z, self.sigma, self.w = models, z, sigma, w

    @staticmethod
    def _rows(a, index):
        """Shared parameters (0-d sigma/w, (3, 32) z) as they are; per-hit ones restricted to index."""
        shared = np.ndim(a) == 0 or (np.ndim(a) == 2)
        return a if index is None or shared else a[index]

    def eval(self, wi, wo, index=None):
        z = self._rows(self.z, index)
        return self.models.eval_brdf(z, wi, wo).astype(np.float64)

    def pdf(self, wi, wo, index=None):
        from ..neural import proxy

        return proxy.pdf(wo, wi, self._rows(self.sigma, index), self._rows(self.w, index))

    def sample_direction(self, wo, u_lobe, u):
        from ..neural import proxy

        wi, pdf = proxy.sample(wo, self.sigma, self.w, np.concatenate([u_lobe[:, None], u], axis=1))
        return wi, pdf

    def sample(self, wo, u_lobe, u):
        """Self-contained sampling (one decoder batch of its own); the integrator uses ``shade``."""
        wi, pdf = self.sample_direction(wo, u_lobe, u)
        return finish_sample(wi, pdf, self.eval(wi, wo))


class NeuralMaterial:
    """A stack's latent (or a latent texture) decoded by the neural runtime."""

    kind = "neural"
    has_pdf = True

    def __init__(self, models, z=None, proxy=(0.2, 0.5), latent_texture=None):
        self.models = models
        self.z = None if z is None else np.asarray(z, dtype=np.float32).reshape(3, 32)
        self.sigma, self.w = float(proxy[0]), float(proxy[1])
        self.texture = latent_texture
        if self.z is None and self.texture is None:
            raise ValueError("a NeuralMaterial needs a latent z (3, 32) or a latent texture")

    def bind(self, hits):
        if self.texture is None:
            return _BoundNeural(self.models, self.z, np.float64(self.sigma), np.float64(self.w))
        z, prox = self.texture.lookup(hits.uv, hits.footprint)
        sigma = np.asarray(prox[:, 0], dtype=np.float64)
        w = np.asarray(prox[:, 1], dtype=np.float64)
        return _BoundNeural(self.models, z, sigma, w)


def _candidate_sizes(size):
    from ..neural.runtime import DEFAULT_SIZE, SIZES

    if size is not None:
        return [size]
    return [DEFAULT_SIZE] + [x for x in SIZES if x != DEFAULT_SIZE]


def make(stack: Stack, latent_texture=None, size: str | None = None):
    """A NeuralMaterial for ``stack``, or None when no shipped model can serve it.

    ``size`` picks the decoder; None tries the runtime's default size first, then the others, and
    takes the first whose models are shipped (a layered stack also needs that size's layering
    network). A latent texture is decoded by the size it was baked for (its ``model`` metadata).
    Proxy parameters come from the sampling network when it is shipped, else from
    :func:`proxy_guess`.
    """
    try:
        from ..neural import load_models
        from ..neural.layering import encode_layered_stack, load_layering
        from ..neural.sampling import load_sampling
    except ImportError:
        return None
    if latent_texture is not None:
        size = latent_texture.metadata.get("model", size) if hasattr(latent_texture, "metadata") else size
    for candidate in _candidate_sizes(size):
        try:
            models = load_models(candidate)
            if latent_texture is not None:
                return NeuralMaterial(models, None, proxy_guess(stack), latent_texture)
            layering = load_layering(candidate, models.threads) if stack.coatings else None
            z = encode_layered_stack(stack, models, layering)
        except (FileNotFoundError, OSError):
            continue
        except ValueError:
            return None
        try:
            sigma, w = (float(v) for v in load_sampling(candidate, models.threads).proxy_params(z)[0])
        except (FileNotFoundError, OSError):
            sigma, w = proxy_guess(stack)
        material = NeuralMaterial(models, z, (sigma, w))
        material.size = candidate
        return material
    return None

"""Stacks -> latent codes: the encoder for each layer, then the layering network bottom-up.

    z = encode_stack(stack, "tiny")                    # (3, 32) latent of one stack, any depth
    z = encode_arrays(arrays, load_models("tiny"))     # (N, 3, 32) latents of N stacks (texels), batched
    p = load_models("tiny").proxy_params(z)            # (N, 2) proxy (sigma, w) of the sampling network

For each colour channel c, with ``z_base`` the encoder's latent of the base and ``z_top_j`` the
encoder's latent of coating j's interface (``stack.coating_interface``):

    z <- z_base;  for j = 0 .. C-1 (bottom to top):  z <- L(z_top_j, z, albedo_j[c], thickness_j)

``L`` is the layering network of the same size (``ModelSet.run_layering``), trained in the latent space
of that size's decoder. Every channel of every stack is one row of one ONNX call per coating, so a
whole texture of stacks encodes in a few calls. Parameters outside the trained range are clamped
(``stack.clamp_to_trained``) with a ``ClampWarning`` naming the field; NaN, Inf or values outside the
valid range raise ``ValueError`` (``stack.validate``).

``lerp(z_a, z_b, t)`` interpolates latents (supplement section 1.1): the decoded BRDF moves between
the two materials through physically plausible ones, unlike a linear blend of the two BRDFs.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..rows import distinct_rows
from ..stack import LATENT, ClampWarning, Stack, StackArrays, clamp_to_trained, validate
from .features import arrays_features
from .models import ModelSet, load_models


def _models(models: ModelSet | str | None) -> ModelSet:
    if isinstance(models, ModelSet):
        return models
    return load_models("auto" if models is None else models)


def encode_arrays(arrays: StackArrays, models: ModelSet | str | None = None) -> np.ndarray:
    """(N, 3, 32) float32 latents of N stacks with the same number of coatings (texels, hits).

    ``models`` is a ModelSet or a size ("auto" or None: the default size). Coatings need the size's
    layering network (FileNotFoundError naming it when it is not shipped).
    """
    if not isinstance(arrays, StackArrays):
        raise ValueError(f"encode_arrays needs StackArrays, got {type(arrays).__name__}")
    validate(arrays)  # NaN, Inf, complex, misshapen or unphysical values raise here, naming field and row
    models = _models(models)
    fixed, notes = clamp_to_trained(arrays)
    for note in notes:
        warnings.warn(note, ClampWarning, stacklevel=3)
    n, c = len(fixed), fixed.n_coatings
    z = _layer_latents(fixed, models)
    if c == 0 or n == 0:
        return z if c == 0 else np.zeros((0, 3, LATENT), dtype=np.float32)
    z_tops = _layer_latents(fixed.coating_interfaces(), models).reshape(n, c, 3, LATENT)
    zc = z.reshape(n * 3, LATENT)
    for j in range(c):  # bottom-up over coatings; all stacks and channels in one call each
        zc = models.run_layering(
            z_tops[:, j].reshape(n * 3, LATENT),
            zc,
            fixed.coat_albedo[:, j].reshape(n * 3),
            np.repeat(fixed.coat_thickness[:, j], 3),
        )
    return zc.reshape(n, 3, LATENT)


def _layer_latents(arrays: StackArrays, models: ModelSet) -> np.ndarray:
    """Encoder latents (N, 3, 32) of the bases of ``arrays`` (coatings ignored), the features of each
    distinct base computed once: in a texture most texels share their base (or a coat's interface), and
    its features cost more than the rows' hash (``rows.distinct_rows``)."""
    params = np.column_stack(
        [
            arrays.base_kind,
            arrays.base_roughness,
            arrays.base_albedo,
            arrays.base_eta,
            arrays.base_k,
            arrays.base_ior,
        ]
    )
    first, inverse = distinct_rows(params)
    if len(first) == len(params):  # all distinct: no gathers
        return models.run_encoder(arrays_features(arrays))
    return models.run_encoder(arrays_features(arrays.take(first)))[inverse]


def encode_stack(stack: Stack, models: ModelSet | str | None = None) -> np.ndarray:
    """(3, 32) float32 latent of one stack with any number of coatings (see :func:`encode_arrays`)."""
    if not isinstance(stack, Stack):
        raise ValueError(f"encode_stack needs a Stack, got {type(stack).__name__}")
    return encode_arrays(StackArrays.from_stacks([stack]), models)[0]


def lerp(z_a, z_b, t) -> np.ndarray:
    """Latent interpolation (1 - t) z_a + t z_b; ``t`` a scalar or per-row (N,) for latents (N, 3, 32).

    Exact at the ends: t = 0 gives z_a and t = 1 gives z_b bit for bit.
    """
    a = np.asarray(z_a, dtype=np.float32)
    b = np.asarray(z_b, dtype=np.float32)
    if a.shape != b.shape or a.shape[-2:] != (3, LATENT):
        raise ValueError(f"z_a and z_b must have the same shape (..., 3, {LATENT}), got {a.shape} and {b.shape}")
    tt = np.asarray(t, dtype=np.float32)
    if not np.all(np.isfinite(tt)):
        raise ValueError(f"t must be finite, got {t!r}")
    if tt.ndim == 1:
        tt = tt[:, None, None]
    return ((np.float32(1.0) - tt) * a + tt * b).astype(np.float32)

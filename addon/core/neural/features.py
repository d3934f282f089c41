"""Encoder inputs: analytic single-layer parameters -> per-channel feature vectors (numpy).

One row per (material, colour channel). The features describe the layer by what shapes its
BRDF: the base kind (one-hot), the GGX roughness on a log scale, the diffuse albedo, and the
Fresnel reflectance curve sampled at a few incidence cosines (``addon.core.bsdf.fresnel``),
which summarises eta/k of a conductor or the ior of a dielectric in the units the BRDF sees.
Both the runtime and the training code in ``onnx_export`` call these functions.
"""

from __future__ import annotations

import numpy as np

from ..bsdf.fresnel import fresnel_conductor, fresnel_dielectric
from ..stack import BASE_KINDS, TRAINED_RANGES, Coating, Conductor, Dielectric, Diffuse, StackArrays, coating_interface

FRESNEL_COSINES = (1.0, 0.5, 0.2, 0.05)
FEATURE_NAMES = (
    "is_diffuse",
    "is_conductor",
    "is_dielectric",
    "log_alpha",
    "sqrt_alpha",
    "albedo",
    *(f"fresnel_{c:g}" for c in FRESNEL_COSINES),
)
N_FEATURES = len(FEATURE_NAMES)
ALPHA_MIN, ALPHA_MAX = TRAINED_RANGES["roughness"]


def base_features(kind, alpha, albedo, eta, k, ior) -> np.ndarray:
    """(N, 3, N_FEATURES) float32 features for N single layers.

    ``kind`` (N,) indexes ``BASE_KINDS``; ``alpha`` (N,), ``albedo``/``eta``/``k`` (N, 3),
    ``ior`` (N,). Fields a kind does not use are ignored. ``alpha`` is clamped to the
    trained range first (callers warn about clamping; this only keeps logs finite).
    """
    kind = np.asarray(kind, dtype=np.int64).reshape(-1)
    n = kind.shape[0]
    alpha = np.clip(np.asarray(alpha, dtype=np.float64).reshape(n), ALPHA_MIN, ALPHA_MAX)
    albedo = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (n, 3))
    eta = np.broadcast_to(np.asarray(eta, dtype=np.float64), (n, 3))
    k = np.broadcast_to(np.asarray(k, dtype=np.float64), (n, 3))
    ior = np.broadcast_to(np.asarray(ior, dtype=np.float64).reshape(-1), (n,))
    if np.any((kind < 0) | (kind >= len(BASE_KINDS))):
        raise ValueError(f"kind must index {BASE_KINDS}, got values {np.unique(kind).tolist()}")
    out = np.zeros((n, 3, N_FEATURES), dtype=np.float64)
    diffuse, conductor, dielectric = kind == 0, kind == 1, kind == 2
    out[:, :, 0] = diffuse[:, None]
    out[:, :, 1] = conductor[:, None]
    out[:, :, 2] = dielectric[:, None]
    rough = ~diffuse
    out[:, :, 3] = np.where(rough, np.log(alpha / ALPHA_MIN) / np.log(1.0 / ALPHA_MIN), 0.0)[:, None]
    out[:, :, 4] = np.where(rough, np.sqrt(alpha), 0.0)[:, None]
    out[:, :, 5] = np.where(diffuse[:, None], albedo, 0.0)
    rc, rd = np.flatnonzero(conductor), np.flatnonzero(dielectric)  # each Fresnel only where it applies
    for j, c in enumerate(FRESNEL_COSINES):
        out[rc, :, 6 + j] = fresnel_conductor(np.full(len(rc), c), np.maximum(eta[rc], 1e-6), k[rc])
        out[rd, :, 6 + j] = fresnel_dielectric(np.full(len(rd), c), np.maximum(ior[rd], 1.0 + 1e-6))[:, None]
    return out.astype(np.float32)


def arrays_features(arrays: StackArrays) -> np.ndarray:
    """Features of the bases of a ``StackArrays`` batch (coatings ignored): (N, 3, N_FEATURES)."""
    return base_features(
        arrays.base_kind, arrays.base_roughness, arrays.base_albedo, arrays.base_eta, arrays.base_k, arrays.base_ior
    )


def layer_features(layer) -> np.ndarray:
    """(3, N_FEATURES) features of one base layer; a ``Coating`` is encoded as its interface
    (``stack.coating_interface``)."""
    if isinstance(layer, Coating):
        layer = coating_interface(layer)
    if isinstance(layer, Diffuse):
        return base_features([0], [1.0], [layer.albedo], [1.0] * 3, [0.0] * 3, [1.5])[0]
    if isinstance(layer, Conductor):
        return base_features([1], [layer.roughness], [0.0] * 3, [layer.eta], [layer.k], [1.5])[0]
    if isinstance(layer, Dielectric):
        return base_features([2], [layer.roughness], [0.0] * 3, [1.0] * 3, [0.0] * 3, [layer.ior])[0]
    raise ValueError(f"cannot encode a {type(layer).__name__}; expected Diffuse, Conductor, Dielectric or Coating")

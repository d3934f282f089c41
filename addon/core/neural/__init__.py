"""Neural BRDFs at run time: ONNX Runtime networks (no torch).

``models.py`` loads the model set of a decoder size (decoder, encoder, layering and sampling networks,
checked against their cards, one cache); ``encode.py`` turns stacks into latents (``encode_stack``,
``encode_arrays``); ``proxy.py`` is the sampling proxy; ``top_lobe.py`` the exact top-interface lobe a
remainder decoder adds (``top_coat``, ``top_coats``). ``docs/decoders.md`` lists the sizes and their
measurements; ``docs/architecture.md`` ("Neural runtime") the data path.
"""

from ..stack import ClampWarning
from .encode import encode_arrays, encode_stack, lerp
from .features import N_FEATURES, arrays_features, base_features, layer_features
from .models import (
    AUTO,
    DEFAULT_SIZE,
    MODEL_DIR,
    ROLES,
    SIZES,
    ModelFileError,
    ModelSet,
    clear_cache,
    file_digest,
    load_models,
    read_card,
    resolve_size,
)
from .top_lobe import NO_TOP, top_coat, top_coats

__all__ = [
    "AUTO",
    "DEFAULT_SIZE",
    "MODEL_DIR",
    "NO_TOP",
    "N_FEATURES",
    "ROLES",
    "SIZES",
    "ClampWarning",
    "ModelFileError",
    "ModelSet",
    "arrays_features",
    "base_features",
    "clear_cache",
    "encode_arrays",
    "encode_stack",
    "eval_brdf",
    "file_digest",
    "layer_features",
    "lerp",
    "load_models",
    "read_card",
    "resolve_size",
    "top_coat",
    "top_coats",
]


def eval_brdf(z, wi, wo, size: str = AUTO, top=None, calibration=None):
    """f (N, 3) of latent(s) ``z`` of decoder ``size``, with the top coating ``top`` (alpha, ior) of a
    remainder decoder's exact top lobe and an albedo calibration (see ``ModelSet.eval_brdf``)."""
    return load_models(size).eval_brdf(z, wi, wo, top, calibration)

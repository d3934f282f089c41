"""Neural BRDFs at run time: ONNX Runtime decoders and encoders (no torch).

See ``runtime.py`` for the API and ``docs/decoders.md`` for the model zoo and its measurements.
"""

from .features import N_FEATURES, arrays_features, base_features, layer_features
from .runtime import SIZES, ClampWarning, NeuralModels, encode, encode_stack, eval_brdf, load_models

__all__ = [
    "N_FEATURES", "SIZES", "ClampWarning", "NeuralModels", "arrays_features", "base_features", "encode",
    "encode_stack", "eval_brdf", "layer_features", "load_models",
]

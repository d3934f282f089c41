"""Neural BRDF runtime (numpy + ONNX Runtime): load a decoder size, encode layers, decode BRDFs.

    models = load_models("small", threads=2)
    z = models.encode(Conductor(roughness=0.2))        # (3, 32) latent, one pass, no optimisation
    f = models.eval_brdf(z, wi, wo)                      # (N, 3) f in 1/sr, without the cosine

Every decoder size has its own latent space, so a size ships as a pair of ONNX files,
``decoder_<size>.onnx`` (inputs ``z`` (B, 32), ``wi``, ``wo`` (B, 3); output ``f`` (B,)) and
``encoder_<size>.onnx`` (input ``x`` (B, N_FEATURES); output ``z`` (B, 32)), each with a model
card ``<name>.json`` beside it. Parameters outside the trained range are clamped with a
warning; NaN or badly shaped inputs raise ValueError; outputs are finite and >= 0, and 0 where
either direction is below the horizon.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from ..stack import Coating, Dielectric, Layer, Stack, StackArrays, clamp_to_trained
from .features import N_FEATURES, arrays_features, layer_features
from .session import ChunkedSession

MODEL_DIR = Path(__file__).resolve().parents[2] / "models"
SIZES = ("tiny", "small", "medium", "paper")
DEFAULT_SIZE = "small"  # the best error for its speed; see docs/decoders.md
LATENT = 32
# Floats of one hidden layer's activations per ONNX Runtime call (768 KB): the decoder's chunk is
# that over 3 x its width, 2,048 RGB queries for the tiny decoder, 256 for the paper's, so the
# intermediates stay in cache (measured best or near it for tiny, small and medium).
DECODER_CHUNK_FLOATS = 196_608
ENCODER_CHUNK = 4096


class ClampWarning(UserWarning):
    """A parameter was outside the range the networks were trained on and was clamped."""


def _directions(w, name: str) -> np.ndarray:
    a = np.asarray(w, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == 3:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3) (or (3,)), got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(a), axis=1))[0])
        raise ValueError(f"{name} must be finite; row {bad} is {a[bad].tolist()}")
    return a


def _unit_or_up(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 unit directions of rows ``w`` (normalised in float64) and whether each is usable:
    nonzero and above the horizon; unusable rows become +z (their output is zeroed)."""
    w = np.asarray(w, dtype=np.float64)
    n2 = np.einsum("ij,ij->i", w, w)
    ok = (n2 > 0.0) & (w[:, 2] > 0.0) & np.isfinite(n2)
    u = w * (1.0 / np.sqrt(np.where(ok, n2, 1.0)))[:, None]
    if not ok.all():
        u[~ok] = (0.0, 0.0, 1.0)
    return u.astype(np.float32), ok


class NeuralModels:
    """One decoder size and its encoder, as ONNX Runtime sessions."""

    def __init__(self, size: str = DEFAULT_SIZE, threads: int = 2, model_dir: Path | str | None = None):
        if size not in SIZES:
            raise ValueError(f"unknown decoder size {size!r}; sizes are {list(SIZES)}")
        if int(threads) < 1:
            raise ValueError(f"threads must be >= 1, got {threads!r}")
        self.size = size
        self.threads = int(threads)
        d = Path(model_dir) if model_dir is not None else MODEL_DIR
        self.decoder_path = d / f"decoder_{size}.onnx"
        self.encoder_path = d / f"encoder_{size}.onnx"
        card = self.decoder_path.with_suffix(".json")
        self.card = json.loads(card.read_text()) if card.exists() else {}
        width = int(self.card.get("architecture", {}).get("width", 32))
        chunk = max(128, DECODER_CHUNK_FLOATS // (3 * width))
        self._decoder = ChunkedSession(self.decoder_path, threads, chunk)
        # the fused RGB graph (same weights) is faster; the scalar graph is the reference interface
        rgb = d / f"decoder_{size}_rgb.onnx"
        self._rgb = ChunkedSession(rgb, threads, chunk) if rgb.exists() else None
        self._encoder = ChunkedSession(self.encoder_path, threads, ENCODER_CHUNK)

    # ------------------------------------------------------------------ encoding

    def encode_features(self, x: np.ndarray) -> np.ndarray:
        """Latents (N, 3, 32) of per-channel encoder features (N, 3, N_FEATURES)."""
        x = np.asarray(x, dtype=np.float32)
        if x.ndim != 3 or x.shape[1:] != (3, N_FEATURES):
            raise ValueError(f"encoder features must have shape (N, 3, {N_FEATURES}), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("encoder features must be finite")
        z = self._encoder.run(["z"], {"x": x.reshape(-1, N_FEATURES)})[0]
        return z.reshape(-1, 3, LATENT)

    def encode(self, layer: Layer) -> np.ndarray:
        """(3, 32) latent of one layer (Diffuse, Conductor, Dielectric; a Coating is encoded as its
        interface, Dielectric(roughness, ior) over black)."""
        if isinstance(layer, Coating):
            layer = Dielectric(layer.roughness, layer.ior)
        clamped, notes = clamp_to_trained(Stack(layer))
        for note in notes:
            warnings.warn(note, ClampWarning, stacklevel=2)
        return self.encode_features(layer_features(clamped.base)[None])[0]

    def encode_stack(self, stack: Stack) -> np.ndarray:
        """(3, 32) latent of a stack: the encoder for each layer, then the layering network of this
        size bottom-up over the coatings (``layering.encode_layered_stack``). A size whose layering
        network is not shipped raises ``FileNotFoundError`` naming the file."""
        if not isinstance(stack, Stack):
            raise ValueError(f"encode_stack needs a Stack, got {type(stack).__name__}")
        if not stack.coatings:
            return self.encode(stack.base)
        from .layering import LayeringModel, encode_layered_stack

        if getattr(self, "_layering", None) is None:  # the latent needs no sampling network
            self._layering = LayeringModel(self.size, self.threads, sampling=False)
        return encode_layered_stack(stack, self, self._layering)

    def encode_arrays(self, arrays: StackArrays) -> np.ndarray:
        """(N, 3, 32) latents of N single-layer stacks (texels), in batches, clamped to the trained range."""
        if arrays.n_coatings:
            raise ValueError("encode_arrays encodes single layers; stacks with coatings go through "
                             "layering.encode_stack_arrays (encoder, then the layering network)")
        fixed = _clamp_arrays(arrays)
        return self.encode_features(arrays_features(fixed))

    # ------------------------------------------------------------------ decoding

    def eval_brdf(self, z, wi, wo) -> np.ndarray:
        """f (N, 3) in 1/sr (no cosine) for one material ``z`` (3, 32) or per-row latents (N, 3, 32).

        Directions need not be unit length (they are normalised); zero-length directions and
        directions at or below the horizon give 0.
        """
        wi = _directions(wi, "wi")
        wo = _directions(wo, "wo")
        if wi.shape[0] != wo.shape[0]:
            raise ValueError(f"wi has {wi.shape[0]} rows but wo has {wo.shape[0]}")
        n = wi.shape[0]
        z = np.asarray(z, dtype=np.float32)
        if z.shape == (3, LATENT):
            per_row = False
        elif z.ndim == 3 and z.shape[1:] == (3, LATENT) and z.shape[0] == n:
            per_row = True
        else:
            raise ValueError(f"z must have shape (3, {LATENT}) or ({n}, 3, {LATENT}) to match {n} directions, "
                             f"got {z.shape}")
        if not np.all(np.isfinite(z)):
            raise ValueError("z must be finite (the latent holds NaN or Inf)")
        out = np.empty((n, 3), dtype=np.float32)
        zz = z[None]

        def chunk(rows: slice) -> None:  # runs on the session's threads, one chunk of rows each
            a, b = _unit_or_up(wi[rows]), _unit_or_up(wo[rows])
            ok = a[1] & b[1]
            if self._rgb is not None:
                f = self._rgb.run_once(["f"], {"z": z[rows] if per_row else zz, "wi": a[0], "wo": b[0]})[0]
            else:
                m = a[0].shape[0]
                f = self._decoder.run_once(["f"], {
                    "z": z[rows].reshape(-1, LATENT) if per_row else np.tile(z, (m, 1)),
                    "wi": np.repeat(a[0], 3, axis=0), "wo": np.repeat(b[0], 3, axis=0)})[0].reshape(m, 3)
            # 0 below the horizon, and for NaN (an overflowing latent); the graph's exp is >= 0
            out[rows] = np.where(ok[:, None] & (f >= 0.0), f, 0.0)

        (self._rgb or self._decoder).map(chunk, n)
        return out


def _clamp_arrays(arrays: StackArrays) -> StackArrays:
    """Clamp base parameters of a batch into the trained range, warning once with the count."""
    from ..stack import TRAINED_RANGES

    out = arrays.take(slice(None))
    changed = []
    for name, key in (("base_roughness", "roughness"), ("base_ior", "ior"), ("base_eta", "eta"),
                      ("base_k", "k"), ("base_albedo", "albedo")):
        lo, hi = TRAINED_RANGES[key]
        v = getattr(out, name)
        c = np.clip(v, lo, hi)
        # only the fields the row's kind uses matter
        used = {"base_albedo": 0, "base_roughness": (1, 2), "base_eta": 1, "base_k": 1, "base_ior": 2}[name]
        rows = np.isin(out.base_kind, np.atleast_1d(used))
        diff = (c != v).reshape(len(v), -1).any(axis=1) & rows
        if np.any(diff):
            changed.append(f"{name}: {int(diff.sum())} rows clamped to the trained range [{lo}, {hi}]")
        setattr(out, name, c)
    for note in changed:
        warnings.warn(note, ClampWarning, stacklevel=3)
    return out


_DEFAULT: dict[tuple[str, int], NeuralModels] = {}


def load_models(size: str = DEFAULT_SIZE, threads: int = 2, model_dir=None) -> NeuralModels:
    """The models of one decoder size (cached per size and thread count)."""
    key = (size, int(threads)) if model_dir is None else None
    if key is not None and key in _DEFAULT:
        return _DEFAULT[key]
    m = NeuralModels(size, threads, model_dir)
    if key is not None:
        _DEFAULT[key] = m
    return m


def encode(layer: Layer, size: str = DEFAULT_SIZE) -> np.ndarray:
    return load_models(size).encode(layer)


def encode_stack(stack: Stack, size: str = DEFAULT_SIZE) -> np.ndarray:
    return load_models(size).encode_stack(stack)


def eval_brdf(z, wi, wo, size: str = DEFAULT_SIZE) -> np.ndarray:
    return load_models(size).eval_brdf(z, wi, wo)

"""Stacks of any depth -> one latent (3, 32): encoder per layer, then the layering network bottom-up.

    models = load_models("tiny")
    layering = load_layering("tiny")
    z = encode_layered_stack(stack, models, layering)               # (3, 32)
    z, proxy = encode_stack_arrays(arrays, models, layering)        # (N, 3, 32), (N, 2) (sigma, w)

For each colour channel c, with ``z_base`` the encoder's latent of the base and ``z_top_j`` the
encoder's latent of coating j's interface ``Dielectric(roughness_j, ior_j)``:

    z <- z_base;  for j = 0 .. C-1 (bottom to top):  z <- L(z_top_j, z, albedo_j[c], thickness_j)

``L`` is ``layering_<size>.onnx`` (inputs ``z_top``, ``z_bottom`` (B, 32), ``albedo``, ``thickness``
(B,); output ``z`` (B, 32)), trained in the latent space of the decoder of the same size. Every
channel of every stack is one row of one ONNX call per coating, so a whole texture of stacks encodes
in a few calls. Parameters outside the trained range are clamped with a ``ClampWarning`` (counts per
field); NaN, Inf or values outside the valid range (e.g. negative) raise ``ValueError``.

``lerp(z_a, z_b, t)`` interpolates latents (supplement section 1.1): the decoded BRDF moves between
the two materials through physically plausible ones, unlike a linear blend of the two BRDFs.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np

from ..reference.walk import validate_arrays
from ..stack import TRAINED_RANGES, Stack, StackArrays
from .features import base_features
from .runtime import LATENT, MODEL_DIR, SIZES, ClampWarning, NeuralModels, load_models
from .session import ChunkedSession
from .sampling import SamplingModel



class StaleModelWarning(UserWarning):
    """A layering or sampling model was trained with other encoder/decoder files than those shipped beside it."""


def file_digest(path: Path) -> str:
    """sha256 of a model file: the model cards record which encoder/decoder a model was trained with."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_trained_with(card: dict, model_dir: Path, name: str) -> list[str]:
    """Names of the files in ``card["trained_with"]`` whose digest differs from the file in ``model_dir``;
    warns with ``StaleModelWarning`` when any does (the latent spaces no longer match)."""
    stale = [f for f, digest in card.get("trained_with", {}).items()
             if not (model_dir / f).exists() or file_digest(model_dir / f) != digest]
    if stale:
        warnings.warn(f"{name} was trained with other versions of {stale} than those in {model_dir}; its latents "
                      f"do not match them: retrain it (python -m onnx_export.layering train ...)", StaleModelWarning,
                      stacklevel=3)
    return stale


_COAT_FIELDS = (("coat_roughness", "roughness"), ("coat_ior", "ior"), ("coat_albedo", "albedo"),
                ("coat_thickness", "thickness"), ("coat_g", "g"))


class LayeringModel:
    """The layering network of one decoder size and its sampling network, as ONNX Runtime sessions."""

    def __init__(self, size: str, threads: int = 2, model_dir: Path | str | None = None, sampling: bool = True):
        if size not in SIZES:
            raise ValueError(f"unknown decoder size {size!r}; sizes are {list(SIZES)}")
        d = Path(model_dir) if model_dir is not None else MODEL_DIR
        self.size = size
        self.path = d / f"layering_{size}.onnx"
        self._session = ChunkedSession(self.path, threads)
        card = self.path.with_suffix(".json")
        self.card = json.loads(card.read_text()) if card.exists() else {}
        self.stale = check_trained_with(self.card, d, self.path.name)
        self.sampling = SamplingModel(size, threads, d) if sampling else None
        if self.sampling is not None:
            self.stale += check_trained_with(self.sampling.card, d, self.sampling.path.name)

    def layer(self, z_top, z_bottom, albedo, thickness) -> np.ndarray:
        """One application of L: z_top, z_bottom (B, 32), albedo, thickness (B,) -> z (B, 32) float32."""
        zt = np.ascontiguousarray(z_top, dtype=np.float32)
        zb = np.ascontiguousarray(z_bottom, dtype=np.float32)
        a = np.ascontiguousarray(albedo, dtype=np.float32).reshape(-1)
        t = np.ascontiguousarray(thickness, dtype=np.float32).reshape(-1)
        b = zt.shape[0]
        if zt.shape != (b, LATENT) or zb.shape != (b, LATENT) or a.shape != (b,) or t.shape != (b,):
            raise ValueError(f"layer() needs z_top, z_bottom (B, {LATENT}), albedo, thickness (B,); got "
                             f"{zt.shape}, {zb.shape}, {a.shape}, {t.shape}")
        return self._session.run(["z"], {"z_top": zt, "z_bottom": zb, "albedo": a, "thickness": t})[0]


_CACHE: dict[tuple[str, int], LayeringModel] = {}


def load_layering(size: str = "tiny", threads: int = 2) -> LayeringModel:
    """The layering (+ sampling) models of one decoder size, cached per size and thread count."""
    key = (size, int(threads))
    if key not in _CACHE:
        _CACHE[key] = LayeringModel(size, threads)
    return _CACHE[key]


def clamp_coatings(arrays: StackArrays) -> StackArrays:
    """A copy with the coating fields clamped into ``TRAINED_RANGES``; one ClampWarning per clamped field."""
    out = arrays.take(slice(None))
    for name, key in _COAT_FIELDS:
        lo, hi = TRAINED_RANGES[key]
        v = np.asarray(getattr(out, name), dtype=np.float64)
        c = np.clip(v, lo, hi)
        changed = (c != v).reshape(len(out), -1).any(axis=1)
        if np.any(changed):
            i = int(np.flatnonzero(changed)[0])
            warnings.warn(f"{name}: {int(changed.sum())} stack(s) clamped to the trained range [{lo}, {hi}] "
                          f"(first: row {i}, {v[i].tolist()} -> {c[i].tolist()})", ClampWarning, stacklevel=3)
        setattr(out, name, c)
    return out


def _bases_only(arrays: StackArrays) -> StackArrays:
    n = len(arrays)
    return StackArrays(**{f: getattr(arrays, f) for f in StackArrays.FIELDS if f.startswith("base_")},
                       coat_roughness=np.zeros((n, 0)), coat_ior=np.zeros((n, 0)), coat_albedo=np.zeros((n, 0, 3)),
                       coat_thickness=np.zeros((n, 0)), coat_g=np.zeros((n, 0)))


def encode_latents(arrays: StackArrays, models: NeuralModels, layering: LayeringModel | None) -> np.ndarray:
    """(N, 3, 32) float32 latents of N stacks with the same number of coatings (no proxy parameters)."""
    if not isinstance(arrays, StackArrays):
        raise ValueError(f"expected StackArrays, got {type(arrays).__name__}")
    validate_arrays(arrays)  # NaN, Inf, negative or unphysical values raise here, naming field and row
    if arrays.n_coatings and layering is None:
        raise ValueError("stacks with coatings need a LayeringModel (load_layering(size))")
    if layering is not None and layering.size != models.size:
        raise ValueError(f"the layering model is for decoder size {layering.size!r} but the decoder is "
                         f"{models.size!r}; latent spaces differ per size: load both for one size")
    fixed = clamp_coatings(arrays) if arrays.n_coatings else arrays
    z = models.encode_arrays(_bases_only(fixed))  # clamps and warns about base fields
    n, c = len(fixed), fixed.n_coatings
    if c == 0:
        return z
    x = base_features(np.full(n * c, 2), fixed.coat_roughness.reshape(-1), np.zeros((n * c, 3)), np.ones((n * c, 3)),
                      np.zeros((n * c, 3)), fixed.coat_ior.reshape(-1))
    z_tops = models.encode_features(x).reshape(n, c, 3, LATENT)
    zc = z.reshape(n * 3, LATENT)
    for j in range(c):  # bottom-up over coatings; all stacks and channels in one call each
        zc = layering.layer(z_tops[:, j].reshape(n * 3, LATENT), zc, fixed.coat_albedo[:, j].reshape(n * 3),
                            np.repeat(fixed.coat_thickness[:, j], 3))
    return zc.reshape(n, 3, LATENT)


def encode_stack_arrays(arrays: StackArrays, models: NeuralModels | None = None,
                        layering: LayeringModel | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Latents (N, 3, 32) and proxy parameters (N, 2) = (sigma, w) of N stacks (texels), batched.

    Identical rows are encoded once. ``models`` and ``layering`` default to the default decoder size.
    """
    if models is None:
        models = load_models()
    if layering is None:
        layering = load_layering(models.size, models.threads)
    if not isinstance(arrays, StackArrays):
        raise ValueError(f"encode_stack_arrays needs StackArrays, got {type(arrays).__name__}")
    validate_arrays(arrays)
    uniq, inverse = arrays.unique()
    z = encode_latents(uniq, models, layering)
    if layering.sampling is None:
        raise ValueError(f"no sampling model loaded for size {layering.size!r}; proxy parameters need one")
    p = layering.sampling.proxy_params(z)
    return z[inverse], p[inverse]


def encode_layered_stack(stack: Stack, models: NeuralModels | None = None,
                         layering: LayeringModel | None = None) -> np.ndarray:
    """(3, 32) latent of one stack with any number of coatings."""
    if not isinstance(stack, Stack):
        raise ValueError(f"encode_layered_stack needs a Stack, got {type(stack).__name__}")
    if models is None:
        models = load_models()
    if stack.coatings and layering is None:
        layering = load_layering(models.size, models.threads)
    return encode_latents(StackArrays.from_stacks([stack]), models, layering)[0]


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

"""Baking: per-texel stacks -> per-texel latents (+ sampling-proxy parameters) -> LatentTexture.

The encoder is any callable ``encode(StackArrays) -> (latents (N, 3, 32), proxy (N, 2))``; the
neural runtime provides the real one. Identical parameter tuples are encoded once
(deduplication), and the rest runs in large batches.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..stack import StackArrays
from .latent_texture import CHANNEL_NAMES, LatentTexture
from .spatial import SpatialStack

Encoder = Callable[[StackArrays], tuple[np.ndarray, np.ndarray]]
Progress = Callable[[float], None]


def neural_encoder(size: str, threads: int = 2) -> Encoder:
    """The neural runtime's batch encoder for decoder ``size``: per-layer encoder, then the
    layering network bottom-up, then the sampling network for the proxy channels."""
    from ..neural import layering, load_models

    models = load_models(size, threads)
    layer_model = layering.load_layering(models.size, threads)
    return lambda arrays: layering.encode_stack_arrays(arrays, models, layer_model)


def bake_key(spatial: SpatialStack, resolution: tuple[int, int], model: str) -> str:
    """A short hash of everything a bake depends on: stack, driving images, resolution, model."""
    h = hashlib.sha256()
    h.update(spatial.stack.to_json().encode())
    h.update(repr(tuple(resolution)).encode())
    h.update(model.encode())
    for path in sorted(spatial.maps):
        h.update(path.encode())
        h.update(np.ascontiguousarray(spatial.maps[path], dtype=np.float32).tobytes())
    return h.hexdigest()[:16]


class BakeCancelled(Exception):
    """Raised when the ``cancel`` callback of a bake returns True."""


@dataclass
class BakeStats:
    texels: int
    unique: int
    seconds: float

    @property
    def texels_per_second(self) -> float:
        return self.texels / self.seconds if self.seconds > 0 else float("inf")


def bake_texels(
    arrays: StackArrays,
    encode: Encoder,
    *,
    dedup: bool = True,
    batch: int = 65536,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
) -> tuple[np.ndarray, BakeStats]:
    """(N, 98) float32 texels (latents then proxy channels) for N stacks."""
    t0 = time.perf_counter()
    n = len(arrays)
    if dedup:
        todo, inverse = arrays.unique()
    else:
        todo, inverse = arrays, np.arange(n)
    m = len(todo)
    out = np.empty((m, len(CHANNEL_NAMES)), dtype=np.float32)
    for start in range(0, m, batch):  # a loop over batches, not texels
        if cancel is not None and cancel():
            raise BakeCancelled(f"bake cancelled after {start} of {m} distinct texels")
        part = todo.take(slice(start, start + batch))
        z, proxy = encode(part)
        z = np.asarray(z, dtype=np.float32).reshape(len(part), -1)
        proxy = np.asarray(proxy, dtype=np.float32).reshape(len(part), -1)
        if z.shape[1] != 96 or proxy.shape[1] != 2:
            raise ValueError(f"encoder returned latents {z.shape} and proxy {proxy.shape}; expected (N, 96) and (N, 2)")
        out[start : start + len(part), :96] = z
        out[start : start + len(part), 96:] = proxy
        if progress is not None:
            progress(min(1.0, (start + len(part)) / m))
    if not np.isfinite(out).all():
        raise ValueError("the encoder returned non-finite latents")
    return out[inverse], BakeStats(texels=n, unique=m, seconds=time.perf_counter() - t0)


def bake_stack(
    spatial: SpatialStack,
    encode: Encoder,
    *,
    resolution: tuple[int, int] | None = None,
    dedup: bool = True,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    metadata: dict | None = None,
) -> tuple[LatentTexture, BakeStats]:
    """Bake a spatially varying stack into a mip-mapped latent texture."""
    arrays, (h, w) = spatial.texels(resolution)
    texels, stats = bake_texels(arrays, encode, dedup=dedup, progress=progress, cancel=cancel)
    meta = {"stack": spatial.stack.to_json(), "maps": ",".join(sorted(spatial.maps))}
    meta.update(metadata or {})
    return LatentTexture.from_texels(texels.reshape(h, w, -1), meta), stats

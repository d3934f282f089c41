"""Baking: per-texel stacks -> per-texel latents (+ sampling-proxy parameters, + the top coating's
roughness and index) -> LatentTexture.

The encoder is any callable ``encode(StackArrays) -> (latents (N, 3, 32), proxy (N, 2))``; the
neural runtime provides the real one. Identical parameter tuples are encoded once
(deduplication), and the rest runs in large batches.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..neural.top_lobe import top_coats
from ..rows import distinct_rows
from ..stack import StackArrays, clamp_notes
from ..threads import submit_in_context, thread_count
from .latent_texture import CHANNEL_NAMES, LatentTexture
from .mip import HALF_MAX, MipChain, float32_texels, store_texels
from .spatial import SpatialStack

Encoder = Callable[[StackArrays], tuple[np.ndarray, np.ndarray]]
Progress = Callable[[float], None]
ENCODE_SHARE = 0.3  # of a calibrated bake's progress bar: the encoding (the calibration takes the rest)
BATCH = 65536  # texels per encoder call
# Peak memory of a bake, measured by ``benchmarks/bench_bake.py --peak-memory`` (docs/bake.md): the largest
# resident size of a fresh process baking varnished wood under smooth maps (every texel distinct but a few,
# calibrated, its levels measured) and writing its file, less the process before the bake. The bake holds its
# texture in half floats, 267 B per texel with the mip chain, and its distinct texels in half floats besides (200 B
# each), and half a gigabyte whatever the size (the parameter rows, the calibration's walks, the levels'
# measurement). Measured over three runs 0.85-0.86 GB at 1024 texels a side, 1.96-2.12 GB at 2048 and 5.48-5.56 GB
# at 4096 (about 380 and 300 B a texel more: the share of distinct texels falls from 96% to 62%); a mix
# (``bake_mix``) took as much. The check counts a margin above each, and about what a bake of every texel
# distinct would hold.
BAKE_FIXED_BYTES = 512 << 20
BAKE_BYTES_PER_TEXEL = 500
GATHER_TEXELS = 1 << 16  # texels gathered into the chain at once (26 MB of float32 latents)
DEFAULT_MAX_SIDE = 2048  # the add-on's default Bake Resolution: about 2 GB at the peak of a 2048 x 2048 bake


def estimated_bake_bytes(height: int, width: int) -> int:
    """About how much memory baking a ``height`` x ``width`` texture takes at its peak (``BAKE_FIXED_BYTES`` and
    ``BAKE_BYTES_PER_TEXEL``)."""
    return BAKE_FIXED_BYTES + int(height) * int(width) * BAKE_BYTES_PER_TEXEL


def physical_memory_bytes() -> int | None:
    """This computer's physical memory, or None where it cannot be read (Linux and macOS: ``os.sysconf``;
    Windows: ``GlobalMemoryStatusEx``)."""
    try:
        if hasattr(os, "sysconf") and "SC_PHYS_PAGES" in os.sysconf_names:
            return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
        if os.name == "nt":
            import ctypes

            class _Status(ctypes.Structure):
                _fields_ = [
                    ("length", ctypes.c_ulong),
                    ("load", ctypes.c_ulong),
                    ("total_phys", ctypes.c_ulonglong),
                    ("avail_phys", ctypes.c_ulonglong),
                    ("total_page", ctypes.c_ulonglong),
                    ("avail_page", ctypes.c_ulonglong),
                    ("total_virtual", ctypes.c_ulonglong),
                    ("avail_virtual", ctypes.c_ulonglong),
                    ("avail_extended", ctypes.c_ulonglong),
                ]

            status = _Status()
            status.length = ctypes.sizeof(_Status)
            if ctypes.windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(status)):
                return int(status.total_phys)
    except (OSError, ValueError, AttributeError):
        pass
    return None


def check_bake_memory(height: int, width: int, physical: int | None = None) -> None:
    """ValueError, with the numbers and what to do, when baking ``height`` x ``width`` texels would take more than
    three quarters of this computer's memory (``physical``: its size; default read with
    :func:`physical_memory_bytes`; nothing is checked where it cannot be read)."""
    physical = physical_memory_bytes() if physical is None else physical
    need = estimated_bake_bytes(height, width)
    if physical is None or need <= 0.75 * physical:
        return
    side = max(height, width)
    fits = side
    while fits > 1 and estimated_bake_bytes(round(height * fits / side), round(width * fits / side)) > 0.75 * physical:
        fits //= 2
    raise ValueError(
        f"baking {width} x {height} texels takes about {need / 2**30:.1f} GB of memory and this computer has "
        f"{physical / 2**30:.1f} GB: bake at most {fits} texels a side (about "
        f"{estimated_bake_bytes(round(height * fits / side), round(width * fits / side)) / 2**30:.1f} GB)"
    )


def neural_encoder(
    size: str = "auto", threads: int = 2, refine_s: float = 0.0, refine_cache=None, refine_settings=None
) -> Encoder:
    """The neural runtime's batch encoder for decoder ``size`` ("auto": ``neural.resolve_size``): per-layer
    encoder, then the layering network bottom-up, then the sampling network for the proxy channels.

    Its ``metadata`` (``model``: the size, ``model_digest``: the decoder's sha256) goes into every
    texture baked with it, so the renderer decodes the texture with the models it was baked for.

    ``refine_s`` > 0: the rows it is given (distinct texels: ``bake_texels`` deduplicates) are refined
    against the reference (``neural.refine.refine_latent``) in order, while this encoder's total budget of
    ``refine_s`` seconds lasts (each refinement gets what is left, at most ``REFINE_PER_MATERIAL_S``; one
    started near the end may overrun by its reference walks); ``refine_cache`` is its cache folder and
    ``refine_settings`` its ``RefineSettings`` (default: the refinement's own).
    ``metadata["refine_s"]`` records the budget and ``metadata["refined"]`` counts the rows refined."""
    from ..neural import encode_arrays, load_models

    models = load_models(size, threads).load("layering", "sampling")  # a bake needs both: missing or damaged raise now
    if isinstance(refine_s, bool) or not (np.isfinite(refine_s) and refine_s >= 0):
        raise ValueError(f"refine_s must be a finite number of seconds >= 0, got {refine_s!r}")
    left = [float(refine_s)]

    def encode(arrays):
        # every row is encoded: deduplication is bake_texels' job, so it can be measured
        z = encode_arrays(arrays, models)
        if left[0] > 0.0:
            z = _refine_rows(arrays, z, models, left, refine_cache, refine_settings, encode.metadata, encode.step)
        return z, models.proxy_params(z)

    encode.metadata = {"model": models.size, "model_digest": models.digest}
    encode.models = models  # what bake_stack calibrates the texture's texels against
    encode.concurrent = refine_s == 0  # batches may run side by side (a refinement spends one budget in order)
    # called with the rows refined so far in the batch after each one (seconds of work each): the bake hears a
    # cancel and moves its progress there (``_bake_texels`` sets it)
    encode.step = None
    if refine_s > 0:
        encode.metadata.update(refine_s=float(refine_s), refined=0)
    return encode


REFINE_PER_MATERIAL_S = 10.0


def _refine_rows(
    arrays: StackArrays, z: np.ndarray, models, left: list, cache_dir, settings, metadata: dict, step=None
) -> np.ndarray:
    """Refined latents for the first rows of ``arrays`` while the budget ``left[0]`` lasts; ``step(rows done)``
    (optional) after each row, which may raise to stop."""
    from ..neural.refine import refine_latent

    z = np.array(z, dtype=np.float32)
    for i in range(len(arrays)):  # a loop over materials (distinct texels), each seconds of work, not pixels
        if left[0] <= 0.0:
            break
        t = time.perf_counter()
        z[i], _ = refine_latent(
            arrays.stack(i),
            models.size,
            budget_s=min(left[0], REFINE_PER_MATERIAL_S),
            settings=settings,
            threads=models.threads,
            cache_dir=cache_dir,
        )
        left[0] -= time.perf_counter() - t
        metadata["refined"] += 1
        if step is not None:
            step(i + 1)
    return z


def model_key(size: str, digest: str | None, refine_s: float = 0.0, calibrated: bool = False) -> str:
    """The model part of a bake key: the decoder size, the refinement budget when there is one
    (refined texels are not the encoded ones) and, when known, the decoder file's digest
    (``encode.metadata["model_digest"]``, ``ModelSet.digest``), so a bake made with an earlier
    decoder of the same size, or with another refinement budget, is never taken for current; a refined
    bake's key holds the refinement's and the reference estimator's versions too (``refine.REFINE_VERSION``,
    ``reference.ESTIMATOR_VERSION``: its texels were fitted to that estimator's lobes);
    ``calibrated``: the texture carries its albedo calibration, keyed by the calibration's settings
    (``calibrate.settings_key``), so a bake without one, or with other settings, is baked again."""
    if refine_s:
        from ..neural.refine import REFINE_VERSION
        from ..reference import ESTIMATOR_VERSION

        name = f"{size}+refine{refine_s:g}-v{REFINE_VERSION}-e{ESTIMATOR_VERSION}"
    else:
        name = size
    if calibrated:
        from ..neural.calibrate import settings_key

        name += "+calibrated-" + hashlib.sha256(settings_key().encode()).hexdigest()[:8]
    return f"{name}:{digest}" if digest else name


def bake_key(
    spatial: SpatialStack,
    resolution: tuple[int, int],
    model: str,
    mix: SpatialStack | None = None,
    mask: np.ndarray | None = None,
) -> str:
    """A short hash of everything a bake depends on: stack(s), driving images, mask, resolution, model."""
    h = hashlib.sha256()
    if mix is not None:
        h.update(bake_key(mix, resolution, model).encode())
        h.update(np.ascontiguousarray(mask, dtype=np.float32).tobytes())
    h.update(spatial.stack.to_json().encode())
    h.update(repr(tuple(resolution)).encode())
    h.update(model.encode())
    if "+calibrated-" in model and _clamps_top(spatial):  # calibrated by the rule for clamped tops since it came
        from ..neural.calibrate import TOP_RULE

        h.update(TOP_RULE.encode())
    if _top_ior_outside_trained(spatial):  # such texels hold their own top ior since the renderer's lobe takes it
        from ..neural.top_lobe import OWN_TOP_IOR

        h.update(OWN_TOP_IOR.encode())
    for path in sorted(spatial.maps):
        h.update(path.encode())
        h.update(np.ascontiguousarray(spatial.maps[path], dtype=np.float32).tobytes())
    return h.hexdigest()[:16]


def _top_ior_outside_trained(spatial: SpatialStack) -> bool:
    """Whether some texel's top coating has an ior outside the trained range (its lobe takes the coating's own)."""
    from ..neural.top_lobe import outside_trained_ior

    return bool(spatial.stack.coatings) and bool(outside_trained_ior(spatial.top_range("ior")).any())


def _clamps_top(spatial: SpatialStack) -> bool:
    """Whether some texel's top coating leaves the trained ranges (the renderer's top lobe is then the clamped one:
    ``calibrate.top_clamped``), from its parameters' ranges over the texels."""
    from ..stack import TRAINED_RANGES

    if not spatial.stack.coatings:
        return False
    alpha, ior = spatial.top_range("roughness"), spatial.top_range("ior")
    return alpha[0] < TRAINED_RANGES["roughness"][0] or not (
        TRAINED_RANGES["ior"][0] <= ior[0] and ior[1] <= TRAINED_RANGES["ior"][1]
    )


class BakeCancelled(Exception):
    """Raised when the ``cancel`` callback of a bake returns True."""


@dataclass
class BakeStats:
    texels: int
    unique: int
    seconds: float  # encoding the texels
    calibration_seconds: float = 0.0  # the texture's calibration (``bake_stack``), when it has one
    clusters: int = 0  # its factor tables
    # what the networks saw clamped to their trained ranges (``stack.clamp_to_trained``' notes over the distinct
    # texels, ``bake_stack``): a user is told, not only a console
    clamped: tuple = ()

    @property
    def texels_per_second(self) -> float:
        return self.texels / self.seconds if self.seconds > 0 else float("inf")


def bake_texels(
    arrays: StackArrays,
    encode: Encoder,
    *,
    dedup: bool = True,
    batch: int = BATCH,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    threads: int = 0,
) -> tuple[np.ndarray, BakeStats]:
    """(N, 100) float32 texels (latents, proxy, top coating channels) for N stacks; the networks run on
    ``threads`` threads (0: every core; ``addon.core.neural.session.threads_in_force``).

    An encoder that says so (``encode.concurrent``, the neural runtime's without refinement) encodes
    ``threads`` batches side by side, so that one batch's numpy work (features, the layer dedup) overlaps
    another's networks; the texels do not depend on it."""
    texels, stats, _distinct = _bake_in_threads(arrays, encode, dedup, batch, progress, cancel, threads)
    return texels, stats


def _bake_in_threads(arrays, encode, dedup, batch, progress, cancel, threads, gather=True):
    from ..neural.session import threads_in_force

    n_threads = thread_count(threads)
    workers = n_threads if getattr(encode, "concurrent", False) else 1
    with threads_in_force(n_threads):
        return _bake_texels(arrays, encode, dedup, batch, progress, cancel, workers, gather)


def _refine_steps(encode, batch_start, m: int = 0, progress=None, cancel=None) -> None:
    """Give a refining encoder (``neural_encoder``'s, whose ``step`` it calls after each refined row: seconds of
    work each) a step that stops the bake on ``cancel`` and moves ``progress`` over the ``m`` distinct texels,
    counting from ``batch_start[0]``, the batch being encoded; ``batch_start`` None takes it away. Only for batches
    encoded one at a time on the bake's thread (a refining encoder's are)."""
    if not hasattr(encode, "step"):
        return
    if batch_start is None:
        encode.step = None
        return

    def step(rows: int) -> None:
        done = batch_start[0] + rows
        if cancel is not None and cancel():
            raise BakeCancelled(f"bake cancelled while refining, after {done} of {m} distinct texels")
        if progress is not None:
            progress(min(1.0, done / m))

    encode.step = step


def _bake_texels(arrays, encode, dedup, batch, progress, cancel, workers=1, gather=True):
    """``bake_texels``' texels and stats, and the distinct rows it encoded: ``(stacks, texels, counts)``. Without
    ``gather`` the first is ``(distinct texels, inverse)`` instead (None: every row its own), for a caller that
    gathers them where they go (``bake_stack``: into the mip chain's base, with no texture-sized copy between); the
    distinct texels are then half floats, the values the texture stores (ValueError for one a half cannot hold)."""
    t0 = time.perf_counter()
    n = len(arrays)
    inverse = None  # None: every row is its own (no gather at the end)
    todo = arrays
    if dedup:
        first, inverse = distinct_rows(arrays.to_matrix(np.float32))
        if len(first) < n:
            todo = arrays.take(first)
        else:  # all distinct: first and inverse are arange(n)
            inverse = None
    m = len(todo)
    out = np.empty((m, len(CHANNEL_NAMES)), dtype=np.float32 if gather else np.float16)

    batch_start = [0]  # of the batch being encoded (a refining encoder's step counts from it)

    def encode_batch(start: int) -> int:
        part = todo.take(slice(start, start + batch))
        batch_start[0] = start
        z, proxy = encode(part)
        z = np.asarray(z, dtype=np.float32).reshape(len(part), -1)
        proxy = np.asarray(proxy, dtype=np.float32).reshape(len(part), -1)
        if z.shape[1] != 96 or proxy.shape[1] != 2:
            raise ValueError(f"encoder returned latents {z.shape} and proxy {proxy.shape}; expected (N, 96) and (N, 2)")
        # the top coating's channels: what a remainder decoder's exact top lobe needs
        texels = np.concatenate([z, proxy, top_coats(part)], axis=1, dtype=np.float32)
        if not np.isfinite(texels).all():
            raise ValueError("the encoder returned non-finite latents")
        store_texels(texels, out[start : start + len(part)], "the encoder's latents")
        return start + len(part)

    starts = list(range(0, m, batch))
    workers = max(1, min(int(workers), len(starts)))
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="bake") if workers > 1 else None
    try:
        if workers == 1:
            _refine_steps(encode, batch_start, m, progress, cancel)
        pending = []  # batches in flight, oldest first: at most ``workers``
        for i, start in enumerate(starts + [None]):  # a loop over batches, not texels
            if start is not None and cancel is not None and cancel():
                raise BakeCancelled(
                    f"bake cancelled after {starts[i - len(pending)] if pending else start} of {m} distinct texels"
                )
            if start is not None:
                pending.append(submit_in_context(pool, encode_batch, start) if pool else encode_batch(start))
            while pending and (start is None or len(pending) >= workers):
                done = pending.pop(0)
                end = done.result() if pool else done
                if progress is not None:
                    progress(min(1.0, end / m))
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        _refine_steps(encode, None)  # this bake's callbacks go with it
    counts = np.ones(m) if inverse is None else np.bincount(inverse, minlength=m).astype(np.float64)
    clamped = tuple(clamp_notes(todo)) if m else ()
    stats = BakeStats(texels=n, unique=m, seconds=time.perf_counter() - t0, clamped=clamped)
    texels = (out if inverse is None else out[inverse]) if gather else (out, inverse)
    return texels, stats, (todo, out, counts)


def bake_stack(
    spatial: SpatialStack,
    encode: Encoder,
    *,
    resolution: tuple[int, int] | None = None,
    dedup: bool = True,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    metadata: dict | None = None,
    threads: int = 0,
    calibrate: bool = True,
    check_filtering: bool = True,
) -> tuple[LatentTexture, BakeStats]:
    """Bake a spatially varying stack into a mip-mapped latent texture; the networks run on
    ``threads`` threads (0: every core; Blender's render thread setting in the add-on).

    ``calibrate``: the texture's albedo calibration (``textures.calibration``: its distinct texels clustered
    by latent, a factor table per cluster against the reference, about a second per cluster) goes into its
    metadata (``calibration``), which the renderer applies; only with an encoder that carries its models
    (``neural_encoder``'s). ``progress`` runs to 1 over both parts. ``check_filtering``: with such an
    encoder, the mip levels whose latents decode like the average of their texels are measured
    (``textures.filtering``) and recorded (``filter_levels``), so the renderer filters no further.

    ValueError before any work when the bake would take more than three quarters of this computer's memory
    (:func:`check_bake_memory`)."""
    check_bake_memory(*(resolution or spatial.resolution or (1, 1)))  # a clear error, not the system's out-of-memory
    arrays, (h, w) = spatial.texels(resolution)
    models = getattr(encode, "models", None) if calibrate else None
    share = 1.0 if models is None else ENCODE_SHARE
    (distinct, inverse), stats, (rows, _, counts) = _bake_in_threads(
        arrays,
        encode,
        dedup,
        BATCH,
        None if progress is None else (lambda f: progress(share * f)),
        cancel,
        threads,
        gather=False,
    )
    del arrays  # the distinct rows (``rows``) are what the calibration needs
    meta = {"stack": spatial.stack.to_json(), "maps": ",".join(sorted(spatial.maps))}
    meta.update(metadata or {})
    meta.update(getattr(encode, "metadata", {}))  # the encoder's decoder size and digest
    if models is not None:
        from ..neural.session import threads_in_force
        from .calibration import calibrate_texture

        def step(fraction):
            if cancel is not None and cancel():
                raise BakeCancelled("bake cancelled during the texture's calibration")
            if progress is not None:
                progress(share + (1.0 - share) * fraction)

        t = time.perf_counter()
        step(0.0)
        with threads_in_force(thread_count(threads)):
            calibration = calibrate_texture(rows, distinct, counts, models, step, threads=thread_count(threads))
        meta["calibration"] = calibration.to_text()
        stats = dataclasses.replace(
            stats, calibration_seconds=time.perf_counter() - t, clusters=len(calibration.tables)
        )
    del rows, counts
    _still_wanted(progress, cancel, "the mip chain")()
    # The texels gathered a band at a time into the base level of a half-float chain (the values the texture's file
    # stores), then the levels below it in place: the bake's peak holds the distinct texels and the chain, no
    # texture-sized copy besides (BAKE_BYTES_PER_TEXEL).
    chain = MipChain.empty(h, w, distinct.shape[1], dtype=np.float16)
    for start in range(0, h * w, GATHER_TEXELS):  # a loop over bands of texels
        chain.write_texels(start, _band_of_texels(distinct, inverse, start))
    del distinct, inverse
    tex = LatentTexture(chain.fill(), meta)
    encoder_models = getattr(encode, "models", None)
    if check_filtering and encoder_models is not None:
        record_filter_levels(tex, encoder_models, threads, _still_wanted(progress, cancel, "the filtering measurement"))
    return tex, stats


def _band_of_texels(distinct: np.ndarray, inverse: np.ndarray | None, start: int) -> np.ndarray:
    """Texels ``start`` .. ``start + GATHER_TEXELS`` of a texture from its distinct texels and ``inverse`` (None:
    every texel distinct), as ``_bake_texels`` returns them without gathering."""
    rows = slice(start, start + GATHER_TEXELS)
    return distinct[rows] if inverse is None else distinct[inverse[rows]]


def record_filter_levels(tex: LatentTexture, models, threads: int = 0, step=None) -> None:
    """``tex.metadata["filter_levels"]``: how many of its levels decode like the average of their texels
    (``textures.filtering.filterable_levels``, on ``threads`` threads; ``step()`` before each level, which may
    raise to stop)."""
    from ..neural.session import threads_in_force
    from .filtering import filterable_levels

    with threads_in_force(thread_count(threads)):
        tex.metadata["filter_levels"] = filterable_levels(models, tex.levels, step=step)[0]


def _still_wanted(progress: Progress | None, cancel: Callable[[], bool] | None, what: str) -> Callable[[], None]:
    """A step for the bake's last parts (the chain, the filtering measurement: seconds at large sizes), where its
    progress is full: raises BakeCancelled on ``cancel``, and calls ``progress(1.0)``, which may raise too (the
    add-on cancels so)."""

    def step() -> None:
        if cancel is not None and cancel():
            raise BakeCancelled(f"bake cancelled during {what}")
        if progress is not None:
            progress(1.0)

    return step


def bake_mix(
    a: SpatialStack,
    b: SpatialStack,
    mask: np.ndarray,
    encode: Encoder,
    *,
    resolution: tuple[int, int] | None = None,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    metadata: dict | None = None,
    check_filtering: bool = True,
) -> tuple[LatentTexture, BakeStats]:
    """Blend two (spatially varying) stacks through ``mask`` (H, W) in [0, 1] in latent space.

    Each texel's latent is (1 - m) z_a + m z_b (and likewise the proxy parameters): a blended
    texel has one intermediate lobe, where blending the two BRDF values would give two lobes.
    Not calibrated (a blended latent is no stack's); ``check_filtering`` as for :func:`bake_stack`.
    The stacks may differ in everything, including their number of coatings.
    """
    m = np.asarray(mask, dtype=np.float64)
    if m.ndim == 3 and m.shape[2] >= 1:
        m = m[..., 0]
    if m.ndim != 2:
        raise ValueError(f"the mask must be an (H, W) image, got shape {np.shape(mask)}")
    if not np.isfinite(m).all() or m.min() < 0.0 or m.max() > 1.0:
        raise ValueError("the mask must hold values in [0, 1]")
    for name, s in (("first", a), ("second", b)):
        if s.resolution is not None and s.resolution != m.shape:
            raise ValueError(
                f"the {name} stack's images are {s.resolution[1]}x{s.resolution[0]} but the mask is "
                f"{m.shape[1]}x{m.shape[0]}: they must share a resolution"
            )
    h, w = resolution or m.shape
    if h > m.shape[0] or w > m.shape[1]:
        raise ValueError(f"bake resolution {w}x{h} must not exceed the mask's {m.shape[1]}x{m.shape[0]}")
    check_bake_memory(h, w)  # bake_stack's estimate: a mix holds two stacks' distinct texels, in half floats
    from .mip import resample_area

    if (h, w) != m.shape:
        m = resample_area(m[..., None], h, w)[..., 0]
    t0 = time.perf_counter()
    baked = []
    for i, spatial in enumerate((a, b)):  # each stack's distinct texels, in half floats, and where they go
        arrays, _ = _texels_at(spatial, (h, w))
        part = None if progress is None else (lambda f, i=i: progress(0.5 * (i + f)))
        texels, stats, _ = _bake_in_threads(arrays, encode, True, BATCH, part, cancel, 0, gather=False)
        baked.append((texels, stats))
        del arrays
    ((da, ia), sa), ((db, ib), sb) = baked
    t = m.reshape(-1, 1).astype(np.float32)
    chain = MipChain.empty(h, w, len(CHANNEL_NAMES), dtype=np.float16)
    for start in range(0, h * w, GATHER_TEXELS):  # blended a band of texels at a time, into the chain's base
        mix = t[start : start + GATHER_TEXELS]
        ta, tb = (float32_texels(_band_of_texels(d, i, start)) for d, i in ((da, ia), (db, ib)))
        blend = (1.0 - mix) * ta + mix * tb  # two halves' blend, within the half range but for float32 rounding
        chain.write_texels(start, np.clip(blend, -HALF_MAX, HALF_MAX, out=blend))
    del baked, da, ia, db, ib
    meta = {"stack": a.stack.to_json(), "mix_stack": b.stack.to_json()}
    meta.update(metadata or {})
    meta.update(getattr(encode, "metadata", {}))  # the encoder's decoder size and digest
    stats = BakeStats(
        texels=h * w,
        unique=sa.unique + sb.unique,
        seconds=time.perf_counter() - t0,
        clamped=tuple(dict.fromkeys(sa.clamped + sb.clamped)),
    )
    tex = LatentTexture(chain.fill(), meta)
    if check_filtering and getattr(encode, "models", None) is not None:
        record_filter_levels(tex, encode.models, step=_still_wanted(progress, cancel, "the filtering measurement"))
    return tex, stats


def _texels_at(spatial: SpatialStack, resolution: tuple[int, int]):
    """A stack's texels at ``resolution``; a constant stack is repeated to fill it."""
    if spatial.resolution is None:
        return StackArrays.repeat(spatial.stack, resolution[0] * resolution[1]), resolution
    return spatial.texels(resolution)

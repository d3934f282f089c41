"""Wavefront path tracer: all live paths advance one bounce at a time.

Per bounce: one embreex call intersects every live path; area lights, and point, spot and sun lights of a radius
or an angle, are intersected analytically; misses gather the environment; hits are grouped by material and each
material is bound and queried once per group (one ONNX batch per neural material); next-event estimation
picks one light (or the environment) per hit uniformly, traces all shadow rays in one occlusion
call and is combined with BSDF sampling by the power heuristic. Russian roulette starts at
``rr_depth``. Random numbers come from a generator keyed by (seed, pass, chunk, bounce), so a
render is deterministic for fixed settings.

``strategy`` selects the estimator: "mis" (both, power heuristic), "light" (next-event
estimation only; emission found by BSDF sampling counts only after delta events) or "bsdf"
(BSDF sampling only; delta lights, which BSDF sampling cannot hit, are still sampled). All three
converge to the same image, which the tests check.
"""

from __future__ import annotations

import hashlib
import math
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as wait_for_futures
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .. import kernels
from ..neural import session
from ..neural.calibrate import check_mode as calibrate_mode
from ..reference.walk import stopping
from ..threads import submit_in_context, thread_count
from . import materials as mat
from .film import Film
from .lights import NO_IMAGE
from .scene import Scene
from .scratch import Scratch, ScratchPool

STRATEGIES = ("mis", "light", "bsdf")
MODES = ("neural", "reference")


class Cancelled(Exception):
    """Raised inside :func:`render` when the progress callback returns False or its ``stop`` says stop."""


@dataclass
class RenderSettings:
    samples: int = 16
    # bounces after the first hit, as Cycles counts them: 0 is direct lighting only (each first hit's light samples
    # and the emission its sampled direction finds), 1 adds one bounce of indirect light
    max_bounces: int = 8
    seed: int = 0
    strategy: str = "mis"
    mode: str = "neural"
    rr_depth: int = 3
    chunk_paths: int = 1 << 17
    reference_walks: int = 16
    threads: int = 0  # chunks traced at once; 0: one per CPU core
    # albedo calibration of layered stacks in neural mode (``neural.calibrate``): True, False, or
    # "cached" (only calibrations already made, this session or kept on disk: no reference walks)
    calibrate: bool | str = True
    # Blender's Film > Transparent: the sky the camera sees directly is left out, and the film's alpha is the share
    # of camera rays that met a surface (``Film.rgba``); the sky still lights the scene
    transparent: bool = False

    def __post_init__(self):
        if self.strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {STRATEGIES}, got {self.strategy!r}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if int(self.samples) < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if int(self.max_bounces) < 0:
            raise ValueError(f"max_bounces must be >= 0, got {self.max_bounces}")
        if int(self.chunk_paths) < 1:
            raise ValueError(f"chunk_paths must be >= 1, got {self.chunk_paths}")
        if int(self.reference_walks) < 1:
            raise ValueError(f"reference_walks must be >= 1 (walks per reference estimate), got {self.reference_walks}")
        if int(self.threads) < 0:
            raise ValueError(f"threads must be >= 0 (0: one per CPU core), got {self.threads}")
        calibrate_mode(self.calibrate)

    @classmethod
    def threads_for(cls, threads_mode: str, threads: int) -> int:
        """The ``threads`` setting for Blender's render thread setting (``scene.render.threads_mode``
        "AUTO": 0, every core; "FIXED": ``threads``)."""
        if threads_mode not in ("AUTO", "FIXED"):
            raise ValueError(f"threads_mode must be 'AUTO' or 'FIXED', got {threads_mode!r}")
        return 0 if threads_mode == "AUTO" else max(1, int(threads))

    @property
    def thread_count(self) -> int:
        """Chunks of paths traced at once: ``threads``, or one per CPU core when it is 0."""
        return thread_count(self.threads)


@dataclass
class RenderStats:
    """Wall time per phase (seconds) and counts. ``network`` is time waiting on the networks
    (ONNX Runtime batches), ``reference`` inside position-free estimators, ``rays`` the embreex
    time, ``setup`` the scene's preparation before the first path (materials resolved: stacks encoded
    and, on a session's first render of a stack, calibrated; the ray-tracing structure and the light
    tables), ``total`` the render's wall time.

    What is neither rays, networks nor reference estimators is the ``rest``, which splits into ``shading``, the
    work that computes light at the hits (the surface at each hit, the emission rays find, the light samples,
    the materials' f, densities and samples, and the light they add to the image: compiled loops and the numpy
    around them, less the rays and networks inside), and ``bookkeeping``, everything else (camera rays, random
    numbers, sorting hits by material, gathering and compacting paths, Russian roulette, setup).

    Chunks of paths are traced on several threads at once; each thread's time splits into the
    phases and the rest, and the phase times here are those splits summed over the threads and
    scaled by the tracing's wall time (``total`` less ``setup``) / thread time (``thread_seconds``), so
    the phases and the rest (``setup`` included) add up to ``total`` whatever the thread count."""

    paths: int = 0
    rays: int = 0
    seconds: dict = field(
        default_factory=lambda: {
            "rays": 0.0, "network": 0.0, "reference": 0.0, "shading": 0.0, "setup": 0.0, "total": 0.0
        }
    )  # fmt: skip
    nonfinite: int = 0
    material_kinds: list = field(default_factory=list)  # per material index: analytic/neural/reference
    thread_seconds: float = 0.0  # summed wall time of the threads that traced the chunks
    thread_phases: dict = field(default_factory=lambda: {"rays": 0.0, "network": 0.0, "reference": 0.0, "shading": 0.0})

    @property
    def rest(self) -> float:
        """Everything but rays, networks and reference estimators: ``shading`` and ``bookkeeping``."""
        s = self.seconds
        return max(0.0, s["total"] - s["rays"] - s["network"] - s["reference"])

    @property
    def bookkeeping(self) -> float:
        """The rest less the shading (the class docstring)."""
        return max(0.0, self.rest - self.seconds["shading"])

    @property
    def paths_per_second(self) -> float:
        return self.paths / self.seconds["total"] if self.seconds["total"] > 0 else 0.0

    def summary(self) -> str:
        s = self.seconds
        return (
            f"{self.paths} paths in {s['total']:.2f} s ({self.paths_per_second:,.0f}/s): rays {s['rays']:.2f} s, "
            f"network {s['network']:.2f} s, reference {s['reference']:.2f} s, rest {self.rest:.2f} s (shading "
            f"{s['shading']:.2f} s, bookkeeping {self.bookkeeping:.2f} s, of which setup {s['setup']:.2f} s: "
            "materials, calibrations, scene)"
        )


class Tracer:
    """embreex closest-hit and occlusion queries over the scene's triangles (float32 rays); each
    query adds its time and ray count to ``stats``."""

    def __init__(self, mesh):
        self.scene = None
        # the triangles as embree was given them, kept as long as its structure (the mesh itself is not: a kept
        # tracer, ``tracer_for``, holds no normals or uvs)
        self.positions = np.ascontiguousarray(mesh.positions, dtype=np.float32)
        if mesh.triangle_count:
            from embreex import rtcore_scene as rtcs
            from embreex.mesh_construction import TriangleMesh

            self.scene = rtcs.EmbreeScene()
            TriangleMesh(self.scene, self.positions)

    def intersect(self, o, d, stats: RenderStats, scratch: Scratch | None = None, tmax=None):
        """Distance (inf on a miss), triangle (-1), barycentrics of the closest hit of each ray (o, d): arrays of
        ``scratch`` when given (overwritten by its next intersection), else new ones. C-contiguous float32 rays
        are handed to embree as they are. ``tmax`` (N,): how far each ray reaches (none: all the way); a ray
        that meets nothing before it misses."""
        n = len(o)
        if self.scene is None or n == 0:
            return np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros(n), np.zeros(n)
        scratch = scratch or Scratch()
        o32, d32 = _rays32(scratch, "rays32", o, d)
        dists = None
        if tmax is not None:
            (dists,) = scratch.arrays("rays_tmax32", n, ((0, np.float32),))
            np.minimum(tmax, kernels.FAR, out=dists, casting="same_kind")
        t0 = time.perf_counter()
        r = self.scene.run(o32, d32, dists=dists, output=1)
        stats.seconds["rays"] += time.perf_counter() - t0
        stats.rays += n
        return kernels.closest_hits(
            scratch.arrays("closest", n, kernels.CLOSEST_HITS_OUT), r["primID"], r["tfar"], r["u"], r["v"]
        )

    def occluded(self, o, d, tmax, stats: RenderStats, scratch: Scratch | None = None):
        """Whether each ray (o, d) meets a triangle before ``tmax`` (inf or beyond ``kernels.FAR`` taken as
        ``FAR``). float32 arrays (``kernels.sample_lights``' shadow rays) are handed to embree as they are: a
        float32 ``tmax`` must be at most ``FAR`` already."""
        n = len(o)
        if self.scene is None or n == 0:
            return np.zeros(n, dtype=bool)
        scratch = scratch or Scratch()
        o32, d32 = _rays32(scratch, "shadow32", o, d)
        if _is_float32_rows(tmax):
            dist = tmax
        else:
            (dist,) = scratch.arrays("shadow_dist32", n, ((0, np.float32),))
            np.minimum(tmax, kernels.FAR, out=dist, casting="same_kind")
        t0 = time.perf_counter()
        r = self.scene.run(o32, d32, dists=dist, query="OCCLUDED")
        stats.seconds["rays"] += time.perf_counter() - t0
        stats.rays += n
        return np.asarray(r) != -1


def _is_float32_rows(a) -> bool:
    return isinstance(a, np.ndarray) and a.dtype == np.float32 and a.flags.c_contiguous


def _rays32(scratch: Scratch, name: str, o, d) -> tuple[np.ndarray, np.ndarray]:
    """Rays (o, d) in float32 (embree's precision): the arrays themselves when they are C-contiguous float32
    already (the shadow rays ``kernels.sample_lights`` writes), else copies in ``scratch``'s arrays of ``name``."""
    if _is_float32_rows(o) and _is_float32_rows(d):
        return o, d
    o32, d32 = scratch.arrays(name, len(o), ((3, np.float32), (3, np.float32)))
    o32[...], d32[...] = o, d
    return o32, d32


# The last few meshes' ray-tracing structures, by the content of their triangles (``tracer_for``).
TRACERS_KEPT = 2
_TRACERS: OrderedDict = OrderedDict()
_TRACERS_LOCK = threading.Lock()


def clear_tracers() -> None:
    """Forget the ray-tracing structures kept for later renders (``tracer_for``)."""
    with _TRACERS_LOCK:
        _TRACERS.clear()


def tracer_for(mesh) -> Tracer:
    """The :class:`Tracer` of ``mesh``, built once for each content of its triangles and kept for the renders that
    follow (the last :data:`TRACERS_KEPT`): the viewport renders a scene two or three times after an edit (a
    reduced first image, the full passes, the calibrated ones), a view change or an edit of a material leaves the
    triangles as they were, and building the structure took 25 ms of the viewport's 50-80 ms first image on the
    demo scene. Found by a digest of the triangles' positions (0.7 ms there), so a scene exported again with the
    same geometry finds it too."""
    key = getattr(mesh, "_tracer_key", None)  # a mesh's digest is taken once (its renders share it)
    if key is None:
        positions = np.ascontiguousarray(mesh.positions, dtype=np.float32)
        key = mesh._tracer_key = (positions.shape, hashlib.blake2b(positions.data, digest_size=20).digest())
    with _TRACERS_LOCK:
        tracer = _TRACERS.get(key)
        if tracer is None:
            tracer = _TRACERS[key] = Tracer(mesh)
            while len(_TRACERS) > TRACERS_KEPT:
                _TRACERS.popitem(last=False)
        else:
            _TRACERS.move_to_end(key)
        return tracer


def uv_scale(mesh) -> np.ndarray:
    """(triangles,) uv units per world unit of each triangle: sqrt(uv area / world area); 0 for a
    mesh without uvs (no texture footprint)."""
    if not mesh.triangle_count or mesh.uvs is None:
        return np.zeros(mesh.triangle_count)
    uv = mesh.uvs.astype(np.float64)
    a_uv = 0.5 * np.abs(
        (uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1])
        - (uv[:, 2, 0] - uv[:, 0, 0]) * (uv[:, 1, 1] - uv[:, 0, 1])
    )
    return np.sqrt(a_uv / np.maximum(mesh.areas, 1e-30))


def camera_hits(scene: Scene, px, py) -> tuple[np.ndarray, np.ndarray]:
    """Primary rays through the centres of pixels (``px``, ``py``): the triangle each hits (-1 for
    none) and the texture footprint there (uv units; ``inf`` on a miss or a triangle without uvs),
    as the renderer computes it for its first bounce. One intersection call."""
    cam = scene.camera
    px = np.asarray(px, dtype=np.int64).reshape(-1)
    py = np.asarray(py, dtype=np.int64).reshape(-1)
    fp = np.full(len(px), np.inf)
    if not scene.mesh.triangle_count or not len(px):
        return np.full(len(px), -1, dtype=np.int64), fp
    o, d, spread, tmax, near = cam.rays(px, py, np.full((len(px), 2), 0.5))
    t, prim, bu, bv = tracer_for(scene.mesh).intersect(o, d, RenderStats(), tmax=_clipped(cam, tmax))
    prim = np.asarray(prim, dtype=np.int64)
    hit = np.flatnonzero(prim >= 0)
    if len(hit):
        corners, face_normals, tri_uv_scale, tri_offset = _triangle_arrays(scene.mesh)
        f = kernels.surface_hits(
            kernels.rows_of(kernels.SURFACE_HITS_OUT, len(hit)),
            corners,
            face_normals,
            tri_uv_scale,
            tri_offset,
            hit,
            prim,
            bu,
            bv,
            d[hit],
            t,
            spread[hit] * near[hit],  # the cone's width where the ray starts: on the near plane
            spread[hit],
        )[5]
        fp[hit] = np.where(f > 0, f, np.inf)
    return prim, fp


def material_hits_per_path(scene: Scene, chosen: np.ndarray, max_bounces: int, rays: int = 4096, seed: int = 0):
    """How often a path of ``scene`` meets one of the materials ``chosen`` (a flag per material index), on average:
    a pilot of ``rays`` camera rays spread over the image and one diffuse bounce from each surface they hit. The
    first hits count directly; each of the ``max_bounces`` bounces after them meets a chosen material as often as
    the pilot's bounce did, and goes on only as often as it met any surface (no Russian roulette: an estimate from
    above). What *Auto*'s time budget predicts a frame's decoder queries from (``quality.frame_decoder_queries``)."""
    cam = scene.camera
    if not scene.mesh.triangle_count:
        return 0.0
    chosen = np.append(np.asarray(chosen, dtype=bool), False)  # a material index beyond the list: not chosen
    rng = np.random.default_rng(seed)
    side = max(1, int(math.sqrt(rays * cam.width / cam.height)))
    xs = np.linspace(0, cam.width - 1, side).astype(np.int64)
    ys = np.linspace(0, cam.height - 1, max(1, rays // side)).astype(np.int64)
    px, py = (a.reshape(-1) for a in np.meshgrid(xs, ys))
    o, d, _, tmax, _ = cam.rays(px, py, rng.random((len(px), 2)))
    tracer = tracer_for(scene.mesh)
    t, prim, _, _ = tracer.intersect(o, d, RenderStats(), tmax=_clipped(cam, tmax))
    material = np.minimum(scene.mesh.material_index.astype(np.int64), len(chosen) - 1)
    hit = np.flatnonzero(prim >= 0)
    first = float(chosen[material[prim[hit]]].sum()) / len(px)
    if max_bounces < 1 or len(hit) == 0:
        return first
    p = o[hit] + t[hit, None] * d[hit]
    n = scene.mesh.face_normals[prim[hit]].astype(np.float64)
    n *= -np.sign(np.einsum("ij,ij->i", n, d[hit]))[:, None]  # toward the camera
    # cosine-distributed directions about n: a uniform point on the unit sphere, added to n
    z = rng.uniform(-1.0, 1.0, len(hit))
    phi = rng.uniform(0.0, 2.0 * math.pi, len(hit))
    r = np.sqrt(1.0 - z * z)
    w = n + np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-12)
    scale = np.abs(p).max(axis=1, keepdims=True) + 1.0
    t2, prim2, _, _ = tracer.intersect(p + n * (1e-4 * scale), w, RenderStats())
    again = prim2 >= 0
    on_chosen = float(chosen[material[prim2[again]]].sum()) / len(px)  # per camera ray
    going_on = float(again.mean())  # the share of bounces that meet a surface at all
    return first + on_chosen * sum(going_on**k for k in range(max_bounces))


def _triangle_arrays(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-triangle geometry in float64, as ``kernels.surface_hits`` reads it: the corners' position,
    normal and uv side by side (T, 3, 8), the face normals (T, 3), the uv scale (T,) and the triangles' part of
    the offset of the rays leaving them (T,) (``kernels.triangle_offsets``). Made once a mesh and kept by it: the
    viewport renders one scene several times after each edit or view change (its reduced images, its passes), and
    each made them again (0.3 s of each render's setup at 1.6 M triangles)."""
    kept = getattr(mesh, "_surface_arrays", None)
    if kept is None:
        uvs = np.zeros((mesh.triangle_count, 3, 2)) if mesh.uvs is None else mesh.uvs
        corners = np.ascontiguousarray(np.concatenate([mesh.positions, mesh.normals, uvs], axis=2), dtype=np.float64)
        face_normals = np.ascontiguousarray(mesh.face_normals, dtype=np.float64)
        kept = mesh._surface_arrays = (corners, face_normals, uv_scale(mesh), kernels.triangle_offsets(corners))
    return kept


class _Context:
    """What stays fixed during a render: resolved materials, lights, tracer, settings."""

    def __init__(self, scene: Scene, settings: RenderSettings, stats: RenderStats, halt: "_Halt | None" = None):
        self.scene, self.settings, self.stats = scene, settings, stats
        n_mat = max(len(scene.materials), int(scene.mesh.material_index.max()) + 1 if scene.mesh.triangle_count else 0)
        # A stop is heard during the materials' setup too: a session's first render of a stack calibrates it (about
        # a second of reference walks a stack), between the calibration's steps, on whichever thread makes it.
        stop = None if halt is None else (lambda: _check_stop(halt))
        self.materials = mat.resolve_all(
            [scene.materials[i] if i < len(scene.materials) else None for i in range(n_mat)],
            settings.mode,
            settings.reference_walks,
            settings.calibrate,
            settings.thread_count,
            step=stop,
            check=stop,
        )
        stats.material_kinds = [m.kind for m in self.materials]
        self.tracer = tracer_for(scene.mesh)
        self.camera_axis = scene.camera.axis
        env = scene.environment
        self.env = env if env is not None and not env.is_black else None
        lit = [(li, li.table_row()) for li in scene.lights if li.estimated_power() > 0]
        delta = [(li, row) for li, row in lit if kernels.is_delta(row[0])]
        hit = [(li, row) for li, row in lit if not kernels.is_delta(row[0])]  # area lights, spheres, suns' disks
        # Lights next-event estimation chooses among (uniformly).
        nee = list(delta)
        if settings.strategy != "bsdf":
            nee += hit + ([(self.env, self.env.table_row())] if self.env is not None else [])
        self.nee = [li for li, _ in nee]
        self.p_select = 1.0 / len(nee) if nee else 0.0
        # The light tables the kernels read: next-event estimation's lights, the lights rays can hit (not the
        # delta lights), the environment's image arrays.
        self.nee_kinds = np.array([k for _, (k, _) in nee], dtype=np.int64)
        self.nee_params = np.array([r for _, (_, r) in nee]).reshape(len(nee), kernels.N_PARAMS)
        self.hit_kinds = np.array([k for _, (k, _) in hit], dtype=np.int64)
        self.hit_params = np.array([r for _, (_, r) in hit]).reshape(len(hit), kernels.N_PARAMS)
        self.env_arrays = self.env.image_arrays() if self.env is not None else NO_IMAGE
        self.strategy_code = STRATEGIES.index(settings.strategy)
        m = scene.mesh
        self.material_of_triangle = np.asarray(m.material_index, dtype=np.int64)
        self.corners, self.face_normals, self.uv_scale, self.tri_offset = _triangle_arrays(m)


def render(
    scene: Scene,
    settings: RenderSettings | None = None,
    progress: Callable[[Film, int, int], bool] | None = None,
    film: Film | None = None,
    pixels: np.ndarray | None = None,
    stop: threading.Event | Callable[[], bool] | None = None,
    chunk_progress: Callable[[float], object] | None = None,
    scratches: ScratchPool | None = None,
) -> tuple[Film, RenderStats]:
    """Render ``scene``; returns the film (per-pixel mean and standard error) and statistics.

    ``progress(film, done, total)`` is called after every pass of one sample per pixel; returning
    False stops the render (raising :class:`Cancelled`, with the partial film attached as
    ``exc.film``). Pass a ``film`` to continue accumulating into it (progressive refinement): one of
    whole passes (a film that a ``stop`` left in the middle of a pass is refused, ValueError: its pixels
    would get the stopped pass's samples twice).

    ``stop`` (an event, set from any thread) ends the render sooner than ``progress`` can, which is heard
    after a pass only: every chunk being traced checks it before each bounce and before its materials shade,
    and the render before it takes each chunk, so the render raises :class:`Cancelled` within about half a bounce
    (a view moved during a 1280x720 pass of the demo scene: its first image after 0.11-0.20 s with ``stop``,
    0.52-0.73 s when the old render ran to the end of its pass). ``stop`` may instead be a function of the calling
    thread, True to stop (Blender's ``RenderEngine.test_break``, which belongs to the engine's thread): the
    render calls it on that thread only, before each chunk it takes and every :data:`STOP_POLL_SECONDS` while
    it waits for one, and then stops the chunks as the event does. However a render ends (a stop, a False from
    ``progress``, an error), the chunks still being traced stop at their next bounce. After a stop the film
    holds the finished passes and the chunks of the pass stopped that the render took, in order, before it
    (each pixel's ``count`` says which); ``passes`` counts the finished passes.

    Each pass is cut into equal chunks of at most ``chunk_paths`` pixels; ``settings.thread_count``
    chunks (of this pass or the next) are traced at once on a pool of threads (numpy, embreex and ONNX
    Runtime release the GIL in their loops), with as many more queued, so that a thread whose chunk ends
    first starts the next while the film takes the chunks in order. The networks run a chunk's batches on the
    chunk's own thread when every core traces a chunk, and on one pool of every thread that the chunks share
    when there are fewer chunks than threads (a viewport's first pass).
    Chunks draw their random numbers from their own (pass, chunk) key and are added to the film
    in order, so the image does not depend on the thread count.

    ``pixels`` (flat indices, row 0 at the top) restricts the render to those pixels (a render
    region of any shape: the rest of the film gets no sample); default every pixel.

    ``chunk_progress(fraction)`` is called on the calling thread after each chunk is added to the film, with the
    fraction of the render's chunks added so far (1.0 after the last): a progress bar that moves within a pass
    (a 4K pass of the demo scene is 64 chunks and takes seconds).

    ``scratches``: where the chunks take the arrays their bounces write (``render.scratch``); default a pool of
    this render's, freed at its end. A viewport session passes its own, kept from one render to the next.
    """
    settings = settings or RenderSettings()
    halt = _Halt(stop)
    if film is not None and film.count.size and film.count.max() > film.passes:
        raise ValueError(
            "the film holds part of a pass that a stopped render left (some pixels have more samples than its "
            f"{film.passes} passes): continue from a film of whole passes"
        )
    cam = scene.camera
    stats = RenderStats()
    t_start = time.perf_counter()
    film = film or Film(cam.width, cam.height)
    film.transparent = bool(settings.transparent)
    try:
        with session.threads_in_force(settings.thread_count):  # the materials' encoding and calibration: the scene's
            ctx = _Context(scene, settings, stats, halt)
    except Cancelled as exc:  # stopped during a calibration: the film as it came, nothing cached half made
        stats.seconds["setup"] = time.perf_counter() - t_start
        _finish_stats(stats, time.perf_counter() - t_start)
        exc.film, exc.stats = film, stats
        raise
    stats.seconds["setup"] = time.perf_counter() - t_start
    start_pass = film.passes
    npix = cam.width * cam.height
    whole = pixels is None  # every pixel: each chunk is a run of consecutive pixels
    if whole:
        pixels = np.arange(npix)
    else:
        pixels = np.asarray(pixels)
        if pixels.ndim != 1 or pixels.dtype.kind not in "iu" or len(pixels) == 0:
            raise ValueError(
                f"pixels must be a non-empty 1-D array of pixel indices, got {pixels.dtype} {pixels.shape}"
            )
        if pixels.min() < 0 or pixels.max() >= npix or len(np.unique(pixels)) != len(pixels):
            raise ValueError(f"pixels must be distinct indices in [0, {npix}) (width x height of the camera)")
    # chunks of equal size (at most chunk_paths): unequal ones leave a thread idle at the end of every pass
    n_chunks = -(-len(pixels) // int(settings.chunk_paths))  # ceiling division
    chunk = -(-len(pixels) // n_chunks)
    starts = list(range(0, len(pixels), chunk))
    tasks = [(k, c) for k in range(settings.samples) for c in range(len(starts))]
    # A chunk's bounces write into a Scratch of their own (one per chunk traced at once); its radiance and
    # features into one of ``images``, given back once the film has added them (chunks done and not added yet
    # hold theirs). ``images`` is the render's: its buffers go with it; so are the scratches unless given.
    scratches = scratches if scratches is not None else ScratchPool(chunk)
    images = ScratchPool(chunk)

    def trace(task):
        k, c = task
        pix = pixels[starts[c] : starts[c] + chunk]
        scratch, image = scratches.take(chunk), images.take()
        try:
            # the reference estimates of the chunk hear the stop too, between their walks' events
            with stopping(None if halt is None else (lambda: _check_stop(halt))):
                traced = _trace_paths(ctx, pix, start_pass + k, c, halt, scratch, image)
        except BaseException:
            images.give(image)
            raise
        finally:
            scratches.give(scratch)
        return (slice(starts[c], starts[c] + len(pix)) if whole else pix), traced, image

    workers = min(settings.thread_count, len(tasks))
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="render") if workers > 1 else None
    # The networks' threads. With every core tracing a chunk, each chunk's batches run on its own thread: handed
    # to a pool beside the chunks' threads, they waited on one another (two-thread renders, alternating: the demo
    # scene 1.29 s against 1.19, the baked floor 2.80 s against 2.57, the same images). With cores to spare (fewer
    # chunks than threads) the chunks share one pool of every thread, whose work they wait on.
    with session.threads_in_force(1 if workers >= settings.thread_count else settings.thread_count):
        try:
            results = _ordered(pool, trace, tasks, 2 * workers, halt)
            for k, c in tasks:
                pix, (L, features, piece), image = next(results)
                film.add(pix, L, features)
                images.give(image)
                _merge_stats(stats, piece)
                if chunk_progress is not None:
                    chunk_progress((k * len(starts) + c + 1) / len(tasks))
                if c < len(starts) - 1:
                    continue
                film.passes += 1
                _finish_stats(stats, time.perf_counter() - t_start)
                if progress is not None and progress(film, k + 1, settings.samples) is False:
                    raise Cancelled(f"render cancelled after {k + 1} of {settings.samples} samples")
        except Cancelled as exc:  # from the progress callback, or a chunk that found ``stop`` set
            _finish_stats(stats, time.perf_counter() - t_start)
            exc.film, exc.stats = film, stats
            raise
        finally:
            halt.event.set()  # whatever ended the render, the chunks still being traced stop at their next bounce
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
    _finish_stats(stats, time.perf_counter() - t_start)
    return film, stats


STOP_POLL_SECONDS = 0.1  # how often a render polls a ``stop`` function while it waits for a chunk


class _Halt:
    """What a render's chunks read to stop: its own event, set when the render ends however it ends, or when
    ``render``'s ``stop`` says so: an event set from any thread, or a function called on the thread that made
    this object (the one that called ``render``) only."""

    def __init__(self, stop: threading.Event | Callable[[], bool] | None):
        self.event, self.home = threading.Event(), threading.get_ident()
        self.given = stop if isinstance(stop, threading.Event) else None
        self.poll = stop if stop is not None and self.given is None else None

    def is_set(self) -> bool:
        if not self.event.is_set() and (
            (self.given is not None and self.given.is_set())
            or (self.poll is not None and threading.get_ident() == self.home and self.poll())
        ):
            self.event.set()
        return self.event.is_set()


def _ordered(pool, fn, tasks, ahead: int, halt: _Halt):
    """``fn(task)`` for each task, in order; with a pool, at most ``ahead`` tasks submitted and not yet
    consumed (a cancelled render does not leave a queue of passes behind). Raises :class:`Cancelled` before
    a task is taken once ``halt`` is set, and while waiting for one (checked every :data:`STOP_POLL_SECONDS`)."""
    if pool is None:
        for task in tasks:
            _check_stop(halt)
            yield fn(task)
        return
    futures = [submit_in_context(pool, fn, t) for t in tasks[:ahead]]  # the render's thread count in force there
    for i in range(len(tasks)):
        if i + ahead < len(tasks):
            futures.append(submit_in_context(pool, fn, tasks[i + ahead]))
        while not futures[i].done():  # waits only: a chunk's own TimeoutError is its error, not a wait's
            _check_stop(halt)
            wait_for_futures([futures[i]], timeout=STOP_POLL_SECONDS)
        _check_stop(halt)
        result = futures[i].result()
        futures[i] = None
        yield result


_PHASES = ("rays", "network", "reference", "shading")


@contextmanager
def _shading(stats: RenderStats):
    """Add the block's time to ``stats``'s shading, less the rays, networks and reference estimators inside it."""
    s = stats.seconds
    t0, inner = time.perf_counter(), s["rays"] + s["network"] + s["reference"]
    try:
        yield
    finally:
        s["shading"] += time.perf_counter() - t0 - (s["rays"] + s["network"] + s["reference"] - inner)


def _merge_stats(stats: RenderStats, piece: RenderStats) -> None:
    """Add one chunk's counts and thread-time phases."""
    stats.paths += piece.paths
    stats.rays += piece.rays
    stats.nonfinite += piece.nonfinite
    stats.thread_seconds += piece.thread_seconds
    for key in _PHASES:
        stats.thread_phases[key] += piece.seconds[key]


def _finish_stats(stats: RenderStats, wall: float) -> None:
    """Phases in wall time: each thread-time phase scaled by the tracing's wall time / thread time (the class
    docstring)."""
    stats.seconds["total"] = wall
    tracing = max(0.0, wall - stats.seconds["setup"])
    scale = tracing / stats.thread_seconds if stats.thread_seconds > 0 else 0.0
    for key in _PHASES:
        stats.seconds[key] = stats.thread_phases[key] * scale


@dataclass
class _Paths:
    """The live paths of one chunk: ``row`` into the chunk's radiance, the ray (origin ``o``,
    unit direction ``d``), the throughput, how the ray was sampled (for MIS on the emission it
    finds) and its ray cone (``width`` at the origin, ``spread`` per unit distance)."""

    row: np.ndarray
    o: np.ndarray
    d: np.ndarray
    throughput: np.ndarray
    pdf: np.ndarray
    delta: np.ndarray
    mis: np.ndarray
    width: np.ndarray
    spread: np.ndarray
    eps: np.ndarray  # how far the ray's origin is off its surface (``kernels.surface_hits``' offset; 0: the camera)

    def take(self, keep: np.ndarray, out: tuple) -> "_HitPaths":
        """The paths at rows ``keep`` as the shading reads them, in ``out`` (``kernels.HIT_PATHS_OUT``, a row per
        kept path)."""
        return _HitPaths(*kernels.take_paths(out, keep, self.row, self.d, self.throughput, self.width, self.spread))


@dataclass
class _HitPaths:
    """The paths that hit a surface, sorted by its material, as the shading reads them: ``_Paths``'s fields less
    the origin and how the ray was sampled (read by the intersection and the emission it finds, before)."""

    row: np.ndarray
    d: np.ndarray
    throughput: np.ndarray
    width: np.ndarray
    spread: np.ndarray


@dataclass
class _Hits:
    """Surface geometry at the hits: position, geometric and shading normals turned toward the
    viewer, the shading frame (ts, tt, ns), ``wo`` in it, uv, texture footprint, material index."""

    p: np.ndarray
    ng: np.ndarray
    ns: np.ndarray
    ts: np.ndarray
    tt: np.ndarray
    wo: np.ndarray
    uv: np.ndarray
    footprint: np.ndarray
    dist: np.ndarray  # the ray's length to the hit
    front: np.ndarray  # whether the ray came from the side the face normal points to (``kernels.surface_hits``)
    eps: np.ndarray  # how far the rays leaving each hit start off it (``kernels.OFFSET_SCALE``)
    groups: list  # (material index, slice of rows): the hits are sorted by material


@dataclass
class _LightSamples:
    """One next-event sample per hit: local direction ``wi``, arriving radiance, solid-angle pdf,
    delta flag, and whether the shadow ray reached the light."""

    wi: np.ndarray
    radiance: np.ndarray
    pdf: np.ndarray
    delta: np.ndarray
    visible: np.ndarray


def _clipped(cam, tmax: np.ndarray) -> np.ndarray | None:
    """The camera rays' lengths to the far clipping plane, where the camera has one."""
    return tmax if math.isfinite(cam.clip[1]) else None


def _camera_paths(
    ctx: _Context, pix: np.ndarray, rng: np.random.Generator, scratch: Scratch
) -> tuple[_Paths, np.ndarray | None, np.ndarray | None]:
    """Primary rays, one per pixel, jittered inside it; emission they see counts with weight 1. In
    ``scratch``'s "paths.next" arrays, which the first bounce's paths are taken from. With them, how far each
    reaches (the far clipping plane; None: all the way) and how far from the camera it starts (on the near plane;
    None: at the camera): its cone is that wide there."""
    cam = ctx.scene.camera
    n = len(pix)
    paths = _Paths(*scratch.arrays("paths.next", n, kernels.PATHS_OUT))
    px, py, jitter, tmax, near = scratch.arrays(
        "pixels", n, ((0, kernels.I8), (0, kernels.I8), (2, kernels.F8), (0, kernels.F8), (0, kernels.F8))
    )
    np.divmod(pix, cam.width, out=(py, px))
    rng.random(out=jitter)
    cam.rays(px, py, jitter, out=(paths.o, paths.d, paths.spread, tmax, near))
    paths.row[...] = np.arange(n)
    paths.throughput.fill(1.0)
    paths.pdf.fill(1.0)
    paths.delta.fill(True)
    paths.mis.fill(True)
    paths.eps.fill(0.0)
    if cam.clip[0] > 0.0:
        np.multiply(paths.spread, near, out=paths.width)
    else:
        paths.width.fill(0.0)
        near = None
    return paths, _clipped(cam, tmax), near


def _add_emission(
    ctx: _Context,
    paths: _Paths,
    t: np.ndarray,
    L: np.ndarray,
    camera: bool,
    reach: np.ndarray | None = None,
    features: np.ndarray | None = None,
    depth: int = 0,
) -> None:
    """Emission the rays of bounce ``depth`` reach (0: the camera's; a ray of bounce d left a hit of bounce d - 1,
    whose direct light a light's emission it finds is, and counts where next-event estimation there would: up to the
    light's Max Bounces): lights rays can hit in front of the first surface (distance ``t``; for the camera's rays,
    ``camera``, only the lights visible to the camera and before the far clipping plane, ``reach``, each one it
    meets covering its pixel in ``features``), the sky where they escape (t = inf), weighted against next-event
    estimation by how each ray was sampled. A camera ray that escapes to a sky it sees (an opaque film) has the sky's
    radiance, clipped to [0, 1], as its albedo in ``features``, as Cycles' Denoising Albedo has it there (Cycles'
    unclipped: a denoiser's albedo guide is read in [0, 1]); 0 on a transparent film, as in Cycles."""
    if len(ctx.hit_params) == 0 and ctx.env is None:
        return
    sky = ctx.env is not None and not (camera and ctx.settings.transparent)  # a transparent film: no sky seen directly
    kernels.add_emission(
        ctx.hit_kinds, ctx.hit_params, sky, ctx.env_arrays,
        ctx.strategy_code, ctx.p_select,
        paths.o, paths.d, t, paths.row, paths.throughput, paths.pdf, paths.delta, paths.mis, L, paths.eps, camera,
        reach if reach is not None else _NO_REACH, features if features is not None else _NO_FEATURES, depth - 1,
    )  # fmt: skip
    if sky and camera and features is not None:
        escaped = np.flatnonzero(np.isinf(t))
        if len(escaped):  # the lookup ``add_emission`` made of the same unit directions (0.6 ms a 320x180 pass)
            radiance = kernels.environment_radiance(ctx.env_arrays, paths.d[escaped])[0]
            features[paths.row[escaped], :3] = np.clip(radiance, 0.0, 1.0)


_NO_REACH = np.empty(0)
_NO_FEATURES = np.empty((0, Film.FEATURES))


def _surface_hits(ctx: _Context, paths: _HitPaths, hit, t, prim, bu, bv, groups, scratch: Scratch) -> _Hits:
    """The surface where each ray lands: interpolated position, normals and uv; a shading frame
    facing the viewer (shading normals that disagree with the geometry fall back to it); the
    ray cone grown to the hit and its footprint in texture space. ``groups``: the rows of each
    material (the rays come sorted by material). ``hit``: the rows of the intersection's results
    (``t``, ``prim``, ``bu``, ``bv``, one per ray traced) that ``paths`` now holds, in its order."""
    p, ng, ns, uv, paths.width, footprint, ts, tt, wo, dist, front, eps = kernels.surface_hits(
        scratch.arrays("hits", len(hit), kernels.SURFACE_HITS_OUT),
        ctx.corners, ctx.face_normals, ctx.uv_scale, ctx.tri_offset, hit, prim, bu, bv, paths.d, t, paths.width,
        paths.spread,
    )  # fmt: skip
    return _Hits(p, ng, ns, ts, tt, wo, uv, footprint, dist, front, eps, groups)


def _sample_lights(
    ctx: _Context, hits: _Hits, u_light: np.ndarray, stats: RenderStats, scratch: Scratch, depth: int
) -> _LightSamples:
    """Next-event estimation at the hits of bounce ``depth`` (0: the camera rays'): one light (or the sky) chosen
    uniformly per hit, a point on it, and one occlusion query for all shadow rays; light reaching the surface through
    the shading normal's side but not the geometric one's is discarded, and so is a light's past its Max Bounces."""
    m = len(hits.p)
    if not ctx.nee:
        return _LightSamples(
            np.zeros((m, 3)), np.zeros((m, 3)), np.ones(m), np.zeros(m, dtype=bool), np.zeros(m, dtype=bool)
        )
    wi, rad, pdf, delta, visible, rows, org, d, tmax = kernels.sample_lights(
        scratch.arrays("lights", m, kernels.LIGHT_SAMPLES_OUT),
        ctx.nee_kinds, ctx.nee_params, ctx.env_arrays, hits.p, hits.ng, hits.ts, hits.tt, hits.ns, u_light, hits.eps,
        depth,
    )  # fmt: skip
    visible[rows[ctx.tracer.occluded(org, d, tmax, stats, scratch)]] = False
    return _LightSamples(wi, rad, pdf, delta, visible)


_SCATTER = ((3, kernels.F8), (3, kernels.F8), (0, kernels.F8), (0, kernels.B1), (0, kernels.B1))


@dataclass
class _Scatter:
    """The BSDF sample of every hit: local direction, weight f |cos| / pdf, pdf, flags."""

    wi: np.ndarray
    weight: np.ndarray
    pdf: np.ndarray
    delta: np.ndarray
    mis: np.ndarray


def _shade(
    ctx: _Context,
    paths: _HitPaths,
    hits: _Hits,
    lights: _LightSamples,
    u_lobe,
    u_dir,
    seeds,
    L: np.ndarray,
    stats: RenderStats,
    scratch: Scratch,
) -> _Scatter:
    """Scattering at the surface, one query per material: the reflected next-event light
    (MIS-weighted against BSDF sampling) goes into the image, and each hit draws the direction
    its path continues in."""
    # every row is written below: the groups' slices cover the hits
    out = _Scatter(*scratch.arrays("scatter", len(hits.p), _SCATTER))
    for mi, sel in hits.groups:  # a loop over materials; each one's hits are one slice (views, no gathers)
        material = ctx.materials[mi]
        need_pdf = material.has_pdf and ctx.settings.strategy == "mis"
        rows = np.flatnonzero(lights.visible[sel])
        v = rows + sel.start
        with _shading(stats):
            t0, net0 = time.perf_counter(), session.seconds_on_this_thread()
            bound = material.bind(mat.SurfaceHits(hits.uv[sel], hits.footprint[sel], int(seeds[mi]), hits.front[sel]))
            sh = bound.shade(hits.wo[sel], lights.wi[v], rows, u_lobe[sel], u_dir[sel], need_pdf)
            stats.seconds["network"] += session.seconds_on_this_thread() - net0
            if material.kind == "reference":
                stats.seconds["reference"] += time.perf_counter() - t0
            if len(v):
                pdf_bsdf = sh.pdf_light if need_pdf else np.empty(0)  # read only when weighted
                kernels.add_direct(
                    L, v, paths.row, paths.throughput, kernels.float64_rows(sh.f_light), lights.wi, lights.radiance,
                    ctx.p_select, lights.pdf, lights.delta, pdf_bsdf, need_pdf,
                )  # fmt: skip
        bs = sh.sample
        out.wi[sel], out.weight[sel], out.pdf[sel], out.delta[sel] = bs.wi, bs.weight, bs.pdf, bs.delta
        out.mis[sel] = material.has_pdf
    return out


def _continue_paths(
    ctx: _Context, paths: _HitPaths, hits: _Hits, sc: _Scatter, depth: int, rng: np.random.Generator, scratch: Scratch
) -> _Paths:
    """The next rays: throughput times the sample weight, Russian roulette from ``rr_depth``
    (survivors reweighted by 1 / q), paths that died or would cross the geometric surface on the
    wrong side dropped, origins offset off the surface; a non-specular bounce widens the cone."""
    roulette = depth + 1 >= ctx.settings.rr_depth
    n = len(paths.row)
    u_rr = rng.random(out=scratch.arrays("u_rr", n, ((0, kernels.F8),))[0]) if roulette else np.empty(0)
    return _Paths(
        *kernels.continue_paths(
            scratch.arrays("paths.next", n, kernels.PATHS_OUT),
            sc.wi, hits.ts, hits.tt, hits.ns, sc.weight, sc.pdf, sc.delta, sc.mis, hits.p, hits.ng, paths.row,
            paths.throughput, paths.width, paths.spread, u_rr, roulette, hits.eps,
        )
    )  # fmt: skip


_UNIFORMS = ((3, kernels.F8), (0, kernels.F8), (2, kernels.F8))  # a bounce's: light, lobe, direction
_IMAGE_ROWS = ((3, kernels.F8), (Film.FEATURES, kernels.F8))  # a chunk's radiance and first hits' features


def _check_stop(halt: _Halt | None) -> None:
    """Raise :class:`Cancelled` if ``halt`` (a render's :class:`_Halt`) is set."""
    if halt is not None and halt.is_set():
        raise Cancelled("render stopped")


def _trace_paths(
    ctx: _Context,
    pix: np.ndarray,
    pass_index: int,
    chunk_index: int,
    halt: _Halt | None = None,
    scratch: Scratch | None = None,
    image: Scratch | None = None,
) -> tuple[np.ndarray, np.ndarray, RenderStats]:
    """Radiance (N, 3) of one path per pixel of ``pix``, all paths a bounce at a time, the
    features of their first hits (N, 8; see ``Film.add``), and the chunk's statistics
    (its phases in thread time). Raises :class:`Cancelled` before a bounce once ``halt`` is set.
    The bounces write their hits, light samples and paths into ``scratch``'s arrays, and the radiance and
    features are arrays of ``image`` (new ones where None)."""
    scratch = scratch or Scratch(len(pix))
    t_start = time.perf_counter()
    stats = RenderStats()
    s = ctx.settings
    L, features = (image or Scratch()).arrays("image", len(pix), _IMAGE_ROWS)
    L.fill(0.0)
    features.fill(0.0)
    features[:, Film.DEPTH] = Film.NO_DEPTH  # the depth of a camera ray that meets nothing
    paths, tmax, near = _camera_paths(ctx, pix, np.random.default_rng([s.seed, pass_index, chunk_index, 0]), scratch)
    last = s.max_bounces + 1  # the hits of the last bounce's rays: only the emission they find
    for depth in range(last + 1):
        if len(paths.row) == 0:
            break
        _check_stop(halt)
        rng = np.random.default_rng([s.seed, pass_index, chunk_index, depth + 1])
        t, prim, bu, bv = ctx.tracer.intersect(paths.o, paths.d, stats, scratch, tmax if depth == 0 else None)
        with _shading(stats):
            _add_emission(
                ctx, paths, t, L, depth == 0, tmax if depth == 0 else None, features if depth == 0 else None, depth
            )
        if depth == last:
            break
        # Sorted by material (stable), so that each material shades one contiguous slice of rows.
        order = scratch.arrays("order", len(prim), ((0, kernels.I8),))[0]
        hit, starts = kernels.hits_by_material(order, prim, ctx.material_of_triangle, len(ctx.materials))
        if len(hit) == 0:
            break
        # the paths alternate between two groups of arrays: "paths.taken" here, "paths.next" in _continue_paths
        paths = paths.take(hit, scratch.arrays("paths.taken", len(hit), kernels.HIT_PATHS_OUT))
        groups = [(mi, slice(int(starts[mi]), int(starts[mi + 1]))) for mi in np.flatnonzero(np.diff(starts))]
        m = len(hit)
        u_light, u_lobe, u_dir = scratch.arrays("uniforms", m, _UNIFORMS)
        rng.random(out=u_light)
        with _shading(stats):
            hits = _surface_hits(ctx, paths, hit, t, prim, bu, bv, groups, scratch)
            lights = _sample_lights(ctx, hits, u_light, stats, scratch, depth)
        _check_stop(halt)  # the materials' networks next: half of a bounce's time on neural scenes
        rng.random(out=u_lobe)
        rng.random(out=u_dir)
        seeds = rng.integers(0, 2**31, size=len(ctx.materials))
        sc = _shade(ctx, paths, hits, lights, u_lobe, u_dir, seeds, L, stats, scratch)
        if depth == 0:
            dist = hits.dist if near is None else hits.dist + near[hit]  # from the camera, not the near plane
            kernels.first_hit_features(features, paths.row, sc.weight, hits.ns, dist, paths.d, ctx.camera_axis)
        paths = _continue_paths(ctx, paths, hits, sc, depth, rng, scratch)
    bad = ~np.isfinite(L[:, 0] + L[:, 1] + L[:, 2])  # inf - inf is nan: any non-finite channel
    if bad.any():
        stats.nonfinite += int(bad.sum())
        L[bad] = 0.0
    stats.paths = len(pix)
    stats.thread_seconds = time.perf_counter() - t_start
    return L, features, stats

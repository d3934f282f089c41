"""Wavefront path tracer: all live paths advance one bounce at a time.

Per bounce: one embreex call intersects every live path; area lights are intersected
analytically; misses gather the environment; hits are grouped by material and each material is
bound and queried once per group (one ONNX batch per neural material); next-event estimation
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

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..bsdf import frame
from . import materials as mat
from .film import Film
from .lights import AreaLight
from .neural_material import finish_sample
from .scene import Scene

STRATEGIES = ("mis", "light", "bsdf")
MODES = ("neural", "reference")


class Cancelled(Exception):
    """Raised inside :func:`render` when the progress callback returns False."""


@dataclass
class RenderSettings:
    samples: int = 16
    max_bounces: int = 8
    seed: int = 0
    strategy: str = "mis"
    mode: str = "neural"
    rr_depth: int = 3
    chunk_paths: int = 1 << 16
    reference_walks: int = 16

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


@dataclass
class RenderStats:
    """Wall time per phase (seconds) and counts. ``network`` is time inside neural materials,
    ``reference`` inside position-free estimators, ``rays`` the embreex time."""

    paths: int = 0
    rays: int = 0
    seconds: dict = field(default_factory=lambda: {"rays": 0.0, "network": 0.0, "reference": 0.0, "total": 0.0})
    nonfinite: int = 0
    material_kinds: list = field(default_factory=list)  # per material index: analytic/neural/reference

    @property
    def rest(self) -> float:
        s = self.seconds
        return max(0.0, s["total"] - s["rays"] - s["network"] - s["reference"])

    @property
    def paths_per_second(self) -> float:
        return self.paths / self.seconds["total"] if self.seconds["total"] > 0 else 0.0

    def summary(self) -> str:
        s = self.seconds
        return (f"{self.paths} paths in {s['total']:.2f} s ({self.paths_per_second:,.0f}/s): rays {s['rays']:.2f} s, "
                f"network {s['network']:.2f} s, reference {s['reference']:.2f} s, rest {self.rest:.2f} s")


class Tracer:
    """embreex closest-hit and occlusion queries over the scene's triangles (float32 rays)."""

    def __init__(self, mesh, stats: RenderStats):
        self.mesh = mesh
        self.stats = stats
        self.scene = None
        if mesh.triangle_count:
            from embreex import rtcore_scene as rtcs
            from embreex.mesh_construction import TriangleMesh

            self.scene = rtcs.EmbreeScene()
            TriangleMesh(self.scene, np.ascontiguousarray(mesh.positions, dtype=np.float32))

    def intersect(self, o, d):
        n = len(o)
        if self.scene is None or n == 0:
            return np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros(n), np.zeros(n)
        t0 = time.perf_counter()
        r = self.scene.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32), output=1)
        self.stats.seconds["rays"] += time.perf_counter() - t0
        self.stats.rays += n
        prim = r["primID"].astype(np.int64)
        t = np.where(prim >= 0, r["tfar"].astype(np.float64), np.inf)
        return t, prim, r["u"].astype(np.float64), r["v"].astype(np.float64)

    def occluded(self, o, d, tmax):
        n = len(o)
        if self.scene is None or n == 0:
            return np.zeros(n, dtype=bool)
        t0 = time.perf_counter()
        dist = np.minimum(tmax, 1e30).astype(np.float32)
        r = self.scene.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32),
                           dists=np.ascontiguousarray(dist), query="OCCLUDED")
        self.stats.seconds["rays"] += time.perf_counter() - t0
        self.stats.rays += n
        return np.asarray(r) != -1


def _power_heuristic(a, b):
    a2, b2 = a * a, b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        w = a2 / (a2 + b2)
    return np.where(a2 + b2 > 0, w, 0.0)


def _timed(stats: RenderStats, material, fn, *args):
    if material.kind == "analytic":
        return fn(*args)
    t0 = time.perf_counter()
    out = fn(*args)
    key = "network" if material.kind == "neural" else "reference"
    stats.seconds[key] += time.perf_counter() - t0
    return out


def uv_scale(mesh) -> np.ndarray:
    """(triangles,) uv units per world unit of each triangle: sqrt(uv area / world area); 0 for a
    mesh without uvs (no texture footprint)."""
    if not mesh.triangle_count or mesh.uvs is None:
        return np.zeros(mesh.triangle_count)
    uv = mesh.uvs.astype(np.float64)
    a_uv = 0.5 * np.abs((uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1])
                        - (uv[:, 2, 0] - uv[:, 0, 0]) * (uv[:, 1, 1] - uv[:, 0, 1]))
    return np.sqrt(a_uv / np.maximum(mesh.areas, 1e-30))


def texture_footprint(width, cos_o, tri_uv_scale) -> np.ndarray:
    """Footprint in uv units of a ray cone of ``width`` (world units) hitting a surface at
    |cos| ``cos_o`` (floored at 0.05: grazing hits do not blow up) on triangles of uv scale
    ``tri_uv_scale``: the width stretched by 1 / sqrt(cos) (the mean of its two axes)."""
    return width / np.sqrt(np.maximum(np.abs(cos_o), 0.05)) * tri_uv_scale


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
    o, d = cam.generate_rays(px, py, np.full((len(px), 2), 0.5))
    t, prim, _, _ = Tracer(scene.mesh, RenderStats()).intersect(o, d)
    prim = np.asarray(prim, dtype=np.int64)
    hit = prim >= 0
    if hit.any():
        ng = scene.mesh.face_normals[prim[hit]].astype(np.float64)
        cos_o = np.einsum("ij,ij->i", ng, d[hit])
        f = texture_footprint(t[hit] * cam.pixel_spread, cos_o, uv_scale(scene.mesh)[prim[hit]])
        fp[hit] = np.where(f > 0, f, np.inf)
    return prim, fp


class _Context:
    """What stays fixed during a render: resolved materials, lights, tracer, settings."""

    def __init__(self, scene: Scene, settings: RenderSettings, stats: RenderStats):
        self.scene, self.settings, self.stats = scene, settings, stats
        n_mat = max(len(scene.materials), int(scene.mesh.material_index.max()) + 1 if scene.mesh.triangle_count else 0)
        self.materials = [
            mat.resolve(scene.materials[i] if i < len(scene.materials) else None, settings.mode,
                        settings.reference_walks)
            for i in range(n_mat)
        ]
        stats.material_kinds = [m.kind for m in self.materials]
        self.tracer = Tracer(scene.mesh, stats)
        env = scene.environment
        self.env = env if env is not None and not env.is_black else None
        self.area = [li for li in scene.lights if isinstance(li, AreaLight) and li.power > 0]
        delta = [li for li in scene.lights if not isinstance(li, AreaLight) and li.estimated_power() > 0]
        # Lights next-event estimation chooses among (uniformly).
        nee = list(delta)
        if settings.strategy != "bsdf":
            nee += self.area + ([self.env] if self.env is not None else [])
        self.nee = nee
        self.p_select = 1.0 / len(nee) if nee else 0.0
        m = scene.mesh
        if m.triangle_count:
            p = m.positions.astype(np.float64)
            self.eps = 1e-4 * (1.0 + float(np.abs(p).max()))
        else:
            self.eps = 1e-4
        self.uv_scale = uv_scale(m)

    def light_weight(self, pdf_light_solid, prev_pdf, prev_delta, prev_mis):
        """Weight of emission found by BSDF sampling."""
        s = self.settings.strategy
        if s == "bsdf":
            return np.ones_like(prev_pdf)
        if s == "light":
            return prev_delta.astype(np.float64)
        w = _power_heuristic(prev_pdf, self.p_select * pdf_light_solid)
        # Without a BSDF pdf (reference materials) next-event estimation alone carries it.
        w = np.where(prev_mis, w, 0.0)
        return np.where(prev_delta, 1.0, w)


def render(scene: Scene, settings: RenderSettings | None = None,
           progress: Callable[[Film, int, int], bool] | None = None,
           film: Film | None = None) -> tuple[Film, RenderStats]:
    """Render ``scene``; returns the film (per-pixel mean and standard error) and statistics.

    ``progress(film, done, total)`` is called after every pass of one sample per pixel; returning
    False stops the render (raising :class:`Cancelled`, with the partial film attached as
    ``exc.film``). Pass a ``film`` to continue accumulating into it (progressive refinement).
    """
    settings = settings or RenderSettings()
    cam = scene.camera
    stats = RenderStats()
    t_start = time.perf_counter()
    ctx = _Context(scene, settings, stats)
    film = film or Film(cam.width, cam.height)
    start_pass = film.passes
    npix = cam.width * cam.height
    chunk = int(settings.chunk_paths)
    for k in range(settings.samples):
        pass_index = start_pass + k
        for c0 in range(0, npix, chunk):
            pix = np.arange(c0, min(npix, c0 + chunk))
            L = _trace_paths(ctx, pix, pass_index, c0 // chunk)
            bad = ~np.isfinite(L).all(axis=1)
            if bad.any():
                stats.nonfinite += int(bad.sum())
                L[bad] = 0.0
            film.add(pix, L)
            stats.paths += len(pix)
        film.passes += 1
        stats.seconds["total"] = time.perf_counter() - t_start
        if progress is not None and progress(film, k + 1, settings.samples) is False:
            exc = Cancelled(f"render cancelled after {k + 1} of {settings.samples} samples")
            exc.film, exc.stats = film, stats
            raise exc
    stats.seconds["total"] = time.perf_counter() - t_start
    return film, stats


def _trace_paths(ctx: _Context, pix: np.ndarray, pass_index: int, chunk_index: int) -> np.ndarray:
    s = ctx.settings
    cam = ctx.scene.camera
    mesh = ctx.scene.mesh
    n = len(pix)
    rng = np.random.default_rng([s.seed, pass_index, chunk_index, 0])
    o, d = cam.generate_rays(pix % cam.width, pix // cam.width, rng.random((n, 2)))
    L = np.zeros((n, 3))
    path = np.arange(n)  # live path -> row of L
    thr = np.ones((n, 3))
    prev_pdf = np.ones(n)
    prev_delta = np.ones(n, dtype=bool)  # camera rays count emission with weight 1
    prev_mis = np.ones(n, dtype=bool)
    width = np.zeros(n)  # ray-cone width at the origin
    spread = np.full(n, cam.pixel_spread)
    for depth in range(s.max_bounces + 1):
        if len(path) == 0:
            break
        rng = np.random.default_rng([s.seed, pass_index, chunk_index, depth + 1])
        t, prim, bu, bv = ctx.tracer.intersect(o, d)

        # Emission reached by this ray: area lights in front of the surface, then the sky.
        for light in ctx.area:
            tl, pdf_l = light.intersect(o, d)
            m = tl < t
            if m.any():
                w = ctx.light_weight(pdf_l[m], prev_pdf[m], prev_delta[m], prev_mis[m])
                L[path[m]] += thr[m] * light.radiance * w[:, None]
        miss = prim < 0
        if ctx.env is not None and miss.any():
            dm = d[miss]
            w = ctx.light_weight(ctx.env.pdf(dm), prev_pdf[miss], prev_delta[miss], prev_mis[miss])
            L[path[miss]] += thr[miss] * ctx.env.radiance(dm) * w[:, None]
        if depth == s.max_bounces:
            break
        hit = ~miss
        path, o, d, t, prim, bu, bv = path[hit], o[hit], d[hit], t[hit], prim[hit], bu[hit], bv[hit]
        thr, width, spread = thr[hit], width[hit], spread[hit]
        m = len(path)
        if m == 0:
            break

        # Surface geometry at the hits.
        b0 = 1.0 - bu - bv
        tri = mesh.positions[prim].astype(np.float64)
        p = b0[:, None] * tri[:, 0] + bu[:, None] * tri[:, 1] + bv[:, None] * tri[:, 2]
        ng = mesh.face_normals[prim].astype(np.float64)
        nrm = mesh.normals[prim].astype(np.float64)
        ns = frame.normalize(b0[:, None] * nrm[:, 0] + bu[:, None] * nrm[:, 1] + bv[:, None] * nrm[:, 2])
        ns = np.where((frame.dot(ns, ng) > 0)[:, None], ns, ng)  # inconsistent or zero: use ng
        wo_w = -d
        side = np.where(frame.dot(ng, wo_w) >= 0, 1.0, -1.0)[:, None]
        ng, ns = ng * side, ns * side
        ns = np.where((frame.dot(ns, wo_w) > 1e-6)[:, None], ns, ng)  # grazing: fall back to ng
        ts, tt = frame.coordinate_system(ns)
        wo = frame.to_local(wo_w, ts, tt, ns)
        if mesh.uvs is not None:
            uvt = mesh.uvs[prim].astype(np.float64)
            uv = b0[:, None] * uvt[:, 0] + bu[:, None] * uvt[:, 1] + bv[:, None] * uvt[:, 2]
        else:
            uv = np.zeros((m, 2))
        width = width + spread * t
        footprint = texture_footprint(width, frame.dot(ng, wo_w), ctx.uv_scale[prim])

        # Next-event estimation: pick one light per hit, one occlusion call for all.
        u_light = rng.random((m, 3))
        nee_wi = np.zeros((m, 3))
        nee_rad = np.zeros((m, 3))
        nee_pdf = np.ones(m)
        nee_delta = np.zeros(m, dtype=bool)
        nee_dist = np.full(m, np.inf)
        if ctx.nee:
            choice = np.minimum((u_light[:, 0] * len(ctx.nee)).astype(np.int64), len(ctx.nee) - 1)
            for j, light in enumerate(ctx.nee):
                sel = np.nonzero(choice == j)[0]
                if len(sel) == 0:
                    continue
                ls = light.sample(p[sel], u_light[sel, 1:])
                nee_wi[sel], nee_rad[sel], nee_pdf[sel] = ls.wi, ls.radiance, ls.pdf
                nee_dist[sel], nee_delta[sel] = ls.dist, ls.delta
            cos_g = frame.dot(nee_wi, ng)
            useful = (nee_pdf > 0) & (nee_rad.max(axis=1) > 0) & (cos_g != 0)
            org = p + ng * (np.sign(cos_g) * ctx.eps)[:, None]
            tmax = np.where(np.isinf(nee_dist), np.inf, nee_dist * (1 - 1e-4) - ctx.eps)
            unseen = np.zeros(m, dtype=bool)
            idx = np.nonzero(useful)[0]
            unseen[idx] = ctx.tracer.occluded(org[idx], nee_wi[idx], tmax[idx])
            visible = useful & ~unseen
            wi_nee = frame.to_local(nee_wi, ts, tt, ns)
            # Light leaks through shading normals: the geometric and shading sides must agree.
            visible &= np.sign(wi_nee[:, 2]) == np.sign(cos_g)
        else:
            visible = np.zeros(m, dtype=bool)
            wi_nee = np.zeros((m, 3))

        u_lobe = rng.random(m)
        u_dir = rng.random((m, 2))
        new_wi = np.zeros((m, 3))
        weight = np.zeros((m, 3))
        s_pdf = np.zeros(m)
        s_delta = np.zeros(m, dtype=bool)
        s_mis = np.ones(m, dtype=bool)
        roughish = np.ones(m, dtype=bool)
        mat_index = mesh.material_index[prim]
        seeds = rng.integers(0, 2**31, size=len(ctx.materials))
        for mi in np.unique(mat_index):  # a loop over materials
            sel = np.nonzero(mat_index == mi)[0]
            material = ctx.materials[mi]
            bound = material.bind(mat.SurfaceHits(uv[sel], footprint[sel], int(seeds[mi])))
            rows = np.nonzero(visible[sel])[0]
            v = sel[rows]
            joint = getattr(material, "sample_needs_eval", False)
            if joint:
                # Propose directions first, then one evaluation for shadow and sampled directions.
                prop_wi, prop_pdf = bound.sample_direction(wo[sel], u_lobe[sel], u_dir[sel])
                if hasattr(bound, "eval_pair"):  # both directions from the same estimator walks
                    wi_a = prop_wi.copy()
                    wi_a[rows] = wi_nee[v]
                    f_a, f_b = _timed(ctx.stats, material, bound.eval_pair, wi_a, prop_wi, wo[sel])
                    f_all = np.concatenate([f_a[rows], f_b])
                else:
                    f_all = _timed(ctx.stats, material, bound.eval, np.concatenate([wi_nee[v], prop_wi]),
                                   np.concatenate([wo[v], wo[sel]]), np.concatenate([rows, np.arange(len(sel))]))
                bs = finish_sample(prop_wi, prop_pdf, f_all[len(v):])
            if len(v):
                wil, wol = wi_nee[v], wo[v]
                f = f_all[: len(v)] if joint else _timed(ctx.stats, material, bound.eval, wil, wol, rows)
                lw = np.ones(len(v))
                if material.has_pdf and s.strategy == "mis":
                    pb = _timed(ctx.stats, material, bound.pdf, wil, wol, rows)
                    lw = np.where(nee_delta[v], 1.0, _power_heuristic(ctx.p_select * nee_pdf[v], pb))
                contrib = f * (np.abs(wil[:, 2]) * lw / (ctx.p_select * nee_pdf[v]))[:, None] * nee_rad[v]
                L[path[v]] += thr[v] * contrib
            if not joint:
                bs = _timed(ctx.stats, material, bound.sample, wo[sel], u_lobe[sel], u_dir[sel])
            new_wi[sel], weight[sel], s_pdf[sel], s_delta[sel] = bs.wi, bs.weight, bs.pdf, bs.delta
            s_mis[sel] = material.has_pdf
            roughish[sel] = ~bs.delta

        # Continue the paths.
        wi_w = frame.to_world(new_wi, ts, tt, ns)
        cos_g = frame.dot(wi_w, ng)
        ok = (weight.max(axis=1) > 0) & (np.sign(cos_g) == np.sign(new_wi[:, 2])) & (cos_g != 0)
        thr = thr * weight
        if depth + 1 >= s.rr_depth:
            q = np.clip(thr.max(axis=1), 0.05, 1.0)
            ok &= rng.random(m) < q
            thr = thr / q[:, None]
        keep = np.nonzero(ok)[0]
        o = (p + ng * (np.sign(cos_g) * ctx.eps)[:, None])[keep]
        d = frame.normalize(wi_w[keep])
        path, thr = path[keep], thr[keep]
        prev_pdf, prev_delta, prev_mis = s_pdf[keep], s_delta[keep], s_mis[keep]
        # Ray cone: widths carry on; a non-specular bounce widens the cone (a simple heuristic).
        width = width[keep]
        spread = np.where(roughish[keep], np.maximum(spread[keep], 0.2), spread[keep])
    return L

"""Every method on one chart of error against time, the stability matrix and the auto setting, in one run.

    python benchmarks/bench_all.py            # the full run (tens of minutes on 2 cores); writes docs/
    python benchmarks/bench_all.py --quick    # a small configuration (under a minute), same outputs

Needs the ``bpy`` module (Cycles). Writes into ``--out`` (default ``docs/``):

- ``benchmarks.md``: every table below, with the command and the configuration;
- ``benchmarks_brdf.png``: BRDF level, lobe error against time per RGB evaluation, for each shipped
  decoder size (stacks encoded as the renderer encodes them), the position-free reference at 1 to
  1024 walks, and Cycles' Principled coat (``benchmarks/cycles_brdf.py``, measured in Cycles) on the
  same held-out stacks (``tests/data/heldout_single.npz``, ``heldout_layered_lobes.npz``);
- ``benchmarks_render.png``: render level, MSE against a high-sample reference-mode render of the demo
  scene against render time, for neural rendering with each decoder size, reference mode and Cycles,
  with the Pareto front marked;
- ``benchmarks.json``: the measured numbers (what the tests compare in shape);
- ``stability.md``: the stability matrix (``benchmarks/stability.py``).

Lobe error (docs/architecture.md, Measurement): relative RMSE of f cos(theta_o) lobe images at incident elevations
0/30/60/75 degrees, per stack and elevation; median and 90th percentile over them. The stored
layered reference lobes are Monte Carlo estimates: their noise variance is removed from every
error (``addon.core.quality.noise_corrected_error``). Timings come from a shared 2-core machine:
compare ratios within one run.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from addon.core import lobe, quality, reference  # noqa: E402


@dataclass
class Config:
    single: tuple  # indices into the single-layer held-out set (None = all)
    layered: tuple  # indices into the layered held-out set (None = all)
    cycles_single: tuple
    cycles_layered: tuple
    walks: tuple
    ref_pixels: int  # lobe pixels per stack and elevation for the reference's walk sweep
    cycles_res: int
    cycles_samples: int
    size: tuple  # render size (width, height)
    bounces: int
    reference_spp: int
    budgets: tuple  # samples per pixel of our render curves
    cycles_budgets: tuple
    auto_tolerance: float
    auto_spp: int
    cycles_angles: tuple | None = None  # incident elevations Cycles renders (None: all four)
    speed_repeats: int = 3
    texture_sizes: tuple = ((320, 180), (1920, 1080))  # image sizes of the footprint table
    auto_res: int = quality.LOBE_RES  # lobe size and reference walks of the auto setting's measurement
    auto_walks: int = quality.REFERENCE_WALKS


FULL = Config(
    single=None,
    layered=None,
    cycles_single=(0, 5, 9, 14, 20, 28, 33, 38),
    cycles_layered=None,
    walks=(1, 4, 16, 64, 256, 1024),
    ref_pixels=48,
    cycles_res=192,
    cycles_samples=16,
    size=(80, 45),
    bounces=4,
    reference_spp=256,
    budgets=(1, 2, 4, 8, 16),
    cycles_budgets=(1, 4, 16, 64),
    auto_tolerance=0.3,
    auto_spp=16,
)
QUICK = Config(
    single=(0, 5),
    layered=(0, 12),
    cycles_single=(),
    cycles_layered=(0,),
    walks=(1, 4, 16),
    ref_pixels=12,
    cycles_res=24,
    cycles_samples=1,
    size=(24, 14),
    bounces=2,
    reference_spp=4,
    cycles_angles=(60.0,),
    speed_repeats=1,
    texture_sizes=((64, 36),),
    budgets=(1, 2),
    cycles_budgets=(1, 2),
    auto_tolerance=0.3,
    auto_spp=1,
    auto_res=8,
    auto_walks=16,
)


def _pick(items, idx):
    return list(range(len(items))) if idx is None else [i for i in idx if i < len(items)]


def _stats(errors) -> dict:
    e = np.asarray(errors, dtype=np.float64)
    return {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)), "n": int(e.size)}


def heldout_sets(cfg: Config) -> dict:
    from onnx_export.heldout import load as load_heldout

    out = {}
    for name, path, idx in (
        ("single", "heldout_single.npz", cfg.single),
        ("layered", "heldout_layered_lobes.npz", cfg.layered),
    ):
        h = load_heldout(ROOT / "tests/data" / path)
        rows = _pick(h["stacks"], idx)
        out[name] = {
            "stacks": [h["stacks"][i] for i in rows],
            "rows": rows,
            "lobe": h["lobe"][rows],
            "stderr": h["lobe_stderr"][rows],
            "angles": [float(a) for a in h["angles"]],
        }
    return out


def _per_image_errors(pred: np.ndarray, ref: np.ndarray, se: np.ndarray) -> list[float]:
    """One noise-corrected error per (stack, elevation) image."""
    return [
        quality.noise_corrected_error(p, r, s)
        for p, r, s in zip(
            pred.reshape(-1, *pred.shape[2:]),
            ref.reshape(-1, *ref.shape[2:]),
            se.reshape(-1, *se.shape[2:]),
            strict=True,
        )
    ]


# ----------------------------------------------------------------------------- BRDF level


def brdf_decoders(sets: dict, threads: int, repeats: int = 3) -> list[dict]:
    from bench_decoders import speed

    rows = []
    for size in quality.available_sizes():
        sp = speed(size, threads, repeats=repeats)
        for name, s in sets.items():
            res = s["lobe"].shape[2]
            preds, keep = [], []
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # clamping is reported by the stability matrix
                for i, st in enumerate(s["stacks"]):
                    try:
                        preds.append(quality.decoder_lobes(st, size, res, threads))
                        keep.append(i)
                    except (FileNotFoundError, NotImplementedError):
                        pass
            if not keep:
                rows.append({"method": f"decoder {size}", "set": name, "available": False})
                continue
            errs = _per_image_errors(np.stack(preds), s["lobe"][keep], s["stderr"][keep])
            rows.append(
                {
                    "method": f"decoder {size}",
                    "kind": "decoder",
                    "set": name,
                    "available": True,
                    "seconds_per_eval": 1.0 / sp["rgb_evals_per_s"],
                    **_stats(errs),
                }
            )
        print(f"decoder {size}: {rows[-2:]}", file=sys.stderr, flush=True)
    return rows


def brdf_reference(sets: dict, cfg: Config) -> list[dict]:
    """The plain estimator (eval_brdf) at each walk count on a fixed subset of lobe pixels."""
    s = sets["layered"]
    res = s["lobe"].shape[2]
    wo_grid, mask = lobe.lobe_grid(res)
    on = np.flatnonzero(mask)
    rng = np.random.default_rng(7)
    pix = np.sort(rng.choice(on, size=min(cfg.ref_pixels, len(on)), replace=False))
    wo = wo_grid[pix]
    n_ang = len(s["angles"])
    wi_all = np.concatenate([np.broadcast_to(lobe.incident_direction(t), wo.shape) for t in s["angles"]])
    wo_all = np.tile(wo, (n_ang, 1))
    groups: dict[int, list[int]] = {}
    for i, st in enumerate(s["stacks"]):  # one batch per coating count: rows = stack x elevation x pixel
        groups.setdefault(len(st.coatings), []).append(i)
    rows = []
    for walks in cfg.walks:
        errs, seconds, evals = [], 0.0, 0
        for idx in groups.values():
            arrays = reference.pack_stacks([s["stacks"][i] for i in idx for _ in range(len(wo_all))])
            wi = np.tile(wi_all, (len(idx), 1))
            wo_b = np.tile(wo_all, (len(idx), 1))
            t0 = time.perf_counter()
            f, _ = reference.eval_brdf(arrays, wi, wo_b, walks=walks, seed=100 + walks)
            seconds += time.perf_counter() - t0
            evals += len(wi)
            f = (f * wo_b[:, 2:3]).reshape(len(idx), n_ang, len(wo), 3)
            for k, i in enumerate(idx):
                for a in range(n_ang):
                    ref = s["lobe"][i, a].reshape(-1, 3)[pix]
                    se = s["stderr"][i, a].reshape(-1, 3)[pix]
                    errs.append(quality.noise_corrected_error(f[k, a], ref, se))
        rows.append(
            {
                "method": f"reference {walks} walks",
                "kind": "reference",
                "walks": walks,
                "set": "layered",
                "available": True,
                "seconds_per_eval": seconds / evals,
                **_stats(errs),
            }
        )
        print(rows[-1], file=sys.stderr, flush=True)
    # Single-layer stacks have no coating: the reference is their exact analytic BSDF.
    t = sets["single"]
    wi = np.broadcast_to(lobe.incident_direction(30.0), wo.shape).copy()
    t0 = time.perf_counter()
    for st in t["stacks"]:
        reference.eval_brdf(st, wi, wo, walks=1)
    rows.append(
        {
            "method": "reference (exact, no coating)",
            "kind": "reference",
            "walks": 1,
            "set": "single",
            "available": True,
            "seconds_per_eval": (time.perf_counter() - t0) / (len(wo) * len(t["stacks"])),
            "median": 0.0,
            "p90": 0.0,
            "n": len(t["stacks"]) * 4,
        }
    )
    return rows


def brdf_cycles(sets: dict, cfg: Config, cy) -> list[dict]:
    rows = []
    for name, idx in (("single", cfg.cycles_single), ("layered", cfg.cycles_layered)):
        s = sets[name]
        # configuration indices are rows of the full held-out set
        rows_i = [k for k, r in enumerate(s["rows"]) if idx is None or r in idx]
        if not rows_i:
            continue
        angles = s["angles"] if cfg.cycles_angles is None else list(cfg.cycles_angles)
        ai = [s["angles"].index(t) for t in angles]
        preds, spe = [], []
        for i in rows_i:
            img, sec = cy.lobes(s["stacks"][i], s["lobe"].shape[2], angles)
            preds.append(img)
            spe.append(sec)
        errs = _per_image_errors(np.stack(preds), s["lobe"][rows_i][:, ai], s["stderr"][rows_i][:, ai])
        rows.append(
            {
                "method": "Cycles Principled coat",
                "kind": "cycles",
                "set": name,
                "available": True,
                "seconds_per_eval": float(np.mean(spe)),
                **_stats(errs),
                "calibration": cy.calibration,
            }
        )
        print(rows[-1], file=sys.stderr, flush=True)
    return rows


# ----------------------------------------------------------------------------- render level


def _neural_variant(scene_fn, size: str):
    """The demo scene with every layered material on decoder ``size`` (None if one cannot be encoded)."""
    from addon.core.render.materials import LayeredSpec

    scene = scene_fn()
    mats, _, _ = quality.assign_decoders(scene, size, calibrate=True)  # as the renderer's default
    if any(isinstance(m, LayeredSpec) and m.stack.coatings for m in mats):
        return None
    scene.materials = mats
    return scene


def _auto_variant(scene_fn, tolerance: float, res: int, walks: int):
    """The demo scene under the auto setting (``quality.assign_decoders``); returns it and the choices."""
    scene = scene_fn()
    scene.materials, choices, _ = quality.assign_decoders(
        scene, "auto", tolerance, res=res, walks=walks, calibrate=True
    )
    return scene, {k: {"size": c.size, "errors": c.errors, "met": c.met} for k, c in choices.items()}


def render_level(cfg: Config, out: Path) -> dict:
    import bpy
    from bench_render import build_blender_scene, mse, ours, render_cycles

    from addon.core.render.demo_scene import demo_scene

    w, h = cfg.size

    def scene_fn():
        return demo_scene(w, h)

    t0 = time.perf_counter()
    ref, _ = ours(scene_fn(), cfg.reference_spp, cfg.bounces, "reference", seed=1000)
    ref_seconds = time.perf_counter() - t0
    print(f"reference render {ref_seconds:.1f} s", file=sys.stderr, flush=True)
    curves = {}
    ours(scene_fn(), 1, 1, "reference")  # warm-up
    pts = []
    for spp in cfg.budgets:
        img, st = ours(scene_fn(), spp, cfg.bounces, "reference", seed=spp)
        pts.append({"spp": spp, "seconds": st.seconds["total"], "mse": mse(img, ref)})
    curves["reference mode"] = pts
    largest = None
    for size in quality.available_sizes():
        scene = _neural_variant(scene_fn, size)
        if scene is None:
            continue
        largest = size
        ours(scene, 1, 1, "neural")  # warm-up: sessions, first-call overheads
        pts = []
        for spp in cfg.budgets:
            img, st = ours(_neural_variant(scene_fn, size), spp, cfg.bounces, "neural", seed=spp)
            pts.append({"spp": spp, "seconds": st.seconds["total"], "mse": mse(img, ref)})
        curves[f"neural {size}"] = pts
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        bs = build_blender_scene(bpy, scene_fn())
        render_cycles(bpy, bs, 8, 8, 1, 1, Path(tmp))  # warm-up
        pts = []
        for spp in cfg.cycles_budgets:
            img, sec = render_cycles(bpy, bs, w, h, spp, cfg.bounces, Path(tmp))
            pts.append({"spp": spp, "seconds": sec, "mse": mse(img, ref)})
        curves["Cycles Principled coat"] = pts
    for k, v in curves.items():
        print(k, v, file=sys.stderr, flush=True)

    # The auto setting against always the largest decoder, same samples.
    auto = None
    if largest is not None:
        auto_scene, choices = _auto_variant(scene_fn, cfg.auto_tolerance, cfg.auto_res, cfg.auto_walks)
        largest_scene = _neural_variant(scene_fn, largest)
        for sc in (auto_scene, largest_scene):
            ours(sc, 1, 1, "neural")  # warm-up: every session loaded before timing
        img_a, st_a = ours(auto_scene, cfg.auto_spp, cfg.bounces, "neural", seed=77)
        img_l, st_l = ours(largest_scene, cfg.auto_spp, cfg.bounces, "neural", seed=77)
        auto = {
            "tolerance": cfg.auto_tolerance,
            "spp": cfg.auto_spp,
            "largest": largest,
            "choices": choices,
            "auto_seconds": st_a.seconds["total"],
            "largest_seconds": st_l.seconds["total"],
            "auto_network_seconds": st_a.seconds["network"],
            "largest_network_seconds": st_l.seconds["network"],
            "auto_reference_seconds": st_a.seconds["reference"],
            "auto_mse": mse(img_a, ref),
            "largest_mse": mse(img_l, ref),
        }
        print(auto, file=sys.stderr, flush=True)
    return {
        "reference_spp": cfg.reference_spp,
        "reference_seconds": ref_seconds,
        "size": [w, h],
        "bounces": cfg.bounces,
        "curves": curves,
        "pareto": pareto(curves),
        "auto": auto,
        "textures": texture_footprints(sizes=cfg.texture_sizes),
    }


def texture_footprints(source: int = 4096, sizes=((320, 180), (1920, 1080))) -> dict:
    """Per demo material and image size: the smallest on-screen footprint and the texture it needs."""
    from addon.core.render.demo_scene import demo_scene

    out = {}
    for w, h in sizes:
        scene = demo_scene(w, h)
        t0 = time.perf_counter()
        fp = quality.primary_footprints(scene)
        sec = time.perf_counter() - t0
        out[f"{w}x{h}"] = {
            "seconds": sec,
            "materials": {
                name: {
                    "footprint": float(f),
                    "resolution": list(quality.texture_resolution_for_footprint(f, (source, source))),
                }
                for name, f in zip(scene.material_names, fp, strict=True)
            },
        }
    return out


def pareto(curves: dict) -> list[list]:
    """Points (method, spp) on the Pareto front of (seconds, MSE): nothing is both faster and more accurate."""
    pts = sorted(((p["seconds"], p["mse"], m, p["spp"]) for m, ps in curves.items() for p in ps))
    front, best = [], math.inf
    for _seconds, err, m, spp in pts:
        if err < best:
            front.append([m, spp])
            best = err
    return front


# ----------------------------------------------------------------------------- outputs


def chart_brdf(rows: list[dict], path: Path, command: str, floor: float | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 5))
    markers = {"single": "o", "layered": "s"}
    for set_name in ("single", "layered"):
        ref = [
            r
            for r in rows
            if r.get("kind") == "reference" and r["set"] == set_name and "walks" in r and r["method"].endswith("walks")
        ]
        if ref:
            low = floor if floor else 1e-3  # an error below the stored reference's noise is drawn at that noise

            def y(r):
                return 100 * max(r["median"], low)

            ax.loglog(
                [r["seconds_per_eval"] for r in ref],
                [y(r) for r in ref],
                "-",
                marker=markers[set_name],
                color="C0",
                label=f"reference, 1-{ref[-1]['walks']} walks ({set_name})",
            )
            for r in ref:
                below = " (below the noise)" if r["median"] < low else ""
                ax.annotate(
                    f"{r['walks']}{below}",
                    (r["seconds_per_eval"], y(r)),
                    fontsize=7,
                    textcoords="offset points",
                    xytext=(4, 4),
                )
        for i, r in enumerate(x for x in rows if x.get("kind") == "decoder" and x["set"] == set_name):
            ax.loglog(
                [r["seconds_per_eval"]],
                [100 * r["median"]],
                marker=markers[set_name],
                color="C1",
                linestyle="none",
                label=f"decoders ({set_name})" if i == 0 else None,
            )
            ax.annotate(
                r["method"].split()[-1],
                (r["seconds_per_eval"], 100 * r["median"]),
                fontsize=7,
                textcoords="offset points",
                xytext=(4, -10),
            )
        for r in (x for x in rows if x.get("kind") == "cycles" and x["set"] == set_name):
            ax.loglog(
                [r["seconds_per_eval"]],
                [100 * r["median"]],
                marker=markers[set_name],
                color="C3",
                linestyle="none",
                label=f"Cycles Principled coat ({set_name})",
            )
    if floor:
        ax.axhline(
            100 * floor,
            color="0.5",
            ls=":",
            lw=1,
            label="noise of the stored layered reference (errors below it read as 0)",
        )
    ax.set_xlabel("seconds per RGB evaluation (CPU, 2 threads; Cycles: render time / shading points)")
    ax.set_ylabel("lobe error, median relative RMSE (%)")
    ax.set_title("BRDF level: error against time per evaluation (held-out stacks)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.text(0.01, 0.01, command, fontsize=6, color="0.4")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def chart_render(r: dict, path: Path, command: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    front = {tuple(x) for x in r["pareto"]}
    for i, (m, pts) in enumerate(r["curves"].items()):
        ax.loglog([p["seconds"] for p in pts], [p["mse"] for p in pts], "o-", color=f"C{i}", label=m)
        for p in pts:
            ax.annotate(str(p["spp"]), (p["seconds"], p["mse"]), fontsize=7, textcoords="offset points", xytext=(3, 3))
    fp = sorted((p["seconds"], p["mse"]) for m, pts in r["curves"].items() for p in pts if (m, p["spp"]) in front)
    ax.loglog([a for a, _ in fp], [b for _, b in fp], "k--", lw=1, label="Pareto front")
    ax.scatter([a for a, _ in fp], [b for _, b in fp], s=90, facecolors="none", edgecolors="k", zorder=4)
    if r.get("auto"):
        a = r["auto"]
        ax.loglog(
            [a["auto_seconds"]],
            [a["auto_mse"]],
            "*",
            ms=12,
            color="k",
            label=f"auto (tolerance {a['tolerance']:g}, {a['spp']} spp)",
        )
        ax.loglog(
            [a["largest_seconds"]],
            [a["largest_mse"]],
            "*",
            ms=12,
            mfc="none",
            color="k",
            label=f"always {a['largest']} ({a['spp']} spp, same seed)",
        )
    w, h = r["size"]
    ax.set_xlabel("render time (s)")
    ax.set_ylabel(f"MSE against a {r['reference_spp']}-spp reference-mode render")
    ax.set_title(f"Render level: demo scene {w}x{h}, {r['bounces']} bounces (labels: samples per pixel)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.text(0.01, 0.01, command, fontsize=6, color="0.4")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(data: dict, command: str) -> str:
    cfg = data["config"]
    lines = [
        "# Benchmarks: speed against accuracy",
        "",
        f"Produced by `{command}` in {data['seconds']:.0f} s ({platform.machine()}, 2 CPU threads, no GPU; this "
        "machine's speed varies by up to 1.5x between runs: compare ratios within one run). Decoder sizes "
        f"shipped at the time: {', '.join(data['sizes']) or 'none'}.",
        "",
        "## BRDF level",
        "",
        "Lobe error (relative RMSE of f cos(theta_o) at 0/30/60/75 degrees incidence, noise of the stored "
        "reference removed) against seconds per RGB evaluation, on the held-out stacks "
        f"(`tests/data/heldout_single.npz`: {data['n_single']} stacks; `heldout_layered_lobes.npz`: "
        f"{data['n_layered']} stacks). Decoders: stacks encoded as the renderer encodes them (encoder + layering "
        "network), time from `benchmarks/bench_decoders.py`'s `speed` (batch 65,536, one material). Reference: "
        f"`eval_brdf` at each walk count on {cfg['ref_pixels']} fixed lobe pixels per stack and elevation. Cycles: "
        f"the Principled coat approximation measured in Cycles (`benchmarks/cycles_brdf.py`, {cfg['cycles_res']}^2 "
        f"fisheye pixels, {cfg['cycles_samples']} samples; its time is render time over shading points, ray "
        "casting included).",
        "",
        "| method | set | stacks x elevations | median error | p90 error | seconds per eval |",
        "|---|---|---|---|---|---|",
    ]
    for r in data["brdf"]:
        if not r.get("available", True):
            lines.append(f"| {r['method']} | {r['set']} | - | cannot encode these stacks | - | - |")
            continue
        lines.append(
            f"| {r['method']} | {r['set']} | {r['n']} | {100 * r['median']:.1f}% | {100 * r['p90']:.1f}% | "
            f"{r['seconds_per_eval']:.3g} |"
        )
    lines += [
        "",
        "The stored layered reference lobes have a median relative noise of "
        f"{100 * data['reference_noise_floor']:.1f}%: "
        "after its variance is removed, errors below that level are not resolved and read as 0 (the reference at "
        "the highest walk counts). Cycles' figures include the resampling of its fisheye image onto the lobe grid, "
        "which blurs lobes sharper than a pixel (about 1 degree; coats with alpha around 0.02 or below).",
        "",
        "![BRDF level](benchmarks_brdf.png)",
        "",
    ]
    r = data["render"]
    w, h = r["size"]
    lines += [
        "## Render level",
        "",
        f"Demo scene (`addon.core.render.demo_scene`) at {w}x{h}, {r['bounces']} bounces; error = MSE of linear "
        f"radiance against a {r['reference_spp']}-spp reference-mode render ({r['reference_seconds']:.0f} s). Neural "
        "rows force every layered material onto one decoder size, calibrated as the renderer calibrates by default "
        "(`addon.core.neural.calibrate`; made once per material and session before the timed renders); Cycles "
        "renders the same geometry, lights and sky "
        "with the Principled coat approximation (its error does not vanish with samples: it is another material "
        "model).",
        "",
        "| method | samples | seconds | MSE | on the Pareto front |",
        "|---|---|---|---|---|",
    ]
    front = {tuple(x) for x in r["pareto"]}
    for m, pts in r["curves"].items():
        for p in pts:
            lines.append(
                f"| {m} | {p['spp']} | {p['seconds']:.2f} | {p['mse']:.4g} | "
                f"{'yes' if (m, p['spp']) in front else ''} |"
            )
    lines += ["", "![render level](benchmarks_render.png)", ""]
    a = r.get("auto")
    lines += ["## The auto quality setting on the demo scene", ""]
    if a is None:
        lines.append("No decoder can encode the demo scene's stacks: not measured.")
    else:
        saved = a["largest_seconds"] - a["auto_seconds"]
        lines += [
            f"Tolerance {a['tolerance']:g} (relative lobe error), {a['spp']} samples per pixel, against always using "
            f"the largest shipped decoder ({a['largest']}). Per material, `addon.core.quality.choose_decoder` picks "
            "the smallest decoder whose measured error on that stack is shown under the tolerance (its upper "
            "bound is), else the most accurate one (with a warning).",
            "",
            "| material | chosen | measured error per size tried | within tolerance |",
            "|---|---|---|---|",
        ]
        for name, c in a["choices"].items():
            errs = ", ".join(f"{k} {100 * v:.1f}%" if math.isfinite(v) else f"{k} n/a" for k, v in c["errors"].items())
            lines.append(f"| {name} | {c['size'] or 'reference'} | {errs} | {'yes' if c['met'] else 'no'} |")
        lines += [
            "",
            "| setting | seconds | network s | MSE |",
            "|---|---|---|---|",
            f"| auto | {a['auto_seconds']:.2f} | {a['auto_network_seconds']:.2f} | {a['auto_mse']:.4g} |",
            f"| always {a['largest']} | {a['largest_seconds']:.2f} | {a['largest_network_seconds']:.2f} | "
            f"{a['largest_mse']:.4g} |",
            "",
            f"Time saved by auto: {saved:.2f} s ({100 * saved / max(a['largest_seconds'], 1e-9):.0f}%); error cost: "
            f"MSE {a['auto_mse'] - a['largest_mse']:+.3g} (same seed; both against the reference render). "
            + (
                "Every material chose the largest decoder here: the two settings differ only by timing noise."
                if all(c["size"] == a["largest"] for c in a["choices"].values())
                else "On an image this small the decoders' share of the render time is small and the per-call overhead "
                "of ONNX Runtime is large, so the network-time column is the one to compare."
            ),
        ]
    tex = r.get("textures") or {}
    if tex:
        lines += [
            "",
            "### Textures no finer than the footprint",
            "",
            "Smallest camera-ray footprint per demo material (`addon.core.quality.primary_footprints`, one ray "
            "per pixel) and the latent-texture resolution it needs out of a 4096^2 source "
            "(`texture_resolution_for_footprint`); a latent texel is 100 half floats (200 bytes).",
            "",
            "| image | material | footprint (uv) | texture needed | memory vs 4096^2 |",
            "|---|---|---|---|---|",
        ]
        for img, d in tex.items():
            for name, m in d["materials"].items():
                rh, rw = m["resolution"]
                lines.append(f"| {img} | {name} | {m['footprint']:.3g} | {rw}x{rh} | {100 * rh * rw / 4096**2:.2f}% |")
    lines += ["", "## Stability", "", "See [stability.md](stability.md) (written by the same command).", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small configuration (the tests' harness check)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-stability", action="store_true")
    a = ap.parse_args(argv)
    cfg = QUICK if a.quick else FULL
    command = "python benchmarks/bench_all.py" + (" --quick" if a.quick else "")
    t0 = time.perf_counter()
    sets = heldout_sets(cfg)

    def stage(name):
        print(f"[{time.perf_counter() - t0:6.1f} s] {name}", file=sys.stderr, flush=True)

    stage("decoders")
    brdf = brdf_decoders(sets, a.threads, cfg.speed_repeats)
    stage("reference walks")
    brdf += brdf_reference(sets, cfg)
    stage("Cycles BRDF")
    from cycles_brdf import CyclesBRDF

    cy = CyclesBRDF(cfg.cycles_res, cfg.cycles_samples)
    brdf += brdf_cycles(sets, cfg, cy)
    stage("render level")
    render_data = render_level(cfg, a.out)
    stage("stability")
    a.out.mkdir(parents=True, exist_ok=True)
    if not a.skip_stability:
        import stability

        # the quick run checks the harness on a few cases (tests/core/test_stability.py covers every case)
        few = ("alpha_to_0", "grazing", "three_coatings", "out_of_range", "nan_direction") if a.quick else None
        # a fresh Blender scene (the render level replaced it); the quick run leaves Cycles out
        cy = None if a.quick else CyclesBRDF(cfg.cycles_res, cfg.cycles_samples)
        cells = stability.run(a.quick, case_names=few, cycles=cy)
        (a.out / "stability.md").write_text(stability.markdown(cells, command))
    lay = sets["layered"]  # relative noise of the stored layered reference lobes: errors below it read as 0
    floor = [
        math.sqrt(float(np.sum(e**2)) / max(float(np.sum(r**2)), 1e-300))
        for r, e in zip(
            lay["lobe"].reshape(-1, *lay["lobe"].shape[2:]),
            lay["stderr"].reshape(-1, *lay["stderr"].shape[2:]),
            strict=True,
        )
    ]
    data = {
        "command": command,
        "seconds": time.perf_counter() - t0,
        "sizes": quality.available_sizes(),
        "reference_noise_floor": float(np.median(floor)),
        "n_single": len(sets["single"]["stacks"]),
        "n_layered": len(sets["layered"]["stacks"]),
        "config": {k: v for k, v in vars(cfg).items()},
        "brdf": brdf,
        "render": render_data,
    }
    stage("outputs")
    chart_brdf(brdf, a.out / "benchmarks_brdf.png", command, data["reference_noise_floor"])
    chart_render(render_data, a.out / "benchmarks_render.png", command)
    (a.out / "benchmarks.json").write_text(json.dumps(data, indent=1, default=float) + "\n")
    (a.out / "benchmarks.md").write_text(markdown(data, command))
    print(f"wrote {a.out / 'benchmarks.md'} in {data['seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

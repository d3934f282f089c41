"""Render-level fidelity: per-object mean radiance of the demo scene, neural mode against reference mode.

    python benchmarks/bench_fidelity.py --width 96 --height 54 --samples 64 --out docs/fidelity.md

renders ``addon.core.render.demo_scene`` twice with the renderer's default settings (except the sample
count and the resolution), once with ``mode="neural"`` (the default decoder size, or ``--size``) and once
with ``mode="reference"`` (the position-free Monte Carlo layered BSDF at every layered hit), and compares
the mean radiance over the pixels whose centre sees each object. The noise of each mean is its standard
error from the per-pixel variance of the samples (pixels are independent: the squared standard errors of
the pixel means add); the ratio's noise combines both. With ``--runs N`` each mode is rendered N times
with other seeds and the spread of the per-run ratios is stated too.

Writes a markdown table (``--out``) with this command, and a JSON of the numbers beside it. The reference
renders do not depend on the networks and cost most of the time: ``--reference-cache FILE`` keeps their
per-object means (JSON, keyed by resolution, samples, seeds and the reference settings) and reuses them
when the same comparison is made again with other models.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from addon.core.render.demo_scene import demo_scene  # noqa: E402
from addon.core.render.integrator import RenderSettings, camera_hits, render  # noqa: E402


def object_masks(scene) -> dict[str, np.ndarray]:
    """Flat pixel masks (H * W,) of the objects whose triangles the pixel centres hit, by material name."""
    cam = scene.camera
    py, px = np.divmod(np.arange(cam.width * cam.height), cam.width)
    prim, _ = camera_hits(scene, px, py)
    mat = np.where(prim >= 0, scene.mesh.material_index[np.maximum(prim, 0)], -1)
    return {name: mat == i for i, name in enumerate(scene.material_names) if (mat == i).any()}


def object_means(film, masks: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per object: mean radiance (RGB and its channel mean) over its pixels and the standard errors."""
    mean = film.mean().reshape(-1, 3).astype(np.float64)
    se = film.stderr().reshape(-1, 3)
    out = {}
    for name, m in masks.items():
        n = int(m.sum())
        rgb = mean[m].mean(axis=0)
        rgb_se = np.sqrt((se[m] ** 2).sum(axis=0)) / n
        lum = float(rgb.mean())
        lum_se = float(np.sqrt((se[m].mean(axis=1) ** 2).sum()) / n)  # the channel mean of each pixel's mean
        out[name] = {"pixels": n, "rgb": rgb.tolist(), "rgb_stderr": rgb_se.tolist(), "mean": lum, "stderr": lum_se}
    return out


def render_means(
    scene, masks, mode: str, samples: int, seed: int, size: str | None, calibrate: bool = True, pixels=None
) -> tuple[dict, float]:
    """Per-object means (:func:`object_means`) of one render and its seconds (:func:`render_film`)."""
    film, secs = render_film(scene, mode, samples, seed, size, calibrate, pixels)
    return object_means(film, masks), secs


def render_film(
    scene,
    mode: str,
    samples: int,
    seed: int,
    size: str | None,
    calibrate: bool = True,
    pixels=None,
    max_bounces: int | None = None,
) -> tuple[object, float]:
    """The film of ``scene`` rendered in ``mode`` with default settings but the sample count and seed (and
    in neural mode the layered objects' decoder ``size``, when given, and the calibration; ``max_bounces`` when
    given), and its seconds."""
    settings = RenderSettings(samples=samples, mode=mode, seed=seed, calibrate=calibrate)
    if max_bounces is not None:
        settings.max_bounces = max_bounces
    materials = scene.materials
    if size is not None and mode == "neural":  # the layered objects' neural materials of that size
        from addon.core.render import neural_material
        from addon.core.render.materials import LayeredSpec, analytic_for_stack

        def sized(m):
            if not isinstance(m, LayeredSpec) or (analytic_for_stack(m.stack) is not None and m.latent_texture is None):
                return m
            made = neural_material.make(m.stack, m.latent_texture, size=size, calibrate=calibrate)
            if made is None:
                raise ValueError(f"no shipped models of size {size!r} serve {m.name!r}")
            return made

        scene.materials = [sized(m) for m in materials]
    t = time.perf_counter()
    try:
        film, _ = render(scene, settings, pixels=pixels)
    finally:
        scene.materials = materials
    return film, time.perf_counter() - t


def object_passes(a, key: dict, cached: dict | None, masks: dict, secs: dict) -> dict:
    """{name: (neural means, reference means)} of the objects of ``--objects`` rendered on their own pixels
    with ``--object-samples`` samples (the reference from the cache when it holds them)."""
    out = {}
    for name in a.objects if a.object_samples else []:
        if name not in masks:
            raise SystemExit(f"--objects: no object {name!r} in view; objects: {sorted(masks)}")
        scene = demo_scene(a.width, a.height)
        pix = np.flatnonzero(masks[name])
        one = {name: masks[name]}
        neural, dt = render_means(scene, one, "neural", a.object_samples, a.seed, a.size, not a.no_calibrate, pix)
        secs["neural"] += dt
        okey = {**key, "object": name, "object_samples": a.object_samples}
        ref = ((cached or {}).get("objects") or {}).get(name)
        if ref is None or ref.get("key") != okey:
            means, dt = render_means(scene, one, "reference", a.object_samples, a.seed, None, pixels=pix)
            ref = {"key": okey, "means": means, "seconds": dt}
        secs["reference"] += ref["seconds"]
        out[name] = (neural, ref)
        print(f"{name}: its own pixels at {a.object_samples} spp done", file=sys.stderr, flush=True)
    return out


def reference_key(width: int, height: int, samples: int, seeds: list[int], max_bounces: int | None = None) -> dict:
    """What a reference render of the same scene depends on (the key of a reference cache): the image,
    the samples and seeds, and the renderer's reference settings (Max Bounces: ``max_bounces`` when given)."""
    defaults = RenderSettings()
    if max_bounces is not None:
        defaults.max_bounces = max_bounces
    return {
        "width": width,
        "height": height,
        "samples": samples,
        "seeds": list(seeds),
        "reference_walks": defaults.reference_walks,
        "max_bounces": defaults.max_bounces,
        # how Max Bounces counts (after the first hit, as Cycles): a render cached when it counted one more is
        # another render, never reused
        "bounces_counted": "after the first hit",
    }


def compare(neural: dict, reference: dict) -> dict:
    """Per object: neural / reference of the mean radiance (channel mean and per channel) and its noise."""
    out = {}
    for name, r in reference.items():
        n = neural[name]
        ratio = n["mean"] / max(r["mean"], 1e-12)
        rel = np.hypot(n["stderr"] / max(n["mean"], 1e-12), r["stderr"] / max(r["mean"], 1e-12))
        rgb = np.asarray(n["rgb"]) / np.maximum(np.asarray(r["rgb"]), 1e-12)
        out[name] = {
            "ratio": ratio,
            "ratio_stderr": float(ratio * rel),
            "rgb_ratio": rgb.tolist(),
            "neural_rel_stderr": n["stderr"] / max(n["mean"], 1e-12),
            "reference_rel_stderr": r["stderr"] / max(r["mean"], 1e-12),
        }
    return out


def table(cmp: dict, runs: list[dict] | None) -> list[str]:
    lines = [
        "| object | neural / reference (mean of RGB) | R / G / B | noise of neural, reference (rel. std. error) |"
        + (" per-run ratios |" if runs else ""),
        "|---|---|---|---|" + ("---|" if runs else ""),
    ]
    for name, c in cmp.items():
        row = (
            f"| {name} | {c['ratio']:.3f} +- {c['ratio_stderr']:.3f} | "
            + " / ".join(f"{x:.3f}" for x in c["rgb_ratio"])
            + f" | {c['neural_rel_stderr']:.3f}, {c['reference_rel_stderr']:.3f} |"
        )
        if runs:
            row += " " + ", ".join(f"{r[name]['ratio']:.3f}" for r in runs) + " |"
        lines.append(row)
    return lines


def summary(cmp: dict, exclude=("tiles",)) -> dict:
    """|ratio - 1| over the layered objects (the floor is Lambertian in both modes unless textured)."""
    dev = np.array([abs(c["ratio"] - 1.0) for name, c in cmp.items() if name not in exclude])
    return {
        "median_abs_deviation": float(np.median(dev)),
        "max_abs_deviation": float(dev.max()),
        "objects": [name for name in cmp if name not in exclude],
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=54)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=1, help="independent renders per mode (seeds seed, seed + 1, ...)")
    ap.add_argument("--size", default=None, help="decoder size of the neural mode (default: the renderer's)")
    ap.add_argument(
        "--no-calibrate",
        action="store_true",
        help="neural mode without the albedo calibration (addon.core.neural.calibrate; the renderer's default)",
    )
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "fidelity.md")
    ap.add_argument(
        "--reference-cache",
        type=Path,
        default=None,
        help="JSON of the reference renders' per-object means: read when it matches, else written",
    )
    ap.add_argument(
        "--object-samples",
        type=int,
        default=0,
        help="render the objects of --objects again on their own pixels with this many samples per pixel "
        "(both modes): for the objects whose reference is the noisiest",
    )
    ap.add_argument("--objects", nargs="*", default=[], help="objects (material names) for --object-samples")
    a = ap.parse_args(argv)
    if a.samples < 2 or a.runs < 1 or a.width < 1 or a.height < 1:
        ap.error(
            f"--samples must be >= 2 (a standard error needs two), --runs, --width, --height >= 1; got "
            f"{a.samples}, {a.runs}, {a.width}, {a.height}"
        )
    cmd = "python benchmarks/bench_fidelity.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    per_run, secs = [], {"neural": 0.0, "reference": 0.0}
    key = reference_key(a.width, a.height, a.samples, [a.seed + k for k in range(a.runs)])
    cached = None
    if a.reference_cache is not None and a.reference_cache.exists():
        c = json.loads(a.reference_cache.read_text())
        cached = c if c.get("key") == key else None
    ref_runs = cached["runs"] if cached else []
    for k in range(a.runs):
        scene = demo_scene(a.width, a.height)
        masks = object_masks(scene)
        neural, dt = render_means(scene, masks, "neural", a.samples, a.seed + k, a.size, not a.no_calibrate)
        secs["neural"] += dt
        if cached is None:
            ref, dt = render_means(scene, masks, "reference", a.samples, a.seed + k, None)
            secs["reference"] += dt
            ref_runs.append({"means": ref, "seconds": dt})
        print(f"run {k}: neural and reference done", file=sys.stderr, flush=True)
        per_run.append(compare(neural, ref_runs[k]["means"]))
    if cached is not None:
        secs["reference"] = sum(r["seconds"] for r in ref_runs)
    objects = object_passes(a, key, cached, masks, secs)
    for name, (neural, ref) in objects.items():  # the object's own, longer renders replace its row
        for r in per_run:
            r[name] = compare(neural, ref["means"])[name]
    extra = {name: o[1] for name, o in objects.items()}
    old = (cached or {}).get("objects", {})
    rendered = cached is None or any(old.get(name) != ref for name, ref in extra.items())
    if a.reference_cache is not None and rendered:  # a cache that was only read stays as it is
        a.reference_cache.parent.mkdir(parents=True, exist_ok=True)
        a.reference_cache.write_text(
            json.dumps({"key": key, "command": cmd, "runs": ref_runs, "objects": {**old, **extra}}, indent=1) + "\n"
        )
    cmp = (
        per_run[0]
        if a.runs == 1
        else {
            name: {
                "ratio": float(np.mean([r[name]["ratio"] for r in per_run])),
                "ratio_stderr": float(np.std([r[name]["ratio"] for r in per_run], ddof=1) / np.sqrt(a.runs)),
                "rgb_ratio": np.mean([r[name]["rgb_ratio"] for r in per_run], axis=0).tolist(),
                "neural_rel_stderr": float(np.mean([r[name]["neural_rel_stderr"] for r in per_run])),
                "reference_rel_stderr": float(np.mean([r[name]["reference_rel_stderr"] for r in per_run])),
            }
            for name in per_run[0]
        }
    )
    s = summary(cmp)
    if objects:
        lines_objects = (
            f" Rows of {', '.join(objects)}: rendered again on the object's own pixels with {a.object_samples} "
            "samples per pixel in both modes (its reference is the noisiest)."
        )
    else:
        lines_objects = ""
    size = (a.size or "the renderer's default") + (", no albedo calibration" if a.no_calibrate else ", calibrated")
    lines = [
        "# Render-level fidelity: neural mode against reference mode",
        "",
        f"Made by `{cmd}`: the demo scene (`addon/core/render/demo_scene.py`) at {a.width} x {a.height}, "
        f"{a.samples} samples per pixel, default render settings otherwise, neural decoder size: {size}. "
        "Per object: the mean radiance over the pixels whose centre sees it, neural / reference, with its "
        "standard error (from the per-pixel variance of both renders"
        + (f"; over {a.runs} independent runs: the spread of the per-run ratios" if a.runs > 1 else "")
        + "). The floor (`tiles`) is the same Lambertian material in both modes: its ratio shows the noise "
        "and the indirect light of the spheres." + lines_objects,
        "",
        *table(cmp, per_run if a.runs > 1 else None),
        "",
        f"Layered objects: median |ratio - 1| {s['median_abs_deviation']:.3f}, max {s['max_abs_deviation']:.3f} "
        f"(target: 0.03 / 0.06). Render time: neural {secs['neural']:.0f} s, reference {secs['reference']:.0f} s "
        f"(all runs, a shared 2-core CPU).",
        "",
    ]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(lines) + "\n")
    a.out.with_suffix(".json").write_text(
        json.dumps({"command": cmd, "objects": cmp, "summary": s, "runs": per_run, "seconds": secs}, indent=1) + "\n"
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main()

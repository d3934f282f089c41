"""Render-level grazing light: layered spheres near their terminator, neural mode against reference mode.

    python benchmarks/bench_terminator.py --sizes tiny small medium paper --uncalibrated-too \
        --reference-cache docs/terminator_reference.npz

A decoder that reflects too much light arriving at grazing incidence draws a bright line along the
terminator of every coated sphere under a small light. The per-object means of ``bench_fidelity.py`` dilute
that line in the sphere's lit half; this benchmark measures it where it is. It renders
``addon.core.render.demo_scene.terminator_scene`` (coated gold and red car paint on a grey floor, one point
light nearly level with them, no sky) in neural mode (the renderer's default size and settings, or
each of ``--sizes``, calibrated as the renderer's default is, and with ``--uncalibrated-too`` also
without) and in reference mode, and compares the mean radiance of each sphere's
pixels in bands of the angle between the surface normal and the light (computed for the pixel centre's
ray on the analytic sphere): 0-60, 60-75, 75-80, 80-84, 84-87, 87-90 degrees. Only those pixels are
rendered: the shadowed side, lit by the floor alone, is not part of the measurement. Each ratio's noise is
from the per-pixel variance of both renders.

Writes markdown tables (``--out``) with this command, a JSON beside it, and a PNG of the first
configuration's render beside the reference's and their ratio (``--out`` with ``.png``). The reference
render does not depend on the networks: ``--reference-cache FILE.npz`` keeps it (its key: resolution,
samples, seed, reference settings, scene) and reuses it for other models.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT, ROOT / "benchmarks"):  # the add-on, and bench_fidelity beside this file when imported
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from bench_fidelity import compare, object_means, reference_key, render_film  # noqa: E402

from addon.core.render import write_png  # noqa: E402
from addon.core.render.demo_scene import (  # noqa: E402
    SPHERE_RADIUS,
    TERMINATOR_LIGHT,
    TERMINATOR_PRESETS,
    sphere_centres,
    terminator_scene,
)
from addon.core.render.integrator import camera_hits  # noqa: E402
from addon.core.stack import PRESETS  # noqa: E402

# Bands of the angle between the normal and the light (degrees).
BAND_EDGES = (0.0, 60.0, 75.0, 80.0, 84.0, 87.0, 90.0)


def light_angles(scene, names) -> dict[str, np.ndarray]:
    """Per sphere, flat (H * W,) the angle (degrees) between the sphere's normal and the direction to the
    light where the pixel centre's ray meets the analytic sphere, NaN where the pixel does not see it (on
    the mesh, by its material) or the ray misses the analytic sphere (its silhouette's edge)."""
    cam = scene.camera
    py, px = np.divmod(np.arange(cam.width * cam.height), cam.width)
    prim, _ = camera_hits(scene, px, py)
    mat = np.where(prim >= 0, scene.mesh.material_index[np.maximum(prim, 0)], -1)
    o, d = cam.generate_rays(px, py, np.full((len(px), 2), 0.5))
    light = np.asarray(TERMINATOR_LIGHT, dtype=np.float64)
    out = {}
    for name, c in sphere_centres(scene, names).items():
        oc = o - c
        b = np.einsum("ij,ij->i", oc, d)
        disc = b * b - (np.einsum("ij,ij->i", oc, oc) - SPHERE_RADIUS**2)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        p = o + t[:, None] * d
        n = (p - c) / SPHERE_RADIUS
        to_light = light - p
        to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, to_light), -1.0, 1.0)))
        sees = (mat == scene.material_names.index(name)) & (disc > 0)
        out[name] = np.where(sees, angle, np.nan)
    return out


def band_masks(angles: dict[str, np.ndarray], edges=BAND_EDGES) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """{"<sphere>, <lo>-<hi> deg": flat pixel mask} for the bands that hold at least one pixel, and each
    band's lower edge by the same names."""
    masks, lows = {}, {}
    for name, a in angles.items():
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            m = (a >= lo) & (a < hi)
            if m.any():
                masks[f"{name}, {lo:.0f}-{hi:.0f} deg"] = m
                lows[f"{name}, {lo:.0f}-{hi:.0f} deg"] = lo
    return masks, lows


def reference_film(scene, pixels, a, key: dict):
    """(mean (H, W, 3), stderr (H, W, 3), seconds) of the reference render: rendered, or read from
    ``--reference-cache`` when its key matches (then written there when rendered)."""
    cache = a.reference_cache
    if cache is not None and cache.exists():
        c = np.load(cache, allow_pickle=False)
        if json.loads(str(c["key"])) == key:
            return c["mean"], c["stderr"], float(c["seconds"])
    film, secs = render_film(scene, "reference", a.samples, a.seed, None, pixels=pixels, max_bounces=a.max_bounces)
    mean, se = film.mean().astype(np.float32), film.stderr().astype(np.float32)  # as the cache keeps them
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache, key=json.dumps(key), mean=mean, stderr=se, seconds=secs)
    return mean, se, secs


class _Film:
    """The per-pixel mean and standard error that :func:`bench_fidelity.object_means` reads."""

    def __init__(self, mean, stderr):
        self._mean, self._stderr = mean, stderr

    def mean(self):
        return self._mean

    def stderr(self):
        return self._stderr


def table(cmp: dict, ref: dict) -> list[str]:
    lines = [
        "| sphere, angle to the light | pixels | reference radiance | neural / reference | R / G / B | "
        "noise of neural, reference (rel. std. error) |",
        "|---|---|---|---|---|---|",
    ]
    for name, c in cmp.items():
        r = ref[name]
        lines.append(
            f"| {name} | {r['pixels']} | {r['mean']:.4f} | {c['ratio']:.3f} +- {c['ratio_stderr']:.3f} | "
            + " / ".join(f"{x:.3f}" for x in c["rgb_ratio"])
            + f" | {c['neural_rel_stderr']:.3f}, {c['reference_rel_stderr']:.3f} |"
        )
    return lines


GRAZING_FROM = 80.0  # degrees: the bands of the glow


def summary(cmp: dict, lows: dict[str, float]) -> dict:
    """The largest ratio and the median and largest |ratio - 1| over the bands from :data:`GRAZING_FROM`
    degrees on, and the median and largest |ratio - 1| over the lit bands before them (``lows``: each band's
    lower edge)."""
    near = [cmp[n]["ratio"] for n in cmp if lows[n] >= GRAZING_FROM]
    lit = [cmp[n]["ratio"] for n in cmp if lows[n] < GRAZING_FROM]
    dev = lambda r: np.abs(np.asarray(r) - 1.0)  # noqa: E731
    return {
        "grazing_max_ratio": float(max(near)),
        "grazing_median_abs_deviation": float(np.median(dev(near))),
        "grazing_max_abs_deviation": float(dev(near).max()),
        "lit_median_abs_deviation": float(np.median(dev(lit))),
        "lit_max_abs_deviation": float(dev(lit).max()),
    }


# The lobe at the terminator: coated gold lit at LOBE_THETA_I degrees, seen from these (elevation, azimuth)
# pairs in degrees (azimuth 0: on the light's side, 180: towards the mirror direction).
LOBE_THETA_I = 83.0
LOBE_VIEWS = ((0, 0), (25, 0), (25, 90), (25, 180), (45, 0), (45, 90), (45, 180))
LOBE_WALKS = 65536


def lobe_directions():
    """(wi, wo) (P, 3) each, local frame: the light at :data:`LOBE_THETA_I`, the views of :data:`LOBE_VIEWS`."""
    ti = np.radians(LOBE_THETA_I)
    wi = np.tile([np.sin(ti), 0.0, np.cos(ti)], (len(LOBE_VIEWS), 1))
    t, p = (np.radians([v[k] for v in LOBE_VIEWS]) for k in (0, 1))
    wo = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=1)
    return wi, wo


def lobe_reference(stack, walks: int = LOBE_WALKS) -> tuple[np.ndarray, np.ndarray]:
    """The reference's f (P,) (RGB mean) at :func:`lobe_directions` and its standard error."""
    from addon.core import reference

    f, se = reference.eval_brdf(stack, *lobe_directions(), walks=walks, seed=11)
    return f.mean(axis=1), np.sqrt((se**2).mean(axis=1) / 3)


def lobe_ratios(stack, size, calibrate: bool, ref: np.ndarray) -> list[float]:
    """The rendered material's f over the reference's at :func:`lobe_directions` (RGB means)."""
    from addon.core.render import neural_material

    material = neural_material.make(stack, size=size, calibrate=calibrate)
    f = material.bind(None).eval(*lobe_directions())
    return (f.mean(axis=1) / np.maximum(ref, 1e-12)).tolist()


def band_table(results: list[dict], bands: list[str]) -> list[str]:
    """One row per configuration and sphere: the ratio in each band."""
    spheres = list(dict.fromkeys(b.split(", ")[0] for b in bands))
    names = list(dict.fromkeys(b.split(", ")[1] for b in bands))
    lines = ["| neural mode | sphere | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for r in results:
        for sph in spheres:
            cells = [f"{r['bands'][f'{sph}, {n}']['ratio']:.2f}" if f"{sph}, {n}" in r["bands"] else "" for n in names]
            lines.append(f"| {r['label']} | {sph} | " + " | ".join(cells) + " |")
    return lines


def lobe_table(results: list[dict], ref, se, walks: int) -> list[str]:
    """The section of coated gold's lobe at the terminator (none with ``--no-lobe``)."""
    if ref is None:
        return []
    views = [f"{t} / {p}" for t, p in LOBE_VIEWS]
    rel = [e / max(x, 1e-12) for x, e in zip(ref, se, strict=True)]
    return [
        f"## Coated gold's lobe at {LOBE_THETA_I:g} degrees",
        "",
        f"f(wi, wo) of the rendered material over the reference's (RGB means), the light at {LOBE_THETA_I:g} "
        "degrees from the normal, the viewer at the elevation / azimuth of each column in degrees (azimuth 0: "
        f"on the light's side, 180: towards its mirror direction). Reference: {walks:,} walks per pair; "
        "its value and relative standard error in the last rows. The band ratios above average these over "
        "the pixels' view directions.",
        "",
        "| neural mode | " + " | ".join(views) + " |",
        "|---|" + "---|" * len(views),
        *(f"| {r['label']} | " + " | ".join(f"{x:.2f}" for x in r["lobe"]) + " |" for r in results),
        "| reference f | " + " | ".join(f"{x:.4f}" for x in ref) + " |",
        "| reference rel. std. error | " + " | ".join(f"{x:.3f}" for x in rel) + " |",
        "",
    ]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=54)
    ap.add_argument("--samples", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--sizes", nargs="+", default=[None], help="decoder sizes of the neural mode (default: the renderer's)"
    )
    ap.add_argument("--no-calibrate", action="store_true", help="neural mode without the albedo calibration only")
    ap.add_argument("--uncalibrated-too", action="store_true", help="each size calibrated and without calibration")
    ap.add_argument(
        "--no-lobe",
        dest="lobe",
        action="store_false",
        help="skip the table of coated gold's lobe at the terminator (its reference walks take a minute)",
    )
    ap.add_argument("--lobe-walks", type=int, default=LOBE_WALKS, help="reference walks per pair of that table")
    ap.add_argument("--reference-cache", type=Path, default=None, help="NPZ of the reference render (read or written)")
    ap.add_argument(
        "--max-bounces",
        type=int,
        default=None,
        help="Max Bounces of both renders (default: the renderer's); 0 measures the spheres' direct light alone, "
        "without the floor's bounce light, which both modes render alike and which pulls every ratio towards 1",
    )
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "terminator.md")
    a = ap.parse_args(argv)
    if a.samples < 2 or a.width < 8 or a.height < 8 or a.lobe_walks < 2:
        ap.error(
            f"--samples and --lobe-walks must be >= 2 and --width, --height >= 8; got {a.samples}, {a.lobe_walks}, "
            f"{a.width}, {a.height}"
        )
    cmd = "python benchmarks/bench_terminator.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    scene = terminator_scene(a.width, a.height)
    angles = light_angles(scene, TERMINATOR_PRESETS)
    masks, lows = band_masks(angles)
    pixels = np.flatnonzero(np.any(list(masks.values()), axis=0))  # the spheres' lit sides only
    key = {
        **reference_key(a.width, a.height, a.samples, [a.seed], a.max_bounces),
        "presets": list(TERMINATOR_PRESETS),
        "light": list(TERMINATOR_LIGHT),
    }
    ref_mean, ref_se, secs_ref = reference_film(scene, pixels, a, key)
    ref = object_means(_Film(ref_mean, ref_se), masks)
    calibrations = [False] if a.no_calibrate else ([True, False] if a.uncalibrated_too else [True])
    gold = PRESETS[TERMINATOR_PRESETS[0]]
    lobe_ref, lobe_se = lobe_reference(gold, a.lobe_walks) if a.lobe else (None, None)
    results, first_image = [], None
    for size in a.sizes:
        for calibrate in calibrations:
            film, secs = render_film(scene, "neural", a.samples, a.seed, size, calibrate, pixels, a.max_bounces)
            neural = object_means(film, masks)
            cmp = compare(neural, ref)
            label = (size or "default size") + (", calibrated" if calibrate else ", decoder alone")
            results.append(
                {
                    "label": label,
                    "bands": cmp,
                    "neural": neural,
                    "summary": summary(cmp, lows),
                    "seconds": secs,
                    "lobe": lobe_ratios(gold, size, calibrate, lobe_ref) if a.lobe else None,
                }
            )
            first_image = film.mean() if first_image is None else first_image
            print(f"{label}: done", file=sys.stderr, flush=True)
    png = a.out.with_suffix(".png")
    r0 = results[0]
    lines = [
        "# Grazing light at the terminator: neural mode against reference mode",
        "",
        f"Made by `{cmd}`: `terminator_scene` (`addon/core/render/demo_scene.py`: coated gold and red car paint "
        f"under one point light nearly level with them, no sky) at {a.width} x {a.height}, {a.samples} samples per "
        "pixel, only the spheres' lit pixels, "
        + (
            "default render settings otherwise. "
            if a.max_bounces is None
            else f"Max Bounces {a.max_bounces}"
            + (" (direct light alone: no floor bounce to dilute the ratios)" if a.max_bounces == 0 else "")
            + ", default render settings otherwise. "
        )
        + "Per sphere and band of the angle "
        "between the surface normal and the light: the mean radiance of its pixels, neural / reference, with its "
        "standard error from the per-pixel variance of both renders. A decoder that reflects too much grazing "
        "light shows as ratios over 1 in the bands from 80 degrees: the bright line along the terminator.",
        "",
        "## Summary",
        "",
        "| neural mode | largest ratio, 80-90 deg | median / max abs(ratio - 1), 80-90 deg | "
        "median / max abs(ratio - 1), 0-80 deg | neural seconds |",
        "|---|---|---|---|---|",
        *(
            f"| {r['label']} | {r['summary']['grazing_max_ratio']:.2f} | "
            f"{r['summary']['grazing_median_abs_deviation']:.3f} / {r['summary']['grazing_max_abs_deviation']:.3f} | "
            f"{r['summary']['lit_median_abs_deviation']:.3f} / {r['summary']['lit_max_abs_deviation']:.3f} | "
            f"{r['seconds']:.0f} |"
            for r in results
        ),
        "",
        f"Reference render: {secs_ref:.0f} s (a shared 2-core CPU; calibrations are part of the neural seconds).",
        "",
        "## Ratio per band",
        "",
        *band_table(results, list(masks)),
        "",
        *lobe_table(results, lobe_ref, lobe_se, a.lobe_walks),
        f"## {r0['label']}, in full",
        "",
        *table(r0["bands"], ref),
        "",
        f"![neural, reference, ratio]({png.name}) {r0['label']}. Left: neural; middle: reference; right: their "
        "ratio (grey 1, white 2 or more, black 0), on the rendered pixels.",
        "",
    ]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(lines) + "\n")
    a.out.with_suffix(".json").write_text(
        json.dumps({"command": cmd, "reference": ref, "reference_seconds": secs_ref, "results": results}, indent=1)
        + "\n"
    )
    h, w = a.height, a.width
    on = np.zeros(h * w, dtype=bool)
    on[pixels] = True
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = first_image.mean(-1) / ref_mean.mean(-1)
    ratio_img = np.where(on.reshape(h, w) & np.isfinite(ratio), np.clip(ratio, 0.0, 2.0) / 2.0, 0.0)
    ratio_img = np.repeat(ratio_img[..., None], 3, axis=2) ** 2.2  # linear, so that the PNG's grey reads 1
    exposure = 0.8 / max(float(np.percentile(ref_mean.reshape(-1, 3)[on].mean(-1), 99)), 1e-6)
    gap = np.ones((h, 2, 3))
    side = np.concatenate([first_image * exposure, gap, ref_mean * exposure, gap, ratio_img], axis=1)
    write_png(png, side)
    print("\n".join(lines))


if __name__ == "__main__":
    main()

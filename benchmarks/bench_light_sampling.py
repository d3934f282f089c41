"""Rectangle lights sampled by the solid angle they fill against by area: noise and time, written to
docs/light_sampling.md.

    python benchmarks/bench_light_sampling.py [--seeds 8] [--rounds 3] [--out docs/light_sampling.md]

The demo's tilted area light (``AreaLight(solid_angle=...)``, the one switch between the two) over:

- a Lambertian floor seen by the demo's camera, direct light only (160 x 90, 8 spp): what next-event estimation
  alone gives, the floor 3-5 of the light's radii away from it;
- the demo scene (240 x 135, 16 spp, 4 bounces): spheres of layered materials, the sky, the textured floor.

Noise: each pixel's variance over ``--seeds`` renders of the same seeds in both ways, then its mean and median over
the image (the two ways' images must agree: their means are printed). Time: the demo at 480 x 270, 16 spp,
4 bounces, the two ways alternating in one process, ``--rounds`` rounds, the best of three renders each.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


TABLE_HEAD = (
    "| scene | image mean, by area / by solid angle | variance, by area (mean) | by solid angle (mean) "
    "| by area / by solid angle | by area (median) | by solid angle (median) |\n|---|---|---|---|---|---|---|"
)


def _with_sampling(scene, solid_angle: bool):
    """``scene`` with its area lights sampled by solid angle or by area."""
    from addon.core.render import AreaLight

    lights = [
        dataclasses.replace(li, solid_angle=solid_angle) if isinstance(li, AreaLight) else li for li in scene.lights
    ]
    return dataclasses.replace(scene, lights=lights)


def _floor_scene():
    from addon.core.render import LambertMaterial, Scene, shapes
    from addon.core.render.demo_scene import demo_scene

    demo = demo_scene(160, 90)
    floor = shapes.quad((0.0, 0.0, 0.0), (20.0, 0.0, 0.0), (0.0, 20.0, 0.0))
    return Scene(demo.camera, floor, [LambertMaterial((0.8, 0.8, 0.8))], [demo.lights[0]])


def pixel_variance(scene, settings, seeds: int) -> tuple[float, float, float]:
    """(image mean, mean and median of each pixel's variance over ``seeds`` renders)."""
    from addon.core.render import render

    images = np.stack(
        [
            render(scene, dataclasses.replace(settings, seed=s))[0].rgba()[..., :3].astype(np.float64)
            for s in range(1, seeds + 1)
        ]
    )
    v = images.var(axis=0, ddof=1)
    return float(images.mean()), float(v.mean()), float(np.median(v))


def render_seconds(scene, settings, renders: int = 3) -> float:
    """The best of ``renders`` renders' seconds."""
    from addon.core.render import render

    best = np.inf
    for i in range(renders):
        t = time.perf_counter()
        render(scene, dataclasses.replace(settings, seed=i))
        best = min(best, time.perf_counter() - t)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "light_sampling.md")
    args = ap.parse_args(argv)
    from addon.core.render import RenderSettings
    from addon.core.render.demo_scene import demo_scene

    cases = [
        ("Lambertian floor, direct light (160 x 90, 8 spp)", _floor_scene(), RenderSettings(samples=8, max_bounces=0)),
        ("demo scene (240 x 135, 16 spp, 4 bounces)", demo_scene(240, 135), RenderSettings(samples=16, max_bounces=4)),
    ]
    rows = []
    for name, scene, settings in cases:
        got = {way: pixel_variance(_with_sampling(scene, way), settings, args.seeds) for way in (False, True)}
        (mean_a, var_a, med_a), (mean_s, var_s, med_s) = got[False], got[True]
        rows.append(
            f"| {name} | {mean_a:.4f} / {mean_s:.4f} | {var_a:.3g} | {var_s:.3g} | **{var_a / var_s:.2f}x** | "
            f"{med_a:.3g} | {med_s:.3g} |"
        )
        print(rows[-1], flush=True)
    demo = demo_scene(480, 270)
    timing = RenderSettings(samples=16, max_bounces=4)
    render_seconds(demo, dataclasses.replace(timing, samples=1), renders=1)  # compiled, warmed
    seconds = {False: [], True: []}
    for _ in range(args.rounds):
        for way in (False, True):
            seconds[way].append(render_seconds(_with_sampling(demo, way), timing))
    area, solid = seconds[False], seconds[True]
    ratio = np.median(solid) / np.median(area)
    print(f"time by area {area}, by solid angle {solid}", flush=True)
    flags = (f" --seeds {args.seeds}" if args.seeds != 8 else "") + (
        f" --rounds {args.rounds}" if args.rounds != 3 else ""
    )
    args.out.write_text(
        f"""# Rectangle lights: by solid angle or by area

Written by `python benchmarks/bench_light_sampling.py{flags}`: the demo's tilted area light sampled by the solid
angle it fills (Ureña et al. 2013, as Cycles samples it; the renderer's way) and by area (its way before), the same
{args.seeds} seeds each way. Variance: of each pixel over the seeds, its mean and median over the image.

{TABLE_HEAD}
"""
        + "\n".join(rows)
        + f"""

The demo at 480 x 270, 16 spp, 4 bounces, alternating in one process, {args.rounds} rounds, the best of three
renders each: by area {min(area):.3f}-{max(area):.3f} s, by solid angle {min(solid):.3f}-{max(solid):.3f} s: solid
angle takes **{ratio:.3f}x** the time (a sample by solid angle costs some 60 ns more: a Van Oosterom-Strackee solid
angle, one arc tangent, and Ureña's warp, a few roots).
"""
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Stacks nobody chose: neural mode against the reference's albedo in a white sky, and the reference against itself.

    python benchmarks/bench_stack_sweep.py

The fidelity and terminator benchmarks measure the presets. Users make other stacks, so this one draws them at
random (seeded) and renders each where its error shows plainly: a plane alone in a white sky (radiance 1 from
every direction), seen through a narrow camera at a few view angles, direct light only. A pixel's radiance is then
the material's directional albedo at the view, whose truth the reference's analog walks give without next-event
estimation (``reference.albedo``). Two groups of stacks:

- **trained ranges**: 1-3 coatings drawn as the training stacks are (``onnx_export.data.sample_layered_params``, a
  seed the training does not use): what the networks saw;
- **valid ranges**: values an artist may type beyond them: smooth and near-smooth surfaces (alpha 0 or 0.005), any
  ior from 1 to 3.5 (index-matched coats), thick media (to 30) and anisotropic phase functions, which the
  networks see clamped (``stack.clamp_to_trained``).

Neural mode renders with the renderer's defaults (decoder size, albedo calibration). A pair counts as *off* when a
channel is more than 10% and 0.01 away from the reference. The third section checks the reference's own two
estimators against each other on random stacks (``reference.eval_brdf`` integrated over cosine-distributed
directions against the analog walk's non-delta albedo), as ``tests/core/test_reference.py`` does on fewer.

Writes ``--out`` (markdown, with this command) and a JSON beside it. About 10 minutes on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core import reference  # noqa: E402
from addon.core.render import Camera, Environment, RenderSettings, Scene, render, shapes  # noqa: E402
from addon.core.render.materials import LayeredSpec  # noqa: E402
from addon.core.stack import Coating, Conductor, Dielectric, Diffuse, Stack  # noqa: E402
from onnx_export.data import sample_layered_params  # noqa: E402

VIEWS_DEG = (20.0, 60.0, 80.0)
OFF_RATIO, OFF_ABS = 0.10, 0.01
SWEEP_SEED = 90210  # not a training or validation seed


def trained_stacks(n: int, seed: int) -> list[Stack]:
    """``n`` stacks of 1-3 coatings drawn as the training's (equal counts of each depth)."""
    rng = np.random.default_rng(seed)
    out = []
    for c in (1, 2, 3):
        k = n // 3 + (1 if c <= n % 3 else 0)
        a = sample_layered_params(rng, k, c)
        out += [a.stack(i) for i in range(k)]
    return out


def valid_stacks(n: int, seed: int) -> list[Stack]:
    """``n`` stacks of 1-2 coatings with values beyond the trained ranges as often as inside them."""
    rng = np.random.default_rng(seed)

    def alpha():
        return float(rng.choice([0.0, 0.005, math.exp(rng.uniform(math.log(0.01), 0.0))]))

    def ior():
        return float(rng.choice([rng.uniform(1.0, 1.05), rng.uniform(1.05, 2.0), rng.uniform(2.0, 3.5)]))

    out = []
    for _ in range(n):
        kind = rng.integers(3)
        if kind == 0:
            base = Diffuse(tuple(rng.uniform(0.0, 1.0, 3)))
        elif kind == 1:
            base = Conductor(alpha(), eta=tuple(rng.uniform(0.1, 3.0, 3)), k=tuple(rng.uniform(0.5, 6.0, 3)))
        else:
            base = Dielectric(alpha(), float(rng.uniform(1.0, 3.5)))
        coats = []
        for _ in range(rng.integers(1, 3)):
            medium = tuple(rng.uniform(0.0, 1.0, 3)) if rng.random() < 0.6 else 0.0
            thickness = (
                float(rng.choice([rng.uniform(0.0, 5.0), rng.uniform(5.0, 30.0)])) if rng.random() < 0.7 else 0.0
            )
            coats.append(Coating(alpha(), ior(), medium, thickness, float(rng.uniform(-0.9, 0.9))))
        out.append(Stack(base, tuple(coats)))
    return out


def white_sky_albedo(stack: Stack, view_deg: float, mode: str, samples: int, seed: int) -> np.ndarray:
    """The mean radiance (3,) of a plane of ``stack`` alone in a white sky, seen at ``view_deg`` from its normal
    through a 1-degree camera (8 x 8 pixels), direct light only: its directional albedo there."""
    t = math.radians(view_deg)
    cam = Camera.look_at((0.0, -20.0 * math.sin(t), 20.0 * math.cos(t)), (0, 0, 0), fov_deg=1.0, width=8, height=8)
    scene = Scene(
        cam, shapes.quad((0, 0, 0), (20, 0, 0), (0, 20, 0)), [LayeredSpec(stack)], [], Environment((1.0,) * 3)
    )
    film, _ = render(scene, RenderSettings(samples=samples, max_bounces=0, seed=seed, mode=mode))
    return film.mean().reshape(-1, 3).mean(axis=0).astype(np.float64)


def sweep(stacks: list[Stack], samples: int, walks: int, log) -> list[dict]:
    rows = []
    for i, stack in enumerate(stacks):  # a loop over stacks, each render vectorised over its paths
        for view in VIEWS_DEG:
            t = math.radians(view)
            truth, _ = reference.albedo(stack, np.array([[0.0, -math.sin(t), math.cos(t)]]), samples=walks, seed=i)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the clamp notes of out-of-range stacks: every row has some
                got = white_sky_albedo(stack, view, "neural", samples, seed=i)
            ratio = got / np.maximum(truth[0], 1e-12)
            off = bool(np.any((np.abs(ratio - 1.0) > OFF_RATIO) & (np.abs(got - truth[0]) > OFF_ABS)))
            rows.append(
                {
                    "stack": stack.to_json(),
                    "view": view,
                    "neural": got.tolist(),
                    "reference": truth[0].tolist(),
                    "worst": float(np.max(np.abs(ratio - 1.0) * (np.maximum(got, truth[0]) > OFF_ABS))),
                    "off": off,
                }
            )
        log(f"{i + 1}/{len(stacks)} stacks")
    return rows


def estimator_check(n: int, directions: int, seed: int, log) -> list[dict]:
    """``reference.eval_brdf`` against the analog walk on ``n`` random stacks of the test's draw (half of the
    surfaces smooth): z-scores of their difference per channel."""
    sys.path.insert(0, str(ROOT / "tests" / "core"))
    from test_reference import analog_albedo, direction, eval_albedo, random_layered_stack

    out = []
    for i in range(n):  # a loop over stacks, each estimate vectorised over its walks
        rng = np.random.default_rng(seed + i)
        stack = random_layered_stack(rng)
        wo = direction(float(rng.uniform(0.0, 75.0)))
        a, sa = analog_albedo(stack, wo, directions, seed=i)
        e, se = eval_albedo(stack, wo, directions, seed=i + 100_000)
        z = (e - a) / np.maximum(np.sqrt(sa**2 + se**2), 1e-12)
        out.append({"stack": stack.to_json(), "z": z.tolist(), "eval": e.tolist(), "walk": a.tolist()})
        if (i + 1) % 25 == 0:
            log(f"{i + 1}/{n} estimator checks")
    return out


def _summary(rows: list[dict]) -> str:
    worst = np.array([r["worst"] for r in rows])
    off = sum(r["off"] for r in rows)
    return (
        f"| {len(rows)} | {np.median(worst):.3f} | {np.percentile(worst, 90):.3f} | {worst.max():.3f} | "
        f"{off} ({100.0 * off / len(rows):.0f}%) |"
    )


def describe(stack: Stack) -> str:
    """A stack in a line, bottom to top: the base and each coating's alpha, ior, optical thickness with its mean
    single-scattering albedo, and g where it is not 0 (the JSON beside the report holds every value)."""
    b = stack.base
    parts = [f"{type(b).__name__} a {b.roughness:.3g}" if hasattr(b, "roughness") else "Diffuse"]
    if isinstance(b, Dielectric):
        parts[0] += f" ior {b.ior:.3g}"
    for c in stack.coatings:
        text = f"coat a {c.roughness:.3g} ior {c.ior:.3g}"
        if c.thickness > 0:
            text += f" tau {c.thickness:.3g} albedo {np.mean(c.albedo):.2f}"
            text += f" g {c.g:.2f}" if c.g else ""
        parts.append(text)
    return " / ".join(parts)


def _worst_rows(rows: list[dict], k: int) -> list[str]:
    out = []
    for r in sorted(rows, key=lambda r: -r["worst"])[:k]:
        n, ref = np.round(r["neural"], 3).tolist(), np.round(r["reference"], 3).tolist()
        out.append(f"| {r['worst']:.2f} | {r['view']:.0f} | {n} | {ref} | {describe(Stack.from_json(r['stack']))} |")
    return out


def report(cmd: str, groups: dict, checks: list[dict], seconds: float, samples: int, walks: int) -> str:
    lines = [
        "# Stacks nobody chose: neural mode and the reference on random stacks",
        "",
        f"Command: `{cmd}`",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU threads, no GPU; "
        f"{seconds / 60:.0f} minutes.",
        "",
        "Each stack is a plane alone in a white sky, seen at "
        + ", ".join(f"{v:.0f}" for v in VIEWS_DEG)
        + f" degrees from its normal, direct light only, {samples} samples per pixel on 8 x 8 pixels in neural mode "
        f"(the renderer's defaults: decoder size and albedo calibration); the truth is the directional albedo of "
        f"{walks} analog walks of the reference. *worst*: the largest |neural / reference - 1| over the channels "
        f"(channels where both are below {OFF_ABS} left out); *off*: a channel more than {OFF_RATIO:.0%} and "
        f"{OFF_ABS} away. The stacks are drawn by `benchmarks/bench_stack_sweep.py` (module docstring).",
        "",
        "## Neural mode against the reference's albedo",
        "",
        "| stacks | view/stack pairs | median worst | 90th percentile | max | off |",
        "|---|---|---|---|---|---|",
    ]
    for name, rows in groups.items():
        lines.append(f"| {name} " + _summary(rows))
    for name, rows in groups.items():
        lines += [
            "",
            f"### The ten worst pairs, {name}",
            "",
            "| worst | view deg | neural | reference | stack |",
            "|---|---|---|---|---|",
            *_worst_rows(rows, 10),
        ]
    z = np.array([np.max(np.abs(c["z"])) for c in checks])
    lines += [
        "",
        "## The reference against itself",
        "",
        f"{len(checks)} stacks of `tests/core/test_reference.py`'s draw (`random_layered_stack`: 1-3 coatings, half "
        "of the surfaces smooth, neighbouring indices 0.1 apart or more, rough transmission lobes at least "
        "`MIN_TRANSMISSION_WIDTH` wide), a view from "
        "0 to 75 degrees each: `eval_brdf`'s albedo (pi f over cosine-distributed directions) against the analog "
        "walk's over its non-delta paths, as z-scores of their difference (the largest over the channels).",
        "",
        "| stacks | median max abs(z) | above 3 | above 4 | largest |",
        "|---|---|---|---|---|",
        f"| {len(z)} | {np.median(z):.2f} | {int((z > 3).sum())} | {int((z > 4).sum())} | {z.max():.1f} |",
        "",
        "Normal noise alone would put 0.3% (channels fully correlated) to 0.8% (independent) of the stacks above 3, "
        "and under 0.02% above 4.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trained", type=int, default=60, help="stacks drawn over the trained ranges")
    ap.add_argument("--valid", type=int, default=60, help="stacks drawn over the valid ranges")
    ap.add_argument("--checks", type=int, default=200, help="stacks of the reference's own check")
    ap.add_argument("--samples", type=int, default=128, help="samples per pixel of the neural renders")
    ap.add_argument("--walks", type=int, default=30000, help="analog walks of each reference albedo")
    ap.add_argument("--directions", type=int, default=20000, help="directions of each estimator check")
    ap.add_argument("--seed", type=int, default=SWEEP_SEED)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "stack_sweep.md")
    a = ap.parse_args(argv)
    if min(a.trained, a.valid, a.checks) < 1 or a.samples < 1 or a.walks < 1 or a.directions < 1:
        ap.error("the counts must be positive")
    cmd = " ".join(["python benchmarks/bench_stack_sweep.py", *(shlex.quote(x) for x in (argv or sys.argv[1:]))])

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    groups = {
        "trained ranges": sweep(trained_stacks(a.trained, a.seed), a.samples, a.walks, log),
        "valid ranges": sweep(valid_stacks(a.valid, a.seed + 1), a.samples, a.walks, log),
    }
    checks = estimator_check(a.checks, a.directions, a.seed + 2, log)
    text = report(cmd, groups, checks, time.perf_counter() - t0, a.samples, a.walks)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(text)
    a.out.with_suffix(".json").write_text(json.dumps({"command": cmd, **groups, "checks": checks}, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()

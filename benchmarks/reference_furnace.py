"""White furnace of the reference at every valid coat thickness, and how long its walks are.

    python benchmarks/reference_furnace.py            # writes docs/reference_furnace.md
    python benchmarks/reference_furnace.py --quick    # fewer walks, same output

1. The directional albedo (30 degrees) of a white Lambertian base under one ior-1.5 coat with a
   white (non-absorbing) medium, for coat thickness 0, 1, 5, 20 and 100 and roughness 0 and 0.3,
   with its standard error and time; beside it, the same walks cut at 256 events (the depth cap
   the walk had before it ended walks by Russian roulette only).
2. Walk lengths at thickness 100, smooth coat, white base: the mean and the longest number of
   events per walk, the fraction of walks (= of the energy, every walk carries weight 1 there)
   still inside after n events, and the decay time of that tail, for ior 1.5 / g 0 and for the
   slowest corner of the valid range (ior 4, g -0.99).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core import reference  # noqa: E402
from addon.core.reference import walk  # noqa: E402
from addon.core.stack import Coating, Diffuse, Stack, StackArrays  # noqa: E402
from addon.core.xp import Rng  # noqa: E402

THICKNESS = (0.0, 1.0, 5.0, 20.0, 100.0)
OLD_CAP = 256
WO = np.array([[np.sin(np.radians(30.0)), 0.0, np.cos(np.radians(30.0))]])
MARKS = (256, 1000, 10_000, 50_000, 100_000)


def white(roughness: float, thickness: float, ior: float = 1.5, g: float = 0.0) -> Stack:
    return Stack(Diffuse(1.0), (Coating(roughness, ior, 1.0, thickness, g),))


def furnace_row(roughness: float, thickness: float, walks: int) -> dict:
    stack = white(roughness, thickness)
    t0 = time.perf_counter()
    a, se = reference.albedo(stack, WO, samples=walks, seed=1)
    seconds = time.perf_counter() - t0
    cap = walk.MAX_DEPTH
    walk.MAX_DEPTH = OLD_CAP
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            old, old_se = reference.albedo(stack, WO, samples=walks, seed=1)
    finally:
        walk.MAX_DEPTH = cap
    return dict(
        roughness=roughness,
        thickness=thickness,
        walks=walks,
        albedo=float(a[0, 0]),
        se=float(se[0, 0]),
        seconds=seconds,
        old=float(old[0, 0]),
        old_se=float(old_se[0, 0]),
    )


def walk_lengths(ior: float, g: float, walks: int) -> dict:
    stack = white(0.0, 100.0, ior, g)
    lay = walk.Layers.from_arrays(StackArrays.from_stacks([stack]))
    alive = []
    t0 = time.perf_counter()
    _, w, _ = walk.run_walks(
        lay,
        np.zeros(walks, dtype=np.int64),
        np.repeat(WO, walks, axis=0),
        None,
        Rng(np, 2),
        nee=False,
        alive_per_event=alive,
    )
    seconds = time.perf_counter() - t0
    alive = np.array([walks] + alive, dtype=np.float64)  # alive[n]: walks inside after n events
    frac = alive / walks
    # decay time of the tail: a log-linear fit from 10% inside down to the last 5 walks
    lo = int(np.argmax(frac <= 0.1))
    hi = int(np.flatnonzero(alive >= 5)[-1])
    tau = float("nan")
    if hi > lo + 10:
        slope = np.polyfit(np.arange(lo, hi + 1), np.log(frac[lo : hi + 1]), 1)[0]
        tau = -1.0 / slope if slope < 0 else float("inf")
    at_cap = frac[hi] * np.exp(-(walk.MAX_DEPTH - hi) / tau) if np.isfinite(tau) else float("nan")
    return dict(
        ior=ior,
        g=g,
        walks=walks,
        albedo=float(w[:, 0].mean()),
        mean=float(alive[1:].sum() / walks),
        longest=len(alive) - 1,
        seconds=seconds,
        inside={m: float(frac[m]) if m < len(frac) else 0.0 for m in MARKS},
        tau=tau,
        at_cap=float(at_cap),
    )


def write(path: Path, rows: list[dict], lengths: list[dict], command: str) -> None:
    out = [
        "# White furnace of the reference at every valid thickness",
        "",
        f"Written by `{command}` ({platform.machine()}, numpy {np.__version__}, shared CPU: times are noisy).",
        "",
        "A white Lambertian base under one ior-1.5 coat whose medium does not absorb (albedo 1, g 0),",
        "directional albedo at 30 degrees from the analog walk (`reference.albedo`, seed 1). With a smooth",
        "coat every event conserves energy, so the albedo must be exactly 1 with a standard error of 0 (every",
        "walk returns weight 1). A rough coat (alpha 0.3) loses the energy of multiple microfacet bounces at",
        "each interface event (single-scattering microfacet model), so its albedo is below 1 by design.",
        f'"cut at {OLD_CAP}" is the same walks ended after {OLD_CAP} events, as the walk did before it ended',
        "walks by Russian roulette only.",
        "",
        f"| roughness | thickness | walks | albedo | std. error | time (s) | cut at {OLD_CAP} |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['roughness']:g} | {r['thickness']:g} | {r['walks']} | {r['albedo']:.6f} | {r['se']:.2g} | "
            f"{r['seconds']:.1f} | {r['old']:.4f} ± {r['old_se']:.2g} |"
        )
    out += [
        "",
        "## Walk lengths at thickness 100 (smooth coat, white base)",
        "",
        "Every walk carries weight 1 here, so the fraction of walks still inside after n events is the",
        'fraction of the energy a depth cap at n would lose. The tail decays exponentially; "at the cap"',
        f"extrapolates it to the safety cap `MAX_DEPTH` = {walk.MAX_DEPTH} events.",
        "",
        "| ior | g | walks | albedo | mean events | longest | "
        + " | ".join(f"inside after {m}" for m in MARKS)
        + " | decay time (events) | at the cap | time (s) |",
        "|---|---|---|---|---|---|" + "---|" * len(MARKS) + "---|---|---|",
    ]
    for r in lengths:
        inside = " | ".join(f"{r['inside'][m]:.2g}" for m in MARKS)
        out.append(
            f"| {r['ior']:g} | {r['g']:g} | {r['walks']} | {r['albedo']:.6f} | {r['mean']:.0f} | "
            f"{r['longest']} | {inside} | {r['tau']:.3g} | {r['at_cap']:.1g} | {r['seconds']:.0f} |"
        )
    path.write_text("\n".join(out) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer walks (same output file)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "reference_furnace.md")
    args = ap.parse_args(argv)
    smooth, rough, thick = (128, 512, 32) if args.quick else (1000, 4000, 256)
    rows = []
    for roughness, walks in ((0.0, smooth), (0.3, rough)):
        for t in THICKNESS:
            rows.append(furnace_row(roughness, t, walks if t < 100.0 else thick))
            print(rows[-1], flush=True)
    lengths = []
    for ior, g, walks in ((1.5, 0.0, 200 if args.quick else 1000), (4.0, -0.99, 30 if args.quick else 100)):
        lengths.append(walk_lengths(ior, g, walks))
        print(lengths[-1], flush=True)
    command = "python benchmarks/reference_furnace.py" + (" --quick" if args.quick else "")
    write(args.out, rows, lengths, command)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

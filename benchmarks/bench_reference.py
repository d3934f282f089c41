"""Speed and noise of the position-free Monte Carlo reference (addon/core/reference).

    python benchmarks/bench_reference.py            # writes docs/reference_benchmark.md and .png
    python benchmarks/bench_reference.py --quick    # smaller runs, same outputs
    python benchmarks/bench_reference.py --backend torch [--device cuda] [--quick]
        # walks per second only, numpy next to the backend: docs/reference_benchmark_<backend>.md

Measures, on this machine's CPU with numpy:

1. walks per second of ``eval_brdf`` (NEE estimator, one lobe grid of pairs) and of the analog
   walk (``albedo``) for every preset;
2. the standard error against the walk count (median relative standard error over a lobe
   grid), which should fall as 1/sqrt(walks);
3. the cost of a reference lobe image (f cos on the projected hemisphere, docs/architecture.md, Measurement)
   at 1% noise (relative RMS of the per-pixel standard error), extrapolated from a pilot run
   with the measured 1/sqrt(walks) law, for the plain estimator (one walk per pixel and
   walk count) and the amortised one (``eval_brdf_many``: each walk from the incident
   direction serves every pixel, by reciprocity).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core import lobe, reference  # noqa: E402
from addon.core.stack import PRESETS  # noqa: E402


def lobe_pairs(res: int, theta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    wo, mask = lobe.lobe_grid(res)
    wo = wo[mask]
    wi = np.broadcast_to(lobe.incident_direction(theta), wo.shape).copy()
    return wi, wo, wo[:, 2]


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def lobe_noise(f: np.ndarray, se: np.ndarray, cos_o: np.ndarray) -> float:
    """Relative RMS noise of a lobe image: RMS(se cos) / RMS(f cos) over pixels and channels."""
    num = np.sqrt(np.mean((se * cos_o[:, None]) ** 2))
    den = np.sqrt(np.mean((f * cos_o[:, None]) ** 2))
    return float(num / den) if den > 0 else float("inf")


def backend_speed(args) -> int:
    """Walks per second of every preset with numpy and with ``args.backend`` (same calls)."""
    q = args.quick
    res = 16 if q else 24
    walks = 32 if q else 64
    k = 20000 if q else 60000
    be = dict(backend=args.backend, device=args.device)
    dev = args.device or ("cpu" if args.backend == "torch" else "cuda")
    cmd = (
        f"python benchmarks/bench_reference.py --backend {args.backend}"
        + (f" --device {args.device}" if args.device else "")
        + (f" --threads {args.threads}" if args.threads else "")
        + (" --quick" if q else "")
    )
    if args.backend == "torch":
        import torch

        if args.threads:
            torch.set_num_threads(args.threads)
        dev += f", torch {torch.__version__}, CPU threads: {torch.get_num_threads()}"
    lines = [
        f"# Reference walks per second: numpy and {args.backend} ({dev})",
        "",
        f"Command: `{cmd}` (numpy {np.__version__}, Python {platform.python_version()}, {platform.machine()}).",
        "The same source runs on both (`addon/core/xp.py`); timings from a shared machine: rough.",
        f"`eval_brdf`: a {res}x{res} lobe grid at 30 degrees x {walks} walks per pixel; analog: `albedo`, "
        f"{k} walks from one direction. Each is timed after one small warm-up call.",
        "",
        f"| preset | coatings | eval numpy | eval {args.backend} | analog numpy | analog {args.backend} |",
        "|---|---|---|---|---|---|",
    ]
    wd = lobe.incident_direction(30.0)[None]
    for name, stack in PRESETS.items():
        wi, wo, _ = lobe_pairs(res, 30.0)
        row = []
        for kw in ({}, be):
            reference.eval_brdf(stack, wi[:8], wo[:8], walks=2, seed=0, **kw)  # warm-up
            _, dt = timed(lambda: reference.eval_brdf(stack, wi, wo, walks=walks, seed=1, **kw))
            _, dt_a = timed(lambda: reference.albedo(stack, wd, samples=k, seed=2, **kw))
            row.append((wi.shape[0] * walks / dt, k / dt_a))
        lines.append(
            f"| {name} | {len(stack.coatings)} | {row[0][0]:,.0f} | {row[1][0]:,.0f} | "
            f"{row[0][1]:,.0f} | {row[1][1]:,.0f} |"
        )
        print(lines[-1], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"reference_benchmark_{args.backend}.md"
    path.write_text("\n".join(lines) + "\n")
    print(f"wrote {path}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller runs (noisier figures)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument(
        "--backend",
        choices=("numpy", "torch", "cupy"),
        default="numpy",
        help="array library of the walks; other than numpy: walks/s only, next to numpy's",
    )
    ap.add_argument("--device", default=None, help="cpu, cuda or cuda:N (torch, cupy)")
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch.set_num_threads(N) for --backend torch on the CPU (1 on a shared machine)",
    )
    args = ap.parse_args(argv)
    if args.backend != "numpy":
        return backend_speed(args)
    q = args.quick
    res = 16 if q else 24
    pilot_walks = 32 if q else 64
    cmd = "python benchmarks/bench_reference.py" + (" --quick" if q else "")
    lines = [
        "# Reference (position-free Monte Carlo) benchmark",
        "",
        f"Command: `{cmd}` (numpy {np.__version__}, Python {platform.python_version()}, "
        f"{platform.machine()}, numpy backend; `--backend torch|cupy` measures the others).",
        "Timings come from a shared 2-core machine with other work running: treat them as rough.",
        "",
        "## Walks per second",
        "",
        f"`eval_brdf`: a {res}x{res} lobe grid at 30 degrees incidence x {pilot_walks} walks per pixel "
        "(one walk = one full random walk with its next-event connections); analog walk: `albedo` "
        "from one direction.",
        "",
        "| preset | coatings | eval walks/s | analog walks/s | lobe noise at pilot |",
        "|---|---|---|---|---|",
    ]
    speed: dict[str, float] = {}
    for name, stack in PRESETS.items():
        wi, wo, cos_o = lobe_pairs(res, 30.0)
        (f, se), dt = timed(lambda: reference.eval_brdf(stack, wi, wo, walks=pilot_walks, seed=1))
        n_walks = wi.shape[0] * pilot_walks
        speed[name] = n_walks / dt
        k = 20000 if q else 60000
        _, dt_a = timed(lambda: reference.albedo(stack, lobe.incident_direction(30.0)[None], samples=k, seed=2))
        lines.append(
            f"| {name} | {len(stack.coatings)} | {speed[name]:,.0f} | {k / dt_a:,.0f} | "
            f"{lobe_noise(f, se, cos_o):.3f} |"
        )
        print(f"{name}: {speed[name]:,.0f} eval walks/s, {k / dt_a:,.0f} analog walks/s", flush=True)

    # ---- standard error against walk count
    counts = [8, 32, 128, 512] if q else [8, 32, 128, 512, 2048]
    chosen = ["lacquered_plastic", "varnished_wood", "red_car_paint", "three_layer"]
    curves: dict[str, list[float]] = {}
    sres = 8 if q else 12
    for name in chosen:
        wi, wo, cos_o = lobe_pairs(sres, 30.0)
        curves[name] = []
        for w in counts:
            f, se = reference.eval_brdf(PRESETS[name], wi, wo, walks=w, seed=3)
            curves[name].append(lobe_noise(f, se, cos_o))
        print(f"stderr curve {name}: {np.round(curves[name], 4)}", flush=True)
    lines += [
        "",
        "## Standard error against walk count",
        "",
        f"Relative RMS standard error of a {sres}x{sres} lobe image at 30 degrees (see the chart "
        "`reference_stderr.png`); 1/sqrt(walks) is the expected slope.",
        "",
        "| preset | " + " | ".join(f"{w} walks" for w in counts) + " |",
        "|---|" + "---|" * len(counts),
    ]
    for name in chosen:
        lines.append(f"| {name} | " + " | ".join(f"{v:.4f}" for v in curves[name]) + " |")

    # ---- cost of a lobe image at 1% noise
    lres = 32
    lines += [
        "",
        "## Cost of a reference lobe image at 1% noise",
        "",
        f"A {lres}x{lres} lobe image (the disk's pixels); pilot runs, then walks needed = pilot walks x "
        "(noise / 0.01)^2 and seconds = pilot seconds x that ratio. *Plain*: `eval_brdf` with the "
        "same walks for every pixel. *Amortised*: `eval_brdf_many`, walks from the incident "
        "direction connecting to every pixel (reciprocity).",
        "",
        "| preset | theta_i | plain: walks/pixel | plain: s | amortised: walks | amortised: s | speed-up |",
        "|---|---|---|---|---|---|---|",
    ]
    thetas = (30.0,) if q else (0.0, 60.0)
    amort_walks = 128 if q else 512
    for name in PRESETS:
        for theta in thetas:
            wi, wo, cos_o = lobe_pairs(lres, theta)
            npix = wi.shape[0]
            (f, se), dt = timed(lambda: reference.eval_brdf(PRESETS[name], wi, wo, walks=pilot_walks // 2, seed=4))
            noise = lobe_noise(f, se, cos_o)
            ratio = (noise / 0.01) ** 2
            plain_walks, plain_s = pilot_walks // 2 * ratio, dt * ratio
            (fm, sm), dtm = timed(
                lambda: reference.eval_brdf_many(
                    PRESETS[name], wo[None], lobe.incident_direction(theta)[None], walks=amort_walks, seed=5
                )
            )
            noise_m = lobe_noise(fm[0], sm[0], cos_o)
            ratio_m = (noise_m / 0.01) ** 2
            if noise < 1e-6:
                lines.append(f"| {name} | {theta:.0f} | exact (no coating: the base BSDF) | {dt:.2f} | - | - | - |")
            else:
                lines.append(
                    f"| {name} | {theta:.0f} | {plain_walks:,.0f} | {plain_s:,.1f} | {amort_walks * ratio_m:,.0f} | "
                    f"{dtm * ratio_m:,.1f} | {plain_s / max(dtm * ratio_m, 1e-9):.1f}x |"
                )
            print(
                f"lobe {name} {theta}: plain {plain_s:.1f} s, amortised {dtm * ratio_m:.1f} s ({npix} pixels)",
                flush=True,
            )
    lines += [
        "",
        "Notes: the amortised estimator needs about as many walks *in total* as the plain one needs *per "
        "pixel*, because every walk connects to every pixel; its time is dominated by those connections "
        "(one BSDF evaluation per vertex and pixel), hence the modest speed-up. Presets whose lobes are sharp "
        "(near-specular top coats, red_car_paint's alpha 0.01 top over an alpha 0.15 coat, grazing "
        "incidence) need the most walks. Stacks without coatings are evaluated exactly (zero variance).",
    ]

    # ---- the MIS trap: pbrt-v4's reverse density against the matching one
    from addon.core.reference import walk
    from addon.core.stack import Coating, Diffuse, Stack

    lines += [
        "",
        "## The MIS density trap (docs/architecture.md, Physics traps)",
        "",
        "Directional albedo at normal incidence of a white Lambertian under a rough coat (ior 1.5): the "
        "analog walk (no MIS) against `eval_brdf` integrated over cosine-distributed wi, with the matching "
        "density in the exit strategy's MIS weight (ours) and with pbrt-v4's reverse density "
        '(`walk.EXIT_DENSITY = "pbrt_reverse"`, an ablation).',
        "",
        "| coat alpha | analog walk | eval, matching density | eval, pbrt's reverse density | pbrt bias |",
        "|---|---|---|---|---|",
    ]
    n_alb = 20000 if q else 100000
    u = np.random.default_rng(7).random((n_alb, 2))
    r, phi = np.sqrt(u[:, 0]), 2.0 * np.pi * u[:, 1]
    wi_c = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=1)
    wo_n = np.repeat(np.array([[0.0, 0.0, 1.0]]), n_alb, axis=0)
    for alpha in (0.1, 0.3, 0.6):
        stack = Stack(Diffuse(1.0), (Coating(roughness=alpha, ior=1.5),))
        _, w = reference.sample(stack, wo_n, 8)
        a, sa = w[:, 0].mean(), w[:, 0].std() / np.sqrt(n_alb)
        res = []
        for mode in ("matching", "pbrt_reverse"):
            walk.EXIT_DENSITY = mode
            f, _ = reference.eval_brdf(stack, wi_c, wo_n, walks=1, seed=9)
            e = np.pi * f[:, 0]
            res.append((e.mean(), e.std() / np.sqrt(n_alb)))
        walk.EXIT_DENSITY = "matching"
        lines.append(
            f"| {alpha} | {a:.4f} ± {sa:.4f} | {res[0][0]:.4f} ± {res[0][1]:.4f} | "
            f"{res[1][0]:.4f} ± {res[1][1]:.4f} | {(res[1][0] / a - 1) * 100:+.1f}% |"
        )
        print(f"MIS trap alpha {alpha}: analog {a:.4f}, matching {res[0][0]:.4f}, pbrt {res[1][0]:.4f}", flush=True)

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "reference_benchmark.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for name in chosen:
            ax.loglog(counts, curves[name], "o-", label=name)
        c0 = curves[chosen[0]][0]
        ax.loglog(counts, [c0 * np.sqrt(counts[0] / w) for w in counts], "k--", label="1/sqrt(walks)")
        ax.set_xlabel("walks per pixel")
        ax.set_ylabel("relative RMS standard error of the lobe")
        ax.set_title(f"Reference noise vs walks ({sres}x{sres} lobe, 30 deg)\n{cmd}", fontsize=8)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.out / "reference_stderr.png", dpi=110)
    except ImportError:
        print("matplotlib missing: no chart written")
    print(f"wrote {args.out / 'reference_benchmark.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

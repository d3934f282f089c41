"""Albedo calibration (addon.core.neural.calibrate): what it fixes near the horizon and what it costs.

    python benchmarks/bench_calibration.py --sizes tiny small --out docs/calibration.md

For each decoder size, on the held-out grazing set (``tests/data/heldout_grazing.npz``, 32 held-out
stacks with one to four coatings; ``onnx_export.heldout_grazing``), network / reference ratios with and
without the calibration, as ``tests/training/test_grazing.py`` measures them:

- the median albedo ratio at 75 and 85 degrees per coating count (the albedo bias),
- the largest albedo ratio and the largest f cos(theta_i) ratio (viewer on the normal) at 80-89.5 degrees
  over all stacks (the glow at the terminator);

and, for the presets, the seconds one calibration takes here (reference walks and the decoded lobe).
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from addon.core.neural import calibrate as cal  # noqa: E402
from addon.core.neural import encode_stack, load_models  # noqa: E402
from addon.core.stack import PRESETS  # noqa: E402
from onnx_export.heldout_grazing import GRAZING_ANGLES_DEG, grazing_ratios, load, medians_by_coatings  # noqa: E402

GRAZING = ROOT / "tests" / "data" / "heldout_grazing.npz"


def grazing_rows(size: str, calibrate: bool) -> tuple[dict, dict]:
    """``tests/training/test_grazing.py``'s figures for one size, decoder alone or calibrated: on the lobe grid
    (median albedo ratio per coating count at 75 and 85 degrees, the largest albedo and f cos ratios at
    80-89.5 degrees), and for the directional albedo integrated in full (the decoded lobe by importance
    sampling, the stored analog-walk reference: medians per coating count, the largest ratio at 75 / 85
    degrees and at 80-89.5 degrees)."""
    r = grazing_ratios(load_models(size), load(GRAZING), calibrate=calibrate)
    a = r["angles"]
    near = a >= 80
    grid = {"albedo_max": float(r["albedo"][:, near].max()), "fcos_max": float(r["fcos"][:, near].max())}
    full = {
        "max": float(r["albedo_full"][:, (a == 75.0) | (a == 85.0)].max()),
        "max_grazing": float(r["albedo_full"][:, near].max()),
    }
    for row, key in ((grid, "albedo"), (full, "albedo_full")):
        row.update({f"median_{t:g}_{c}": m for (t, c), m in medians_by_coatings(r, key).items()})
    grid["coatings"] = [int(c) for c in np.unique(r["n_coatings"])]
    return grid, full


def grid_coverage(angles=(75.0, 85.0)) -> list[str]:
    """What the held-out grazing set's 16 x 16 lobe grid holds of each reference lobe: the reference's own grid
    albedo (the stored sum of its lobe image) / its directional albedo from analog walks (stored too), per
    coating count at ``angles``: medians and ranges. Where a sharp grazing lobe falls between grid points, the
    grid holds a fraction of its energy, and a network / reference ratio on the grid measures the lobes at those
    points only."""
    data = load(GRAZING)
    k = [list(data["angles"]).index(t) for t in angles]
    ratio = np.asarray(data["albedo"], dtype=np.float64)[:, k].mean(-1) / np.maximum(
        np.asarray(data["albedo_full"], dtype=np.float64)[:, k].mean(-1), 1e-12
    )
    n_coat = np.asarray(data["n_coatings"])
    head = " | ".join(f"{t:g} deg, {c} coat." for t in angles for c in np.unique(n_coat))
    cells = " | ".join(
        f"{np.median(ratio[n_coat == c, j]):.2f} ({ratio[n_coat == c, j].min():.2f}-{ratio[n_coat == c, j].max():.2f})"
        for j in range(len(angles))
        for c in np.unique(n_coat)
    )
    return [
        "## What the lobe grid holds of a reference lobe",
        "",
        "The held-out grazing set's albedo is the sum of a 16 x 16 lobe image (uniform on the projected disk, "
        "`onnx_export.heldout_grazing`). Its reference albedo on that grid / the same stacks' directional albedo "
        "from analog walks (the set's `albedo_full`, integrated in full), median (range) per coating count:",
        "",
        f"| | {head} |",
        "|---|" + "---|" * (len(angles) * len(np.unique(n_coat))),
        f"| reference: grid / analog | {cells} |",
        "",
        "The grid holds well under the lobe's whole energy at grazing, and from one stack to the next anything "
        "from a few percent to all of it: the specular peaks fall between its points. The tables' first rows "
        "(network / reference on that grid, above) therefore compare the two lobes at those points, a check of "
        "the lobes' shape; the directional albedo, what the albedo targets are about, is the second table of each size "
        "(integrated in full).",
        "",
    ]


_SESSION_SCRIPT = """
import os, sys, time
sys.path.insert(0, {root!r})
from addon.core import quality
from addon.core.neural import calibrate
from addon.core.render import RenderSettings, render
from addon.core.render.demo_scene import demo_scene

if {folder!r}:
    calibrate.use_disk_cache(os.path.join({folder!r}, "calibrations"))
    quality.use_disk_cache(os.path.join({folder!r}, "quality"))
scene = demo_scene(64, 36)
t0 = time.perf_counter()
scene.materials, _, _ = quality.assign_decoders(scene, "auto", calibrate=True)
auto = time.perf_counter() - t0
_, stats = render(scene, RenderSettings(samples=1, max_bounces=2))
print(auto, stats.seconds["setup"], stats.seconds["total"])
"""


def session_rows(repeats: int = 3) -> list[str]:
    """The first render of the demo scene in a new session (a fresh process, 64 x 36, 1 spp), as the add-on's F12
    makes it with its defaults: *Auto* chooses each sphere's decoder (measuring its error, calibrated), then the
    render's setup makes the calibrations. Without a disk cache, with an empty one (filled by that render), and
    with the one a session before filled (the add-on's: its extension's user folder)."""
    import subprocess
    import tempfile

    def first_render(folder: str) -> tuple[float, float, float]:
        run = subprocess.run(
            [sys.executable, "-c", _SESSION_SCRIPT.format(root=str(ROOT), folder=folder)],
            capture_output=True,
            text=True,
            check=True,
            timeout=1200,
        )
        auto, setup, total = run.stdout.split()[-3:]
        return float(auto), float(setup), float(total)

    rows = {"no disk cache": [], "empty disk cache (filled by this render)": [], "the disk cache a session filled": []}
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            rows["no disk cache"].append(first_render(""))
            rows["empty disk cache (filled by this render)"].append(first_render(tmp))
            rows["the disk cache a session filled"].append(first_render(tmp))
    lines = [
        "## A new session's first render",
        "",
        "The demo scene's first render in a fresh process (64 x 36, 1 spp, 2 bounces) as F12 makes it with the "
        "add-on's defaults: *Auto* chooses each sphere's decoder (`quality.assign_decoders`, its errors measured "
        f"calibrated), then the render's setup makes the calibrations; {repeats} times each, alternating, seconds. "
        "`calibrate.use_disk_cache` and `quality.use_disk_cache` keep both on disk; the add-on gives them the "
        "extension's user folder.",
        "",
        "| disk cache | Auto's choice s | render setup s | render s |",
        "|---|---|---|---|",
    ]
    for name, values in rows.items():
        cells = " | ".join(", ".join(f"{v[i]:.2f}" for v in values) for i in range(3))
        lines.append(f"| {name} | {cells} |")
    return lines + [""]


def ratio_table(rows: dict, coats: list[int], extra_heads: list[str], extra_keys: list[str]) -> list[str]:
    """A markdown table of the decoder's and the calibrated rows: medians at 75 and 85 degrees per coating
    count, then the ``extra_keys`` columns."""
    head = " | ".join(f"{t:g} deg, {c} coat." for t in (75, 85) for c in coats)
    out = [f"| | {head} | " + " | ".join(extra_heads) + " |", "|---|" + "---|" * (2 * len(coats) + len(extra_heads))]
    for flag, label in ((False, "decoder"), (True, "calibrated")):
        r = rows[flag]
        cells = " | ".join(f"{r[f'median_{t:g}_{c}']:.3f}" for t in (75, 85) for c in coats)
        out.append(f"| {label} | {cells} | " + " | ".join(f"{r[k]:.2f}" for k in extra_keys) + " |")
    return out


def cost_rows(size: str) -> list[tuple[str, float]]:
    models = load_models(size)
    rows = []
    for name, stack in PRESETS.items():
        if not stack.coatings:
            continue
        z = encode_stack(stack, models)
        cal.clear_cache()
        t = time.perf_counter()
        cal.calibrate(stack, models, z, models.proxy_params(z)[0])
        rows.append((name, time.perf_counter() - t))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["tiny", "small"])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "calibration.md")
    a = ap.parse_args(argv)
    command = "python benchmarks/bench_calibration.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    lines = [
        "# Albedo calibration: grazing ratios and cost",
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPU threads. Calibration: "
        f"{len(cal.COSINES)} incident angles (cos theta {', '.join(f'{c:g}' for c in cal.COSINES)}), "
        f"{sum(cal.WALKS):,} reference walks and {len(cal.COSINES) * cal.DECODED_SAMPLES:,} decoded "
        "samples per material (`addon/core/neural/calibrate.py`); a remainder decoder's target is the albedo of "
        "the light that entered the top interface (the walks without the top's first reflections), each target "
        f"kept at the decoded albedo where the two are within {cal.NOISE_THRESHOLD:g} of the walks' standard "
        "errors.",
        "",
        "## Held-out grazing set: network / reference (1 = exact)",
        "",
        "Median albedo ratio per coating count at 75 and 85 degrees; the largest albedo and f cos(theta_i) "
        "ratios over all 32 stacks at 80-89.5 degrees (targets: median within 5%, nothing over 2).",
        "",
    ]
    for size in a.sizes:
        measured = {flag: grazing_rows(size, flag) for flag in (False, True)}
        rows, true = {f: m[0] for f, m in measured.items()}, {f: m[1] for f, m in measured.items()}
        coats = rows[False]["coatings"]
        lines += [f"### {size}", ""]
        lines += ratio_table(rows, coats, ["largest albedo ratio", "largest f cos ratio"], ["albedo_max", "fcos_max"])
        lines += [
            "",
            "Directional albedo integrated in full (importance-sampled decoded lobe; the set's analog-walk "
            "reference, other seeds than the calibration's; not the 16 x 16 lobe grid above, which samples sharp "
            f"grazing lobes at a few points), {size}, median decoded / reference, and the largest ratio over all 32 "
            f"stacks (at {', '.join(f'{t:g}' for t in GRAZING_ANGLES_DEG)} degrees):",
            "",
            *ratio_table(
                true, coats, ["largest ratio at 75 / 85 deg", "largest ratio at 80-89.5 deg"], ["max", "max_grazing"]
            ),
            "",
        ]
        print(size, rows, true, flush=True)
    lines += grid_coverage()
    print("\n".join(lines[-12:]), flush=True)
    lines += session_rows()
    print("\n".join(lines[-8:]), flush=True)
    lines += [
        "## Cost per preset (seconds, one calibration, this machine)",
        "",
        "| preset | " + " | ".join(a.sizes) + " |",
    ]
    lines.append("|---|" + "---|" * len(a.sizes))
    costs = {size: dict(cost_rows(size)) for size in a.sizes}
    for name in costs[a.sizes[0]]:
        lines.append(f"| {name} | " + " | ".join(f"{costs[s][name]:.2f}" for s in a.sizes) + " |")
    a.out.write_text("\n".join(lines) + "\n")
    print(f"Wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The main job: evaluate the bundled presets and write images.

    python bake/demo.py --out output

Writes, for every preset stack, its reference lobe images (f cos on the projected outgoing
hemisphere at the DESIGN incident angles) as PNG, and an albedo table (Markdown) with the
standard errors of the position-free Monte Carlo reference.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core import lobe, reference  # noqa: E402
from addon.core.stack import PRESETS  # noqa: E402


def write_png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

    img = (lobe.to_display(rgb) * 255.0 + 0.5).astype(np.uint8)
    tmp = path.with_suffix(".tmp.png")
    Image.fromarray(img).save(tmp)
    tmp.replace(path)


def preset_lobes(out: Path, res: int, walks: int, seed: int) -> list[str]:
    rows = ["| preset | albedo R | albedo G | albedo B | std. error (max) | seconds |", "|---|---|---|---|---|---|"]
    lobe_dir = out / "lobes"
    lobe_dir.mkdir(parents=True, exist_ok=True)
    wo_normal = np.array([[0.0, 0.0, 1.0]])
    for name, stack in PRESETS.items():
        t0 = time.perf_counter()
        tiles = []
        for theta in lobe.INCIDENT_ANGLES_DEG:
            img = lobe.lobe_image(
                lambda wi, wo: reference.eval_brdf(stack, wi, wo, walks=walks, seed=seed)[0], theta, res
            )
            tiles.append(img)
        strip = np.concatenate(tiles, axis=1)
        # Exposure: show each preset's lobes relative to its brightest incident angle.
        peak = np.percentile(strip, 99.5)
        write_png(lobe_dir / f"{name}.png", strip / max(peak, 1e-6))
        a, se = reference.albedo(stack, wo_normal, samples=4 * walks * 64, seed=seed)
        dt = time.perf_counter() - t0
        rows.append(
            f"| {name} | {a[0, 0]:.4f} | {a[0, 1]:.4f} | {a[0, 2]:.4f} | {se.max():.4f} | {dt:.1f} |"
        )
        print(f"  {name}: albedo {np.round(a[0], 4)} +- {se.max():.4f} ({dt:.1f} s)", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("output"), help="output folder (created)")
    ap.add_argument("--lobe-res", type=int, default=48, help="lobe image resolution")
    ap.add_argument("--walks", type=int, default=32, help="reference walks per lobe pixel")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(f"error: cannot create output folder {args.out}: {e}", file=sys.stderr)
        return 2
    print(f"Reference lobes of {len(PRESETS)} presets -> {args.out / 'lobes'}", flush=True)
    rows = preset_lobes(args.out, args.lobe_res, args.walks, args.seed)
    table = args.out / "albedo.md"
    header = (
        "Directional albedo at normal incidence (position-free Monte Carlo reference).\n\n"
        f"Command: `python bake/demo.py --out {args.out} --lobe-res {args.lobe_res} --walks {args.walks}`\n\n"
    )
    table.write_text(header + "\n".join(rows) + "\n")
    print(f"Wrote {table}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The main job: evaluate the bundled presets and render the demo scene; write images.

    python bake/demo.py --out output

Writes, for every preset stack, its reference lobe images (f cos on the projected outgoing
hemisphere at the incident angles of docs/architecture.md, Measurement) as PNG, and an albedo table (Markdown) with the
standard errors of the position-free Monte Carlo reference. Then renders the bundled demo
scene (layered presets and a textured floor under a sky and an area light) headless with the
add-on's path tracer, as ``demo_render.png`` (sRGB), ``demo_render.exr`` (linear) and
``demo_render.md`` (settings and timings). Images are written by the add-on's own writers
(OpenImageIO, which Blender and the bpy module ship), as Render Preview writes them.
"""

from __future__ import annotations

import argparse
import itertools
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core import lobe, reference  # noqa: E402
from addon.core.render.film import write_png  # noqa: E402
from addon.core.stack import PRESETS  # noqa: E402
from addon.core.threads import thread_count  # noqa: E402


def _preset_lobes(name: str, lobe_dir: Path, res: int, walks: int, seed: int):
    """One preset's lobe strip written as PNG, its albedo at normal incidence with its standard error, and the
    seconds it took (a worker process's task: the reference walks hold the GIL, so threads would not help)."""
    t0 = time.perf_counter()
    stack = PRESETS[name]
    tiles = []
    for theta in lobe.INCIDENT_ANGLES_DEG:
        img = lobe.lobe_image(
            lambda wi, wo, stack=stack: reference.eval_brdf(stack, wi, wo, walks=walks, seed=seed)[0], theta, res
        )
        tiles.append(img)
    strip = np.concatenate(tiles, axis=1)
    # Exposure: show each preset's lobes relative to its brightest incident angle.
    peak = np.percentile(strip, 99.5)
    write_png(lobe_dir / f"{name}.png", strip / max(peak, 1e-6))
    a, se = reference.albedo(stack, np.array([[0.0, 0.0, 1.0]]), samples=4 * walks * 64, seed=seed)
    return a, se, time.perf_counter() - t0


def preset_lobes(out: Path, res: int, walks: int, seed: int) -> list[str]:
    """Every preset's lobes and albedo, presets side by side in worker processes (one per core), reported in
    the presets' order; each preset is seeded, so what is written does not depend on the worker count."""
    rows = ["| preset | albedo R | albedo G | albedo B | std. error (max) | seconds |", "|---|---|---|---|---|---|"]
    lobe_dir = out / "lobes"
    lobe_dir.mkdir(parents=True, exist_ok=True)
    names = list(PRESETS)
    with ProcessPoolExecutor(max_workers=min(len(names), thread_count(0))) as pool:
        done = pool.map(_preset_lobes, names, *(itertools.repeat(v) for v in (lobe_dir, res, walks, seed)))
        for name, (a, se, dt) in zip(names, done, strict=True):
            rows.append(f"| {name} | {a[0, 0]:.4f} | {a[0, 1]:.4f} | {a[0, 2]:.4f} | {se.max():.4f} | {dt:.1f} |")
            print(f"  {name}: albedo {np.round(a[0], 4)} +- {se.max():.4f} ({dt:.1f} s)", flush=True)
    return rows


def bake_floor(out: Path):
    """Bake the varnished tile floor (spatially varying stack) into a latent texture, or None
    (with a message) when no shipped decoder size has its layering and sampling networks."""
    from addon.core.neural import SIZES
    from addon.core.render.demo_scene import bake_floor as bake_floor_texture
    from addon.core.textures import LatentTexture
    from addon.core.textures.bake import neural_encoder

    for size in SIZES:
        try:
            encode = neural_encoder(size)
        except (FileNotFoundError, ValueError):
            continue
        t0 = time.perf_counter()
        tex, stats = bake_floor_texture(encode, metadata={"model": size})
        path = out / "varnished_tiles.exr"
        try:
            tex.write_exr(path)
            tex = LatentTexture.read_exr(path)  # render what was written
        except RuntimeError as e:
            print(f"  (latent texture not written: {e})")
        print(
            f"Baked the floor: {tex.width}x{tex.height} texels, {stats.unique} distinct, {size} decoder, "
            f"calibrated in {stats.clusters} cluster(s) ({stats.calibration_seconds:.1f} s), "
            f"filtered across {tex.filter_levels} of {len(tex.levels)} mip levels, "
            f"{time.perf_counter() - t0:.1f} s -> {path}",
            flush=True,
        )
        return tex
    print("  no decoder size ships layering + sampling networks: the floor renders as a plain texture")
    return None


def render_demo(out: Path, width: int, height: int, samples: int, bounces: int, mode: str, seed: int) -> None:
    from addon.core.render import RenderSettings, render, write_exr
    from addon.core.render.demo_scene import demo_scene
    from addon.core.render.warm_up import warm_up

    t0 = time.perf_counter()  # as the add-on does at registration: compile (or load) the loops first
    warm_up()
    compile_s = time.perf_counter() - t0
    print(f"  renderer's compiled loops ready in {compile_s:.1f} s (compiled on the first run, then cached)")
    floor = bake_floor(out) if mode == "neural" else None
    scene = demo_scene(width, height, floor_texture=floor)
    settings = RenderSettings(samples=samples, max_bounces=bounces, seed=seed, mode=mode, reference_walks=2)
    t0 = time.perf_counter()

    def progress(film, done, total):
        if done == total or done % max(1, total // 4) == 0:
            print(f"  sample {done}/{total} ({time.perf_counter() - t0:.1f} s)", flush=True)
        return True

    film, stats = render(scene, settings, progress=progress)
    image = film.mean()
    write_png(out / "demo_render.png", image)
    written = ["demo_render.png"]
    try:
        write_exr(out / "demo_render.exr", image)
        written.append("demo_render.exr")
    except RuntimeError as e:
        print(f"  (no EXR: {e})")
    kinds = ", ".join(f"{name}: {kind}" for name, kind in zip(scene.material_names, stats.material_kinds, strict=True))
    (out / "demo_render.md").write_text(
        "Demo scene render (layered presets and a textured floor; sky + area light).\n\n"
        f"Command: `python bake/demo.py --out {shlex.quote(str(out))} --render-size {width}x{height} "
        f"--samples {samples} --bounces {bounces} --mode {mode} --seed {seed}`\n\n"
        f"- materials: {kinds}\n"
        f"- {stats.summary()}\n"
        f"- non-finite samples: {stats.nonfinite}\n"
        f"- before the render, the renderer's compiled loops were ready in {compile_s:.1f} s (compiled on the "
        "first run after installing or after a formula changed, loaded from the disk cache after that)\n"
    )
    print(f"  {stats.summary()}")
    print(f"Wrote {', '.join(str(out / w) for w in written)}")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 320x180, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size must be at least 1x1, got {text!r}")
    return w, h


class _BadInput(Exception):
    """Invalid command-line input: one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line and exit code 2, instead of argparse's usage block
        raise _BadInput(f"{message} (demo.py --help lists the options)")


def main(argv: list[str] | None = None) -> int:
    """Exit codes: 0 done, 1 failed, 2 bad input, 130 interrupted (Ctrl-C)."""
    try:
        return _main(argv)
    except SystemExit as e:  # --help
        return 0 if not e.code else 2
    except _BadInput as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nerror: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # one clear line, not a traceback
        print(f"error: demo failed: {type(e).__name__}: {e}", file=sys.stderr)
        return 1


def _main(argv: list[str] | None) -> int:
    ap = _Parser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("output"), help="output folder (created)")
    ap.add_argument("--lobe-res", type=int, default=48, help="lobe image resolution")
    ap.add_argument("--walks", type=int, default=32, help="reference walks per lobe pixel")
    ap.add_argument("--seed", type=int, default=0, help="seed of the reference lobes' walks and of the render")
    ap.add_argument("--render-size", type=_size, default=(320, 180), help="demo render size WxH")
    ap.add_argument("--samples", type=int, default=16, help="demo render paths per pixel")
    ap.add_argument("--bounces", type=int, default=4, help="demo render max bounces")
    ap.add_argument(
        "--mode",
        choices=("neural", "reference"),
        default="neural",
        help="layered materials: neural decoder (reference where it cannot serve a stack) or reference",
    )
    ap.add_argument("--skip-lobes", action="store_true", help="only render the demo scene")
    args = ap.parse_args(argv)
    for name, value, least in (
        ("--samples", args.samples, 1),
        ("--bounces", args.bounces, 0),
        ("--lobe-res", args.lobe_res, 1),
        ("--walks", args.walks, 1),
        ("--seed", args.seed, 0),
    ):
        if value < least:
            raise _BadInput(f"{name} must be >= {least}, got {value}")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _BadInput(f"cannot create output folder {args.out}: {e}") from None
    if not args.skip_lobes:
        print(f"Reference lobes of {len(PRESETS)} presets -> {args.out / 'lobes'}", flush=True)
        rows = preset_lobes(args.out, args.lobe_res, args.walks, args.seed)
        table = args.out / "albedo.md"
        header = (
            "Directional albedo at normal incidence (position-free Monte Carlo reference).\n\n"
            f"Command: `python bake/demo.py --out {shlex.quote(str(args.out))} --lobe-res {args.lobe_res} "
            f"--walks {args.walks} --seed {args.seed}`\n\n"
        )
        table.write_text(header + "\n".join(rows) + "\n")
        print(f"Wrote {table}")
    w, h = args.render_size
    print(f"Demo scene render {w}x{h}, {args.samples} samples, mode {args.mode} -> {args.out}", flush=True)
    render_demo(args.out, w, h, args.samples, args.bounces, args.mode, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())

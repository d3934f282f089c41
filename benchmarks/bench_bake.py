"""Bake speed and size: texels per second with and without deduplication, EXR bytes per megapixel,
and the lobes of a texture that blends two stacks through a mask (latent vs BRDF blending).

    python benchmarks/bench_bake.py [--size tiny] [--res 512]

Writes docs/bake.md and docs/bake_mix_lobes.png.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from addon.core import lobe  # noqa: E402
from addon.core.stack import preset  # noqa: E402
from addon.core.textures.bake import BAKE_BYTES_PER_TEXEL, BAKE_FIXED_BYTES, bake_mix, bake_stack, neural_encoder  # noqa: E402
from addon.core.textures.spatial import SpatialStack  # noqa: E402


def driving_images(res: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A worn varnish: smooth noise for the coat roughness, 8 grey levels of thickness (so some
    parameter tuples repeat, as they do in painted masks)."""
    rng = np.random.default_rng(seed)
    coarse = rng.random((res // 32 + 2, res // 32 + 2))
    y, x = np.mgrid[0:res, 0:res] / 32.0
    y0, x0 = y.astype(int), x.astype(int)
    fy, fx = y - y0, x - x0
    noise = (
        coarse[y0, x0] * (1 - fx) * (1 - fy)
        + coarse[y0, x0 + 1] * fx * (1 - fy)
        + coarse[y0 + 1, x0] * (1 - fx) * fy
        + coarse[y0 + 1, x0 + 1] * fx * fy
    )
    return {
        "coatings[0].roughness": 0.02 + 0.3 * noise,
        "coatings[0].thickness": np.round(noise * 7) / 7 * 2.0,
    }


def high_water() -> int:
    """This process's largest resident size so far, kB (Linux ``VmHWM``; ``ru_maxrss`` would count the parent's
    too in a forked child)."""
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))


_PEAK_SCRIPT = """
import sys
sys.path.insert(0, {root!r})
from benchmarks.bench_bake import driving_images, high_water
from addon.core.stack import preset
from addon.core.textures.bake import bake_stack, neural_encoder
from addon.core.textures.spatial import SpatialStack

encode = neural_encoder({size!r})
spatial = SpatialStack(preset("varnished_wood"), driving_images({side}))
before = high_water()
tex, stats = bake_stack(spatial, encode)
baked = high_water()
tex.write_exr({exr!r})
print(before, baked, high_water(), stats.unique)
"""

_MIX_SCRIPT = """
import sys
sys.path.insert(0, {root!r})
import numpy as np
from benchmarks.bench_bake import driving_images, high_water
from addon.core.stack import preset
from addon.core.textures.bake import bake_mix, neural_encoder
from addon.core.textures.spatial import SpatialStack

encode = neural_encoder({size!r})
wood = SpatialStack(preset("varnished_wood"), driving_images({side}))
mask = np.tile(np.linspace(0.0, 1.0, {side}), ({side}, 1))
before = high_water()
tex, stats = bake_mix(wood, SpatialStack(preset("coated_gold")), mask, encode)
tex.write_exr({exr!r})
print(before, high_water())
"""

_READ_SCRIPT = """
import sys, time
sys.path.insert(0, {root!r})
from benchmarks.bench_bake import high_water
from addon.core.textures import LatentTexture

before = high_water()
t0 = time.perf_counter()
tex = LatentTexture.read_exr({exr!r})
print(time.perf_counter() - t0, before, high_water(), tex.levels.flat.nbytes)
"""


def peak_memory(side: int, size: str) -> dict:
    """The bake's peak memory at ``side`` x ``side`` (default settings, every texel distinct but a few): the
    largest resident size of a fresh process (``VmHWM``, Linux) before ``bake_stack``, after it and after writing
    its file, in bytes, and the distinct texels; a mix's (``bake_mix`` of those texels with a constant stack through
    a ramp, its file written), before and after, in another; then the texture read back in a third (as a render
    reads it): seconds of ``read_exr``, the resident size before and after, and the bytes of the chain it holds."""
    import subprocess

    def fresh(script: str, **fields) -> list[str]:
        run = subprocess.run(
            [sys.executable, "-c", script.format(root=str(ROOT), **fields)],
            capture_output=True,
            text=True,
            check=True,
            timeout=3600,
        )
        return run.stdout.split()

    with tempfile.TemporaryDirectory() as tmp:
        exr = str(Path(tmp) / "texture.exr")
        before, baked, written, unique = fresh(_PEAK_SCRIPT, size=size, side=side, exr=exr)[-4:]
        seconds, read_before, read_after, held = fresh(_READ_SCRIPT, exr=exr)[-4:]
        mix_before, mix_after = fresh(_MIX_SCRIPT, size=size, side=side, exr=exr)[-2:]
    kib = dict(before=before, baked=baked, written=written, read_before=read_before, read_after=read_after)
    kib.update(mix_before=mix_before, mix_after=mix_after)
    return {
        **{key: float(value) * 1024 for key, value in kib.items()},
        "unique": int(unique),
        "read_s": float(seconds),
        "held": int(held),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="tiny", help="decoder size (its encoder/layering/sampling models are used)")
    ap.add_argument("--res", type=int, default=512, help="texture side in texels")
    ap.add_argument(
        "--out", type=Path, default=ROOT / "docs", help="folder for bake.md and the chart (made if missing)"
    )
    ap.add_argument(
        "--peak-memory",
        type=int,
        nargs="*",
        default=[1024, 2048],
        metavar="SIDE",
        help="texture sides whose bake's peak memory is measured, each in a fresh process (none: skip)",
    )
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    import bpy

    bpy.utils.expose_bundled_modules()
    encode = neural_encoder(args.size)
    stack = preset("varnished_wood")
    rows = []
    maps = driving_images(args.res)
    cases = {
        "constant stack (1 distinct texel)": SpatialStack(
            stack, {"coatings[0].thickness": np.full((args.res, args.res), 0.6)}
        ),
        "8-level thickness map": SpatialStack(stack, {"coatings[0].thickness": maps["coatings[0].thickness"]}),
        "smooth roughness + thickness maps": SpatialStack(stack, maps),
    }
    exr_sizes = []
    defaults = []
    for label, spatial in cases.items():
        for dedup in (True, False):
            times = []
            for _ in range(2):  # the first bake of a case also pays ONNX Runtime's first calls at its batch sizes
                t0 = time.perf_counter()
                tex, stats = bake_stack(spatial, encode, dedup=dedup, calibrate=False, check_filtering=False)
                times.append(time.perf_counter() - t0)
            first_s, bake_s = times
            with tempfile.TemporaryDirectory() as d:
                t1 = time.perf_counter()
                tex.write_exr(Path(d) / "t.exr")
                write_s = time.perf_counter() - t1
                size = (Path(d) / "t.exr").stat().st_size
            mpix = args.res * args.res / 1e6
            exr_sizes.append(size / mpix)
            rows.append(
                f"| {label} | {'yes' if dedup else 'no'} | {stats.unique:,} | {stats.texels / bake_s:,.0f} | "
                f"{stats.unique / bake_s:,.0f} | {bake_s:.2f} | {first_s:.2f} | {write_s:.2f} | "
                f"{size / mpix / 2**20:.1f} |"
            )
            print(rows[-1], flush=True)
        # The bake as the sidebar and the bake command run it: calibrated, its filterable levels measured.
        t0 = time.perf_counter()
        tex, stats = bake_stack(spatial, encode)
        total = time.perf_counter() - t0
        defaults.append(
            f"| {label} | {stats.unique:,} | {total:.2f} | {stats.seconds:.2f} | {stats.calibration_seconds:.2f} "
            f"({stats.clusters}) | {total - stats.seconds - stats.calibration_seconds:.2f} | "
            f"{tex.filter_levels} of {len(tex.levels)} | {stats.unique / total:,.0f} |"
        )
        print(defaults[-1], flush=True)

    peaks = []
    if args.peak_memory and sys.platform.startswith("linux"):  # /proc/self/status
        for side in args.peak_memory:
            m = peak_memory(side, args.size)
            gb = {key: value / 2**30 for key, value in m.items() if key not in ("unique", "read_s")}
            bake_bytes = m["written"] - m["before"]
            peaks.append(
                f"| {side} x {side} | {m['unique']:,} | {gb['before']:.2f} | {gb['baked']:.2f} | {gb['written']:.2f} | "
                f"{bake_bytes / 2**30:.2f} | {bake_bytes / side**2:,.0f} | {gb['mix_after'] - gb['mix_before']:.2f} | "
                f"{m['read_s']:.2f} | {gb['read_after'] - gb['read_before']:.2f} | {gb['held']:.2f} |"
            )
            print(peaks[-1], flush=True)

    # Blending two stacks through a mask: the lobe of a half-way texel.
    a, b = preset("coated_gold"), preset("frosted_copper")
    mask = np.tile(np.linspace(0.0, 1.0, 9), (4, 1))
    tex, _ = bake_mix(SpatialStack(a), SpatialStack(b), mask, encode)
    from addon.core.neural import load_models

    models = load_models(args.size)
    texel = tex.levels[0]
    z = {t: texel[0, int(round(t * 8)), :96].reshape(3, 32) for t in (0.0, 0.5, 1.0)}
    top = {t: texel[0, int(round(t * 8)), 98:] for t in z}  # the top-coat channels (a remainder decoder's top lobe)
    theta = 45.0
    lobes = {
        t: lobe.lobe_image(lambda wi, wo, zz=zz, tt=top[t]: models.eval_brdf(zz, wi, wo, tt), theta, 96)
        for t, zz in z.items()
    }
    brdf_mix = 0.5 * (lobes[0.0] + lobes[1.0])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(12, 3.3))
    peak = max(np.percentile(im, 99.7) for im in (*lobes.values(), brdf_mix))
    panels = [
        ("coated gold (mask 0)", lobes[0.0]),
        ("latent blend (mask 0.5)", lobes[0.5]),
        ("BRDF blend (mean of ends)", brdf_mix),
        ("frosted copper (mask 1)", lobes[1.0]),
    ]
    for ax, (title, im) in zip(axes, panels, strict=True):
        ax.imshow(lobe.to_display(im / peak))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(
        f"Texels of a latent texture blending two stacks through a mask; f cos lobes at {theta:.0f} deg "
        f"({args.size} decoder)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(args.out / "bake_mix_lobes.png", dpi=110)

    cmd = f"python benchmarks/bench_bake.py --size {args.size} --res {args.res}" + (
        f" --peak-memory {' '.join(map(str, args.peak_memory))}" if args.peak_memory else " --peak-memory"
    )
    text = [
        "# Baking latent textures: speed and size",
        "",
        "Driving images of `bake/bake.py` (`--map PATH=FILE[@SPACE][:LO:HI]`, `--mask FILE[@SPACE]`) follow one",
        "colour-space rule (`addon.core.textures.colour_maps`), what a Blender user gets by default: an image "
        "driving a",
        "colour (albedo) is decoded from sRGB to linear when it is stored as 8- or 16-bit integers without a linear",
        "colour-space tag (OpenImageIO's `oiio:ColorSpace`), as Blender's default \"sRGB\" (a byte 128 reads 0.216);",
        "float images (EXR, HDR) are linear; every other parameter and the mask read the raw values, as Blender's",
        '"Non-Color" (a byte 128 reads 0.502). `@srgb`, `@linear`, `@non-color` or `@auto` overrides the rule '
        "per image.",
        "",
        f"Command: `{cmd}` ({os.cpu_count()}-thread CPU, ONNX Runtime on every core; `{args.size}` encoder + "
        "layering + sampling models).",
        f"Load average just after the run ended: {os.getloadavg()[1]:.1f} over 5 minutes (shared with other jobs: "
        "compare rows of one run).",
        f"Stack: `varnished_wood` driven by {args.res}x{args.res} images. Texels/s counts every texel of the",
        "texture (base level), distinct texels/s the rows the networks encoded; the mip chain is part of the bake",
        "time, the half-float EXR write is timed separately. Each case is baked twice: the rates are the",
        "second bake's; the first bake (its seconds beside them) also pays ONNX Runtime's first calls at batch",
        "sizes the process has not run yet. Deduplication hashes the float32 parameter rows that vary",
        "(`addon.core.rows.distinct_rows`) and sorts only the hashes. These bakes leave out the texture's albedo",
        "calibration and the measurement of its filterable levels (`bake_stack(..., calibrate=False, "
        "check_filtering=False)`): the second table below has the bake with both, the default "
        "([texture_calibration.md](texture_calibration.md)).",
        "",
        "| driving images | dedup | distinct texels encoded | texels/s | distinct texels/s | bake s | first bake s | "
        "EXR write s | EXR MiB per megapixel |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "The EXR holds 100 half-float channels (96 latent, 2 proxy, the top coat's alpha and ior) with the full",
        "mip chain, zip-compressed;",
        "uncompressed that is 100 x 2 bytes x 4/3 = 267 bytes per texel (254 MiB per megapixel). Constant",
        "regions compress to almost nothing.",
        "",
        "The same images baked with the default settings (`bake_stack(spatial, encode)`, as the sidebar's *Bake "
        "Latent Texture* and `bake/bake.py` run it): the texture's albedo calibration (reference walks for at most "
        "eight clusters of texels) and the measurement of its filterable mip levels come on top of the encoding, "
        "and for up to a few hundred thousand distinct texels they cost more than it. Both are bounded (eight "
        "clusters of eight texels; a crop of at most 128 x 128 texels per level), so their share falls as the "
        "texture grows.",
        "",
        "| driving images | distinct texels | bake s | encoding s | calibration s (clusters) | "
        "filter levels and the rest s | filterable levels | distinct texels/s |",
        "|---|---|---|---|---|---|---|---|",
        *defaults,
        "",
        "Peak memory of a bake with the default settings, each side in a fresh process (`--peak-memory`): the "
        "largest resident size before `bake_stack` (the models, the maps), after it, and after its file is written "
        "(`write_exr`, as the sidebar's bake and `bake/bake.py` do); the bake's GB and bytes per texel are that last "
        "peak less the first. The bake holds its texture in half floats, the values its file stores "
        "(`MipChain.fill` reduces each level in float32 a band of rows at a time), and its distinct texels in half "
        "floats too. The mix's GB: `bake_mix` of the same texels with coated gold through a ramp, its file written, "
        "in its own process (the same check guards it). "
        f"The bake's memory check counts `textures.bake.BAKE_FIXED_BYTES` = {BAKE_FIXED_BYTES / 2**30:.1f} GB and "
        f"`BAKE_BYTES_PER_TEXEL` = {BAKE_BYTES_PER_TEXEL:,} bytes a texel, above each bake's GB here (a margin for "
        "other stacks and maps, and for bakes whose texels are all distinct). Then the texture read back in "
        "another fresh process, as a render reads it "
        "(`LatentTexture.read_exr`): its seconds, what the read added to the process at its peak, and the chain "
        "it holds (half floats, as the file stores them).",
        "",
        "| texture | distinct texels | process before GB | peak baked GB | peak written GB | the bake's GB | "
        "bytes per texel | the mix's GB | read s | read peak GB | texture held GB |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        *peaks,
        "",
        "![latent vs BRDF blending](bake_mix_lobes.png)",
        "",
        "A texel half-way through the mask holds the latent (z_a + z_b) / 2: its lobe is one intermediate lobe,",
        "where averaging the two BRDFs gives the two lobes superimposed.",
    ]
    (args.out / "bake.md").write_text("\n".join(text) + "\n")
    print(f"wrote {args.out / 'bake.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

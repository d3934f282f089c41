"""Batch bake of latent textures.

Runs as a plain script with the ``bpy`` module, or inside Blender:

    python bake/bake.py --preset varnished_wood --map "coatings[0].roughness=rough.png:0.01:0.4" --out textures/
    python bake/bake.py --preset coated_gold --mix frosted_copper --mask worn.png --out textures/ --name worn_gold
    python bake/bake.py --blend scene.blend --material Wood --material CarPaint --out textures/
    blender -b --python bake/bake.py -- --blend scene.blend --material Wood --out textures/

Writes ``<out>/<material>.exr`` (tiled, mip-mapped, half-float latent texture) and
``<out>/<material>.json`` (stack, driving images, models, timings) per material.

Work is split into (material, band of rows) items: ``--shard i/n`` takes every n-th item from
the i-th, so shards can run anywhere; each finished band is kept as ``.<material>.bands/NNNN.npy``
and whichever shard completes a material's last band assembles its EXR. Finished outputs and
bands are skipped when the inputs are unchanged, so an interrupted bake resumes. Every file is
written under a temporary name and renamed, so nothing half-written sits where a finished file
is expected. Exit codes: 0 done, 1 bake failed, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core.stack import PRESETS, preset  # noqa: E402
from addon.core.textures.bake import _texels_at, bake_key, bake_texels, neural_encoder  # noqa: E402
from addon.core.textures.mip import resample_area  # noqa: E402
from addon.core.textures.latent_texture import LatentTexture, read_image  # noqa: E402
from addon.core.textures.spatial import SpatialStack  # noqa: E402


class BadInput(Exception):
    """Invalid command-line input: reported with exit code 2."""


@dataclass
class Job:
    name: str
    spatial: SpatialStack
    resolution: tuple[int, int]
    sources: dict[str, str]  # parameter path -> image description, for the sidecar
    mix: SpatialStack | None = None  # blended in latent space through ``mask``
    mask: np.ndarray | None = None

    def key(self, model: str) -> str:
        return bake_key(self.spatial, self.resolution, model, self.mix, self.mask)

    def texels(self):
        """Per-texel stacks at the bake resolution, and of the mixed stack with the mask (or None)."""
        arrays = _texels_at(self.spatial, self.resolution)[0]
        if self.mix is None:
            return arrays, None, None
        h, w = self.resolution
        m = self.mask if self.mask.shape == (h, w) else resample_area(self.mask[..., None], h, w)[..., 0]
        return arrays, _texels_at(self.mix, self.resolution)[0], m.reshape(-1, 1)


_MAP = re.compile(r"^(?P<path>[^=]+)=(?P<file>.+?)(?::(?P<lo>[-+0-9.eE]+):(?P<hi>[-+0-9.eE]+))?$")


def parse_map(spec: str) -> tuple[str, Path, float, float]:
    """``PATH=FILE[:LO:HI]``: image values in [0, 1] are mapped linearly onto [LO, HI]."""
    m = _MAP.match(spec)
    if not m:
        raise BadInput(f"--map {spec!r} must look like 'coatings[0].roughness=rough.png' or '...=rough.png:0.01:0.5'")
    lo = float(m.group("lo")) if m.group("lo") is not None else 0.0
    hi = float(m.group("hi")) if m.group("hi") is not None else 1.0
    return m.group("path").strip(), Path(m.group("file")), lo, hi


def parse_shard(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d+)/(\d+)", text or "")
    if not m or int(m.group(2)) < 1 or int(m.group(1)) >= int(m.group(2)):
        raise BadInput(f"--shard {text!r} must be i/n with 0 <= i < n, e.g. 0/4")
    return int(m.group(1)), int(m.group(2))


def preset_job(args) -> list[Job]:
    try:
        stack = preset(args.preset)
    except ValueError as e:
        raise BadInput(str(e)) from None
    maps, sources = {}, {}
    for spec in args.map or []:
        path, file, lo, hi = parse_map(spec)
        try:
            img = read_image(file)
        except (FileNotFoundError, ValueError) as e:
            raise BadInput(f"--map {path}: {e}") from None
        maps[path] = lo + (hi - lo) * img
        sources[path] = f"{file.name} [{lo}, {hi}]"
    try:
        spatial = SpatialStack(stack, maps)
    except ValueError as e:
        raise BadInput(str(e)) from None
    mix = mask = None
    if args.mix or args.mask:
        if not (args.mix and args.mask):
            raise BadInput("--mix and --mask go together: --mix PRESET --mask IMAGE blends the two stacks")
        try:
            mix = SpatialStack(preset(args.mix))
            mask = read_image(args.mask)[..., 0].astype(np.float64)
        except (FileNotFoundError, ValueError) as e:
            raise BadInput(f"--mix/--mask: {e}") from None
        if spatial.resolution is not None and spatial.resolution != mask.shape:
            raise BadInput(f"--mask is {mask.shape[1]}x{mask.shape[0]} but the driving images are "
                           f"{spatial.resolution[1]}x{spatial.resolution[0]}: they must share a resolution")
        sources["mask"] = f"{args.mask.name} (mixes in {args.mix})"
    native = mask.shape if mask is not None else (spatial.resolution or (1, 1))
    res = tuple(args.resolution) if args.resolution else native
    if not (1 <= res[0] <= native[0] and 1 <= res[1] <= native[1]):
        raise BadInput(f"bake resolution {res[1]}x{res[0]} must be between 1x1 and the driving images' "
                       f"{native[1]}x{native[0]}")
    return [Job(args.name or args.preset, spatial, res, sources, mix, mask)]


def blend_jobs(args) -> list[Job]:
    if not args.blend.is_file():
        raise BadInput(f"--blend: file not found: {args.blend}")
    import bpy

    from addon.blender.bake_inputs import spatial_stack_from_material

    bpy.ops.wm.open_mainfile(filepath=str(args.blend))
    jobs = []
    names = args.material or [m.name for m in bpy.data.materials if spatial_stack_from_material(m) is not None]
    for name in names:
        mat = bpy.data.materials.get(name)
        if mat is None:
            known = sorted(m.name for m in bpy.data.materials)
            raise BadInput(f"--material {name!r} is not in {args.blend.name}; materials there: {known}")
        try:
            found = spatial_stack_from_material(mat)
        except ValueError as e:
            raise BadInput(f"material {name!r}: {e}") from None
        if found is None:
            raise BadInput(f"material {name!r} has no layer stack to bake")
        spatial, sources = found
        try:
            _, res = spatial.texels(tuple(args.resolution) if args.resolution else None)
        except ValueError as e:
            raise BadInput(f"material {name!r}: {e}") from None
        jobs.append(Job(name, spatial, res, sources))
    if not jobs:
        raise BadInput(f"{args.blend.name} has no material with a layer stack")
    return jobs


def _atomic_save_npy(path: Path, array: np.ndarray) -> None:
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as f:
        np.save(f, array)
    os.replace(tmp, path)


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(text)
    os.replace(tmp, path)


class ProgressBar:
    def __init__(self, total: int, stream=sys.stderr):
        self.total, self.done, self.stream, self.t0 = max(total, 1), 0, stream, time.perf_counter()

    def update(self, label: str, fraction_of_item: float = 1.0, advance: bool = False) -> None:
        done = self.done + fraction_of_item
        if advance:
            self.done += 1
        frac = min(done / self.total, 1.0)
        bar = "#" * int(30 * frac)
        self.stream.write(f"\r[{bar:<30}] {100 * frac:5.1f}% {label[:40]:<40} {time.perf_counter() - self.t0:6.1f}s")
        self.stream.flush()

    def close(self) -> None:
        self.stream.write("\n")


def run(jobs: list[Job], out: Path, encode, model: str, shard: tuple[int, int], band_rows: int,
        dedup: bool = True, log=print) -> dict:
    """Bake this shard's items, assemble every material whose bands are all present."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise BadInput(f"--out {out}: not writable ({e})") from None
    items = []
    for job in jobs:
        key = job.key(model)
        sidecar = out / f"{job.name}.json"
        if (out / f"{job.name}.exr").is_file() and sidecar.is_file():
            try:
                if json.loads(sidecar.read_text()).get("key") == key:
                    log(f"{job.name}: up to date, skipped")
                    continue
            except (OSError, json.JSONDecodeError):
                pass
        bands = -(-job.resolution[0] // band_rows)
        items += [(job, key, b) for b in range(bands)]
    mine = [it for k, it in enumerate(items) if k % shard[1] == shard[0]]
    bar = ProgressBar(len(mine))
    stats = {"bands_baked": 0, "bands_skipped": 0, "texels": 0, "unique": 0, "seconds": 0.0, "assembled": []}
    cache: dict[str, object] = {}
    for job, key, band in mine:
        folder = out / f".{job.name}.bands"
        folder.mkdir(exist_ok=True)
        target = folder / f"{key}_{band:04d}.npy"
        if target.is_file():
            stats["bands_skipped"] += 1
            bar.update(f"{job.name} band {band} (kept)", advance=True)
            continue
        if job.name not in cache:
            cache[job.name] = job.texels()
        arrays, mixed, mask = cache[job.name]
        h, w = job.resolution
        rows = slice(band * band_rows * w, min((band + 1) * band_rows, h) * w)
        texels, st = bake_texels(arrays.take(rows), encode, dedup=dedup,
                                 progress=lambda f: bar.update(f"{job.name} band {band}", f))
        if mixed is not None:  # blend in latent space: one intermediate lobe per texel
            other, st2 = bake_texels(mixed.take(rows), encode, dedup=dedup)
            texels = ((1.0 - mask[rows]) * texels + mask[rows] * other).astype(np.float32)
            st.unique += st2.unique
        _atomic_save_npy(target, texels)
        bar.update(f"{job.name} band {band}", advance=True)
        stats["bands_baked"] += 1
        stats["texels"] += st.texels
        stats["unique"] += st.unique
        stats["seconds"] += st.seconds
    bar.close()
    for job in jobs:
        key = job.key(model)
        folder = out / f".{job.name}.bands"
        bands = -(-job.resolution[0] // band_rows)
        files = [folder / f"{key}_{b:04d}.npy" for b in range(bands)]
        if not all(f.is_file() for f in files) or (out / f"{job.name}.exr").is_file() and _fresh(out, job, key):
            continue
        t0 = time.perf_counter()
        h, w = job.resolution
        texels = np.concatenate([np.load(f) for f in files]).reshape(h, w, -1)
        meta = {"stack": job.spatial.stack.to_json(), "model": model, "key": key}
        LatentTexture.from_texels(texels, meta).write_exr(out / f"{job.name}.exr")
        sidecar = {
            "key": key,
            "material": job.name,
            "stack": job.spatial.stack.to_dict(),
            "maps": job.sources,
            "resolution": [w, h],
            "model": model,
            "seconds_assemble_and_write": round(time.perf_counter() - t0, 3),
            "this_shard": {"texels": stats["texels"], "unique_texels": stats["unique"],
                           "encode_seconds": round(stats["seconds"], 3)},
        }
        _atomic_write_text(out / f"{job.name}.json", json.dumps(sidecar, indent=2))
        for f in files:
            f.unlink(missing_ok=True)
        try:
            folder.rmdir()
        except OSError:
            pass
        stats["assembled"].append(job.name)
        log(f"{job.name}: wrote {out / (job.name + '.exr')} ({w}x{h})")
    return stats


def _fresh(out: Path, job: Job, key: str) -> bool:
    try:
        return json.loads((out / f"{job.name}.json").read_text()).get("key") == key
    except (OSError, json.JSONDecodeError):
        return False


def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="bake.py", description="Bake layered materials into latent textures.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--blend", type=Path, help=".blend file holding the materials")
    src.add_argument("--preset", help=f"bake a preset stack: {', '.join(sorted(PRESETS))}")
    ap.add_argument("--material", action="append", help="material name in --blend (repeatable; default: all with a stack)")
    ap.add_argument("--map", action="append", help="with --preset: PATH=IMAGE[:LO:HI] drives a parameter by an image")
    ap.add_argument("--name", help="with --preset: output name (default: the preset's)")
    ap.add_argument("--mix", help="with --preset and --mask: a second preset blended in latent space")
    ap.add_argument("--mask", type=Path, help="with --mix: image whose first channel (0..1) blends towards --mix")
    ap.add_argument("--resolution", type=int, nargs=2, metavar=("H", "W"), help="bake resolution (<= the images')")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--model", default="small", help="decoder size whose latent space to bake into")
    ap.add_argument("--shard", default="0/1", help="i/n: bake every n-th work item starting at i")
    ap.add_argument("--band-rows", type=int, default=256, help="rows per work item")
    ap.add_argument("--no-dedup", action="store_true", help="encode every texel, even repeated ones")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None, encode=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    try:
        args = parse_args(argv)
    except SystemExit as e:
        return 2 if e.code else 0
    try:
        shard = parse_shard(args.shard)
        if args.band_rows < 1:
            raise BadInput(f"--band-rows must be >= 1, got {args.band_rows}")
        if args.preset is None and args.map:
            raise BadInput("--map goes with --preset; in a .blend the images are set on the material")
        jobs = blend_jobs(args) if args.blend else preset_job(args)
        if encode is None:
            try:
                encode = neural_encoder(args.model)
            except (FileNotFoundError, ValueError, ImportError) as e:
                raise BadInput(f"--model {args.model}: {e}") from None
        stats = run(jobs, args.out, encode, args.model, shard, args.band_rows, dedup=not args.no_dedup)
    except BadInput as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except Exception as e:  # a failed bake: one clear line, non-zero exit
        print(f"error: bake failed: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    print(f"baked {stats['bands_baked']} band(s), kept {stats['bands_skipped']}, assembled {stats['assembled']}")
    return 0


if __name__ == "__main__":
    code = main()
    if "bpy" in sys.modules and not getattr(sys.modules["bpy"].app, "module", True):
        sys.stdout.flush()
        os._exit(code)  # inside Blender: leave with the bake's exit code
    sys.exit(code)

"""Batch bake of latent textures.

Runs as a plain script with the ``bpy`` module, or inside Blender:

    python bake/bake.py --preset varnished_wood --map "coatings[0].roughness=rough.png:0.01:0.4" --out textures/
    python bake/bake.py --preset coated_gold --mix frosted_copper --mask worn.png --out textures/ --name worn_gold
    python bake/bake.py --blend scene.blend --material Wood --material CarPaint --out textures/
    python bake/bake.py --blend scene.blend --out textures/ --attach
    blender -b --python bake/bake.py -- --blend scene.blend --material Wood --out textures/

Driving images are read by one colour-space rule (``addon.core.textures.colour_maps``): an
image driving a colour (albedo) is decoded from sRGB to linear when it is stored as 8- or 16-bit
integers without a linear colour-space tag, as Blender's default "sRGB"; float images (EXR, HDR)
are linear; every other parameter and the mask read the raw values (Blender's "Non-Color").
``--map PATH=FILE@SPACE`` or ``--mask FILE@SPACE`` overrides it (auto, srgb, linear, non-color).

Writes ``<out>/<file>.exr`` (tiled, mip-mapped, half-float latent texture) and
``<out>/<file>.json`` (stack, driving images, models, timings) per material, where ``<file>`` is
the material name (or ``--name``) made safe as a file name: a name holding path separators or
other characters a file name cannot hold gets them replaced and a short hash of the name
appended, so every output stays inside ``--out`` and different materials never share a file.
A ``--blend`` material's texture is keyed as the add-on keys its own bake of it (``encoder_model_key``),
and ``--attach`` points the material at it and saves the .blend (``attach_textures``), so a render
of the .blend uses it.

Work is split into (material, band of rows) items: ``--shard i/n`` takes every n-th item from
the i-th, so shards can run anywhere, at the same time too; each finished band is kept as
``.<file>.bands/<key>_<R>rows_NNNN.npy``, where the key hashes every input and R is ``--band-rows``,
so a band is only ever reused for the same inputs and rows (and only if it reads back whole and
finite). Whichever shard finds all bands present assembles the EXR; when several do at once each
publishes the same texels, and bands are deleted only after a publish, by the publisher (a shard
that finds them gone checks that the texture was published). Finished outputs (whole: the size
their sidecar recorded) and bands are skipped when the inputs are unchanged, so an interrupted
bake resumes. Every file is written under a temporary name unique to its process and renamed
atomically, so nothing half-written sits where a finished file is expected; an interrupted bake
removes its temporary files, and those of a killed one are removed by the next run.
Exit codes: 0 done, 1 bake failed, 2 bad input, 130 interrupted (Ctrl-C, SIGINT),
143 terminated (SIGTERM); finished bands are kept in every case.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import signal
import sys
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core.stack import (  # noqa: E402
    PRESETS,
    Stack,
    alpha_from_artist_roughness,
    artist_roughness_from_alpha,
    preset,
)
from addon.core.textures import colour_maps, files  # noqa: E402
from addon.core.textures.bake import (  # noqa: E402
    _texels_at,
    bake_key,
    bake_texels,
    model_key,
    neural_encoder,
    record_filter_levels,
)
from addon.core.textures.calibration import calibrate_baked  # noqa: E402
from addon.core.textures.latent_texture import CHANNEL_NAMES, LatentTexture, read_image_file  # noqa: E402
from addon.core.textures.mip import MipChain, resample_area  # noqa: E402
from addon.core.textures.spatial import SpatialStack, parse_parameter_path  # noqa: E402

EXIT_DONE, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_SIGNAL = {signal.SIGINT: 130, signal.SIGTERM: 143}  # 128 + signal number, as shells report it


class BadInput(Exception):
    """Invalid command-line input: reported with exit code 2."""


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived: unwinds like KeyboardInterrupt, so every temporary file is removed."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@dataclass
class Job:
    name: str
    spatial: SpatialStack
    resolution: tuple[int, int]
    sources: dict[str, str]  # parameter path -> image description, for the sidecar
    mix: SpatialStack | None = None  # blended in latent space through ``mask``
    mask: np.ndarray | None = None
    # with --blend: the add-on's ``bake_state.inputs_digest`` of the material at this resolution, for a model key;
    # recorded in the texture, so the add-on renders it while the material's maps' images cannot be read
    inputs: Callable[[str], str] | None = None

    @property
    def file(self) -> str:
        """The output file stem: the name made safe (see ``files.safe_file_name``)."""
        return files.safe_file_name(self.name)

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


_SPACE = r"(?:@(?P<space>[A-Za-z][\w-]*))?"
_MAP = re.compile(r"^(?P<path>[^=]+)=(?P<file>.+?)" + _SPACE + r"(?::(?P<lo>[-+0-9.eE]+):(?P<hi>[-+0-9.eE]+))?$")
_MASK = re.compile(r"^(?P<file>.+?)" + _SPACE + "$")


def parse_map(spec: str) -> tuple[str, Path, float, float, str]:
    """``PATH=FILE[@SPACE][:LO:HI]``: image values in [0, 1], decoded by the colour-space rule
    (``colour_maps``; SPACE overrides it), are mapped onto [LO, HI] (:func:`map_range`)."""
    m = _MAP.match(spec)
    if not m:
        raise BadInput(f"--map {spec!r} must look like 'coatings[0].roughness=rough.png' or '...=rough.png:0.01:0.5'")
    try:
        lo = float(m.group("lo")) if m.group("lo") is not None else 0.0
        hi = float(m.group("hi")) if m.group("hi") is not None else 1.0
    except ValueError:
        raise BadInput(f"--map {spec!r}: LO and HI must be numbers, e.g. ':0.01:0.5'") from None
    return m.group("path").strip(), Path(m.group("file")), lo, hi, _space(m.group("space"), f"--map {spec!r}")


def map_range(field: str, img: np.ndarray, lo: float, hi: float, what: str) -> np.ndarray:
    """A driving image's values (0 to 1) as ``field``'s values from LO (at 0) to HI (at 1), in float64 (LO itself,
    not float32's rounding of it). Linear, except a roughness: LO and HI are GGX alphas (the stack's unit), and the
    values between them are linear in the artist's roughness (the square root of alpha), as the sidebar's maps and
    Blender's roughness maps are, so one image gives one material whichever way it is baked (linear in alpha, a
    grey of 0.5 over 0.01:0.4 had baked 0.205 where the sidebar's same range bakes 0.134)."""
    t = img.astype(np.float64)
    if field != "roughness":
        return lo + (hi - lo) * t
    if lo < 0.0 or hi < 0.0:
        raise BadInput(f"{what}: a roughness range must not be negative (GGX alpha), got [{lo}, {hi}]")
    a, b = artist_roughness_from_alpha(lo), artist_roughness_from_alpha(hi)
    return alpha_from_artist_roughness(a + (b - a) * t)


def _space(name: str | None, what: str) -> str:
    try:
        return colour_maps.colour_space(name or "auto")
    except ValueError as e:
        raise BadInput(f"{what}: {e}") from None


def read_map(file: Path, field: str, space: str) -> tuple[np.ndarray, str]:
    """A driving image's values for ``field`` by the colour-space rule, and how they were decoded."""
    if file.is_dir():  # "image not found" said of a folder that is there
        raise ValueError(f"{file} is a folder, not an image file")
    pixels, is_float, tag, alpha = read_image_file(file)
    how = colour_maps.decoding(field, space, is_float, tag)
    return colour_maps.decode(pixels, how, alpha), ("sRGB -> linear" if how == "srgb" else "raw")


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
        path, file, lo, hi, space = parse_map(spec)
        try:
            field = parse_parameter_path(stack, path)[2]
            img, how = read_map(file, field, space)
        except (FileNotFoundError, ValueError) as e:
            raise BadInput(f"--map {path}: {e}") from None
        maps[path] = map_range(field, img, lo, hi, f"--map {path}")
        sources[path] = f"{file.name} ({how}) [{lo}, {hi}]"
    try:
        spatial = SpatialStack(stack, maps)
    except ValueError as e:
        raise BadInput(str(e)) from None
    mix = mask = None
    if args.mix or args.mask:
        if not (args.mix and args.mask):
            raise BadInput("--mix and --mask go together: --mix PRESET --mask IMAGE blends the two stacks")
        m = _MASK.match(str(args.mask))
        space = _space(m.group("space"), f"--mask {args.mask}")
        args.mask = Path(m.group("file"))
        try:
            mix = SpatialStack(preset(args.mix))
            mask = read_map(args.mask, "mask", space)[0][..., 0].astype(np.float64)
        except (FileNotFoundError, ValueError) as e:
            raise BadInput(f"--mix/--mask: {e}") from None
        check_mask(mask, args.mask)
        if spatial.resolution is not None and spatial.resolution != mask.shape:
            raise BadInput(
                f"--mask is {mask.shape[1]}x{mask.shape[0]} but the driving images are "
                f"{spatial.resolution[1]}x{spatial.resolution[0]}: they must share a resolution"
            )
        sources["mask"] = f"{args.mask.name} (mixes in {args.mix})"
    native = mask.shape if mask is not None else (spatial.resolution or (1, 1))
    res = tuple(args.resolution) if args.resolution else native
    if not (1 <= res[0] <= native[0] and 1 <= res[1] <= native[1]):
        raise BadInput(
            f"bake resolution {res[1]}x{res[0]} must be between 1x1 and the driving images' {native[1]}x{native[0]}"
        )
    return [Job(args.name or args.preset, spatial, res, sources, mix, mask)]


def check_mask(mask: np.ndarray, path: Path) -> None:
    """A mask blends two latents, so it must hold finite values in [0, 1]: outside it extrapolates."""
    bad = ~np.isfinite(mask) | (mask < 0.0) | (mask > 1.0)
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise BadInput(
            f"--mask {path}: {int(bad.sum())} texel(s) outside [0, 1], first {mask[y, x]} at "
            f"(x={x}, y={y}); a mask's first channel must hold finite values in [0, 1]"
        )


def addon_module(bpy, name: str):
    """The module ``name`` (``bake_inputs``, ``bake_state``) of the add-on whose properties the materials carry.

    Inside Blender with the extension enabled that is the enabled extension's (its properties
    are registered); with the plain ``bpy`` module nothing is registered, so this checkout's
    add-on is registered here.
    """
    import importlib

    prop = bpy.types.Material.bl_rna.properties.get("neural_layers")
    if prop is None:
        from addon import blender

        blender.register()
        prop = bpy.types.Material.bl_rna.properties["neural_layers"]
    owners = [
        c
        for c in bpy.types.PropertyGroup.__subclasses__()
        if c.__name__ == prop.fixed_type.identifier and getattr(c, "is_registered", False)
    ]
    package = owners[-1].__module__.rsplit(".", 1)[0] if owners else "addon.blender"
    return importlib.import_module(f"{package}.{name}")


def material_reader(bpy):
    """``spatial_stack_from_material`` of the add-on whose properties the materials carry (``addon_module``). The
    stack it returns is rebuilt with this checkout's core classes, which the rest of the bake uses."""
    read = addon_module(bpy, "bake_inputs").spatial_stack_from_material

    def spatial_stack(mat):
        found = read(mat)
        if found is None:
            return None
        spatial, sources = found
        return SpatialStack(Stack.from_json(spatial.stack.to_json()), dict(spatial.maps)), sources

    return spatial_stack


def blend_jobs(args) -> list[Job]:
    if not args.blend.is_file():
        raise BadInput(f"--blend: file not found: {args.blend}")
    try:
        import bpy
    except ImportError:
        raise BadInput(
            "--blend needs Blender's Python or the bpy module (pip install bpy==5.0.1) to read "
            f"{args.blend.name}; --preset bakes need neither"
        ) from None

    spatial_stack_from_material = material_reader(bpy)
    inputs_digest = addon_module(bpy, "bake_state").inputs_digest
    try:
        bpy.ops.wm.open_mainfile(filepath=str(args.blend))
    except RuntimeError as e:
        raise BadInput(f"--blend {args.blend}: cannot open it as a .blend file ({str(e).strip()})") from None
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
        jobs.append(Job(name, spatial, res, sources, inputs=partial(inputs_digest, mat, res)))
    if not jobs:
        raise BadInput(f"{args.blend.name} has no material with a layer stack")
    return jobs


def attach_textures(jobs: list[Job], out: Path, model_id: str, log=print) -> None:
    """``--attach``: point each material of ``jobs`` in the open .blend at its published texture in ``out``, as the
    add-on's own bake does (``bake_state.attach_texture``: the path relative to the .blend), and save the .blend, so
    a render of it uses them. A material is attached only where its texture is published and its own settings
    (Model Size, Refine (s)) key the bake the command made (``model_id``: --model, --refine, calibrated), so the
    add-on finds the texture current; BadInput names the others, after the .blend is saved with the rest."""
    import bpy

    state = addon_module(bpy, "bake_state")
    user_error = addon_module(bpy, "operator_base").UserError
    refused, attached = [], []
    for job in jobs:
        mat = bpy.data.materials[job.name]
        key = job.key(model_id)
        if not _fresh(out, job, key):
            refused.append(f"{job.name!r} has no published texture yet (attach once every shard is done)")
            continue
        try:
            own = state.bake_model_key(state.bake_size(mat), mat.neural_layers.bake_refine)
        except user_error as e:  # a model size it cannot resolve, models that are not there
            refused.append(f"{job.name!r}: {e}")
            continue
        if own != model_id:
            refused.append(
                f"{job.name!r}: its Model Size and Refine (s) key its bakes {own!r}, this bake is {model_id!r} "
                "(bake with its --model and --refine, calibrated)"
            )
            continue
        state.attach_texture(mat, str((out / f"{job.file}.exr").resolve()), key, job.resolution)
        attached.append(job.name)
    if attached:
        bpy.ops.wm.save_mainfile()
        log(f"attached {attached} to their textures in {bpy.data.filepath}")
    if refused:
        raise BadInput("--attach: " + "; ".join(refused))


def _atomic_save_npy(path: Path, array: np.ndarray) -> None:
    with files.publishing(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


def _atomic_write_text(path: Path, text: str) -> None:
    files.write_bytes(path, text.encode("utf-8"))


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


def _check_output_folder(out: Path, jobs: list[Job]) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = files.temp_path(out / "write-test")  # unique: shards probe the same folder at once
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise BadInput(f"--out {out}: not writable ({e})") from None
    seen: dict[str, str] = {}
    for job in jobs:  # file systems that ignore case would still put two of them in one file
        other = seen.setdefault(job.file.casefold(), job.name)
        if other != job.name:
            raise BadInput(
                f"materials {other!r} and {job.name!r} would both write {job.file}.exr on a file system "
                f"that ignores case; rename one (or bake them into different --out folders)"
            )


def _band_folder(out: Path, job: Job) -> Path:
    return out / f".{job.file}.bands"


def _band_path(out: Path, job: Job, key: str, band: int, band_rows: int) -> Path:
    """Where band ``band`` of bands of ``band_rows`` rows of the material's bake ``key`` is kept: the key, the rows a
    band holds and its index, all that decides which texels it holds, so a band is only reused for the same rows (a
    resume with another ``--band-rows`` took the bands of the first run by their index alone, and published them
    out of place)."""
    return _band_folder(out, job) / f"{key}_{band_rows}rows_{band:04d}.npy"


def _band_rows(job: Job, band: int, band_rows: int) -> int:
    return min((band + 1) * band_rows, job.resolution[0]) - band * band_rows


def _load_band(path: Path, rows: int, width: int) -> np.ndarray:
    """A kept band, or ValueError if it is not whole: the right shape, float32 and finite."""
    try:
        band = np.load(path, allow_pickle=False)
    except (EOFError, OSError, ValueError) as e:
        if isinstance(e, FileNotFoundError):
            raise
        raise ValueError(f"band {path.name} is unreadable ({e})") from None
    want = (rows * width, len(CHANNEL_NAMES))
    if band.shape != want or band.dtype != np.float32:
        raise ValueError(f"band {path.name} is {band.dtype} {band.shape}, expected float32 {want}")
    if not np.isfinite(band).all():
        raise ValueError(f"band {path.name} holds non-finite texels")
    return band


def _kept_band(target: Path, rows: int, width: int, log) -> bool:
    """Whether a band from an earlier run can be reused; an invalid one is removed so it is baked again."""
    if not target.is_file():
        return False
    try:
        _load_band(target, rows, width)
        return True
    except FileNotFoundError:
        return False
    except ValueError as e:
        log(f"{e}: baking it again")
        target.unlink(missing_ok=True)
        return False


def _bake_band(job: Job, band: int, band_rows: int, encode, dedup: bool, cache: dict, bar) -> tuple[np.ndarray, object]:
    if job.name not in cache:
        cache[job.name] = job.texels()
    arrays, mixed, mask = cache[job.name]
    h, w = job.resolution
    rows = slice(band * band_rows * w, min((band + 1) * band_rows, h) * w)
    texels, st = bake_texels(
        arrays.take(rows), encode, dedup=dedup, progress=lambda f: bar.update(f"{job.name} band {band}", f)
    )
    if mixed is not None:  # blend in latent space: one intermediate lobe per texel
        other, st2 = bake_texels(mixed.take(rows), encode, dedup=dedup)
        texels = ((1.0 - mask[rows]) * texels + mask[rows] * other).astype(np.float32)
        st.unique += st2.unique
    if not np.isfinite(texels).all():
        raise ValueError(f"{job.name} band {band}: non-finite latents; nothing was kept")
    return texels, st


def encoder_model_key(encode, model: str, calibrate: bool = True) -> str:
    """The model part of the bake keys of textures baked with ``encode`` (``textures.bake.model_key``): the size
    ``model`` and, when the encoder tells it (``encode.metadata``), the decoder file's digest and the refinement
    budget; calibrated when the textures are (``calibrate``, with an encoder that carries its models:
    ``neural_encoder``'s), as the add-on keys its own calibrated bakes (``bake_state.bake_model_key``)."""
    metadata = getattr(encode, "metadata", None) or {}
    calibrated = calibrate and getattr(encode, "models", None) is not None
    return model_key(model, metadata.get("model_digest"), metadata.get("refine_s", 0.0), calibrated=calibrated)


def run(
    jobs: list[Job],
    out: Path,
    encode,
    model: str,
    shard: tuple[int, int],
    band_rows: int,
    dedup: bool = True,
    log=print,
    calibrate: bool = True,
) -> dict:
    """Bake this shard's items, assemble every material whose bands are all present.

    The bake key of a material hashes its inputs and the model: the size and, when the encoder
    tells it (``encode.metadata["model_digest"]``), the decoder file's digest, so bands and
    textures of a retrained model are never reused; the refinement budget (``--refine``); and whether the
    textures are calibrated (``calibrate``, with an encoder that carries its models: ``neural_encoder``'s)."""
    model_metadata = getattr(encode, "metadata", None) or {}
    models = getattr(encode, "models", None) if calibrate else None
    model_id = encoder_model_key(encode, model, calibrate)
    _check_output_folder(out, jobs)
    files.remove_stale_temps(out)
    # Items are numbered over every job, published or not, so that a shard takes the same items whenever it runs:
    # numbered over the unpublished ones only, a shard run after another had published a material took items
    # shifted by that material's bands, and the shards run one after another left materials unbaked.
    items, fresh = [], set()
    for job in jobs:
        key = job.key(model_id)
        if _fresh(out, job, key):
            log(f"{job.name}: up to date, skipped")
            _remove_bands(out, job)
            fresh.add(id(job))
        bands = -(-job.resolution[0] // band_rows)
        items += [(job, key, b) for b in range(bands)]
    mine = [it for k, it in enumerate(items) if k % shard[1] == shard[0] and id(it[0]) not in fresh]
    bar = ProgressBar(len(mine))
    stats = {"bands_baked": 0, "bands_skipped": 0, "texels": 0, "unique": 0, "seconds": 0.0, "assembled": []}
    stats["model_key"] = model_id
    cache: dict[str, object] = {}
    clamped: set[tuple[str, str]] = set()
    for job, key, band in mine:
        folder = _band_folder(out, job)
        target = _band_path(out, job, key, band, band_rows)
        rows = _band_rows(job, band, band_rows)
        if _kept_band(target, rows, job.resolution[1], log) or _fresh(out, job, key):
            stats["bands_skipped"] += 1  # kept from an earlier run, or another shard already published
            bar.update(f"{job.name} band {band} (kept)", advance=True)
            continue
        texels, st = _bake_band(job, band, band_rows, encode, dedup, cache, bar)
        for attempt in (0, 1):  # a shard that just published may have removed the (then empty) folder
            folder.mkdir(exist_ok=True)
            try:
                _atomic_save_npy(target, texels)
                break
            except FileNotFoundError:
                if attempt:
                    raise
        bar.update(f"{job.name} band {band}", advance=True)
        stats["bands_baked"] += 1
        stats["texels"] += st.texels
        stats["unique"] += st.unique
        stats["seconds"] += st.seconds
        for note in st.clamped:  # the networks' trained ranges: said once a job and field, not once a band
            field = note.split(":", 1)[0]  # a band's note counts its own rows
            if (job.name, field) not in clamped:
                clamped.add((job.name, field))
                log(f"{job.name}: {note}; baked clamped")
    bar.close()
    for job in jobs:

        def rebake(band, job=job):
            return _bake_band(job, band, band_rows, encode, dedup, cache, bar)[0]

        inputs = job.inputs(model_id) if job.inputs is not None else None
        if assemble(
            out, job, job.key(model_id), model, band_rows, stats, rebake, log, model_metadata, models, cache, inputs
        ):
            stats["assembled"].append(job.name)
            log(f"{job.name}: wrote {out / (job.file + '.exr')} ({job.resolution[1]}x{job.resolution[0]})")
    return stats


def assemble(
    out: Path,
    job: Job,
    key: str,
    model: str,
    band_rows: int,
    stats: dict,
    rebake,
    log=print,
    model_metadata: dict | None = None,
    models=None,
    cache: dict | None = None,
    inputs: str | None = None,
) -> bool:
    """Publish the material's texture if all its bands are present; True if this process published it.

    Several shards may get here at once: each reads the bands and publishes (atomically, the
    same texels); bands are removed only after a publish, so a shard that finds one gone checks
    that the texture it was about to write is there. A band found damaged is baked again by
    ``rebake(band) -> texels``. ``model_metadata`` (the encoder's decoder size and digest) goes into the texture.
    With ``models`` (the encoder's), a material without a mix gets its albedo calibration
    (``textures.calibration``) from its texels and stacks (``cache``: ``run``'s, holding them when this
    process baked bands of it), and every texture the count of mip levels it may be filtered across
    (``textures.filtering``). ``inputs`` (a --blend material's ``Job.inputs``) goes into the texture's header.
    """
    h, w = job.resolution
    bands = -(-h // band_rows)
    paths = [_band_path(out, job, key, b, band_rows) for b in range(bands)]
    if _fresh(out, job, key) or not all(p.is_file() for p in paths):
        return False
    t0 = time.perf_counter()
    # The bands go straight into the base level of a half-float mip chain, the values the file stores (no
    # texture-sized copy besides the chain).
    chain = MipChain.empty(h, w, len(CHANNEL_NAMES), dtype=np.float16)
    texels = chain[0].reshape(h * w, -1)
    for b, p in enumerate(paths):
        start = b * band_rows * w
        try:
            band = _load_band(p, _band_rows(job, b, band_rows), w)
        except FileNotFoundError:
            if _fresh(out, job, key):
                return False  # another shard published it and removed the bands
            raise RuntimeError(
                f"{job.name}: its bands were removed while assembling, and no texture for these "
                f"inputs was published (another bake of different inputs into {out}?)"
            ) from None
        except ValueError as e:  # damaged after it was kept: never reused, baked again here
            log(f"{e}: baking it again")
            p.unlink(missing_ok=True)
            band = rebake(b)
        chain.write_texels(start, band)  # a latent beyond the half range: a clear error, and the band is kept
    meta = {"stack": job.spatial.stack.to_json(), "model": model, "key": key, **(model_metadata or {})}
    if inputs is not None:
        meta["inputs"] = inputs
    calibration_s = None
    if models is not None and job.mix is None:  # a blended texel's latent is no stack's: nothing to walk
        t = time.perf_counter()
        arrays = ((cache or {}).get(job.name) or job.texels())[0]
        meta["calibration"] = calibrate_baked(arrays, texels, models).to_text()
        calibration_s = round(time.perf_counter() - t, 3)
    tex = LatentTexture(chain.fill(), meta)
    if models is not None:  # the mip levels the renderer may filter across (textures.filtering)
        record_filter_levels(tex, models)
    tex.write_exr(out / f"{job.file}.exr")
    sidecar = {
        "key": key,
        "exr_bytes": (out / f"{job.file}.exr").stat().st_size,  # a texture cut short later is not fresh (``_fresh``)
        "material": job.name,
        "stack": job.spatial.stack.to_dict(),
        "maps": job.sources,
        "resolution": [w, h],
        "model": model,
        "seconds_assemble_and_write": round(time.perf_counter() - t0, 3),
        "seconds_calibration": calibration_s,
        "this_shard": {
            "texels": stats["texels"],
            "unique_texels": stats["unique"],
            "encode_seconds": round(stats["seconds"], 3),
        },
    }
    _atomic_write_text(out / f"{job.file}.json", json.dumps(sidecar, indent=2))
    _remove_bands(out, job)
    return True


def _remove_bands(out: Path, job: Job) -> None:
    """Once the texture is published its bands are not needed, nor those of earlier inputs."""
    folder = _band_folder(out, job)
    if not folder.is_dir():
        return
    for entry in folder.glob("*.npy"):
        entry.unlink(missing_ok=True)
    files.remove_stale_temps(folder)
    with contextlib.suppress(OSError):
        folder.rmdir()  # only if empty: another shard may still be writing a temporary file there


def _fresh(out: Path, job: Job, key: str) -> bool:
    """Whether the published texture and its sidecar are both of these inputs, and the texture is whole: the size
    its sidecar recorded when it was published (a texture cut short, by a full disk or a copy that stopped, was
    taken as up to date, and its missing tiles failed only in the render). A sidecar that records no size (written
    before sidecars did) cannot tell: the texture is baked again."""
    exr = out / f"{job.file}.exr"
    try:
        sidecar = json.loads((out / f"{job.file}.json").read_text())
        if sidecar.get("key") != key or sidecar.get("exr_bytes") != exr.stat().st_size:
            return False
    except (OSError, ValueError, AttributeError):  # no texture or sidecar, or a sidecar that is not an object
        return False
    return _exr_key(exr) == key


def _exr_key(path: Path) -> str | None:
    """The bake key in a texture's header (the sidecar alone could describe another texture)."""
    from addon.core.textures.latent_texture import oiio_module

    inp = oiio_module().ImageInput.open(str(path))
    if inp is None:
        return None
    try:
        value = inp.spec().get_string_attribute("nlm:key")
        return value or None
    finally:
        inp.close()


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit code 2, instead of argparse's usage block
        raise BadInput(f"{message} (bake.py --help lists the options)")


def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = _Parser(prog="bake.py", description="Bake layered materials into latent textures.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--blend", type=Path, help=".blend file holding the materials")
    src.add_argument("--preset", help=f"bake a preset stack: {', '.join(sorted(PRESETS))}")
    ap.add_argument(
        "--material", action="append", help="material name in --blend (repeatable; default: all with a stack)"
    )
    ap.add_argument(
        "--attach",
        action="store_true",
        help="with --blend: point each baked material at its texture (as the sidebar's bake does) and save the "
        ".blend, so rendering it uses the textures; run it once every shard is done (a rerun skips what is up to "
        "date). A material is attached where its Model Size and Refine (s) match --model and --refine",
    )
    ap.add_argument(
        "--map",
        action="append",
        help="with --preset: PATH=IMAGE[@SPACE][:LO:HI] drives a parameter by an "
        "image. Colour space: an image driving albedo is decoded from sRGB to linear when it is stored "
        "as 8/16-bit integers without a linear tag (Blender's default sRGB); float images (EXR, HDR) are "
        "linear; every other parameter and the mask read the values raw (Blender's Non-Color). "
        f"@SPACE overrides it: {', '.join(colour_maps.COLOUR_SPACES)} (e.g. base.albedo=colour.png@linear). "
        "LO:HI are in the stack's own units (addon.core.stack): a roughness is the GGX alpha, the square of the "
        "roughness Blender's sidebar shows (sidebar 0.5 is 0.25 here); between them a roughness map is linear in "
        "the sidebar's roughness, as the sidebar's maps are",
    )
    ap.add_argument("--name", help="with --preset: output name (default: the preset's)")
    ap.add_argument("--mix", help="with --preset and --mask: a second preset blended in latent space")
    ap.add_argument(
        "--mask",
        type=Path,
        help="with --mix: IMAGE[@SPACE] whose first channel (0..1, raw unless @srgb) blends towards --mix",
    )
    ap.add_argument("--resolution", type=int, nargs=2, metavar=("H", "W"), help="bake resolution (<= the images')")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument(
        "--model",
        default="auto",
        help="decoder size whose latent space to bake into (auto: the default size, addon.core.neural.resolve_size)",
    )
    ap.add_argument("--shard", default="0/1", help="i/n: bake every n-th work item starting at i")
    ap.add_argument("--band-rows", type=int, default=256, help="rows per work item")
    ap.add_argument("--no-dedup", action="store_true", help="encode every texel, even repeated ones")
    ap.add_argument(
        "--no-calibrate",
        action="store_true",
        help="leave out each texture's albedo calibration against the reference (addon.core.textures.calibration: "
        "about a second per cluster of texels, at most 8, when a material is assembled)",
    )
    ap.add_argument(
        "--refine",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="refine the latents of distinct texels against the reference, in order, up to this many "
        "seconds in all (addon.core.neural.refine; cached in OUT/.refine)",
    )
    return ap.parse_args(argv)


def _bake(argv: list[str], encode) -> int:
    args = parse_args(argv)
    shard = parse_shard(args.shard)
    if args.band_rows < 1:
        raise BadInput(f"--band-rows must be >= 1, got {args.band_rows}")
    if args.preset is None and (args.map or args.mix or args.mask or args.name):
        raise BadInput("--map, --mix, --mask and --name go with --preset; in a .blend they are set on the material")
    if args.attach and args.blend is None:
        raise BadInput("--attach goes with --blend: it points the .blend's materials at their textures")
    if not (np.isfinite(args.refine) and args.refine >= 0):
        raise BadInput(f"--refine must be a number of seconds >= 0, got {args.refine}")
    jobs = blend_jobs(args) if args.blend else preset_job(args)
    if encode is None:
        try:
            encode = neural_encoder(args.model, refine_s=args.refine, refine_cache=args.out / ".refine")
        except (OSError, ValueError, ImportError) as e:  # missing (FileNotFoundError) or damaged models
            raise BadInput(f"--model {args.model}: {e}") from None
    model = getattr(encode, "metadata", {}).get("model", args.model)  # "auto" resolved by the encoder
    stats = run(
        jobs, args.out, encode, model, shard, args.band_rows, dedup=not args.no_dedup, calibrate=not args.no_calibrate
    )
    print(f"baked {stats['bands_baked']} band(s), kept {stats['bands_skipped']}, assembled {stats['assembled']}")
    if args.attach:
        attach_textures(jobs, args.out, stats["model_key"])
    return EXIT_DONE


@contextlib.contextmanager
def _signals_interrupt(fired: list):
    """SIGINT and SIGTERM raise :class:`Interrupted` (once: a second signal during the clean-up is ignored);
    ``fired`` receives the signal number."""

    def handler(signum, frame):
        if not fired:
            fired.append(signum)
            raise Interrupted(signum)

    previous = {}
    try:
        for sig in EXIT_SIGNAL:
            previous[sig] = signal.signal(sig, handler)
    except ValueError:  # not the main thread: signals stay as they are
        pass
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def main(argv: list[str] | None = None, encode=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    fired: list = []
    try:
        with _signals_interrupt(fired):
            try:
                return _bake(argv, encode)
            except KeyboardInterrupt:
                raise Interrupted(signal.SIGINT) from None
    except SystemExit as e:  # --help
        return EXIT_DONE if not e.code else EXIT_BAD_INPUT
    except BadInput as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Interrupted as e:
        print(
            f"\nerror: interrupted by {e}; finished bands are kept, rerun the same command to resume", file=sys.stderr
        )
        return EXIT_SIGNAL[e.signum]
    except Exception as e:  # a failed bake: one clear line, non-zero exit
        if fired:  # it failed because a signal cut a step short (an interrupted write, say): report the signal
            name = signal.Signals(fired[0]).name
            print(f"\nerror: interrupted by {name} ({type(e).__name__}: {e}); finished bands are kept", file=sys.stderr)
            return EXIT_SIGNAL[fired[0]]
        print(f"error: bake failed: {type(e).__name__}: {e}", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    code = main()
    if "bpy" in sys.modules and not getattr(sys.modules["bpy"].app, "module", True):
        sys.stdout.flush()
        os._exit(code)  # inside Blender: leave with the bake's exit code
    sys.exit(code)

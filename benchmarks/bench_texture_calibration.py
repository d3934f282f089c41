"""Latent textures calibrated by clusters of texels: each texel's albedo against the reference.

    python benchmarks/bench_texture_calibration.py --size tiny

A baked latent texture holds one latent per texel; the renderer calibrates it with a factor table per
cluster of texels (``addon.core.textures.calibration``, made by the bake). For textures of the kinds an
artist bakes (the demo's varnished tile floor, a flake colour that varies per texel, a coat roughness ramp,
a base colour gradient), it bakes the texture as ``bake_stack`` does and then, for some of its distinct
texels (the two most common, and random others), compares the directional albedo at the calibration's
grid angles (``neural.calibrate.COSINES``, normal incidence to 88.9 degrees) with reference walks of that
texel's stack on other seeds than the bake's:

- decoder: the texel's latent decoded as it is (how textures rendered before they were calibrated);
- texture: with the table of its cluster (how the renderer shades it now);
- own: with a calibration of that texel alone (``neural.calibrate.calibrate``: what a table per texel
  would give, a second per distinct texel).

Each figure is the whole albedo (exact top lobe + decoded part), |decoded / reference - 1| averaged over
RGB and the grid's angles ("all angles") or its four most grazing ones (83.7-88.9 degrees); "exits" is the
same for the light's split over exit elevations (the reference's walks binned by the cosine they leave
at, the quantity the table itself fits): the sum of the bins' absolute errors over the albedo.

Then where the user sees it: the demo's floor (its latent texture, baked as ``bake/demo.py`` bakes it) under
the demo's sky and area light, without the spheres, rendered in neural mode, calibrated and not, and in
reference mode (which shades each hit with its own texel's stack, from the same maps): the mean radiance
of the floor's pixels, whole and in bands of the angle between the view ray and the floor's normal (the
far floor is seen near grazing), neural / reference, with the noise of both.

Writes ``--out`` (markdown with this command) and a JSON beside it. The reference render does not depend
on the networks: ``--reference-cache FILE.npz`` keeps it (its key: resolution, samples, seed, reference
settings, scene).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT, ROOT / "benchmarks"):  # the add-on, and the benchmarks beside this file when imported
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from bench_fidelity import compare, object_means, reference_key, render_film  # noqa: E402
from bench_terminator import _Film, reference_film  # noqa: E402

from addon.core.neural import calibrate as cal  # noqa: E402
from addon.core.render.demo_scene import FLOOR_STACK, demo_scene, floor_maps  # noqa: E402
from addon.core.render.integrator import camera_hits  # noqa: E402
from addon.core.render.materials import LayeredSpec  # noqa: E402
from addon.core.stack import PRESETS  # noqa: E402
from addon.core.textures import LatentTexture  # noqa: E402
from addon.core.textures.bake import _bake_in_threads, bake_stack, neural_encoder  # noqa: E402
from addon.core.textures.calibration import TextureCalibration, calibrate_texture  # noqa: E402
from addon.core.textures.spatial import SpatialStack  # noqa: E402

REFERENCE_SEED = 7  # the bake's calibrations use seeds 0 .. 7 (one per cluster)
GRAZING = 4  # the last grid angles: cos theta 0.11 .. 0.02


def textures(seed: int = 1) -> dict[str, SpatialStack]:
    """The benchmark's spatially varying stacks, by name."""
    rng = np.random.default_rng(seed)
    side = 64
    ramp = np.tile(np.linspace(0.0, 1.0, side, dtype=np.float32), (side, 1))
    hue = np.stack([0.15 + 0.7 * ramp, 0.5 + 0.3 * np.sin(6.0 * ramp), 0.85 - 0.7 * ramp], axis=-1)
    return {
        "varnished tile floor (the demo's)": SpatialStack(FLOOR_STACK, floor_maps()),
        "red car paint, flake colour noise": SpatialStack(
            PRESETS["red_car_paint"],
            {"coatings[0].albedo": rng.uniform(0.05, 0.95, (side, side, 3)).astype(np.float32)},
        ),
        "coated gold, coat roughness ramp": SpatialStack(
            PRESETS["coated_gold"], {"coatings[0].roughness": (0.02 + 0.38 * ramp).astype(np.float32)}
        ),
        "lacquered plastic, base colour gradient": SpatialStack(
            PRESETS["lacquered_plastic"], {"base.albedo": hue.astype(np.float32)}
        ),
    }


def texel_errors(models, stack, texel: np.ndarray, table: np.ndarray) -> dict[str, np.ndarray]:
    """Per way of decoding (decoder, texture, own): the whole albedo's relative error (K,) per grid angle
    and the exit bins' (K,), against an independent reference."""
    z, proxy, top = texel[:96].reshape(3, 32), texel[96:98], texel[98:]
    ref = cal.reference_parts(stack, seed=REFERENCE_SEED)
    moments = cal.decoded_moments(models, z, *proxy, seed=REFERENCE_SEED, top=top)
    own = cal.calibrate(stack, models, z, proxy).table
    above = ref.albedo - ref.below_top  # the top lobe's first reflections: exact in every way of decoding
    out = {}
    for name, t in (("decoder", None), ("texture", table), ("own", own)):
        energy = moments.pairs.sum(axis=2) if t is None else cal.table_energy(moments, t)
        albedo = energy.sum(axis=1) + above
        out[name] = {
            "albedo": np.abs(albedo / ref.albedo - 1.0).mean(axis=-1),
            "exits": (np.abs(energy - ref.below_top_by_exit).sum(axis=1) / ref.albedo).mean(axis=-1),
        }
    out["reference_noise"] = (ref.albedo_stderr / ref.albedo).mean(axis=-1)
    return out


def measure(name: str, spatial: SpatialStack, encode, threads: int, n_random: int, seed: int, log) -> dict:
    arrays, (h, w) = spatial.texels()
    t = time.perf_counter()
    _, stats, (rows, distinct, counts) = _bake_in_threads(arrays, encode, True, 65536, None, None, threads)
    encode_s = time.perf_counter() - t
    t = time.perf_counter()
    calibration = calibrate_texture(rows, distinct, counts, encode.models)
    calibration_s = time.perf_counter() - t
    TextureCalibration.from_text(calibration.to_text())  # what the texture stores is what is measured
    which = calibration.at(distinct[:, :96].reshape(-1, 3, 32)).which
    common = list(np.argsort(-counts, kind="stable")[:2])
    others = [i for i in np.random.default_rng(seed).permutation(len(rows)) if i not in common][:n_random]
    per_texel = []
    for i in common + others:  # a loop over a few sampled texels, each seconds of reference walks
        e = texel_errors(encode.models, rows.stack(int(i)), distinct[i], calibration.tables[which[i]])
        per_texel.append(
            {
                "texel_share": float(counts[i] / counts.sum()),
                "cluster": int(which[i]),
                **{k: {m: v.tolist() for m, v in e[k].items()} if k != "reference_noise" else e[k].tolist() for k in e},
            }
        )
        log(f"[{name}] texel {len(per_texel)} of {len(common) + len(others)}")
    return {
        "name": name,
        "size": f"{w}x{h}",
        "distinct": int(len(rows)),
        "clusters": int(len(calibration.tables)),
        "encode_s": encode_s,
        "calibration_s": calibration_s,
        "texels": per_texel,
    }


WAYS = ("decoder", "texture", "own")
VIEW_BANDS = (0.0, 60.0, 75.0, 80.0, 85.0, 90.0)  # degrees between the view ray and the floor's normal


def floor_masks(scene) -> dict[str, np.ndarray]:
    """Flat pixel masks of the floor, whole and by the angle of the pixel centre's view ray to the normal."""
    cam = scene.camera
    py, px = np.divmod(np.arange(cam.width * cam.height), cam.width)
    prim, _ = camera_hits(scene, px, py)
    _, d = cam.generate_rays(px, py, np.full((len(px), 2), 0.5))
    theta = np.degrees(np.arccos(np.clip(-d[:, 2], -1.0, 1.0)))  # the floor's normal is +z
    floor = prim >= 0
    masks = {"whole floor": floor}
    for lo, hi in zip(VIEW_BANDS[:-1], VIEW_BANDS[1:], strict=True):
        masks[f"view {lo:g}-{hi:g} deg"] = floor & (theta >= lo) & (theta < hi)
    return {k: m for k, m in masks.items() if m.any()}


def render_level(tex, a) -> dict:
    """The floor's means in neural mode (calibrated, not) over reference mode's (see the docstring)."""
    scene = demo_scene(a.width, a.height, presets=(), floor_texture=tex)
    masks = floor_masks(scene)
    pixels = np.flatnonzero(masks["whole floor"])
    key = {**reference_key(a.width, a.height, a.samples, [a.seed]), "scene": "demo floor (varnished tiles)"}
    ref_mean, ref_se, ref_s = reference_film(scene, pixels, a, key)
    ref = object_means(_Film(ref_mean, ref_se), masks)
    out = {"reference_s": ref_s, "pixels": {k: int(m.sum()) for k, m in masks.items()}}
    out["filter_levels"] = tex.filter_levels
    every = LatentTexture(tex.levels, {k: v for k, v in tex.metadata.items() if k != "filter_levels"})
    variants = (("calibrated", True, tex), ("decoder alone", False, tex), ("calibrated, every level", True, every))
    for name, calibrate, texture in variants:
        scene.materials[0] = LayeredSpec(*_floor_spec(scene.materials[0], texture))
        film, secs = render_film(scene, "neural", a.samples, a.seed, None, calibrate, pixels)
        out[name] = {"seconds": secs, "bands": compare(object_means(film, masks), ref)}
    return out


def _floor_spec(spec, texture) -> tuple:
    """The floor's ``LayeredSpec`` fields with another latent texture."""
    return spec.stack, texture, spec.name, spec.latent, spec.spatial


def render_markdown(r: dict, a) -> list[str]:
    lines = [
        "## Where the user sees it: the demo's floor, neural / reference",
        "",
        f"{a.width}x{a.height} pixels, {a.samples} samples per pixel, the floor's pixels only (reference "
        f"{r['reference_s']:.0f} s; neural calibrated {r['calibrated']['seconds']:.1f} s, decoder alone "
        f"{r['decoder alone']['seconds']:.1f} s). The bake measured {r['filter_levels']} filterable mip level(s) "
        "(`addon.core.textures.filtering`); *every level* filters the latents across the whole chain, as "
        "textures without that measurement are looked up. Noise: the relative standard errors of neural and "
        "reference.",
        "",
        "| floor pixels | pixels | calibrated (mean of RGB) | R / G / B | decoder alone | R / G / B | "
        "calibrated, every level | noise |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for band, c in r["calibrated"]["bands"].items():
        u = r["decoder alone"]["bands"][band]
        e = r["calibrated, every level"]["bands"][band]
        lines.append(
            f"| {band} | {r['pixels'][band]} | {c['ratio']:.3f} +- {c['ratio_stderr']:.3f} | "
            + " / ".join(f"{x:.3f}" for x in c["rgb_ratio"])
            + f" | {u['ratio']:.3f} +- {u['ratio_stderr']:.3f} | "
            + " / ".join(f"{x:.3f}" for x in u["rgb_ratio"])
            + f" | {e['ratio']:.3f} +- {e['ratio_stderr']:.3f}"
            + f" | {c['neural_rel_stderr']:.3f}, {c['reference_rel_stderr']:.3f} |"
        )
    return lines + [""]


def summary(result: dict) -> dict:
    """Per way: the mean over the sampled texels of (all angles, grazing) for albedo and exits, and the
    worst texel's albedo error at grazing."""
    out = {}
    for way in WAYS:
        a = np.array([t[way]["albedo"] for t in result["texels"]])
        x = np.array([t[way]["exits"] for t in result["texels"]])
        out[way] = {
            "albedo_all": float(a.mean()),
            "albedo_grazing": float(a[:, -GRAZING:].mean()),
            "exits_all": float(x.mean()),
            "exits_grazing": float(x[:, -GRAZING:].mean()),
            "worst_grazing": float(a[:, -GRAZING:].mean(axis=1).max()),
        }
    out["reference_noise"] = float(np.mean([t["reference_noise"] for t in result["texels"]]))
    return out


def markdown(results: list[dict], cmd: str, size: str, render: dict | None = None, a=None) -> str:
    lines = [
        "# Latent textures: calibrated by clusters of texels",
        "",
        f"Command: `{cmd}`",
        "",
        *_paragraphs((__doc__ or "").split("\n\n", 2)[2].rsplit("Writes", 1)[0]),
        f"Decoder: {size}. Percent; lower is better.",
        "",
    ]
    for r in results:
        s = summary(r)
        lines += [
            f"## {r['name']}",
            "",
            f"{r['size']} texels, {r['distinct']} distinct, {r['clusters']} cluster(s); encoded in "
            f"{r['encode_s']:.2f} s, calibrated in {r['calibration_s']:.1f} s; {len(r['texels'])} texels "
            f"measured (reference noise {100 * s['reference_noise']:.1f}% of the albedo, per angle and channel).",
            "",
            "| | albedo, all angles | albedo, 83.7-88.9 deg | exits, all angles | exits, 83.7-88.9 deg | "
            "worst texel, albedo at 83.7-88.9 deg |",
            "|---|---|---|---|---|---|",
        ]
        for way in WAYS:
            v = s[way]
            lines.append(
                f"| {way} | {100 * v['albedo_all']:.1f} | {100 * v['albedo_grazing']:.1f} | "
                f"{100 * v['exits_all']:.1f} | {100 * v['exits_grazing']:.1f} | {100 * v['worst_grazing']:.1f} |"
            )
        lines.append("")
    if render is not None:
        lines += render_markdown(render, a)
    return "\n".join(lines)


def _paragraphs(text: str) -> list[str]:
    """Markdown of a docstring's paragraphs: lines joined, list items kept one per line."""
    out = []
    for block in text.strip().split("\n\n"):
        items = [" ".join(part.split()) for part in ("\n" + block).split("\n- ")]
        if items[0]:
            out.append(items[0])
        out += [f"- {item}" for item in items[1:]]
        out.append("")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="tiny", help="decoder size (default: tiny, the renderer's)")
    ap.add_argument(
        "--texels", type=int, default=6, help="random distinct texels per texture, besides the two most common"
    )
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--width", type=int, default=96, help="the floor's render (--no-render: none)")
    ap.add_argument("--height", type=int, default=54)
    ap.add_argument("--samples", type=int, default=256)
    ap.add_argument("--no-render", dest="render", action="store_false")
    ap.add_argument("--reference-cache", type=Path, default=None, help="NPZ of the reference render (read or written)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "texture_calibration.md")
    a = ap.parse_args(argv)
    if a.texels < 0 or a.threads < 1 or a.samples < 2 or a.width < 8 or a.height < 8:
        ap.error(
            f"--texels must be >= 0, --threads >= 1, --samples >= 2 and --width, --height >= 8; got {a.texels}, "
            f"{a.threads}, {a.samples}, {a.width}, {a.height}"
        )
    cmd = "python benchmarks/bench_texture_calibration.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    encode = neural_encoder(a.size, threads=a.threads)

    def log(s):
        print(s, file=sys.stderr, flush=True)

    results = [measure(n, sp, encode, a.threads, a.texels, a.seed, log) for n, sp in textures().items()]
    render = None
    if a.render:
        floor, _ = bake_stack(textures()["varnished tile floor (the demo's)"], encode, threads=a.threads)
        render = render_level(floor, a)
        log("[render] done")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(markdown(results, cmd, encode.models.size, render, a) + "\n")
    data = {"command": cmd, "results": results, "render": render}
    a.out.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n")
    print(json.dumps({r["name"]: summary(r) for r in results}, indent=1))


if __name__ == "__main__":
    main()

"""Layering and sampling benchmark: encoding speed, held-out error per coating count, sampling efficiency.

    python benchmarks/bench_layering.py --threads 2 --update-cards

writes ``docs/layering.md`` (tables, with this command), ``docs/layering_lobes_<size>.png`` (reference vs
neural lobe images of held-out stacks) and, with ``--update-cards``, the measured speed and errors into
``addon/models/layering_<size>.json``. Every shipped decoder size that has a layering model is measured.

    python benchmarks/bench_layering.py --errors-only --sizes paper --heldout cache/data/validation_layered.npz \
        --out cache/v

measures the error tables alone on another set of ``onnx_export.heldout_layered`` (a validation set, a
set of training stacks), for choosing between training rounds without looking at the held-out set.

- Speed: stacks encoded per second by ``encode_stack`` (one stack per call) and by
  ``encode_arrays`` + ``proxy_params`` (N distinct stacks in one call), for 1 to 3 coatings, ONNX Runtime on CPU.
- Error: the runtime path (encoders + layering network + decoder, no projection, no per-material
  optimisation) against the reference lobes of ``tests/data/heldout_layered.npz``: relative RMSE of the
  lobe images at 0/30/60/75 degrees (median, 90th percentile), the absolute directional-albedo error,
  and its sign per incident elevation (the albedo bias: median relative error, > 0 too bright), with
  the single-layer held-out materials through the encoder and decoder alone as the baseline row, and
  the reciprocity of the decoded lobes (the lobe with the decoder's two directions swapped against it);
  and the lobe error of the same latents with their albedo calibration, the renderer's default for a
  material's own latent (``heldout_layered.runtime_errors(..., calibrated=True)``).
- Sampling efficiency: variance of the one-sample estimate of the radiance reflected from an analytic
  environment (``benchmarks/sampling_efficiency.sky_radiance``) at equal sample count, for cosine sampling
  and for the top interface's GGX lobe, divided by the proxy's (sigma, w from the sampling network).
  Variances are relative (var / mean^2), averaged over outgoing elevations cos = 0.3, 0.6, 0.9.
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
sys.path.insert(0, str(ROOT))

from addon.core import lobe  # noqa: E402
from addon.core.neural import MODEL_DIR, SIZES, encode_arrays, encode_stack, load_models, top_coat  # noqa: E402
from addon.core.stack import StackArrays  # noqa: E402
from benchmarks.sampling_efficiency import (  # noqa: E402
    cosine_sampler,
    ggx_sampler,
    material_sampler,
    one_bounce_variance,
)
from onnx_export.data import sample_layered_params  # noqa: E402
from onnx_export.heldout_layered import DIFFUSE_INDEX, SPECULAR_INDEX, load, runtime_errors  # noqa: E402

HELDOUT = ROOT / "tests" / "data" / "heldout_layered.npz"


def shown_path(p: Path) -> str:
    """``p`` relative to the repository where it lies inside it (no machine's paths in the tables)."""
    p = p.resolve()
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else p.name


def speed(models, reps: int, batch: int) -> dict:
    rng = np.random.default_rng(0)
    out = {}
    for c in (1, 2, 3):
        arrays = sample_layered_params(rng, batch, c)
        stacks = [arrays.stack(i) for i in range(reps)]
        encode_stack(stacks[0], models)  # warm up
        t = time.perf_counter()
        for s in stacks:  # one call per stack: the interactive case
            encode_stack(s, models)
        single = reps / (time.perf_counter() - t)
        models.proxy_params(encode_arrays(arrays.take(slice(0, 64)), models))
        t = time.perf_counter()
        models.proxy_params(encode_arrays(arrays, models))
        batched = batch / (time.perf_counter() - t)
        out[c] = {"single_per_s": single, "batched_per_s": batched, "batch": batch}
    return out


def sampling_ratios(models, stacks, n: int) -> list[dict]:
    ct = np.array([0.3, 0.6, 0.9])
    wo = np.stack([np.sqrt(1 - ct**2), np.zeros(3), ct], axis=1)
    rows = []
    for i, s in enumerate(stacks):
        z = encode_arrays(StackArrays.from_stacks([s]), models)
        p = models.proxy_params(z)
        sigma, w = p[0]
        top = top_coat(s)
        brdf = lambda wi, wo_, z=z[0]: models.eval_brdf(z, wi, wo_, top)  # noqa: E731
        rel = {}
        for name, smp in (  # "proxy": the renderer's sampler (with the exact top lobe's for a remainder decoder)
            ("proxy", material_sampler(models, sigma, w, top)),
            ("cosine", cosine_sampler()),
            ("ggx_top", ggx_sampler(s.coatings[-1].roughness)),
        ):
            mean, var = one_bounce_variance(brdf, wo, smp, n, seed=11 + i)
            rel[name] = float(np.mean(var / np.maximum(mean, 1e-12) ** 2))
        rows.append(
            {
                "config": i,
                "sigma": float(sigma),
                "w": float(w),
                "rel_var": rel,
                "cosine_over_proxy": rel["cosine"] / rel["proxy"],
                "ggx_over_proxy": rel["ggx_top"] / rel["proxy"],
            }
        )
    return rows


def lobe_figure(res: dict, data: dict, size: str, path: Path, per_count: int = 2) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    picks = [(c, k) for c in sorted(res) for k in range(min(per_count, len(res[c]["index"])))]
    angles = list(data["angles"])
    fig, axes = plt.subplots(len(picks), 2 * len(angles), figsize=(2 * len(angles) * 1.3, len(picks) * 1.45))
    for r, (c, k) in enumerate(picks):
        i = res[c]["index"][k]
        for a, t in enumerate(angles):
            ref = data["lobe"][i, a]
            neu = res[c]["lobes"][k, a]
            scale = 1.0 / max(float(np.percentile(ref, 99.5)), 1e-6)
            for j, (img, lab) in enumerate(((ref, "ref"), (neu, "neural"))):
                ax = axes[r, 2 * a + j]
                ax.imshow(lobe.to_display(img, scale))
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(f"{lab} {t:.0f}°", fontsize=7)
            axes[r, 2 * a + 1].set_xlabel(f"err {res[c]['errors'][k, a]:.2f}", fontsize=6)
        axes[r, 0].set_ylabel(f"#{i}: {c} coat.", fontsize=7)
    fig.suptitle(f"held-out stacks: reference vs layering network, decoder {size}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=200, help="stacks encoded one at a time")
    ap.add_argument("--batch", type=int, default=8192, help="stacks encoded in one batched call")
    ap.add_argument("--samples", type=int, default=8192, help="samples per outgoing direction (variance)")
    ap.add_argument(
        "--heldout",
        type=Path,
        default=HELDOUT,
        help="the stacks and reference lobes (onnx_export.heldout_layered: held-out, validation or training-fit set)",
    )
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--update-cards", action="store_true")
    ap.add_argument(
        "--errors-only",
        action="store_true",
        help="the error tables only, no speed and no sampling (a validation set, a training-fit set)",
    )
    ap.add_argument("--sizes", nargs="+", choices=SIZES, default=None, help="decoder sizes (default: all shipped)")
    a = ap.parse_args(argv)
    if a.errors_only and a.update_cards:
        ap.error("--update-cards records speed and sampling too: run without --errors-only")
    cmd = "python benchmarks/bench_layering.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    data = load(a.heldout)
    set_name = "Held-out" if a.heldout.resolve() == HELDOUT else "Stack"
    a.out.mkdir(parents=True, exist_ok=True)
    # single layers through the encoder and the same decoder: whether a bias is the layering network's
    single_path = a.heldout.with_name("heldout_single.npz")
    single_data = load(single_path) if single_path.exists() else None
    if single_data is not None and not np.allclose(single_data["angles"], data["angles"]):
        print(
            f"{single_path} is measured at other elevations than {a.heldout}: no single-layer baseline row",
            file=sys.stderr,
        )
        single_data = None
    sizes = [s for s in (a.sizes or SIZES) if (MODEL_DIR / f"layering_{s}.onnx").exists()]
    if not sizes:
        ap.error(f"no layering model of size {', '.join(a.sizes or SIZES)} under {MODEL_DIR.name}/")
    lines = [
        "# Layering network and sampling network: measurements",
        "",
        f"Made by `{cmd}` (CPU, ONNX Runtime, {a.threads} threads on a 2-core machine whose speed varies by "
        f"up to 1.5x between runs). {set_name} set: `{shown_path(a.heldout)}` ({len(data['stacks'])} stacks: "
        + ", ".join(f"{n} with {c} coating{'s' * (c > 1)}" for c, n in enumerate(np.bincount(data["n_coatings"])) if n)
        + f"; made by `{data['command']}`).",
        "",
    ]
    results = {}
    for size in sizes:
        models = load_models(size, threads=a.threads)
        res = runtime_errors(models, data)
        calibrated = runtime_errors(models, data, calibrated=True)
        single = runtime_errors(models, single_data)[0] if single_data is not None else None
        lobe_figure(res, data, size, a.out / f"layering_lobes_{size}.png")
        results[size] = {"errors": res}
        lines += [
            f"## Decoder `{size}`",
            "",
            f"### {set_name} error by number of coatings (runtime path, no projection)",
            "",
            "Layers = base + coatings (a two-layer stack has one coating). Reference noise: the stored "
            "reference's own relative standard error, which the lobe error includes.",
            "",
            "| coatings | layers | stacks | lobe error median | lobe error p90 | reference noise median / p90 | "
            "albedo abs. error mean | albedo abs. error p90 |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for c, r in res.items():
            e, al, nz = r["errors"], r["albedo_error"], r["reference_noise"]
            lines.append(
                f"| {c} | {c + 1} | {len(r['index'])} | {np.median(e):.3f} | {np.percentile(e, 90):.3f} | "
                f"{np.median(nz):.3f} / {np.percentile(nz, 90):.3f} | {al.mean():.4f} | {np.percentile(al, 90):.4f} |"
            )
        lines += [
            "",
            "Calibrated: the same latents decoded with each stack's albedo calibration, as the renderer decodes "
            "a material's own latent by default (`neural_material.make(..., calibrate=True)`: about a second of "
            "reference walks per stack, `addon.core.neural.calibrate`; latent textures are calibrated by clusters "
            "of texels, docs/texture_calibration.md).",
            "",
            "| coatings | layers | stacks | calibrated lobe error median | calibrated lobe error p90 | "
            "albedo abs. error mean | albedo abs. error p90 |",
            "|---|---|---|---|---|---|---|",
        ]
        for c, r in calibrated.items():
            e, al = r["errors"], r["albedo_error"]
            lines.append(
                f"| {c} | {c + 1} | {len(r['index'])} | {np.median(e):.3f} | {np.percentile(e, 90):.3f} | "
                f"{al.mean():.4f} | {np.percentile(al, 90):.4f} |"
            )
        lines += [
            "",
            "Albedo bias by incident elevation: median over stacks of (network - reference) / reference "
            "of the directional albedo (RGB mean; > 0: the network reflects too much).",
            "",
            "| coatings | " + " | ".join(f"{t:g} deg" for t in data["angles"]) + " |",
            "|---|" + "---|" * len(data["angles"]),
        ]
        rows = (
            [(f"0 (single layers, encoder + decoder; {len(single['index'])} stacks of `heldout_single.npz`)", single)]
            if single is not None
            else []
        ) + list(res.items())
        for label, r in rows:
            lines.append(f"| {label} | " + " | ".join(f"{b:+.3f}" for b in np.median(r["albedo_bias"], axis=0)) + " |")
        lines += [
            "",
            "Reciprocity: relative RMSE of the lobe decoded with the two directions swapped, f(wo, wi) "
            "cos(theta_o), against the lobe as measured, and the lobe error of that swapped lobe against the "
            "reference, median / p90 over stacks and elevations (the reference is reciprocal; the decoder "
            "is not by construction).",
            "",
            "| coatings | " + " | ".join(str(label).split(" (")[0] for label, _ in rows) + " |",
            "|---|" + "---|" * len(rows),
        ]
        for key, name in (("reciprocity", "reciprocity"), ("errors_swapped", "lobe error, directions swapped")):
            lines.append(
                f"| {name} | "
                + " | ".join(f"{np.median(r[key]):.3f} / {np.percentile(r[key], 90):.3f}" for _, r in rows)
                + " |"
            )
        lines += ["", f"![lobes](layering_lobes_{size}.png)", ""]
        if a.errors_only:
            continue
        sp = speed(models, a.reps, a.batch)
        ratios = sampling_ratios(models, data["stacks"], a.samples)
        results[size] |= {"speed": sp, "ratios": ratios}
        lines += [
            "### Encoding speed (stacks per second)",
            "",
            "| coatings | one stack per call | batched (one call) | batch size |",
            "|---|---|---|---|",
        ]
        for c, s in sp.items():
            lines.append(f"| {c} | {s['single_per_s']:.0f} | {s['batched_per_s']:.0f} | {s['batch']} |")
        lines += [
            "",
            "### Sampling efficiency (variance ratio at equal sample count; > 1: the proxy is better)",
            "",
            f"{a.samples} samples per outgoing direction; "
            'relative variance averaged over cos(theta_o) = 0.3, 0.6, 0.9. "proxy": the renderer\'s sampler '
            + (
                "(a remainder decoder: the proxy, fitted to the remainder, mixed with exact samples of the top lobe)."
                if models.remainder
                else "(the proxy alone)."
            ),
            "",
            "| config | coatings | proxy sigma | proxy w | cosine / proxy | top GGX / proxy |",
            "|---|---|---|---|---|---|",
        ]
        for r in ratios:
            tag = {SPECULAR_INDEX: " (specular)", DIFFUSE_INDEX: " (diffuse)"}.get(r["config"], "")
            lines.append(
                f"| {r['config']}{tag} | {len(data['stacks'][r['config']].coatings)} | {r['sigma']:.3f} | "
                f"{r['w']:.2f} | {r['cosine_over_proxy']:.2f} | {r['ggx_over_proxy']:.2f} |"
            )
        cr = np.array([r["cosine_over_proxy"] for r in ratios])
        gr = np.array([r["ggx_over_proxy"] for r in ratios])
        lines += [
            "",
            f"Over all {len(ratios)} held-out stacks: cosine / proxy median {np.median(cr):.2f} "
            f"(proxy better on {int((cr > 1).sum())}), top GGX / proxy median {np.median(gr):.2f} "
            f"(proxy better on {int((gr > 1).sum())}).",
            "",
        ]
        if a.update_cards:
            p = MODEL_DIR / f"layering_{size}.json"
            card = json.loads(p.read_text())
            card["speed"] = {
                f"coatings_{c}": {k: round(v) if k != "batch" else v for k, v in s.items()} for c, s in sp.items()
            } | {"threads": a.threads, "command": cmd, "note": "stacks encoded per second, shared CPU (noisy)"}
            card["heldout_runtime"] = {
                f"coatings_{c}": {
                    "lobe_error_median": float(np.median(r["errors"])),
                    "lobe_error_p90": float(np.percentile(r["errors"], 90)),
                    "calibrated_lobe_error_median": float(np.median(calibrated[c]["errors"])),
                    "calibrated_lobe_error_p90": float(np.percentile(calibrated[c]["errors"], 90)),
                    "albedo_abs_error_mean": float(r["albedo_error"].mean()),
                    "reciprocity_median": float(np.median(r["reciprocity"])),
                    "albedo_bias_median_by_angle": {
                        f"{t:g}": float(b)
                        for t, b in zip(data["angles"], np.median(r["albedo_bias"], axis=0), strict=False)
                    },
                }
                for c, r in res.items()
            }
            card["sampling_efficiency"] = {
                "specular": ratios[SPECULAR_INDEX],
                "diffuse": ratios[DIFFUSE_INDEX],
                "median_cosine_over_proxy": float(np.median(cr)),
                "median_ggx_over_proxy": float(np.median(gr)),
            }
            p.write_text(json.dumps(card, indent=1) + "\n")
    (a.out / "layering.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

"""ONNX export of a decoder size and its encoder, parity check against torch, and model cards.

    python -m onnx_export.export --size small --decoder cache/runs/small/ckpt.pt \
        --encoder cache/runs/small/encoder.pt --metrics cache/runs/small/metrics.json

writes ``addon/models/decoder_<size>.onnx`` and ``encoder_<size>.onnx`` with a model card
(``.json``) each. The card's held-out errors and speed come from ``--metrics`` (written by
``benchmarks/bench_decoders.py``) when given; its data commands are those the training checkpoint recorded
when it loaded the data (``train_decoder.data_records``).

Every graph is checked against torch (``PARITY_TOLERANCE``): the files are written beside ``--out`` first and
replace what is there only when every parity holds; otherwise the export exits non-zero naming the graph and
leaves ``--out`` as it was.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch

from addon.core.neural.features import FEATURE_NAMES, N_FEATURES
from onnx_export.cli import command_line
from onnx_export.evaluate import load_decoder
from onnx_export.layered_data import data_command, holds_layering_data
from onnx_export.nets import Decoder, Encoder, LatentProjection, RGBDecoder, macs_per_eval, n_params
from onnx_export.train_decoder import decoder_design

MODEL_DIR = Path(__file__).resolve().parents[1] / "addon" / "models"
OPSET = 17
PARITY_TOLERANCE = 1e-4  # max relative difference of ONNX Runtime against torch that an export accepts


def export_decoder(dec: Decoder, path: Path) -> None:
    dec.eval()
    b = 8
    args = (
        torch.zeros(b, 32),
        torch.tensor([[0.0, 0.0, 1.0]]).expand(b, 3).contiguous(),
        torch.tensor([[0.0, 0.0, 1.0]]).expand(b, 3).contiguous(),
    )
    torch.onnx.export(
        dec,
        args,
        str(path),
        input_names=["z", "wi", "wo"],
        output_names=["f"],
        dynamic_axes={"z": {0: "batch"}, "wi": {0: "batch"}, "wo": {0: "batch"}, "f": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )


def export_rgb_decoder(dec: Decoder, path: Path) -> None:
    """The runtime's fused graph: zc (Bz, 3W) with Bz in {1, B} (``RGBDecoder.project``), wi, wo (B, 3) -> f (B, 3)."""
    rgb = RGBDecoder(dec).eval()
    b = 8
    args = (
        torch.zeros(1, 3 * rgb.width),
        torch.tensor([[0.0, 0.0, 1.0]]).expand(b, 3).contiguous(),
        torch.tensor([[0.0, 0.0, 1.0]]).expand(b, 3).contiguous(),
    )
    torch.onnx.export(
        rgb,
        args,
        str(path),
        input_names=["zc", "wi", "wo"],
        output_names=["f"],
        dynamic_axes={"zc": {0: "latents"}, "wi": {0: "batch"}, "wo": {0: "batch"}, "f": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )


def export_latent_graph(dec: Decoder, path: Path) -> None:
    """The runtime's projection of latents for the fused graph: z (B, 3, 32) -> zc (B, 3W) (``LatentProjection``)."""
    torch.onnx.export(
        LatentProjection(RGBDecoder(dec).eval()).eval(),
        (torch.zeros(2, 3, 32),),
        str(path),
        input_names=["z"],
        output_names=["zc"],
        dynamic_axes={"z": {0: "batch"}, "zc": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )


def latent_graph_parity(dec: Decoder, path: Path, n: int = 2048, seed: int = 0) -> float:
    """Max relative difference between the latent graph (ONNX Runtime) and ``RGBDecoder.project`` in torch."""
    import onnxruntime as ort

    z = (np.random.default_rng(seed).standard_normal((n, 3, 32)) * 0.5).astype(np.float32)
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(["zc"], {"z": z})[0]
    with torch.no_grad():
        ref = RGBDecoder(dec).eval().project(torch.from_numpy(z)).numpy()
    return max_relative_difference(got, ref)


def rgb_decoder_parity(dec: Decoder, path: Path, n: int = 2048, seed: int = 0) -> float:
    """Max relative difference between the fused RGB graph (ONNX Runtime) and the scalar torch
    decoder, for one shared latent and for per-row latents (each projected by ``RGBDecoder.project``, as the
    runtime projects them); the graph gets the directions both as unit vectors and scaled by lengths from 1e-3
    to 1e3 (it normalises them itself)."""
    import onnxruntime as ort

    rng = np.random.default_rng(seed)
    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rgb = RGBDecoder(dec).eval()
    wi = np.concatenate([random_directions(rng, n // 2), random_directions(rng, n - n // 2, grazing=True)])
    wo = random_directions(rng, n)
    worst = 0.0
    for zb in (1, n):
        z = (rng.standard_normal((zb, 3, 32)) * 0.5).astype(np.float32)
        zr = np.broadcast_to(z, (n, 3, 32)).reshape(-1, 32)
        with torch.no_grad():
            ref = (
                dec(
                    torch.from_numpy(np.ascontiguousarray(zr)),
                    torch.from_numpy(np.repeat(wi, 3, 0)),
                    torch.from_numpy(np.repeat(wo, 3, 0)),
                )
                .numpy()
                .reshape(n, 3)
            )
        for scale_i, scale_o in ((1.0, 1.0), tuple(10.0 ** rng.uniform(-3, 3, (2, n, 1)).astype(np.float32))):
            with torch.no_grad():
                zc = rgb.project(torch.from_numpy(z)).numpy()
            got = s.run(["f"], {"zc": zc, "wi": wi * scale_i, "wo": wo * scale_o})[0]
            worst = max(worst, max_relative_difference(got, ref))
    return worst


def export_encoder(enc: Encoder, path: Path) -> None:
    enc.eval()
    torch.onnx.export(
        enc,
        (torch.zeros(4, N_FEATURES),),
        str(path),
        input_names=["x"],
        output_names=["z"],
        dynamic_axes={"x": {0: "batch"}, "z": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )


def random_directions(rng, n, grazing=False):
    u = rng.random((n, 2))
    z = u[:, 0] * (0.02 if grazing else 1.0)
    r = np.sqrt(1 - z * z)
    phi = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1).astype(np.float32)


def max_relative_difference(a: np.ndarray, b: np.ndarray, floor: float = 1e-6) -> float:
    """max |a - b| / max(|b|, floor) over all entries."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), floor)))


def decoder_parity(dec: Decoder, path: Path, n: int = 4096, seed: int = 0) -> float:
    """Max relative difference between ONNX Runtime and torch on random latents and directions
    (half of them grazing)."""
    import onnxruntime as ort

    rng = np.random.default_rng(seed)
    z = (rng.standard_normal((n, 32)) * 0.5).astype(np.float32)
    wi = np.concatenate([random_directions(rng, n // 2), random_directions(rng, n - n // 2, grazing=True)])
    wo = random_directions(rng, n)
    with torch.no_grad():
        ref = dec(torch.from_numpy(z), torch.from_numpy(wi), torch.from_numpy(wo)).numpy()
    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = s.run(["f"], {"z": z, "wi": wi, "wo": wo})[0]
    return max_relative_difference(got, ref)


def encoder_parity(enc: Encoder, path: Path, x: np.ndarray) -> float:
    import onnxruntime as ort

    with torch.no_grad():
        ref = enc(torch.from_numpy(x)).numpy()
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(["z"], {"x": x})[0]
    return max_relative_difference(got, ref, floor=1e-3)


def macs_rgb_one_material(dec: Decoder) -> int:
    """Multiply-adds per RGB evaluation of the fused graph for one material (latent part amortised;
    the direction term of the first layer is one product for the three channels, (F, 3W))."""
    lin = [m for m in dec.net if isinstance(m, torch.nn.Linear)]
    first = 3 * lin[0].out_features * (lin[0].in_features - 32)
    return int(first + 3 * sum(m.in_features * m.out_features for m in lin[1:]))


def rgb_graph_card(dec: Decoder, rgb_path: Path, latents_path: Path) -> dict:
    """The ``rgb_graph`` entry of a decoder card: the fused graph's contract, cost and parity, and those of its
    latent graph."""
    return {
        "file": rgb_path.name,
        "inputs": "zc (1 or B, 3W): latents z (1 or B, 3, 32) times the first layer's latent columns plus its bias, "
        "the three channels side by side (the latent graph's output); wi (B, 3), wo (B, 3): directions of any "
        "nonzero length",
        "outputs": "f (B, 3), 0 where either direction is at or below the horizon (or zero)",
        "note": "same weights; the runtime projects the latents with the latent graph (once a material, or once a "
        "texel of a latent texture); the graph normalises the directions in float32, and computes the direction "
        "features and their first-layer product once per query",
        "macs_per_rgb_eval_one_material": macs_rgb_one_material(dec),
        "onnx_runtime_vs_torch_max_relative_difference": rgb_decoder_parity(dec, rgb_path),
        "latent_graph": {
            "file": latents_path.name,
            "inputs": "z (B, 3, 32)",
            "outputs": "zc (B, 3W)",
            "macs_per_latent": 3 * 32 * RGBDecoder(dec).width,
            "onnx_runtime_vs_torch_max_relative_difference": latent_graph_parity(dec, latents_path),
        },
    }


def onnx_param_count(path: Path) -> int:
    m = onnx.load(str(path))
    return int(sum(int(np.prod(t.dims)) for t in m.graph.initializer if len(t.dims) > 0))


def torch_from_onnx(path: Path, card: dict) -> torch.nn.Module:
    """Rebuild the torch module of an exported model from the ONNX weights and the card's
    architecture, so parity can be checked without the training checkpoint."""
    from onnx import numpy_helper

    arch = card["architecture"]
    if card["name"].startswith("decoder"):
        mod: torch.nn.Module = Decoder(arch["width"], arch["depth"], arch["features"], arch["activation"])
    else:
        mod = Encoder(arch["n_features"], arch["width"], arch["depth"])
    weights = {
        t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in onnx.load(str(path)).graph.initializer
    }
    mod.load_state_dict(weights)
    return mod.eval()


def initializers(path: Path) -> dict[str, np.ndarray]:
    from onnx import numpy_helper

    return {t.name: numpy_helper.to_array(t) for t in onnx.load(str(path)).graph.initializer}


def regraph_decoder(size: str, model_dir: Path = MODEL_DIR) -> dict:
    """Re-export the three decoder graphs of a shipped size from their own weights, after a change
    to the graph code (``nets.direction_features``) that leaves the weights alone.

    Checks that every weight is bit-identical before and after, refreshes the parity figures of
    the decoder card, and moves the digest of ``decoder_<size>.onnx`` in the cards of the models
    trained against it (layering, sampling: ``trained_with``) to the new file: those models are
    still valid, since what they were trained against is the weights. The numpy decoder's weights
    file (``decoder_weights``), which names the ONNX file's digest, is written again too."""
    from addon.core.neural.models import file_digest
    from onnx_export.decoder_weights import export_weights

    dpath = model_dir / f"decoder_{size}.onnx"
    rgb_path = model_dir / f"decoder_{size}_rgb.onnx"
    latents_path = model_dir / f"decoder_{size}_latents.onnx"
    card_path = dpath.with_suffix(".json")
    card = json.loads(card_path.read_text())
    before = initializers(dpath)
    old_digest = file_digest(dpath)
    dec = torch_from_onnx(dpath, card)
    export_decoder(dec, dpath)
    export_rgb_decoder(dec, rgb_path)
    export_latent_graph(dec, latents_path)
    after = initializers(dpath)
    if before.keys() != after.keys() or any(not np.array_equal(before[k], after[k]) for k in before):
        raise RuntimeError(f"re-exporting {dpath.name} changed its weights; retrain the models that depend on it")
    card["onnx_runtime_vs_torch_max_relative_difference"] = decoder_parity(dec, dpath)
    card["rgb_graph"] = rgb_graph_card(dec, rgb_path, latents_path)
    card["files"] = {p.name: file_digest(p) for p in (dpath, rgb_path, latents_path)}
    card_path.write_text(json.dumps(card, indent=1) + "\n")
    new_digest = file_digest(dpath)
    moved = []
    for other in sorted(model_dir.glob("*.json")):
        c = json.loads(other.read_text())
        if c.get("trained_with", {}).get(dpath.name) == old_digest:
            c["trained_with"][dpath.name] = new_digest
            other.write_text(json.dumps(c, indent=1) + "\n")
            moved.append(other.name)
    weights = export_weights(size, model_dir)
    return {
        "decoder": dpath.name,
        "numpy_weights_parity": weights["numpy_vs_onnx_max_relative_difference"],
        "parity": card["onnx_runtime_vs_torch_max_relative_difference"],
        "rgb_parity": card["rgb_graph"]["onnx_runtime_vs_torch_max_relative_difference"],
        "cards_moved": moved,
    }


SINGLE_DATA_COMMAND = "python -m onnx_export.data --set single --materials 4096 --pairs 1024 --out cache/data/single"


def parity_failures(figures: dict[str, float], tolerance: float = PARITY_TOLERANCE) -> list[str]:
    """The entries of ``figures`` (graph -> max relative difference of ONNX Runtime against torch) above
    ``tolerance`` (NaN included), as words for the error."""
    return [f"{k}: {v:.3g}" for k, v in figures.items() if not v <= tolerance]


def data_record(ckpt: dict) -> tuple[str | list[str], int | list[int]]:
    """The data commands and seeds of a ``train_decoder`` checkpoint (one each, or one per set): those it
    recorded when it loaded the data; checkpoints from before the record: the layering folders as they are now
    and the single-layer set's usual command."""
    records = ckpt.get("data_records")
    if records:
        cmds, seeds = [r["command"] for r in records], [r["seed"] for r in records]
    else:
        dirs = [Path(d) for d in ckpt["args"]["data"]]
        cmds = [data_command(d) if holds_layering_data(d) else SINGLE_DATA_COMMAND for d in dirs]
        seeds = [1]
    return (cmds[0] if len(cmds) == 1 else cmds), (seeds[0] if len(seeds) == 1 else seeds)


def training_commands(ckpt: dict) -> list[str]:
    """The train_decoder commands that made a checkpoint, first stage first: a run started with
    ``--init`` from another run's checkpoint is preceded by that run's command (when it is here)."""
    a = ckpt.get("args")
    if a is None:  # a checkpoint assembled by hand (no command made it)
        return []
    out = [command_line("onnx_export.train_decoder", a, skip=("every", "log_every"))]
    init = a.get("init")
    record = ckpt.get("init_record")
    if record is not None:  # started from a shipped decoder's ONNX weights: the command that made them
        earlier = record.get("earlier_stages", []) + ([record["command"]] if record.get("command") else [])
        out = earlier + out
    elif init not in (None, "None") and Path(str(init)).exists():
        out = training_commands(torch.load(str(init), weights_only=False)) + out
    return out


def loss_text(args: dict) -> str:
    kinds = args.get("loss")
    kinds = kinds if isinstance(kinds, (list, tuple)) else [kinds]
    level = float(args.get("level_floor") or 0.0)
    weighted = (
        f"; materials dimmer than the median weighted as bright (--level-floor {level:g}, nets.level_weights)"
        if level > 0.0
        else ""
    )
    if len(kinds) == 1:
        return f"{kinds[0]} on log1p(f cos_i cos_o){weighted}"
    scales = args.get("loss_scales") or [1.0] * len(kinds)
    return (
        "; ".join(f"{d}: {k} x {sc}" for d, k, sc in zip(args["data"], kinds, scales, strict=False))
        + " (l1: on log1p(f cos_i cos_o); l2rel: onnx_export.nets.pair_loss, the mean of Monte Carlo targets)"
        + weighted
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", required=True)
    ap.add_argument("--decoder", type=Path)
    ap.add_argument("--encoder", type=Path)
    ap.add_argument(
        "--regraph",
        action="store_true",
        help="re-export the shipped decoder graphs of --size from their own weights (regraph_decoder)",
    )
    ap.add_argument("--metrics", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=MODEL_DIR)
    a = ap.parse_args(argv)
    if a.regraph:
        print(json.dumps(regraph_decoder(a.size, a.out)))
        return
    if a.decoder is None or a.encoder is None:
        ap.error("--decoder and --encoder are required (or --regraph)")
    a.out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".export-", dir=a.out))  # same file system: each file moves in at once
    try:
        written = export_into(a, stage)
        for p in sorted(stage.iterdir()):
            p.replace(a.out / p.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    print(json.dumps({k: (str(a.out / v.name) if isinstance(v, Path) else v) for k, v in written.items()}))


def export_into(a, folder: Path) -> dict:
    """Export the decoder and encoder checkpoints of ``a`` with their cards into ``folder``; raises
    ``SystemExit`` (before any card is written) when a graph's parity exceeds ``PARITY_TOLERANCE``."""
    dck = torch.load(a.decoder, weights_only=False)
    # trained on remainders (train_decoder --remainder): the card says so, and the runtime adds the exact top lobe
    remainder, transmission = decoder_design(dck.get("args", {}))
    dec, latents = load_decoder(dck)
    eck = torch.load(a.encoder, weights_only=False)
    enc = Encoder(**eck["config"])
    enc.load_state_dict(eck["encoder"])
    dpath = folder / f"decoder_{a.size}.onnx"
    epath = folder / f"encoder_{a.size}.onnx"
    export_decoder(dec, dpath)
    export_encoder(enc, epath)
    dpar = decoder_parity(dec, dpath)
    rgb_path = folder / f"decoder_{a.size}_rgb.onnx"
    latents_path = folder / f"decoder_{a.size}_latents.onnx"
    export_rgb_decoder(dec, rgb_path)
    export_latent_graph(dec, latents_path)
    rgb_card = rgb_graph_card(dec, rgb_path, latents_path)
    rng = np.random.default_rng(1)
    epar = encoder_parity(enc, epath, rng.random((512, N_FEATURES)).astype(np.float32))
    bad = parity_failures(
        {
            dpath.name: dpar,
            rgb_path.name: rgb_card["onnx_runtime_vs_torch_max_relative_difference"],
            latents_path.name: rgb_card["latent_graph"]["onnx_runtime_vs_torch_max_relative_difference"],
            epath.name: epar,
        }
    )
    if bad:
        raise SystemExit(
            f"export of {a.decoder} refused: ONNX Runtime differs from torch by more than {PARITY_TOLERANCE:g} "
            f"(max relative difference) in {'; '.join(bad)}; nothing written to {a.out}"
        )
    metrics = json.loads(a.metrics.read_text()) if a.metrics else {}
    targs = dck["args"]
    data_cmd, data_seed = data_record(dck)
    stages = training_commands(dck)
    from addon.core.neural.models import file_digest

    dcard = {
        "name": f"decoder_{a.size}",
        "role": (
            "neural BRDF decoder f(z_c, wi, wo) -> f_c >= 0 (1/sr, no cosine), one scalar network shared by R, G, B"
            + (
                "; it holds the remainder of a layered stack's BRDF (the light that entered the top coat): the "
                "runtime adds the exact top-interface reflection (addon.core.neural.top_lobe)"
                if remainder
                else ""
            )
            + (
                ", its output times the top coat's Fresnel transmission in and out (top_lobe.remainder_scale)"
                if transmission
                else ""
            )
        ),
        "remainder": remainder,
        "top_transmission": transmission,
        "files": {p.name: file_digest(p) for p in (dpath, rgb_path, latents_path)},
        "inputs": {
            "z": "(B, 32) float32 latent of one colour channel",
            "wi": "(B, 3) float32 unit, toward the light",
            "wo": "(B, 3) float32 unit, toward the viewer",
        },
        "outputs": {"f": "(B,) float32"},
        "architecture": {
            **dec.config(),
            "hidden": f"{dec.depth} x Linear({dec.width}) + ReLU",
            "latent": 32,
            "output": "exp(min(y, 16)), 0 below the horizon",
        },
        "parameters": n_params(dec),
        "macs_per_rgb_eval": 3 * macs_per_eval(dec),
        "training": {
            "data": data_cmd,
            "command": stages[-1],
            **({"earlier_stages": stages[:-1]} if len(stages) > 1 else {}),
            **(
                {"started_from": {k: v for k, v in dck["init_record"].items() if k != "earlier_stages"}}
                if dck.get("init_record")
                else {}
            ),
            "steps": dck["step"],
            "final_loss": dck.get("loss"),
            "seeds": {"data": data_seed, "training": targs.get("seed", 0)},
            "loss": loss_text(targs),
        },
        "onnx_runtime_vs_torch_max_relative_difference": dpar,
        "rgb_graph": rgb_card,
        "opset": OPSET,
        "latent_mean": [round(float(v), 6) for v in latents.mean(0)],
        **{k: v for k, v in metrics.items() if k.startswith(("heldout", "speed"))},
    }
    ecard = {
        "name": f"encoder_{a.size}",
        "role": f"single-layer parameters -> latent of decoder_{a.size}, per colour channel",
        "files": {epath.name: file_digest(epath)},
        "inputs": {
            "x": f"(B, {N_FEATURES}) float32 features (addon.core.neural.features)",
            "features": list(FEATURE_NAMES),
        },
        "outputs": {"z": "(B, 32) float32"},
        "architecture": {**eck["config"], "hidden": f"{enc.depth} x Linear({enc.width}) + ReLU"},
        "parameters": n_params(enc),
        "macs_per_rgb_eval": 3 * macs_per_eval(enc),
        "training": {"command": command_line("onnx_export.train_encoder", eck["args"]), "history": eck.get("history")},
        "onnx_runtime_vs_torch_max_relative_difference": epar,
        "opset": OPSET,
        **{k: v for k, v in metrics.items() if k.startswith("encoder")},
        "trained_with": {dpath.name: file_digest(dpath)},
    }
    dpath.with_suffix(".json").write_text(json.dumps(dcard, indent=1) + "\n")
    epath.with_suffix(".json").write_text(json.dumps(ecard, indent=1) + "\n")
    return {
        "decoder": dpath,
        "parity": dpar,
        "rgb_parity": rgb_card["onnx_runtime_vs_torch_max_relative_difference"],
        "encoder": epath,
        "encoder_parity": epar,
    }


if __name__ == "__main__":
    main()

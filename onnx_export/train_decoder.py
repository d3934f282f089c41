"""Auto-decoder training: one latent per training BRDF channel, optimised jointly with the decoder.

    python -m onnx_export.train_decoder --size tiny --data cache/data/single --steps 6000 \
        --out cache/runs/tiny

Each step draws ``--batch`` BRDF channels and ``--pairs`` direction pairs of each. The loss
compares log1p(f cos_i cos_o) of the prediction and the target (``l1``: the median under Monte
Carlo noise, fine for exact targets; ``l2``: the mean, the right choice for noisy targets).
Checkpoints (decoder, latents, optimiser, batch generator, step) go to ``OUT/ckpt.pt`` every ``--every``
steps and at the end; rerunning the same command resumes from there and continues as the uninterrupted run
would have (``--steps`` may grow; any other change of the arguments is refused, naming the flag). Each
checkpoint records the commands of the data as they were loaded (``data_records``, for the model card).
Progress goes to stderr.

``--init`` takes another run's checkpoint, or a shipped ``decoder_<size>.onnx`` (its weights; the
latents then come from ``--init-latents-from``): a size whose training checkpoint is gone continues
from what it ships. ``--grazing-floor`` weights the grazing pairs (``nets.pair_loss``).

The same command runs under ``torchrun --nproc_per_node N`` (``onnx_export.distributed``): every
process draws the same batch from the same seed, takes its 1/N of the BRDF channels, and the averaged
gradients are those of the whole batch, so N processes follow the one-process run; process 0 logs and
checkpoints.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from addon.core.stack import StackArrays
from onnx_export import data as datamod
from onnx_export import layered_data
from onnx_export.cli import check_resume, nonnegative_int, positive_int
from onnx_export.distributed import processes, quiet_unless_main
from onnx_export.nets import (
    PAIR_LOSSES,
    Decoder,
    cosine_lr,
    he_init,
    level_weights,
    macs_per_eval,
    make_decoder,
    n_params,
    pair_loss,
    stack_levels,
)
from onnx_export.remainder import remainder_scales, top_reflection


def load_set(path: Path) -> dict:
    """One training set as wi, wo, f (M, P, 3) and its ``arrays`` (StackArrays, one row per material).

    Reads both formats: ``onnx_export.data`` (pairs per material) and ``onnx_export.layered_data``
    (``wi`` per outgoing direction, flattened here to pairs)."""
    if layered_data.holds_layering_data(path):
        d = layered_data.load(path)
        s, p, m = d["wi"].shape[:3]
        return {
            "wi": d["wi"].reshape(s, p * m, 3),
            "wo": np.repeat(d["wo"], m, axis=1),
            "f": d["f"].reshape(s, p * m, 3),
            "stderr": d["stderr"].reshape(s, p * m, 3),
            "arrays": d["arrays"],
        }
    d = datamod.load(path)
    n = len(d["p_base_kind"])
    d["arrays"] = StackArrays(
        **{f: d[f"p_{f}"] for f in StackArrays.FIELDS if f.startswith("base_")},
        **{
            f: np.zeros((n, 0) + ((3,) if f == "coat_albedo" else ()))
            for f in StackArrays.FIELDS
            if f.startswith("coat_")
        },
    )
    return d


def data_records(paths: list[Path]) -> list[dict]:
    """The command and seed of each data set under ``paths`` as they are now (read from the chunks' manifests,
    ``data.data_command`` / ``layered_data.data_command``): what a checkpoint records of the data it loaded."""
    out = []
    for p in map(Path, paths):
        mod = layered_data if layered_data.holds_layering_data(p) else datamod
        out.append(
            {"command": mod.data_command(p), "seed": (datamod.read_manifest(p) or {}).get("seed", mod.DEFAULT_SEED)}
        )
    return out


def decoder_design(args: dict) -> tuple[bool, bool]:
    """(remainder, top_transmission) of a decoder trained with the stored arguments ``args`` (a checkpoint's
    ``args``, values or their ``str``): what its outputs hold (``--remainder``) and are multiplied by
    (``--top-transmission``)."""
    remainder = args.get("remainder") in (True, "True")
    return remainder, remainder and args.get("top_transmission") in (True, "True")


def load_training_tensors(
    paths: list[Path], materials: int | None = None, remainder: bool = False, transmission: bool = False
) -> dict:
    """wi, wo, f (M, P, 3) of all data sets, cut to the smallest number of pairs P of any set
    (pairs are in random order), plus ``source`` (M,): which set each material came from, and
    ``arrays``: each set's StackArrays (not cut to ``materials``). ``remainder``: the targets of
    layered stacks are their BRDF minus the exact top-interface reflection (``remainder.py``);
    ``transmission``: ``scale`` (M, P) is the top coat's transmission in and out of each pair, what the
    decoder's output is multiplied by before the loss (``top_lobe.remainder_scale``; 1 without coatings)."""
    parts = [load_set(p) for p in paths]
    pmin = min(p["wi"].shape[1] for p in parts)
    parts = [{k: (v[:, :pmin] if k in ("wi", "wo", "f", "stderr") else v) for k, v in p.items()} for p in parts]
    if remainder:
        for p in parts:
            p["f"] = p["f"] - top_reflection(p["arrays"], p["wi"], p["wo"])
    if transmission:
        if not remainder:
            raise ValueError("the top coat's transmission scales a remainder: it needs --remainder")
        for p in parts:
            p["scale"] = remainder_scales(p["arrays"], p["wi"], p["wo"])[..., 0]
    keys = ("wi", "wo", "f", "scale")
    d = {k: np.concatenate([p[k] for p in parts]) for k in keys if all(k in p for p in parts)}
    if "stderr" in parts[0] or any("stderr" in p for p in parts):
        d["stderr"] = np.concatenate([p.get("stderr", np.zeros_like(p["f"])) for p in parts])
    d["source"] = np.concatenate([np.full(p["wi"].shape[0], i, np.float32) for i, p in enumerate(parts)])
    if materials:
        d = {k: v[:materials] for k, v in d.items()}
    return {k: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float32)) for k, v in d.items()} | {
        "arrays": [p["arrays"] for p in parts]
    }


def initial_latents(sets: list[StackArrays], size: str, materials: int | None, threads: int) -> np.ndarray:
    """(units, 32) latents of every training channel of ``sets`` (one StackArrays per data set) in a
    shipped size's latent space: single-layer materials through its encoder, layered stacks through its
    encoder and layering network."""
    from addon.core.neural import encode_arrays, load_models

    models = load_models(size, threads=threads)
    out = [encode_arrays(a, models) for a in sets]
    z = np.concatenate(out)
    if materials:
        z = z[:materials]
    return z.reshape(-1, 32)


class AutoDecoder(torch.nn.Module):
    """The decoder and the latents of the training channels as one module (what DistributedDataParallel wraps)."""

    def __init__(self, dec: Decoder, latents: torch.nn.Parameter):
        super().__init__()
        self.dec, self.latents = dec, latents

    def forward(self, units: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, pairs: int):
        z = self.latents[units]
        return self.dec(z.repeat_interleave(pairs, dim=0), wi, wo), (z**2).mean()


def init_decoder(dec: Decoder, path: Path) -> dict:
    """Load a shipped decoder's ONNX weights into ``dec`` (same architecture); returns the checkpoint-like
    record of where it started (file name and sha256)."""
    from onnx_export.export import torch_from_onnx

    card = json.loads(path.with_suffix(".json").read_text())
    src = torch_from_onnx(path, card)
    if src.config() != dec.config():
        raise ValueError(f"{path.name} is {src.config()}, the run trains {dec.config()}: give the size it was made for")
    dec.load_state_dict(src.state_dict())
    tr = card.get("training", {})
    return {
        "file": path.name,
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "command": tr.get("command"),
        "earlier_stages": tr.get("earlier_stages", []),
    }


def start_from(args, t: dict, dec: Decoder, latents: torch.nn.Parameter, log) -> dict | None:
    """The starting point of ``--init-latents-from`` and ``--init`` (in that order); returns the record of
    a shipped ONNX decoder started from (None otherwise)."""
    n_units = latents.shape[0]
    if args.init_latents_from:  # start in a shipped size's latent space: its encoder (+ layering network)
        z0 = initial_latents(t["arrays"], args.init_latents_from, args.materials, args.threads)
        latents.data.copy_(torch.from_numpy(z0))
        log(
            f"latents start from the {args.init_latents_from} encoder / layering network "
            f"(mean |z| {float(np.abs(z0).mean()):.3f})"
        )
    if args.init and Path(args.init).suffix == ".onnx":  # a shipped decoder: its weights (latents: see above)
        record = init_decoder(dec, Path(args.init))
        log(f"decoder from {args.init} (sha256 {record['sha256'][:12]})")
        return record
    if args.init:  # start from another run: its decoder, and its latents for the units both share
        s0 = torch.load(args.init, weights_only=False)
        dec.load_state_dict(s0["decoder"])
        k = min(n_units, s0["latents"].shape[0])
        latents.data[:k] = s0["latents"][:k]
        if not args.init_latents_from:
            latents.data[k:] = s0["latents"].mean(0)
        log(f"decoder and {k} latents from {args.init}")
    return None


def set_losses(
    pred, f, wi, wo, row_set, kinds, scales, grazing_floor: float, ema_set: list, row_weight=None
) -> torch.Tensor:
    """Mean loss of a batch whose rows come from several data sets, each with its own loss (exact targets:
    l1; noisy: l2rel) and scale, each row's term times ``row_weight`` when given (``unit_level_weights``);
    updates each set's running mean ``ema_set`` (unscaled)."""
    terms = torch.zeros_like(pred)
    for i, kind in enumerate(kinds):
        m = row_set == i
        if m.any():
            terms[m] = scales[i] * pair_loss(pred[m], f[m], wi[m], wo[m], kind, grazing_floor)
            if row_weight is not None:
                terms[m] = terms[m] * row_weight[m]
            v = terms[m].mean().item() / scales[i].item()
            ema_set[i] = v if ema_set[i] is None else 0.98 * ema_set[i] + 0.02 * v
    return terms.mean()


def unit_level_weights(t: dict, floor: float) -> torch.Tensor | None:
    """(units,) the loss weight of each BRDF channel (material * 3 + channel) for ``--level-floor``: its
    material's ``nets.level_weights`` within its own data set (levels of the targets as compared, the
    remainder for ``--remainder``), scaled so that each set's channels weigh 1 on average and the sets'
    shares of the loss stay as ``--data-weights`` and ``--loss-scales`` set them; None for ``floor`` <= 0."""
    if floor <= 0.0:
        return None
    w = torch.empty(t["f"].shape[0])
    for i in torch.unique(t["source"]):
        m = t["source"] == i
        lv = stack_levels(t["f"][m], t["wi"][m], t["wo"][m], torch.ones(t["f"][m].shape[:2]))
        wm = level_weights(lv, floor)
        w[m] = wm / wm.mean()
    return w.repeat_interleave(3)


def brdf_loss(pred, target, wi, wo, kind: str) -> torch.Tensor:
    return pair_loss(pred, target, wi, wo, kind).mean()


def batch_of(t: dict, units: torch.Tensor, pairs: int, gen: torch.Generator):
    """Rows for ``units`` (material * 3 + channel): (B*Q, 3) wi, wo and (B*Q,) targets."""
    m, c = units // 3, units % 3
    p_total = t["wi"].shape[1]
    idx = torch.randint(0, p_total, (units.shape[0], pairs), generator=gen)
    wi = t["wi"][m[:, None], idx].reshape(-1, 3)
    wo = t["wo"][m[:, None], idx].reshape(-1, 3)
    f = t["f"][m[:, None], idx, c[:, None]].reshape(-1)
    if "scale" in t:  # the decoder's output times the top coat's transmission (--top-transmission)
        return wi, wo, f, t["scale"][m[:, None], idx].reshape(-1)
    return wi, wo, f


RESUME_FREE = ("steps", "every", "log_every", "threads", "out")  # what a resumed run may change


def check_arguments(args) -> None:
    """``ValueError`` for arguments that do not fit each other (before any work)."""
    n_sets = len(args.data)
    if (
        len(args.loss) not in (1, n_sets)
        or len(args.loss_scales or [0] * n_sets) != n_sets
        or len(args.data_weights or [0] * n_sets) != n_sets
    ):
        raise ValueError(
            f"--loss, --loss-scales and --data-weights take one value per --data set ({n_sets}) "
            f"(--loss may also take one for all)"
        )
    if (args.width > 0) != (args.depth > 0) or args.width < 0 or args.depth < 0:
        raise ValueError(
            f"--width and --depth go together, each >= 1 (or both 0: the --size's), got --width {args.width} "
            f"--depth {args.depth}"
        )


def train(args, log=print) -> dict:
    check_arguments(args)
    ckpt = Path(args.out) / "ckpt.pt"
    saved = torch.load(ckpt, weights_only=False) if ckpt.exists() else None
    if saved is not None:  # a resumed run continues the same one
        check_resume(saved["args"], vars(args) | {"data": [str(p) for p in args.data]}, RESUME_FREE, ckpt)
    procs = processes()
    mine = procs.rows(args.batch)  # this process's BRDF channels of every batch
    log = quiet_unless_main(log, procs)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    t = load_training_tensors(
        args.data,
        args.materials,
        remainder=getattr(args, "remainder", False),
        transmission=getattr(args, "top_transmission", False),
    )
    records = data_records(args.data)  # the data as loaded: their commands for the model card
    n_units = t["wi"].shape[0] * 3
    dec = make_decoder(args.size, features=args.features, activation=args.activation)
    if args.width and args.depth:
        dec = Decoder(args.width, args.depth, args.features, args.activation)
    if args.init_scheme == "he":
        he_init(dec)
    latents = torch.nn.Parameter(torch.randn(n_units, 32, generator=gen) * 0.01)
    init_record = start_from(args, t, dec, latents, log)
    # sampling weight of each unit: data set i gets the share data_weights[i] of every batch
    src = t["source"].repeat_interleave(3)
    w = torch.tensor(args.data_weights or [1.0] * len(args.data), dtype=torch.float32)
    counts = torch.bincount(src.long(), minlength=len(w)).float()
    unit_w = (w / counts.clamp(min=1))[src.long()]
    kinds = args.loss * len(args.data) if len(args.loss) == 1 else list(args.loss)
    scales = torch.tensor(args.loss_scales or [1.0] * len(args.data), dtype=torch.float32)
    units_per_set = [int(c) for c in counts.tolist()]  # src is per unit (material * 3 + channel)
    unit_level_w = unit_level_weights(t, getattr(args, "level_floor", 0.0))
    opt = torch.optim.Adam(
        [{"params": dec.parameters(), "lr": args.lr}, {"params": [latents], "lr": args.lr * args.latent_lr_scale}]
    )
    model = AutoDecoder(dec, latents)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    step = 0
    ema, ema_set = None, [None] * len(args.data)
    if saved is not None:
        if saved["latents"].shape != latents.shape:
            raise ValueError(
                f"{ckpt} holds {saved['latents'].shape[0]} BRDF channels, the data under --data now {n_units}: "
                "the data changed since the run started; train into another --out"
            )
        dec.load_state_dict(saved["decoder"])
        latents.data.copy_(saved["latents"])
        opt.load_state_dict(saved["opt"])
        step = saved["step"]
        init_record = saved.get("init_record", init_record)
        if "gen" in saved:  # the batches continue where they stopped (checkpoints before it: drawn afresh)
            gen.set_state(saved["gen"])
        ema, ema_set = saved.get("loss"), list(saved.get("loss_per_set") or ema_set)
        log(f"resumed from {ckpt} at step {step}")
    log(f"decoder {dec.config()} params {n_params(dec)} MACs/eval {macs_per_eval(dec)}; {n_units} BRDF channels")
    t0 = time.perf_counter()
    while step < args.steps:
        lr = cosine_lr(step, args.steps, args.lr)
        opt.param_groups[0]["lr"] = lr
        opt.param_groups[1]["lr"] = lr * args.latent_lr_scale
        units = torch.multinomial(unit_w, args.batch, replacement=True, generator=gen)
        wi, wo, f, *scale = batch_of(t, units, args.pairs, gen)  # the whole batch on every process (same generator)
        rows = slice(mine.start * args.pairs, mine.stop * args.pairs)
        units, wi, wo, f = units[mine], wi[rows], wo[rows], f[rows]
        pred, z_sq = model(units, wi, wo, args.pairs)
        if scale:
            pred = pred * scale[0][rows]
        row_set = src[units].long().repeat_interleave(args.pairs)
        row_w = None if unit_level_w is None else unit_level_w[units].repeat_interleave(args.pairs)
        loss = set_losses(pred, f, wi, wo, row_set, kinds, scales, args.grazing_floor, ema_set, row_w)
        reg = args.latent_reg * z_sq
        opt.zero_grad(set_to_none=True)
        (loss + reg).backward()
        procs.average_gradients(model.parameters())
        if args.clip > 0:
            torch.nn.utils.clip_grad_norm_(list(dec.parameters()) + [latents], args.clip)
        opt.step()
        step += 1
        lv = procs.mean(loss)  # the whole batch's loss (each process holds the mean of its share)
        ema = lv if ema is None else 0.98 * ema + 0.02 * lv
        if step % args.log_every == 0 or step == args.steps:
            el = time.perf_counter() - t0
            per_set = " ".join(f"{v:.5f}" for v in ema_set if v is not None) if len(kinds) > 1 else ""
            log(
                f"step {step}/{args.steps} loss {ema:.5f}{' (sets ' + per_set + ')' if per_set else ''} "
                f"lr {lr:.2e} {el:.0f} s"
            )
        if (step % args.every == 0 or step == args.steps) and procs.main:
            torch.save(
                {
                    "decoder": dec.state_dict(),
                    "config": dec.config(),
                    "latents": latents.data,
                    "opt": opt.state_dict(),
                    "gen": gen.get_state(),
                    "step": step,
                    "args": vars(args) | {"data": [str(p) for p in args.data]},
                    "data_records": records,
                    "loss": ema,
                    "loss_per_set": ema_set,
                    "units_per_set": units_per_set,
                    "init_record": init_record,
                    "world_size": procs.world,
                    "channels_per_process": mine.stop - mine.start,
                },
                ckpt.with_suffix(".tmp"),
            )
            ckpt.with_suffix(".tmp").replace(ckpt)
    return {"loss": ema, "step": step, "loss_per_set": ema_set, "units_per_set": units_per_set}


def parser():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="tiny")
    ap.add_argument(
        "--width", type=nonnegative_int, default=0, help="override the size's width (with --depth; 0: the size's)"
    )
    ap.add_argument(
        "--depth", type=nonnegative_int, default=0, help="override the size's depth (with --width; 0: the size's)"
    )
    ap.add_argument("--data", type=Path, nargs="+", required=True)
    ap.add_argument(
        "--data-weights",
        type=float,
        nargs="+",
        default=None,
        help="share of each --data set in a batch (default: equal shares)",
    )
    ap.add_argument(
        "--init",
        type=Path,
        default=None,
        help="start from this checkpoint's decoder and latents, or from a shipped decoder_<size>.onnx's weights",
    )
    ap.add_argument(
        "--init-latents-from",
        default=None,
        help="start the latents from this shipped size's encoder (its latent space), then optimise them",
    )
    ap.add_argument("--materials", type=nonnegative_int, default=0, help="use only the first N materials (0: all)")
    ap.add_argument("--steps", type=positive_int, default=6000)
    ap.add_argument("--batch", type=positive_int, default=64, help="BRDF channels per step")
    ap.add_argument("--pairs", type=positive_int, default=512, help="direction pairs per BRDF channel per step")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--latent-lr-scale", type=float, default=5.0)
    ap.add_argument("--latent-reg", type=float, default=1e-4)
    ap.add_argument(
        "--init-scheme",
        default="default",
        choices=("default", "he"),
        help="weight init: PyTorch's default, or He-normal (needed for the paper's 16 layers)",
    )
    ap.add_argument("--clip", type=float, default=0.0, help="clip the gradient norm to this (0: off)")
    ap.add_argument("--features", default="iso_bumps", choices=("raw", "iso", "iso_bumps"))
    ap.add_argument("--activation", default="exp", choices=("exp", "softplus"))
    ap.add_argument(
        "--loss",
        nargs="+",
        default=["l1"],
        choices=PAIR_LOSSES,
        help="loss per --data set, or one for all (l1 for exact targets, l2rel for Monte Carlo ones)",
    )
    ap.add_argument(
        "--loss-scales", type=float, nargs="+", default=None, help="factor on each --data set's loss (default 1 each)"
    )
    ap.add_argument(
        "--grazing-floor",
        type=float,
        default=1.0,
        help="divide each pair's loss term by max(min(cos_i, cos_o), this) (nets.pair_loss; 1: off)",
    )
    ap.add_argument(
        "--level-floor",
        type=float,
        default=0.0,
        help="> 0: each material dimmer than its set's median weighted as if it were as bright, down to FLOOR x the "
        "median level (nets.level_weights; its level the RMS of its f cos_i cos_o), so that near-black materials "
        "count by their relative error; 0: off",
    )
    ap.add_argument(
        "--remainder",
        action="store_true",
        help="train on the remainder: each layered stack's BRDF minus its exact top-interface reflection",
    )
    ap.add_argument(
        "--top-transmission",
        action="store_true",
        help="with --remainder: the decoder's output is multiplied by the top coat's Fresnel transmission in and "
        "out (addon.core.neural.top_lobe.remainder_scale), a structural prior that vanishes at the horizon",
    )
    ap.add_argument("--threads", type=positive_int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--every", type=positive_int, default=250, help="checkpoint every N steps")
    ap.add_argument("--log-every", type=positive_int, default=50)
    ap.add_argument("--out", type=Path, required=True)
    return ap


def main(argv=None):
    ap = parser()
    args = ap.parse_args(argv)
    try:
        check_arguments(args)
    except ValueError as e:
        ap.error(str(e))
    res = train(args, log=lambda s: print(s, file=sys.stderr, flush=True))
    if not processes().main:
        return
    record = {"args": vars(args) | {"data": [str(p) for p in args.data]}, **res}
    (Path(args.out) / "train.json").write_text(json.dumps(record, default=str))


if __name__ == "__main__":
    main()

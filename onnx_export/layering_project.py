"""Projected latents of the layering training stacks: the second training signal of the layering network.

    python -m onnx_export.layering_project --size tiny --data cache/data/layering_c1 \
        --out cache/runs/layering_tiny/projected_c1.npz
    python -m onnx_export.layering_project --decoder cache/runs/paper_mixed/ckpt.pt \
        --data cache/data/layering_c1 cache/data/layering_c2 --steps 200 --pairs 64 \
        --out cache/runs/paper_refit/ckpt.pt

Each training stack's reference values are projected into the frozen decoder's latent space by latent
optimisation (``onnx_export.evaluate.project``, the paper's projection). ``onnx_export.layering train
--projected`` then first regresses the layering network onto these latents (a well-conditioned start:
MSE in latent space, no decoder in the loop) and fine-tunes through the decoder afterwards.

With ``--size`` the decoder is a shipped one and the projection starts from zero (an ``.npz`` of the
latents). With ``--decoder`` it is a ``train_decoder`` checkpoint trained on these stacks: the projection
re-fits the latents the joint training left for them (each drawn only a few dozen times there) against
its frozen decoder, starting from them, with each set's training loss, and writes the checkpoint again
with those latents replaced (the decoder and every other latent unchanged; ``refit`` records how).
Stacks are re-fitted a chunk at a time and the checkpoint is written after each, so a rerun of the
same command resumes.

Either way the targets are what the decoder holds, and its output is compared as it was trained: a decoder of
the remainder design (``train_decoder --remainder``, or a shipped card's ``remainder``) is fitted to each
stack's BRDF minus its exact top-interface reflection, and a ``--top-transmission`` one with its output times
the top coat's transmission (``train_decoder.load_training_tensors``, the trainer's own targets).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from addon.core.neural.models import read_card
from onnx_export.cli import command_line
from onnx_export.evaluate import latent_pair_loss, load_decoder, project
from onnx_export.layering import MODEL_DIR, frozen_decoder
from onnx_export.train_decoder import decoder_design, load_training_tensors


def fit_targets(data: Path, stacks: int, remainder: bool, transmission: bool) -> tuple:
    """wi, wo, f (n, P, 3) and the output scale (n, P) or None of the first ``stacks`` stacks of ``data`` (0: all)
    for a decoder of the given design: the targets and scale its training used (``load_training_tensors``)."""
    t = load_training_tensors([Path(data)], stacks or None, remainder=remainder, transmission=transmission)
    return t["wi"], t["wo"], t["f"], t.get("scale")


def project_set(
    size: str, data: Path, steps: int, chunk: int, pairs: int, loss: str, stacks: int = 0, lr: float = 0.03, log=print
) -> np.ndarray:
    """Latents (n, 3, 32) of the stacks of ``data`` projected from zero into the shipped decoder of ``size``,
    against what that decoder holds (its card's ``remainder`` and ``top_transmission``)."""
    dec = frozen_decoder(size)
    card = read_card("decoder", size, MODEL_DIR)
    wi, wo, f, scale = fit_targets(data, stacks, card.get("remainder") is True, card.get("top_transmission") is True)
    n = wi.shape[0]
    z = np.zeros((n, 3, 32), dtype=np.float32)
    t0 = time.perf_counter()
    for s in range(0, n, chunk):  # a loop over chunks of stacks
        z[s : s + chunk] = project(
            dec,
            wi[s : s + chunk],
            wo[s : s + chunk],
            f[s : s + chunk],
            steps=steps,
            lr=lr,
            loss=loss,
            chunk_pairs=pairs,
            scale=None if scale is None else scale[s : s + chunk],
        ).numpy()
        log(f"projected {min(n, s + chunk)}/{n} stacks {time.perf_counter() - t0:.0f} s")
    return z


@torch.no_grad()
def mean_pair_loss(dec, wi, wo, f, z, loss: str, pairs: int = 256, seed: int = 1, scale=None) -> float:
    """Mean ``loss`` of latents z (C, 3, 32) on ``pairs`` fixed pairs of each of the C stacks (C, P, 3), the
    decoder's output times ``scale`` (C, P) when given."""
    gen = torch.Generator().manual_seed(seed)
    p = wi.shape[1]
    idx = torch.randint(0, p, (min(pairs, p),), generator=gen)
    return float(latent_pair_loss(dec, z, wi, wo, f, idx, loss, scale))


def refit_checkpoint(
    ckpt: Path,
    data: list[Path],
    out: Path,
    *,
    steps: int,
    chunk: int,
    pairs: int,
    lr: float,
    loss: str | None,
    seed: int,
    cmd: str = "",
    log=print,
) -> dict:
    """Re-fit the latents of the stacks of ``data`` (sets of the ``train_decoder`` checkpoint ``ckpt``)
    against its frozen decoder, on the targets it was trained on (``--remainder``, ``--top-transmission``:
    ``fit_targets``); write the checkpoint with them replaced to ``out``. Returns ``refit``."""
    s = torch.load(ckpt, weights_only=False)
    if "units_per_set" not in s:
        raise ValueError(f"{ckpt} does not record which latents belong to which data set (train it again)")
    dirs = [Path(d).resolve() for d in s["args"]["data"]]
    kinds = s["args"]["loss"] * len(dirs) if len(s["args"]["loss"]) == 1 else list(s["args"]["loss"])
    config = {
        "from": str(ckpt),
        "data": [str(d) for d in data],
        "steps": steps,
        "pairs": pairs,
        "lr": lr,
        "loss": loss,
        "seed": seed,
    }
    if out.exists():  # resume: the same re-fit, some chunks done
        s_out = torch.load(out, weights_only=False)
        if s_out.get("refit", {}).get("config") != config:
            raise ValueError(
                f"{out} holds another re-fit ({s_out.get('refit', {}).get('config')}); remove it or write elsewhere"
            )
        s = s_out
    refit = s.setdefault("refit", {"config": config, "command": cmd, "sets": {}})
    dec, _ = load_decoder(s)
    for p_ in dec.parameters():
        p_.requires_grad_(False)
    remainder, transmission = decoder_design(s["args"])
    for d in data:
        if Path(d).resolve() not in dirs:
            raise ValueError(f"{ckpt} was not trained on {d}: its sets are {s['args']['data']}")
        i = dirs.index(Path(d).resolve())
        kind = loss or kinds[i]
        start = sum(s["units_per_set"][:i])
        n = s["units_per_set"][i] // 3
        wi, wo, f, scale = fit_targets(Path(d), n, remainder, transmission)
        rec = refit["sets"].setdefault(
            str(d), {"stacks": n, "done": 0, "loss": kind, "loss_before": [], "loss_after": []}
        )
        t0 = time.perf_counter()
        while rec["done"] < n:  # a loop over chunks of stacks; each chunk is one batched projection
            a, b = rec["done"], min(n, rec["done"] + chunk)
            z0 = s["latents"][start + 3 * a : start + 3 * b].reshape(-1, 3, 32)
            sc = None if scale is None else scale[a:b]
            before = mean_pair_loss(dec, wi[a:b], wo[a:b], f[a:b], z0, kind, scale=sc)
            z = project(
                dec,
                wi[a:b],
                wo[a:b],
                f[a:b],
                init=z0,
                steps=steps,
                lr=lr,
                loss=kind,
                chunk_pairs=pairs,
                seed=seed + a,
                scale=sc,
            )
            after = mean_pair_loss(dec, wi[a:b], wo[a:b], f[a:b], z, kind, scale=sc)
            s["latents"][start + 3 * a : start + 3 * b] = z.reshape(-1, 32)
            rec["loss_before"].append(before)
            rec["loss_after"].append(after)
            rec["done"] = b
            out.parent.mkdir(parents=True, exist_ok=True)
            torch.save(s, out.with_suffix(".tmp"))
            out.with_suffix(".tmp").replace(out)
            log(
                f"{d}: re-fitted {b}/{n} stacks, {kind} loss {before:.5f} -> {after:.5f}, "
                f"{time.perf_counter() - t0:.0f} s"
            )
    return refit


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--size", default="tiny", help="a shipped decoder; latents from zero, written as .npz")
    src.add_argument(
        "--decoder",
        type=Path,
        default=None,
        help="a train_decoder checkpoint trained on --data: re-fit its latents, write a checkpoint",
    )
    ap.add_argument("--data", type=Path, nargs="+", required=True)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--chunk", type=int, default=512, help="stacks projected together")
    ap.add_argument("--pairs", type=int, default=128, help="direction pairs per stack per step")
    ap.add_argument("--lr", type=float, default=None, help="Adam step (default 0.03 from zero, 0.01 for a re-fit)")
    ap.add_argument(
        "--loss",
        default=None,
        choices=("l1", "l2", "l2rel"),
        help="default: l1 from zero, each set's training loss for a re-fit",
    )
    ap.add_argument("--stacks", type=int, default=0, help="only the first N stacks (0: all; not with --decoder)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    if a.decoder:
        if a.stacks:
            ap.error("--stacks is for --size: a re-fit covers every stack of each set")
        a.lr = a.lr or 0.01
        cmd = command_line("onnx_export.layering_project", vars(a), skip=("threads", "size", "stacks"))
        refit_checkpoint(
            a.decoder,
            a.data,
            a.out,
            steps=a.steps,
            chunk=a.chunk,
            pairs=a.pairs,
            lr=a.lr,
            loss=a.loss,
            seed=a.seed,
            cmd=cmd,
            log=log,
        )
        return
    if len(a.data) != 1:
        ap.error("--size projects one --data set at a time")
    z = project_set(a.size, a.data[0], a.steps, a.chunk, a.pairs, a.loss or "l1", a.stacks, lr=a.lr or 0.03, log=log)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(a.out, z=z)


if __name__ == "__main__":
    main()

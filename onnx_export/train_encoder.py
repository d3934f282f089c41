"""Encoder training: analytic single-layer parameters -> latent, distilled from an auto-decoder run.

    python -m onnx_export.train_encoder --ckpt cache/runs/tiny/ckpt.pt --data cache/data/single \
        --out cache/runs/tiny/encoder.pt

Stage 1 (distillation): regress the encoder on the latents the auto-decoder learnt for the
training BRDF channels (MSE in latent space). Stage 2 (``--finetune`` steps): train the encoder
end to end through the frozen decoder on the BRDF loss, so that latent-space error that does not
matter for the BRDF is not paid for and error that does is. Both stages are measured on the
held-out set (lobe error of the encoded latents, no projection).

The same command runs under ``torchrun --nproc_per_node N`` (``onnx_export.distributed``): each process
takes its 1/N of every batch, the gradients are averaged, and process 0 measures, logs and saves.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from addon.core.neural.features import N_FEATURES, arrays_features
from onnx_export.distributed import processes, quiet_unless_main
from onnx_export.evaluate import decoder_lobes, load_decoder, lobe_metrics
from onnx_export.heldout import load as load_heldout
from onnx_export.nets import Encoder
from onnx_export.train_decoder import batch_of, brdf_loss, load_set, load_training_tensors


def unit_features(data_dirs, materials=None) -> torch.Tensor:
    """(units, N_FEATURES) encoder inputs of the training BRDF channels (unit = material * 3 + channel)."""
    feats = []
    for d in data_dirs:
        feats.append(arrays_features(load_set(d)["arrays"]))
    x = np.concatenate(feats)
    if materials:
        x = x[:materials]
    return torch.from_numpy(x.reshape(-1, N_FEATURES))


@torch.no_grad()
def heldout_error(enc, dec, heldout) -> dict:
    from addon.core.neural.features import layer_features

    x = torch.from_numpy(np.stack([layer_features(s.base) for s in heldout["stacks"]]))
    z = enc(x.reshape(-1, N_FEATURES)).reshape(-1, 3, 32)
    m = lobe_metrics(decoder_lobes(dec, z, heldout["lobe"].shape[2], heldout["angles"]), heldout["lobe"])
    return {k: v for k, v in m.items() if k != "errors"}


def train(args, log=print) -> dict:
    procs = processes()
    mine_units, mine = procs.rows(args.batch_units, "--batch-units"), procs.rows(args.batch)
    log = quiet_unless_main(log, procs)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    ck = torch.load(args.ckpt, weights_only=False)
    dec, latents = load_decoder(ck)
    for p in dec.parameters():
        p.requires_grad_(False)
    x = unit_features(args.data, args.materials)
    if "units_per_set" in ck and len(ck["units_per_set"]) > len(args.data):
        # a decoder trained on single-layer AND layered sets: the encoder learns the single-layer ones,
        # which come first (the layered stacks are the layering network's job)
        latents = latents[: sum(ck["units_per_set"][: len(args.data)])]
    if x.shape[0] != latents.shape[0]:
        raise ValueError(
            f"{x.shape[0]} training channels in the data but {latents.shape[0]} latents in {args.ckpt}; "
            f"pass the same --data (and --materials) as the decoder run"
        )
    heldout = load_heldout(args.heldout)
    enc = Encoder(N_FEATURES, args.width, args.depth)
    opt = torch.optim.Adam(enc.parameters(), lr=args.lr)
    t0 = time.perf_counter()
    hist = {}
    for step in range(args.distill):
        for g in opt.param_groups:
            g["lr"] = args.lr * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * step / args.distill)))
        idx = torch.randint(0, x.shape[0], (args.batch_units,), generator=gen)[mine_units]
        loss = ((enc(x[idx]) - latents[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        procs.average_gradients(enc.parameters())
        opt.step()
        if (step + 1) % 500 == 0:
            log(f"distill {step + 1}/{args.distill} mse {procs.mean(loss):.5f} {time.perf_counter() - t0:.0f} s")
    if procs.main:
        hist["distilled"] = heldout_error(enc, dec, heldout)
        log(f"held-out after distillation: {json.dumps(hist['distilled'])}")
    if args.finetune:
        t = load_training_tensors(args.data, args.materials)
        opt = torch.optim.Adam(enc.parameters(), lr=args.lr * 0.3)
        for step in range(args.finetune):
            for g in opt.param_groups:
                g["lr"] = args.lr * 0.3 * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * step / args.finetune)))
            units = torch.randint(0, x.shape[0], (args.batch,), generator=gen)
            wi, wo, f = batch_of(t, units, args.pairs, gen)  # the whole batch on every process
            rows = slice(mine.start * args.pairs, mine.stop * args.pairs)
            units, wi, wo, f = units[mine], wi[rows], wo[rows], f[rows]
            z = enc(x[units]).repeat_interleave(args.pairs, dim=0)
            loss = brdf_loss(dec(z, wi, wo), f, wi, wo, "l1")
            opt.zero_grad()
            loss.backward()
            procs.average_gradients(enc.parameters())
            opt.step()
            if (step + 1) % 100 == 0:
                log(f"finetune {step + 1}/{args.finetune} loss {procs.mean(loss):.5f} {time.perf_counter() - t0:.0f} s")
        if procs.main:
            hist["finetuned"] = heldout_error(enc, dec, heldout)
            log(f"held-out after fine-tuning: {json.dumps(hist['finetuned'])}")
    if not procs.main:
        return hist
    torch.save(
        {
            "encoder": enc.state_dict(),
            "config": enc.config(),
            "history": hist,
            "args": {k: str(v) for k, v in vars(args).items()},
            "world_size": procs.world,
        },
        args.out,
    )
    return hist


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", type=Path, required=True)
    ap.add_argument("--data", type=Path, nargs="+", required=True)
    ap.add_argument("--materials", type=int, default=0)
    ap.add_argument("--heldout", type=Path, default=Path("tests/data/heldout_single.npz"))
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--depth", type=int, default=3)
    ap.add_argument("--distill", type=int, default=4000)
    ap.add_argument("--finetune", type=int, default=500)
    ap.add_argument("--batch-units", type=int, default=512)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--pairs", type=int, default=256)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    hist = train(a, log=lambda s: print(s, file=sys.stderr, flush=True))
    if processes().main:
        print(json.dumps(hist))


if __name__ == "__main__":
    main()

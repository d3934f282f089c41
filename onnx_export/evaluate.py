"""Held-out lobe error of a decoder (docs/architecture.md, Measurement), and offline projection of tabulated BRDFs.

    python -m onnx_export.evaluate --ckpt cache/runs/tiny/ckpt.pt --heldout tests/data/heldout_single.npz

``project`` finds the latent (3, 32) of any tabulated BRDF (direction pairs and values) by
optimising the latent against the frozen decoder: the paper's projection, used here for the
held-out set and available for measured data. The lobe error is the relative RMSE of the lobe
image f cos(theta_o) against the stored reference at each incident elevation; we report its
median and 90th percentile over (configuration, elevation), and the albedo error.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from addon.core import lobe
from onnx_export.heldout import load as load_heldout
from onnx_export.nets import Decoder, pair_loss


def load_decoder(ckpt) -> tuple[Decoder, torch.Tensor]:
    """The decoder (eval mode) and latents of a ``train_decoder`` checkpoint: its path, or the loaded dict."""
    s = ckpt if isinstance(ckpt, dict) else torch.load(ckpt, weights_only=False)
    c = s["config"]
    dec = Decoder(c["width"], c["depth"], c["features"], c["activation"])
    dec.load_state_dict(s["decoder"])
    dec.eval()
    return dec, s["latents"]


def latent_pair_loss(dec: Decoder, z, wi, wo, f, idx, loss: str, scale=None) -> torch.Tensor:
    """Mean ``loss`` of latents z (C, 3, 32) at the pairs ``idx`` of the C tabulated BRDFs (C, P, 3):
    every channel of every BRDF at the same pairs. ``scale`` (C, P): what the decoder's output is multiplied
    by before it is compared (a ``--top-transmission`` decoder's ``train_decoder.batch_of`` scale)."""
    c, q = z.shape[0], idx.shape[0]
    wi_r = wi[:, idx].unsqueeze(1).expand(c, 3, q, 3).reshape(-1, 3)
    wo_r = wo[:, idx].unsqueeze(1).expand(c, 3, q, 3).reshape(-1, 3)
    f_r = f[:, idx].permute(0, 2, 1).reshape(-1)
    zz = z.unsqueeze(2).expand(c, 3, q, 32).reshape(-1, 32)
    pred = dec(zz, wi_r, wo_r)
    if scale is not None:
        pred = pred * scale[:, idx].unsqueeze(1).expand(c, 3, q).reshape(-1)
    return pair_loss(pred, f_r, wi_r, wo_r, loss).mean()


def project(
    dec: Decoder,
    wi,
    wo,
    f,
    *,
    init=None,
    steps: int = 300,
    lr: float = 0.02,
    loss: str = "l1",
    chunk_pairs: int | None = None,
    seed: int = 0,
    log=None,
    scale=None,
) -> torch.Tensor:
    """Latents (C, 3, 32) of C tabulated RGB BRDFs given at (C, P, 3) direction pairs with values f (C, P, 3).

    ``init``: one latent (3, 32) for all, or one per BRDF (C, 3, 32); ``chunk_pairs``: pairs drawn per
    step (the same for all C; seeded by ``seed``), all of them when not given; ``scale`` (C, P): the factor on
    the decoder's output before it is compared (``latent_pair_loss``)."""
    wi, wo, f = (torch.as_tensor(np.asarray(a), dtype=torch.float32) for a in (wi, wo, f))
    if scale is not None:
        scale = torch.as_tensor(np.asarray(scale), dtype=torch.float32)
    c, p = wi.shape[:2]
    z = torch.zeros(c, 3, 32) if init is None else torch.as_tensor(init, dtype=torch.float32).expand(c, 3, 32).clone()
    z.requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr)
    for p_ in dec.parameters():
        p_.requires_grad_(False)
    gen = torch.Generator().manual_seed(seed)
    for step in range(steps):
        if chunk_pairs and chunk_pairs < p:
            idx = torch.randint(0, p, (chunk_pairs,), generator=gen)
        else:
            idx = torch.arange(p)
        for g in opt.param_groups:
            g["lr"] = lr * (0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi * step / steps)))
        l = latent_pair_loss(dec, z, wi, wo, f, idx, loss, scale)
        opt.zero_grad()
        l.backward()
        opt.step()
        if log and (step % 100 == 0 or step == steps - 1):
            log(f"project step {step} loss {l.item():.5f}")
    for p_ in dec.parameters():
        p_.requires_grad_(True)
    return z.detach()


@torch.no_grad()
def decoder_lobes(dec: Decoder, z: torch.Tensor, res: int, angles) -> np.ndarray:
    """(C, A, res, res, 3) lobe images of latents z (C, 3, 32)."""
    wo_grid, mask = lobe.lobe_grid(res)
    wo_m = torch.as_tensor(wo_grid[mask], dtype=torch.float32)
    npx = wo_m.shape[0]
    c = z.shape[0]
    out = np.zeros((c, len(angles), res * res, 3))
    for a, t in enumerate(angles):
        wi = torch.as_tensor(lobe.incident_direction(t), dtype=torch.float32).expand(npx, 3)
        for i in range(c):  # one batch per configuration and angle: 3 channels x pixels
            zz = z[i].repeat_interleave(npx, dim=0)
            f = dec(zz, wi.repeat(3, 1), wo_m.repeat(3, 1)).reshape(3, npx).T.numpy()
            out[i, a][mask] = f * wo_grid[mask, 2:3]
    return out.reshape(c, len(angles), res, res, 3)


def lobe_metrics(pred: np.ndarray, ref: np.ndarray) -> dict:
    """Relative RMSE per (configuration, angle), its median / p90, and the albedo error."""
    c, na = ref.shape[:2]
    err = np.array([[lobe.relative_rmse(pred[i, a], ref[i, a]) for a in range(na)] for i in range(c)])
    alb_p = np.array([[lobe.albedo_from_lobe(pred[i, a]) for a in range(na)] for i in range(c)])
    alb_r = np.array([[lobe.albedo_from_lobe(ref[i, a]) for a in range(na)] for i in range(c)])
    return {
        "lobe_error_median": float(np.median(err)),
        "lobe_error_p90": float(np.percentile(err, 90)),
        "albedo_abs_error_mean": float(np.mean(np.abs(alb_p - alb_r))),
        "albedo_abs_error_p90": float(np.percentile(np.abs(alb_p - alb_r), 90)),
        "errors": err,
    }


def evaluate_projection(dec: Decoder, heldout: dict, init=None, steps: int = 300, chunk_pairs=None, log=None) -> dict:
    z = project(
        dec,
        heldout["fit_wi"],
        heldout["fit_wo"],
        heldout["fit_f"],
        init=init,
        steps=steps,
        chunk_pairs=chunk_pairs,
        log=log,
    )
    pred = decoder_lobes(dec, z, heldout["lobe"].shape[2], heldout["angles"])
    m = lobe_metrics(pred, heldout["lobe"])
    m["z"] = z
    return m


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", type=Path, required=True)
    ap.add_argument("--heldout", type=Path, nargs="+", default=[Path("tests/data/heldout_single.npz")])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    dec, lat = load_decoder(a.ckpt)
    res = {}
    for h in a.heldout:
        m = evaluate_projection(dec, load_heldout(h), init=lat.mean(0), steps=a.steps)
        res[h.stem] = {k: v for k, v in m.items() if k not in ("errors", "z")}
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()

"""Projected latents of the layering training stacks: the second training signal of the layering network.

    python -m onnx_export.layering_project --size tiny --data cache/data/layering_c1 \
        --out cache/runs/layering_tiny/projected_c1.npz

Each training stack's reference values are projected into the frozen decoder's latent space by latent
optimisation (``onnx_export.evaluate.project``, the paper's projection). ``onnx_export.layering train
--projected`` then first regresses the layering network onto these latents (a well-conditioned start:
MSE in latent space, no decoder in the loop) and fine-tunes through the decoder afterwards.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from onnx_export.evaluate import project
from onnx_export.layered_data import load
from onnx_export.layering import frozen_decoder


def project_set(size: str, data: Path, steps: int, chunk: int, pairs: int, loss: str, stacks: int = 0,
                log=print) -> np.ndarray:
    dec = frozen_decoder(size)
    d = load(data)
    n, p, m = d["wi"].shape[:3]
    n = min(n, stacks) if stacks else n
    wi = d["wi"][:n].reshape(n, p * m, 3)
    wo = np.repeat(d["wo"][:n], m, axis=1)
    f = d["f"][:n].reshape(n, p * m, 3)
    z = np.zeros((n, 3, 32), dtype=np.float32)
    t0 = time.perf_counter()
    for s in range(0, n, chunk):  # a loop over chunks of stacks
        z[s:s + chunk] = project(dec, wi[s:s + chunk], wo[s:s + chunk], f[s:s + chunk], steps=steps, lr=0.03,
                                 loss=loss, chunk_pairs=pairs).numpy()
        log(f"projected {min(n, s + chunk)}/{n} stacks {time.perf_counter() - t0:.0f} s")
    return z


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="tiny")
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--chunk", type=int, default=512, help="stacks projected together")
    ap.add_argument("--pairs", type=int, default=128, help="direction pairs per stack per step")
    ap.add_argument("--loss", default="l1", choices=("l1", "l2"))
    ap.add_argument("--stacks", type=int, default=0, help="only the first N stacks (0: all)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    z = project_set(a.size, a.data, a.steps, a.chunk, a.pairs, a.loss, a.stacks, log=lambda s: print(s, file=sys.stderr, flush=True))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(a.out, z=z)


if __name__ == "__main__":
    main()

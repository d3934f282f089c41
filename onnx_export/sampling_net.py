"""The sampling network: latent z (3, 32) -> (sigma, w) of the proxy pdf, trained by KL divergence.

    python -m onnx_export.sampling_net --size tiny --materials 3000 --out cache/runs/sampling_tiny

The proxy (``addon/core/neural/proxy.py``, supplement section 1.2) is
q(wi | wo) = (1 - w) Gaussian(sigma) over the projected half vector + w cos(theta_i) / pi.

**Target.** For a material z, the ideal sampling density given wo is the normalised BRDF times cosine,
p(wi | wo) = f(wi, wo) cos(theta_i) / A(wo), with f the decoder's BRDF averaged over R, G, B and A the
directional albedo. The supplement's generalized NDF is this density carried to half-vector space
(wi -> h = normalize(wi + wo), Jacobian 4 |wo . h|) and averaged over wo. A KL divergence does not
change under a change of variables, so KL(p || q) per wo is the same in wi space and in half-vector
space; we compute it in wi space with the proxy's exact pdf (which contains the Jacobian) and
average it over ``WO_COS`` outgoing elevations:

    KL(z; sigma, w) = mean_wo  sum_i pi_i [log p(wi_i | wo) - log q(wi_i | wo; sigma, w)]

with wi_i drawn from a defensive mixture of proxies (cosine and Gaussians of several widths) and
self-normalised importance weights pi_i proportional to f cos / (mixture pdf).

**Training.** q is linear in w: q = (1 - w) q(sigma, 0) + w q(., 1), so for each training material we
tabulate KL on a grid of (log sigma, w) (``proxy.pdf`` evaluated once per sigma), and the network is
trained to minimise the bilinearly interpolated KL of its own output: the KL loss itself, with no
second implementation of the proxy's formula in torch. The table's minimum is the best proxy a
per-material fit could reach; both are reported. Latents come from the runtime encoders and layering
network (``addon.core.neural.encode``) of random stacks with 0 to 3 coatings.

The tables are kept in ``OUT/tables.npz`` with what they were computed for (``tables_key``: size, seed,
materials, held-out materials, samples and the digests of the models that made the latents): a rerun with the
same key reuses them, any other computes them again (with a log line saying what changed).

The same command runs under ``torchrun --nproc_per_node N`` (``onnx_export.distributed``): the tables,
most of the work, are split by batches of materials (each process skips the random numbers of the
others' batches, so the tables are those of one process), the training takes 1/N of every batch, and
process 0 writes the tables, the model and its card.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from addon.core.neural import proxy
from onnx_export.cli import command_line
from onnx_export.distributed import ONE_PROCESS, Processes, processes, quiet_unless_main
from onnx_export.nets import LATENT, macs_per_eval, mlp, n_params

MODEL_DIR = Path(__file__).resolve().parents[1] / "addon" / "models"
OPSET = 17
SIGMA_GRID = np.exp(np.linspace(np.log(0.004), np.log(1.5), 28))
W_GRID = np.linspace(0.0, 1.0, 21)
W_MIN = 0.01  # keep a little cosine lobe: the pdf stays > 0 wherever the BRDF might be
WO_COS = (0.15, 0.35, 0.55, 0.75, 0.9, 0.99)
MIXTURE = ((0.02, 0.0), (0.08, 0.0), (0.3, 0.0), (1.0, 0.0), (1.0, 1.0))  # (sigma, w) of the sampling mixture


class SamplingNet(nn.Module):
    """z (B, 3, 32) -> sigma (B,) in [SIGMA_GRID[0], SIGMA_GRID[-1]] (log-sigmoid), w (B,) in [W_MIN, 1]."""

    def __init__(self, width: int = 64, depth: int = 2):
        super().__init__()
        self.width, self.depth = width, depth
        self.net = mlp(3 * LATENT, width, depth, 2)
        self.register_buffer("log_lo", torch.tensor(float(np.log(SIGMA_GRID[0]))))
        self.register_buffer("log_hi", torch.tensor(float(np.log(SIGMA_GRID[-1]))))

    def forward(self, z):
        y = self.net(z.reshape(z.shape[0], 3 * LATENT))
        log_sigma = self.log_lo + (self.log_hi - self.log_lo) * torch.sigmoid(y[:, 0])
        w = W_MIN + (1.0 - W_MIN) * torch.sigmoid(y[:, 1])
        return torch.exp(log_sigma), w

    def config(self) -> dict:
        return {"width": self.width, "depth": self.depth}


# ----------------------------------------------------------------------------- KL tables


def random_arrays(rng: np.random.Generator, n: int):
    """Random stacks with 0..3 coatings (one StackArrays per coating count)."""
    from onnx_export.data import sample_layered_params, sample_single_params

    counts = rng.multinomial(n, (0.25, 0.4, 0.25, 0.1))
    out = []
    for c, k in enumerate(counts):
        if k:
            out.append(sample_single_params(rng, int(k)) if c == 0 else sample_layered_params(rng, int(k), c))
    return out


def material_tops(arrays_list) -> np.ndarray:
    """(N, 2) top coatings of the materials of ``material_latents`` (a remainder decoder's proxy is fitted
    to the decoded remainder, which the top coat's transmission scales for a ``top_transmission`` one)."""
    from addon.core.neural import top_coats

    return np.concatenate([top_coats(a) for a in arrays_list])


def material_latents(arrays_list, models) -> np.ndarray:
    from addon.core.neural import encode_arrays

    return np.concatenate([encode_arrays(a, models) for a in arrays_list])


def kl_tables(
    models,
    z: np.ndarray,
    samples: int = 160,
    seed: int = 0,
    batch: int = 48,
    log=None,
    procs: Processes = ONE_PROCESS,
    top: np.ndarray | None = None,
):
    """KL (N, len(SIGMA_GRID), len(W_GRID)) of each material's target against the proxy grid; ``top``
    (N, 2): the materials' top coatings, for a remainder decoder (its proxy samples the remainder: the
    renderer samples the exact top lobe itself).

    With several processes each computes every N-th batch of materials, advancing its generator past the
    random numbers of the batches it skips, and the tables are summed: the result is one process's."""
    rng = np.random.default_rng(seed)
    n = z.shape[0]
    nwo = len(WO_COS)
    k = len(MIXTURE)
    per = samples // k
    s_tot = per * k
    table = np.zeros((n, len(SIGMA_GRID), len(W_GRID)), dtype=np.float32)
    t0 = time.perf_counter()
    for b0 in range(0, n, batch):  # a loop over batches of materials
        zb = z[b0 : b0 + batch]
        m = zb.shape[0]
        rows = m * nwo * s_tot
        if (b0 // batch) % procs.world != procs.rank:  # another process's batch: skip its 3 x rows doubles
            rng.bit_generator.advance(3 * rows)
            continue
        ct = np.tile(np.repeat(np.asarray(WO_COS), s_tot), m)
        wo = np.stack([np.sqrt(1 - ct * ct), np.zeros_like(ct), ct], axis=1)
        comp = np.tile(np.repeat(np.arange(k), per), m * nwo)
        sig = np.array([c[0] for c in MIXTURE])[comp]
        wmix = np.array([c[1] for c in MIXTURE])[comp]
        wi, _ = proxy.sample(wo, sig, wmix, rng.random((rows, 3)))
        g = np.mean([proxy.pdf(wo, wi, s_, w_) for s_, w_ in MIXTURE], axis=0)
        tb = None if top is None else np.repeat(top[b0 : b0 + batch], nwo * s_tot, axis=0)
        f = models.eval_brdf(np.repeat(zb, nwo * s_tot, axis=0), wi, wo, tb, with_top_lobe=False)
        f = f.astype(np.float64).mean(axis=1)
        ok = (g > 0) & (wi[:, 2] > 0)
        fc = (f * np.maximum(wi[:, 2], 0.0)).reshape(m * nwo, s_tot)
        r = np.where(ok.reshape(m * nwo, s_tot), fc / np.where(ok, g, 1.0).reshape(m * nwo, s_tot), 0.0)
        # self-normalised weights of the target p = f cos / A; a black material (sum 0) contributes 0
        pi = r / np.maximum(r.sum(axis=1, keepdims=True), 1e-300)
        a = r.mean(axis=1, keepdims=True)  # A(wo) = E_g[f cos / g]
        log_p = np.log(np.maximum(fc, 1e-300) / np.maximum(a, 1e-300))
        cos_pdf = proxy.pdf(wo, wi, 1.0, 1.0).reshape(m * nwo, s_tot)
        for si, s_ in enumerate(SIGMA_GRID):  # a loop over the grid of sigma
            gauss = proxy.pdf(wo, wi, s_, 0.0).reshape(m * nwo, s_tot)
            q = (1.0 - W_GRID[None, None, :]) * gauss[..., None] + W_GRID[None, None, :] * cos_pdf[..., None]
            kl = np.sum(pi[..., None] * (log_p[..., None] - np.log(np.maximum(q, 1e-300))), axis=1)  # (m*nwo, W)
            table[b0 : b0 + m, si] = kl.reshape(m, nwo, -1).mean(axis=1)
        if log and (b0 // batch) % 10 == 0:
            log(f"KL tables {b0 + m}/{n} {time.perf_counter() - t0:.0f} s")
    if procs.world > 1:
        table = procs.total(torch.from_numpy(table)).numpy()
    return table


def interp_table(table: torch.Tensor, sigma: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of tables (B, S, W) at (log sigma, w) (B,)."""
    ls = torch.log(sigma)
    lo, hi = float(np.log(SIGMA_GRID[0])), float(np.log(SIGMA_GRID[-1]))
    u = torch.clamp((ls - lo) / (hi - lo) * (len(SIGMA_GRID) - 1), 0, len(SIGMA_GRID) - 1 - 1e-6)
    v = torch.clamp(w * (len(W_GRID) - 1), 0, len(W_GRID) - 1 - 1e-6)
    i0, j0 = u.floor().long(), v.floor().long()
    fu, fv = u - i0, v - j0
    b = torch.arange(table.shape[0])
    t00, t10 = table[b, i0, j0], table[b, i0 + 1, j0]
    t01, t11 = table[b, i0, j0 + 1], table[b, i0 + 1, j0 + 1]
    return (1 - fu) * (1 - fv) * t00 + fu * (1 - fv) * t10 + (1 - fu) * fv * t01 + fu * fv * t11


def table_minimum(table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-material grid optimum: (min KL (N,), argmin (sigma, w) (N, 2))."""
    flat = table.reshape(table.shape[0], -1)
    i = flat.argmin(axis=1)
    si, wi = np.unravel_index(i, table.shape[1:])
    return flat[np.arange(len(i)), i], np.stack([SIGMA_GRID[si], W_GRID[wi]], axis=1)


# ----------------------------------------------------------------------------- training / export


def export_onnx(net: SamplingNet, path: Path) -> None:
    net.eval()
    torch.onnx.export(
        net,
        (torch.zeros(4, 3, LATENT),),
        str(path),
        input_names=["z"],
        output_names=["sigma", "w"],
        dynamic_axes={"z": {0: "batch"}, "sigma": {0: "batch"}, "w": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )


def parity(net: SamplingNet, path: Path, z: np.ndarray) -> float:
    import onnxruntime as ort

    from onnx_export.export import max_relative_difference

    with torch.no_grad():
        s, w = net(torch.from_numpy(z))
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(["sigma", "w"], {"z": z})
    return max(max_relative_difference(got[0], s.numpy()), max_relative_difference(got[1], w.numpy()))


def net_from_onnx(path: Path, card: dict) -> SamplingNet:
    import onnx
    from onnx import numpy_helper

    net = SamplingNet(card["architecture"]["width"], card["architecture"]["depth"])
    w = {t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in onnx.load(str(path)).graph.initializer}
    net.load_state_dict(w, strict=False)
    return net.eval()


def tables_key(args, models) -> dict:
    """What the KL tables of ``run`` depend on: the run's size, seed, materials, held-out materials and
    samples, and the digests of the models that encode the materials and decode their BRDFs."""
    from addon.core.neural.models import file_digest

    paths = (models.encoder_path, models.decoder_path, models.path("layering"))
    return {
        "size": args.size,
        "seed": int(args.seed),
        "materials": int(args.materials),
        "heldout": int(args.heldout),
        "samples": int(args.samples),
        "models": {p.name: file_digest(p) for p in paths},
    }


def cached_tables(path: Path, key: dict, log) -> dict | None:
    """The tables in ``path`` when they were computed for ``key`` (``tables_key``), else None (with a log line
    naming what differs when there are tables of something else)."""
    if not path.exists():
        return None
    d = dict(np.load(path))
    held = json.loads(str(d.pop("key"))) if "key" in d else {}
    if held == key:
        return d
    changed = [k for k in key if held.get(k) != key[k]]
    words = ", ".join(
        f"{k} {held.get(k, '(not recorded)')} -> {key[k]}" if k != "models" else "the models' digests" for k in changed
    )
    log(f"{path} holds tables of other settings ({words}): computing them again")
    return None


def run(args, log=print) -> dict:
    from addon.core.neural.models import ModelSet, file_digest

    procs = processes()
    mine = procs.rows(args.batch)
    log = quiet_unless_main(log, procs)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    models = ModelSet(args.size, threads=args.threads, model_dir=args.models)
    cache = out / "tables.npz"
    key = tables_key(args, models)
    d = cached_tables(cache, key, log)
    if d is not None:
        z, table, z_ho, table_ho = d["z"], d["table"], d["z_ho"], d["table_ho"]
    else:
        rng = np.random.default_rng([args.seed, 5])
        arrays = random_arrays(rng, args.materials)
        z = material_latents(arrays, models)
        table = kl_tables(models, z, args.samples, seed=args.seed, log=log, procs=procs, top=material_tops(arrays))
        rng_ho = np.random.default_rng([args.seed, 6])  # held-out materials
        arrays_ho = random_arrays(rng_ho, args.heldout)
        z_ho = material_latents(arrays_ho, models)
        table_ho = kl_tables(
            models, z_ho, args.samples, seed=args.seed + 1, log=log, procs=procs, top=material_tops(arrays_ho)
        )
        if procs.main:
            tmp = cache.with_suffix(".tmp.npz")
            np.savez(tmp, z=z, table=table, z_ho=z_ho, table_ho=table_ho, key=np.array(json.dumps(key)))
            tmp.replace(cache)  # whole or not at all
    net = SamplingNet(args.width, args.depth)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    zt, tt = torch.from_numpy(z), torch.from_numpy(table)
    gen = torch.Generator().manual_seed(args.seed)
    t0 = time.perf_counter()
    for step in range(args.steps):
        for g in opt.param_groups:
            g["lr"] = args.lr * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * step / args.steps)))
        idx = torch.randint(0, zt.shape[0], (args.batch,), generator=gen)[mine]
        s, w = net(zt[idx])
        loss = interp_table(tt[idx], s, w).mean()
        opt.zero_grad()
        loss.backward()
        procs.average_gradients(net.parameters())
        opt.step()
        if (step + 1) % 500 == 0:
            log(f"step {step + 1}/{args.steps} KL {procs.mean(loss):.4f} {time.perf_counter() - t0:.0f} s")
    if not procs.main:
        return {}
    net.eval()
    with torch.no_grad():
        s_ho, w_ho = net(torch.from_numpy(z_ho))
        kl_net = interp_table(torch.from_numpy(table_ho), s_ho, w_ho).numpy()
    kl_best, _ = table_minimum(table_ho)
    j_cos = len(W_GRID) - 1
    metrics = {
        "heldout_materials": int(z_ho.shape[0]),
        "kl_network_mean": float(kl_net.mean()),
        "kl_network_median": float(np.median(kl_net)),
        "kl_per_material_optimum_mean": float(kl_best.mean()),
        "kl_cosine_only_mean": float(table_ho[:, 0, j_cos].mean()),
    }
    log(json.dumps(metrics))
    path = Path(args.models) / f"sampling_{args.size}.onnx"
    export_onnx(net, path)
    par = parity(net, path, z_ho[:512].astype(np.float32))
    card = {
        "name": f"sampling_{args.size}",
        "role": f"sampling network in the latent space of decoder_{args.size}: z (3, 32) -> (sigma, w) of the proxy "
        "pdf (1 - w) Gaussian(sigma) over the projected half vector + w cosine lobe (addon.core.neural.proxy)",
        "files": {path.name: file_digest(path)},
        "inputs": {"z": "(B, 3, 32) float32 latent (all three channels)"},
        "outputs": {
            "sigma": f"(B,) float32 in [{SIGMA_GRID[0]:.3g}, {SIGMA_GRID[-1]:.3g}]",
            "w": f"(B,) float32 in [{W_MIN}, 1]",
        },
        "architecture": {
            **net.config(),
            "hidden": f"{net.depth} x Linear({net.width}) + ReLU",
            "output": "sigma = exp(log-sigmoid between the grid ends), w = 0.01 + 0.99 sigmoid",
        },
        "parameters": n_params(net),
        "macs_per_material": macs_per_eval(net),
        "training": {
            "command": command_line("onnx_export.sampling_net", vars(args), skip=("models",)),
            "loss": "KL(BRDF cos / albedo || proxy) averaged over wo with cos(theta_o) in "
            + str(list(WO_COS))
            + ", bilinear in a per-material table over (log sigma, w)",
            "materials": int(z.shape[0]),
            "seeds": {"materials": [args.seed, 5], "training": args.seed},
        },
        "heldout": metrics,
        "onnx_runtime_vs_torch_max_relative_difference": par,
        "opset": OPSET,
        "trained_with": {
            p.name: file_digest(p) for p in (models.encoder_path, models.decoder_path, models.path("layering"))
        },
    }
    path.with_suffix(".json").write_text(json.dumps(card, indent=1) + "\n")
    log(json.dumps({"model": str(path), "parity": par}))
    return card


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="tiny")
    ap.add_argument("--materials", type=int, default=3000)
    ap.add_argument("--heldout", type=int, default=300)
    ap.add_argument("--samples", type=int, default=160, help="wi samples per (material, wo)")
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--depth", type=int, default=2)
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument(
        "--models",
        type=Path,
        default=MODEL_DIR,
        help="where the decoder, encoder and layering models are read and the sampling model is written",
    )
    a = ap.parse_args(argv)
    run(a, log=lambda s: print(s, file=sys.stderr, flush=True))


if __name__ == "__main__":
    main()

"""The layering network: L(z_top_interface, z_bottom, albedo_c, thickness) -> z, one colour channel at a time.

    python -m onnx_export.layering train --size tiny --c1 cache/data/layering_c1 --c2 cache/data/layering_c2 \
        --steps 4000 --finetune 1500 --out cache/runs/layering_tiny
    python -m onnx_export.layering export --size tiny --ckpt cache/runs/layering_tiny/ckpt.pt

``z_top`` is the encoder's latent of the coating's interface ``Dielectric(roughness, ior)`` (reflection
over black), ``z_bottom`` the latent of what lies below: the base, or, applied recursively bottom-up,
the latent of the lower sub-stack. ``albedo_c`` is the slab's single-scattering albedo in the channel
and ``thickness`` its optical thickness. The decoder and the encoder are frozen (read from the shipped
ONNX files of the decoder size), so the layering network lives in their latent space.

Training (stage 1) uses stacks with one coating, stage 2 (``--finetune`` steps) adds stacks with two
coatings (and, with ``--c3`` and ``--c4``, three and four), for which the network is applied as many
times, so that the recursion is trained end to end: each coating count takes an equal share of every stage-2 batch. The
loss goes THROUGH THE FROZEN DECODER against reference values f(wi, wo) (``onnx_export.layered_data``,
a few walks each, so the targets are noisy):

- ``l2rel`` (default): squared error of the first-order change of log1p(f cos_i cos_o),
  ``cc (pred - target) / (1 + cc pred)`` with the denominator held constant in the gradient: a squared
  error in f with a weight that depends only on the prediction, so its minimiser is the MEAN of the
  noisy targets (unbiased), while still scaled like the log loss the decoder was trained with;
- ``l1log``: L1 on log1p(f cos_i cos_o), the decoder's own loss: its minimiser is the median of the
  noise (biased low for the skewed Monte Carlo estimates). Kept to measure the difference.

With ``--projected`` the network is first regressed onto projected latents of the training stacks (MSE
in latent space, no decoder in the loop); ``--decoded-steps`` then continue in function space with
``decoded_lobe_loss``: the relative squared error of the cosine-weighted lobe, RGB together, per
(stack, outgoing direction), the square of the held-out metric. Its target is the lobe decoded from the
projected latents (``--decoded-target latents``) or the Monte Carlo values themselves (``data``; best
with the same stacks computed with more walks, ``--decoded-data``); docs/layering_training.md compares
them. Against data, the stage also runs without ``--projected``, from a trained network
(``--init-from SIZE``): more steps, or more stacks, without a new projection.

Checkpoints go to ``OUT/ckpt.pt`` (resumable, every stage: the optimiser and the batch generator are saved,
so a resumed run continues as the uninterrupted one; a rerun with other arguments than the checkpoint's is
refused, naming the flag); the held-out lobe error (``--heldout``, ``tests/data/heldout_layered.npz``; a
missing file is an error at the start, ``--heldout none`` measures nothing) is measured at the end of each
stage and every ``--eval-every`` steps. With ``--keep-best`` (and a validation set as ``--heldout``)
``OUT/best.pt`` keeps the network of the best of those evaluations (``selection_score``): a later stage that
loses what an earlier one reached does not take it away. ``train`` runs unchanged under ``torchrun --nproc_per_node N``
(``onnx_export.distributed``): each process takes its 1/N of the stacks of every batch, and process 0
measures, logs and checkpoints.
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

from addon.core.neural.features import arrays_features
from addon.core.neural.models import ModelSet, file_digest
from addon.core.stack import TRAINED_RANGES, StackArrays
from onnx_export.cli import check_resume, command_line, positive_int
from onnx_export.distributed import ONE_PROCESS, Processes, processes, quiet_unless_main
from onnx_export.layered_data import data_command
from onnx_export.nets import LATENT, cosine_lr, level_weights, macs_per_eval, mlp, n_params, pair_loss, stack_levels
from onnx_export.remainder import remainder_scales, top_reflection

MODEL_DIR = Path(__file__).resolve().parents[1] / "addon" / "models"
OPSET = 17
THICKNESS_MAX = TRAINED_RANGES["thickness"][1]
# what a resumed ``train`` may change (more steps, logging, evaluation); any other argument must be the checkpoint's
RESUME_FREE = ("steps", "finetune", "every", "eval_every", "log_every", "threads", "out", "cmd", "heldout", "keep_best")


def heldout_path(text: str) -> Path | None:
    """argparse type of ``--heldout``: a path, or ``none`` for no held-out evaluation."""
    return None if text.lower() == "none" else Path(text)


def check_heldout(args) -> None:
    """``FileNotFoundError`` at the start of a run whose ``--heldout`` file is missing (every evaluation, and
    ``--keep-best``, would be skipped without a word); ``ValueError`` for ``--keep-best`` without one."""
    if args.heldout is None:
        if args.keep_best:
            raise ValueError("--keep-best keeps the network of the best held-out evaluation: give --heldout")
        return
    if not Path(args.heldout).exists():
        raise FileNotFoundError(
            f"--heldout {args.heldout}: no such file (make it with onnx_export.heldout_layered, or give "
            "--heldout none to train without held-out evaluations)"
        )


class LayeringNet(nn.Module):
    """z_top (B, 32), z_bottom (B, 32), albedo (B,), thickness (B,) -> z (B, 32) of one colour channel."""

    def __init__(self, width: int = 128, depth: int = 3):
        super().__init__()
        self.width, self.depth = width, depth
        self.net = mlp(2 * LATENT + 4, width, depth, LATENT)

    def forward(self, z_top, z_bottom, albedo, thickness):
        t = thickness.unsqueeze(-1)
        a = albedo.unsqueeze(-1)
        opacity = 1.0 - torch.exp(-t)  # fraction of light the slab interacts with, straight through
        x = torch.cat([z_top, z_bottom, a, opacity, a * opacity, t / THICKNESS_MAX], dim=-1)
        return self.net(x)

    def config(self) -> dict:
        return {"width": self.width, "depth": self.depth}


def compose(
    net: LayeringNet, z_base: torch.Tensor, z_tops: torch.Tensor, albedo: torch.Tensor, thickness: torch.Tensor
) -> torch.Tensor:
    """Latent (S, 3, 32) of S stacks, bottom-up: z_base (S, 3, 32), z_tops (S, C, 3, 32) of the coatings'
    interfaces, albedo (S, C, 3), thickness (S, C)."""
    s = z_base.shape[0]
    z = z_base.reshape(s * 3, LATENT)
    for j in range(z_tops.shape[1]):  # a loop over coatings
        z = net(
            z_tops[:, j].reshape(s * 3, LATENT), z, albedo[:, j].reshape(s * 3), thickness[:, j].repeat_interleave(3)
        )
    return z.reshape(s, 3, LATENT)


# ----------------------------------------------------------------------------- frozen encoder / decoder


def interface_features(arrays: StackArrays) -> np.ndarray:
    """(N, C, 3, F) encoder features of every coating's interface (``StackArrays.coating_interfaces``)."""
    x = arrays_features(arrays.coating_interfaces())
    return x.reshape(len(arrays), arrays.n_coatings, 3, -1)


def encoder_latents(models: ModelSet, arrays: StackArrays) -> tuple[np.ndarray, np.ndarray]:
    """Frozen-encoder latents: base (N, 3, 32) and coating interfaces (N, C, 3, 32)."""
    zb = models.run_encoder(arrays_features(arrays))
    xi = interface_features(arrays)
    zt = models.run_encoder(xi.reshape(-1, 3, xi.shape[-1])).reshape(len(arrays), arrays.n_coatings, 3, LATENT)
    return zb, zt


def frozen_decoder(size: str, model_dir: Path = MODEL_DIR):
    from onnx_export.export import torch_from_onnx

    path = model_dir / f"decoder_{size}.onnx"
    card = json.loads(path.with_suffix(".json").read_text())
    dec = torch_from_onnx(path, card)
    for p in dec.parameters():
        p.requires_grad_(False)
    return dec


# ----------------------------------------------------------------------------- data and loss


class StackSet:
    """Training tensors of one coating count: encoder latents, medium parameters and reference values."""

    def __init__(
        self,
        path: Path,
        models: ModelSet,
        stacks: int = 0,
        use_weight: bool = False,
        remainder: bool = False,
        transmission: bool = False,
        level_floor: float = 0.0,
    ):
        """``remainder``: the values are each stack's BRDF minus its exact top-interface reflection
        (the decoder holds the rest: ``onnx_export.remainder``); ``transmission``: the decoder's values are
        multiplied by the top coat's transmission in and out (``scale``) before they are compared;
        ``level_floor`` > 0: each stack's pairs weigh 1 / clip(level, level_floor x m, m)^2, m the median
        level (``nets.level_weights``), so that a dim stack's loss scales like its relative lobe error."""
        self.use_weight = use_weight
        from onnx_export.layered_data import load

        d = load(path)
        self.command = data_command(Path(path))  # the command of these data as loaded (directories grow)
        a = d["arrays"]
        if stacks:
            a = a.take(slice(0, stacks))
        n = len(a)
        zb, zt = encoder_latents(models, a)
        self.n = n
        self.z_base = torch.from_numpy(zb)
        self.z_tops = torch.from_numpy(zt)
        self.albedo = torch.from_numpy(a.coat_albedo.astype(np.float32))
        self.thickness = torch.from_numpy(a.coat_thickness.astype(np.float32))
        p, m = d["wi"].shape[1:3]
        self.wi = torch.from_numpy(d["wi"][:n].reshape(n, p * m, 3))
        self.wo = torch.from_numpy(np.repeat(d["wo"][:n], m, axis=1))
        f = d["f"][:n].reshape(n, p * m, 3)
        if remainder:
            f = (f - top_reflection(a, d["wi"][:n].reshape(n, p * m, 3), np.repeat(d["wo"][:n], m, axis=1))).astype(
                np.float32
            )
        self.f = torch.from_numpy(f)
        self.scale = None
        if transmission:
            wi_all, wo_all = d["wi"][:n].reshape(n, p * m, 3), np.repeat(d["wo"][:n], m, axis=1)
            self.scale = torch.from_numpy(remainder_scales(a, wi_all, wo_all).astype(np.float32))  # (n, p m, 1)
        self.weight = torch.from_numpy(
            cosine_weights(d["wi"][:n], d["wo"][:n], a.coat_roughness[:, -1]).reshape(n, p * m)
        )
        self.stack_weight = level_weights(stack_levels(self.f, self.wi, self.wo, self.weight), level_floor)
        self.groups = p  # outgoing directions per stack, each with m incident ones

    def decoded_batch(
        self,
        net,
        dec,
        z_target: torch.Tensor | None,
        b: int,
        g: int,
        gen: torch.Generator,
        kind: str = "squared",
        reciprocal: bool = False,
        procs: Processes = ONE_PROCESS,
    ) -> torch.Tensor:
        """Function-space loss of ``b`` random stacks at ``g`` of their outgoing directions each: the
        relative squared error of the cosine-weighted lobe (``decoded_lobe_loss``) between the decoder's
        values for L's latent and the decoder's values for the stack's target latent ``z_target``
        (n, 3, 32), or the stack's Monte Carlo values when ``z_target`` is None (a squared error: its
        minimiser is their mean).

        A group's fixed direction is the decoder's ``wo``; the lobe images of the metric, and half the
        renderer's calls, hold the incident direction fixed instead. The decoder's inputs are not
        symmetric in its two directions, so a latent fitted in one order is not fitted in the other:
        with ``reciprocal`` a random half of the groups is decoded with the two directions swapped,
        against the same values (the reference BRDF is reciprocal), so both orders are trained.

        Every process draws all ``b`` stacks and computes the loss of its share of them (``procs``)."""
        n, pm = self.wi.shape[:2]
        m = pm // self.groups
        s = torch.randint(0, self.n, (b,), generator=gen)
        grp = torch.randint(0, self.groups, (b, g), generator=gen)
        swap = (torch.rand((b, g), generator=gen) < 0.5) if reciprocal else None
        mine = procs.rows(b)
        s, grp, b = s[mine], grp[mine], mine.stop - mine.start
        idx = (grp.unsqueeze(-1) * m + torch.arange(m)).reshape(b, g * m)  # every incident direction of a group
        wi, wo, w = self.wi[s[:, None], idx], self.wo[s[:, None], idx], self.weight[s[:, None], idx]
        d_in, d_out = wi, wo  # the decoder's incident and outgoing directions
        if reciprocal:
            swap = swap[mine].repeat_interleave(m, dim=1).unsqueeze(-1)
            d_in, d_out = torch.where(swap, wo, wi), torch.where(swap, wi, wo)
        z = compose(net, self.z_base[s], self.z_tops[s], self.albedo[s], self.thickness[s])
        pred = decode_pairs(dec, z, d_in, d_out)
        if z_target is None:
            target = self.f[s[:, None], idx]
        else:
            with torch.no_grad():
                target = decode_pairs(dec, z_target[s], d_in, d_out)
        if self.scale is not None:  # reciprocal: the same factor for swapped directions
            pred = pred * self.scale[s[:, None], idx]
            if z_target is not None:
                target = target * self.scale[s[:, None], idx]
        sh = (b, g, m)
        return decoded_lobe_loss(
            pred.reshape(*sh, 3), target.reshape(*sh, 3), wi[..., 2].reshape(sh), w.reshape(sh), kind
        )

    def batch(self, net, dec, b: int, q: int, gen: torch.Generator, procs: Processes = ONE_PROCESS):
        """Decoded values, targets, directions and weights of ``q`` pairs of ``b`` random stacks (this
        process's share of them: every process draws all ``b``)."""
        s = torch.randint(0, self.n, (b,), generator=gen)
        idx = torch.randint(0, self.wi.shape[1], (b, q), generator=gen)
        mine = procs.rows(b)
        s, idx, b = s[mine], idx[mine], mine.stop - mine.start
        z = compose(net, self.z_base[s], self.z_tops[s], self.albedo[s], self.thickness[s])  # (b, 3, 32)
        wi = self.wi[s[:, None], idx]  # (b, q, 3)
        wo = self.wo[s[:, None], idx]
        f = self.f[s[:, None], idx]  # (b, q, 3)
        pred = decode_pairs(dec, z, wi, wo)
        if self.scale is not None:
            pred = pred * self.scale[s[:, None], idx]
        pred = pred.permute(0, 2, 1).reshape(-1)  # (b, 3, q) flattened, as f below
        wi_r = wi.unsqueeze(1).expand(b, 3, q, 3).reshape(-1, 3)
        wo_r = wo.unsqueeze(1).expand(b, 3, q, 3).reshape(-1, 3)
        wt = self.weight[s[:, None], idx] if self.use_weight else None
        if self.stack_weight is not None:
            sw = self.stack_weight[s][:, None].expand(b, q)
            wt = sw if wt is None else wt * sw
        wt = wt.unsqueeze(1).expand(b, 3, q).reshape(-1) if wt is not None else None
        return pred, f.permute(0, 2, 1).reshape(-1), wi_r, wo_r, wt


def coating_data(args, c: int) -> Path:
    """The data directory of ``layering train`` with ``c`` coatings (``--c1`` to ``--c4``)."""
    path = {1: args.c1, 2: args.c2, 3: getattr(args, "c3", None), 4: getattr(args, "c4", None)}.get(c)
    if path is None:
        raise ValueError(f"no data of stacks with {c} coatings: give --c{c} (layering train takes --c1 to --c4)")
    return Path(path)


def recursion_counts(args) -> list[int]:
    """The coating counts above one that stage 2 trains: 2, and 3 with ``--c3``, 4 with ``--c4``."""
    return [2] + [c for c in (3, 4) if getattr(args, f"c{c}", None)]


def stage2_shares(args) -> dict[int, tuple[int, float]]:
    """Stacks per batch and loss weight of each coating count in stage 2, the recursion's counts first:
    equal shares, or ``--c3-share`` of the batch (and of the loss) for three coatings and the rest split
    equally between the other counts."""
    deeper = recursion_counts(args)
    share3 = getattr(args, "c3_share", None)
    if share3 is None:
        n = args.batch // (len(deeper) + 1)
        sizes = {c: n for c in deeper} | {1: args.batch - n * len(deeper)}
        return {c: (b, 1.0 / len(sizes)) for c, b in sizes.items()}
    if 3 not in deeper:
        raise ValueError("--c3-share needs --c3")
    if not 0.0 < share3 < 1.0:
        raise ValueError(f"--c3-share must be in (0, 1), got {share3}")
    others = [c for c in deeper if c != 3]
    n3 = max(1, round(args.batch * share3))
    n = (args.batch - n3) // (len(others) + 1)
    if n < 1:
        raise ValueError(f"--batch {args.batch} leaves no stacks with the other coating counts at --c3-share {share3}")
    rest = (1.0 - share3) / (len(others) + 1)
    return {c: (n, rest) for c in others} | {3: (n3, share3), 1: (args.batch - n3 - n * len(others), rest)}


def stack_set(args, models: ModelSet, path: Path, stacks: int = 0, use_weight: bool | None = None) -> StackSet:
    """A StackSet of ``path`` for ``layering train``: its weighting (``--weighting``, unless ``use_weight``;
    ``--level-floor``) and the decoder's design (``--remainder``, ``--top-transmission``) from ``args``."""
    weight = args.weighting == "cosine" if use_weight is None else use_weight
    return StackSet(
        path,
        models,
        stacks,
        weight,
        remainder=args.remainder,
        transmission=args.top_transmission,
        level_floor=getattr(args, "level_floor", 0.0),
    )


def decode_pairs(dec, z: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """RGB decoder values (b, q, 3) of latents z (b, 3, 32) at b x q direction pairs wi, wo (b, q, 3)."""
    b, q = wi.shape[:2]
    zz = z.unsqueeze(2).expand(b, 3, q, LATENT).reshape(-1, LATENT)
    wi_r = wi.unsqueeze(1).expand(b, 3, q, 3).reshape(-1, 3)
    wo_r = wo.unsqueeze(1).expand(b, 3, q, 3).reshape(-1, 3)
    return dec(zz, wi_r, wo_r).reshape(b, 3, q).permute(0, 2, 1)


def decoded_lobe_loss(pred, target, cos_i, weight, kind: str = "squared") -> torch.Tensor:
    """Mean over groups of ||pred - target||^2 / ||target||^2 of the lobe f cos_i, RGB together, each
    group (..., m) being m incident directions of one outgoing direction with the weights that make their
    sum a cosine-weighted integral (``cosine_weights``): by reciprocity, the square of the lobe image's
    relative RMSE that ``onnx_export.evaluate.lobe_metrics`` reports, for that outgoing direction.

    ``kind="rmse"`` averages its square root instead, the relative RMSE itself: each group's own
    minimiser is unchanged (a monotone function of its error), but a group weighs 1 / (2 RMSE) as much
    in the gradient, so the worst groups no longer dominate the mean, which moves the median more."""
    if kind not in ("squared", "rmse"):
        raise ValueError(f"unknown function-space loss {kind!r}; expected squared or rmse")
    c = cos_i.clamp(min=0.0).unsqueeze(-1)
    num = (weight * (((pred - target) * c) ** 2).sum(-1)).sum(-1)
    den = (weight * ((target * c) ** 2).sum(-1)).sum(-1)
    rel = num / den.clamp(min=1e-12)
    return (rel if kind == "squared" else (rel + 1e-12).sqrt()).mean()


def cosine_weights(wi: np.ndarray, wo: np.ndarray, lobe_alpha: np.ndarray) -> np.ndarray:
    """Per-pair weights (S, P, M) that turn the data's direction distribution into the cosine one.

    The data draw wi given wo from 0.5 lobe (GGX visible normals of the top roughness widened by
    U(1, 2)) + 0.25 cosine + 0.25 uniform (``layered_data.sample_query_directions``), which puts half the
    pairs in the specular peak; the lobe-image error weighs directions by cos(theta_i) (a uniform grid
    on the projected disk). Weighting each pair by cos/pi over the sampling density makes the loss an
    estimate of the cosine-weighted one, so a sharp peak no longer outweighs the rest of the lobe.
    """
    from addon.core.bsdf.conductor import RoughConductor

    s, p, m = wi.shape[:3]
    wi_f = wi.reshape(-1, 3).astype(np.float64)
    wo_f = np.broadcast_to(wo[:, :, None, :], wi.shape).reshape(-1, 3).astype(np.float64)
    a = np.repeat(lobe_alpha.astype(np.float64), p * m)
    lobe_pdf = np.zeros(wi_f.shape[0])
    for u in (1.125, 1.375, 1.625, 1.875):  # midpoint rule over the widening factor U(1, 2)
        lobe_pdf += 0.25 * RoughConductor(np.minimum(a * u, 1.0), np.ones(3), np.ones(3)).pdf(wi_f, wo_f, check=False)
    cos_pdf = np.maximum(wi_f[:, 2], 0.0) / np.pi
    mix = 0.5 * lobe_pdf + 0.25 * cos_pdf + 0.25 / (2.0 * np.pi)
    return (cos_pdf / mix).reshape(s, p, m).astype(np.float32)


def layering_loss(
    pred, target, wi, wo, weight, kind: str, procs: Processes = ONE_PROCESS, grazing_floor: float = 1.0
) -> torch.Tensor:
    """Mean per-pair loss (``nets.pair_loss``; ``l1log`` is its ``l1``; ``grazing_floor`` < 1 weights the
    grazing pairs as there), weighted per pair when ``weight`` is given (then normalised by its mean over
    the whole batch: with several processes, the mean over them of this process's share is the whole
    batch's loss)."""
    if kind not in ("l2rel", "l1log"):
        raise ValueError(f"unknown layering loss {kind!r}; expected l2rel or l1log")
    e = pair_loss(pred, target, wi, wo, "l1" if kind == "l1log" else kind, grazing_floor)
    if weight is None:
        return e.mean()
    return (weight * e).sum() / (procs.total(weight.sum()) / procs.world).clamp(min=1e-12)


# ----------------------------------------------------------------------------- held-out error


@torch.no_grad()
def selection_score(metrics: dict) -> float:
    """What ``--keep-best`` minimises over the evaluations of a run: the mean over coating counts of the
    median plus the 90th percentile of the lobe error (``heldout_error``'s dict), so that neither a better
    median bought with a worse tail nor the reverse counts as progress."""
    per = [d["lobe_error_median"] + d["lobe_error_p90"] for d in metrics.values()]
    return float(np.mean(per))


def heldout_error(
    net: LayeringNet,
    dec,
    models: ModelSet,
    heldout: dict,
    log=None,
    remainder: bool = False,
    transmission=False,
    keep_errors: bool = False,
) -> dict:
    """Lobe error of the layered latents per number of coatings, as onnx_export.evaluate measures it
    (``remainder``: of the exact top-interface reflection plus the decoded lobe, ``transmission``: times
    the top coat's transmission); ``keep_errors``: with each count's (stacks, elevations) errors too."""
    from onnx_export.evaluate import decoder_lobes, lobe_metrics
    from onnx_export.remainder import scale_lobes, top_lobes

    stacks = heldout["stacks"]
    counts = np.array([len(s.coatings) for s in stacks])
    out = {}
    for c in sorted(set(counts.tolist())):
        idx = np.flatnonzero(counts == c)
        a = StackArrays.from_stacks([stacks[i] for i in idx])
        zb, zt = encoder_latents(models, a)
        z = compose(
            net,
            torch.from_numpy(zb),
            torch.from_numpy(zt),
            torch.from_numpy(a.coat_albedo.astype(np.float32)),
            torch.from_numpy(a.coat_thickness.astype(np.float32)),
        )
        pred = decoder_lobes(dec, z, heldout["lobe"].shape[2], heldout["angles"])
        if transmission:
            pred = pred * scale_lobes(a, heldout["lobe"].shape[2], heldout["angles"])
        if remainder:
            pred = pred + top_lobes(a, heldout["lobe"].shape[2], heldout["angles"])
        m = lobe_metrics(pred, heldout["lobe"][idx])
        out[f"coatings_{c}"] = {k: v for k, v in m.items() if k != "errors" or keep_errors} | {"configs": int(idx.size)}
    if log:
        shown = {k: {q: round(v, 4) for q, v in d.items() if q != "errors"} for k, d in out.items()}
        log("held-out: " + json.dumps(shown))
    return out


def lobe_bound(
    net: LayeringNet,
    dec,
    models: ModelSet,
    heldout: dict,
    steps: int = 400,
    pixels: int = 96,
    lr: float = 0.01,
    seed: int = 0,
    log=None,
    remainder: bool = False,
    transmission: bool = False,
) -> dict:
    """What the decoder could hold: the held-out lobes projected into its latent space, per number of
    coatings, by latent optimisation on the scored pixels themselves with the metric as the loss
    (``decoded_lobe_loss``, ``pixels`` random pixels of every image per step), starting from the
    layering network's latents. An optimistic bound on any layering network in this latent space.

    ``remainder``: the decoder holds the remainder design's rest of the BRDF: the projection's
    target is each held-out lobe minus the exact top-interface reflection (``remainder.top_lobes``),
    and what is scored is that reflection plus the decoded lobe, against the whole reference;
    ``transmission``: the decoded lobe is times the top coat's transmission (``remainder.scale_lobes``)."""
    from addon.core import lobe
    from onnx_export.evaluate import decoder_lobes, lobe_metrics
    from onnx_export.remainder import scale_lobes, top_lobes

    stacks, ref_all, angles = heldout["stacks"], heldout["lobe"], heldout["angles"]
    res = ref_all.shape[2]
    wo_grid, mask = lobe.lobe_grid(res)
    wo = torch.as_tensor(wo_grid[mask], dtype=torch.float32)
    wis = torch.as_tensor(np.stack([lobe.incident_direction(t) for t in angles]), dtype=torch.float32)
    counts = np.array([len(st.coatings) for st in stacks])
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for c in sorted(set(counts.tolist())):
        idx = np.flatnonzero(counts == c)
        a = StackArrays.from_stacks([stacks[i] for i in idx])
        zb, zt = encoder_latents(models, a)
        with torch.no_grad():
            z0 = compose(
                net,
                torch.from_numpy(zb),
                torch.from_numpy(zt),
                torch.from_numpy(a.coat_albedo.astype(np.float32)),
                torch.from_numpy(a.coat_thickness.astype(np.float32)),
            )
        top = top_lobes(a, res, angles) if remainder else np.zeros_like(ref_all[idx])
        sc_img = scale_lobes(a, res, angles) if transmission else np.ones(ref_all[idx].shape[:-1] + (1,))
        sc = torch.as_tensor(sc_img.reshape(len(idx), len(angles), res * res, 1)[:, :, mask], dtype=torch.float32)
        ref = torch.as_tensor(
            (ref_all[idx] - top).reshape(len(idx), len(angles), res * res, 3)[:, :, mask] / wo[:, 2:3],
            dtype=torch.float32,
        )  # f (of the remainder) at the pixels (S, A, npx, 3)
        z = z0.clone().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=lr)
        n_s, n_a = len(idx), len(angles)
        for step in range(steps):
            for g in opt.param_groups:
                g["lr"] = lr * (0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi * step / steps)))
            pix = torch.randint(0, wo.shape[0], (n_a, pixels), generator=gen)
            wo_b = wo[pix].unsqueeze(0).expand(n_s, n_a, pixels, 3).reshape(n_s, -1, 3)
            wi_b = wis[:, None, :].expand(n_a, pixels, 3).unsqueeze(0).expand(n_s, n_a, pixels, 3).reshape(n_s, -1, 3)
            pred = decode_pairs(dec, z, wi_b, wo_b).reshape(n_s, n_a, pixels, 3)
            pred = pred * sc[:, torch.arange(n_a)[:, None], pix]
            target = ref[:, torch.arange(n_a)[:, None], pix]
            loss = decoded_lobe_loss(
                pred, target, wo[pix][..., 2].expand(n_s, n_a, pixels), torch.ones(n_s, n_a, pixels)
            )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        m = lobe_metrics(top + sc_img * decoder_lobes(dec, z.detach(), res, angles), ref_all[idx])
        m0 = lobe_metrics(top + sc_img * decoder_lobes(dec, z0, res, angles), ref_all[idx])
        out[f"coatings_{c}"] = {
            "layering": [m0["lobe_error_median"], m0["lobe_error_p90"]],
            "bound": [m["lobe_error_median"], m["lobe_error_p90"]],
            "configs": int(idx.size),
        }
        if log:
            log(
                f"{c} coatings: layering {m0['lobe_error_median']:.4f} / {m0['lobe_error_p90']:.4f}, "
                f"bound {m['lobe_error_median']:.4f} / {m['lobe_error_p90']:.4f} (median / p90)"
            )
    return out


# ----------------------------------------------------------------------------- training


def projected_latents(path: Path, data_dir: Path, n: int, shrink: float = 1.0) -> torch.Tensor:
    """(n, 3, 32) latents of the first ``n`` stacks of ``data_dir`` in the decoder's latent space, from
    ``path``: an ``.npz`` of ``onnx_export.layering_project`` (``z``), or a decoder checkpoint of
    ``onnx_export.train_decoder`` trained with ``data_dir`` among its sets (its auto-decoder latents:
    a projection that comes with the training), possibly re-fitted by ``layering_project --decoder``.

    ``shrink`` < 1 takes a re-fitted checkpoint's latents only that fraction of the way from the ones
    the joint training left (``z0 + shrink (z_refit - z0)``): the re-fit fits each stack's Monte Carlo
    data better, the joint training's latents vary more smoothly from stack to stack, and the layering
    network regresses best onto a mix (docs/layering_training.md)."""
    if Path(path).suffix == ".npz":
        if shrink != 1.0:
            raise ValueError("a shrink applies to a re-fitted decoder checkpoint, not to an .npz of latents")
        return torch.from_numpy(np.load(path)["z"][:n])
    ck = torch.load(path, weights_only=False)
    z = _checkpoint_latents(ck, path, data_dir, n)
    if shrink != 1.0:
        if "refit" not in ck:
            raise ValueError(f"{path} is not a re-fit (onnx_export.layering_project --decoder): nothing to shrink")
        start = ck["refit"]["config"]["from"]
        z0 = _checkpoint_latents(torch.load(start, weights_only=False), start, data_dir, n)
        z = z0 + shrink * (z - z0)
    return z


def _checkpoint_latents(ck: dict, path, data_dir: Path, n: int) -> torch.Tensor:
    """The latents of ``data_dir``'s first ``n`` stacks in the loaded decoder checkpoint ``ck`` (from ``path``)."""
    dirs = [Path(d).resolve() for d in ck["args"]["data"]]
    if Path(data_dir).resolve() not in dirs or "units_per_set" not in ck:
        raise ValueError(f"{path} was not trained on {data_dir}: its sets are {ck['args']['data']}")
    i = dirs.index(Path(data_dir).resolve())
    start = sum(ck["units_per_set"][:i])
    z = ck["latents"][start : start + ck["units_per_set"][i]].reshape(-1, 3, LATENT)
    if z.shape[0] < n:
        raise ValueError(f"{path} holds latents of {z.shape[0]} stacks of {data_dir}, {n} needed")
    return z[:n].float()


def regress_projected(
    net: LayeringNet, sets: dict, targets: dict, args, gen, log, procs: Processes = ONE_PROCESS
) -> None:
    """Stage 0 (``--projected``): MSE of L's output against the stacks' projected latents, over every
    coating count that has them (so the recursion is regressed too)."""
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    t0 = time.perf_counter()
    for step in range(args.regress_steps):
        for g in opt.param_groups:
            g["lr"] = cosine_lr(step, args.regress_steps, args.lr, warmup=20)
        loss = 0.0
        for c, data in sets.items():
            s = torch.randint(0, data.n, (512,), generator=gen)[procs.rows(512, "the regression's batch")]
            z = compose(net, data.z_base[s], data.z_tops[s], data.albedo[s], data.thickness[s])
            loss = loss + ((z - targets[c][s]) ** 2).mean() / len(sets)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        procs.average_gradients(net.parameters())
        opt.step()
        if (step + 1) % 500 == 0:
            log(f"regress {step + 1}/{args.regress_steps} mse {procs.mean(loss):.5f} {time.perf_counter() - t0:.0f} s")


def regress_decoded(
    net: LayeringNet,
    dec,
    sets: dict,
    targets: dict,
    args,
    gen,
    log,
    rec: dict,
    checkpoint=None,
    evaluate=None,
    opt_state=None,
    procs: Processes = ONE_PROCESS,
) -> None:
    """Stage 0b (``--decoded-steps``): the regression in function space. L's latent is decoded at the
    stack's direction pairs and compared as a lobe (``decoded_lobe_loss``, the held-out metric) with the
    lobe of the stack's target latent (``targets[c]``) or, where that is None, with its Monte Carlo values.
    Latents that decode to the same lobe cost nothing here, so a target table that fits the data well
    but wanders along such directions from stack to stack (a re-fit's, ``--decoded-shrink 1``) can be
    followed where the latent-space MSE cannot.

    ``rec`` is the stage's record in the history: ``rec["step"]`` steps are done (a resumed run starts
    there, with the optimiser state ``opt_state``); every ``args.every`` steps ``checkpoint(opt)`` saves,
    and every ``args.eval_every`` steps ``evaluate()`` (the held-out error, or None) goes to ``rec["evals"]``."""
    opt = torch.optim.Adam(net.parameters(), lr=args.decoded_lr)
    if opt_state is not None:
        opt.load_state_dict(opt_state)
    t0, ema = time.perf_counter(), None
    for step in range(rec.get("step", 0), args.decoded_steps):
        for g in opt.param_groups:
            g["lr"] = cosine_lr(step, args.decoded_steps, args.decoded_lr, warmup=20)
        loss = sum(
            data.decoded_batch(
                net,
                dec,
                targets[c],
                args.batch // len(sets),
                2,
                gen,
                args.decoded_loss,
                args.decoded_reciprocal,
                procs,
            )
            for c, data in sets.items()
        ) / len(sets)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        procs.average_gradients(net.parameters())
        nn.utils.clip_grad_norm_(net.parameters(), args.clip)
        opt.step()
        lv = procs.mean(loss)
        ema = lv if ema is None else 0.95 * ema + 0.05 * lv
        done = step + 1
        if done % args.log_every == 0:
            log(f"decoded {done}/{args.decoded_steps} lobe loss {ema:.5f} {time.perf_counter() - t0:.0f} s")
        if evaluate is not None and args.eval_every and done % args.eval_every == 0 and done < args.decoded_steps:
            if (m := evaluate()) is not None:
                rec.setdefault("evals", {})[str(done)] = m
        rec["step"] = done
        if checkpoint is not None and (done % args.every == 0 or done == args.decoded_steps):
            checkpoint(opt)


def projected_targets(args, models: ModelSet, sets: dict, shrink: float) -> tuple[dict, str | None]:
    """The ``--projected`` latents of the training stacks, per coating count, shrunk by ``shrink``, and
    the command of their re-fit (None: none); the two-coating stacks join ``sets`` when the re-fit holds
    them (so the recursion is regressed too)."""
    targets, refit = {1: projected_latents(args.projected, args.c1, sets[1].n, shrink)}, None
    if Path(args.projected).suffix != ".npz":
        ck = torch.load(args.projected, weights_only=False)
        refit = ck.get("refit", {}).get("command")
        if Path(args.c2).resolve() in [Path(d).resolve() for d in ck["args"]["data"]]:
            if 2 not in sets:
                sets[2] = stack_set(args, models, args.c2)
            targets[2] = projected_latents(args.projected, args.c2, sets[2].n, shrink)
    return targets, refit


def decoded_stage_data(args, models: ModelSet, sets: dict) -> tuple[dict, dict]:
    """The stacks of the function-space stage and their targets (None: the Monte Carlo values)."""
    if args.decoded_target == "latents":
        if args.decoded_data:
            raise ValueError("--decoded-data gives Monte Carlo values: it goes with --decoded-target data")
        if not args.projected:
            raise ValueError(
                "--decoded-target latents decodes the --projected latents: give --projected, or --decoded-target data"
            )
        return sets, projected_targets(args, models, sets, args.decoded_shrink)[0]
    coatings = args.decoded_coatings or (sorted(sets) if args.projected else [1, 2])
    for c in coatings:
        if c not in sets:
            sets[c] = stack_set(args, models, coating_data(args, c), args.stacks if c == 1 else 0)
    dsets = {c: sets[c] for c in coatings}
    if args.decoded_data:  # the same stacks and directions with other values (more walks)
        dsets = {
            c: stack_set(args, models, d, sets[c].n, use_weight=True)
            for c, d in zip((1, 2), args.decoded_data, strict=False)
            if c in dsets
        }
        for c in dsets:
            if not (torch.equal(dsets[c].wi, sets[c].wi) and torch.equal(dsets[c].albedo, sets[c].albedo)):
                raise ValueError(
                    f"{args.decoded_data[c - 1]} does not hold the stacks and directions of the "
                    f"{'--c1' if c == 1 else '--c2'} data"
                )
    return dsets, {c: None for c in dsets}


def train(args, log=print) -> dict:  # noqa: C901 (one stage after another; to be cut into stages)
    from onnx_export.heldout_layered import load as load_heldout

    if args.finetune:
        stage2_shares(args)  # a bad --c3-share fails now, not after stage 1
    check_heldout(args)
    ckpt = Path(args.out) / "ckpt.pt"
    resumed = torch.load(ckpt, weights_only=False) if ckpt.exists() else None
    if resumed is not None:  # a resumed run continues the same one
        check_resume(resumed["args"], vars(args), RESUME_FREE, ckpt)
    procs = processes()
    log = quiet_unless_main(log, procs)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    models = ModelSet(args.size, threads=args.threads, model_dir=args.model_dir)
    if args.decoder_ckpt is not None:  # a train_decoder checkpoint not (yet) exported
        from onnx_export.evaluate import load_decoder

        dec = load_decoder(args.decoder_ckpt)[0]
        for prm in dec.parameters():
            prm.requires_grad_(False)
    else:
        dec = frozen_decoder(args.size, Path(args.model_dir or MODEL_DIR))
    trained_with = {p.name: file_digest(p) for p in (models.encoder_path, models.decoder_path)}
    sets = {1: stack_set(args, models, args.c1, args.stacks)}  # two-coating data are loaded when stage 2 starts

    def heldout():  # measured by process 0 only
        return load_heldout(args.heldout) if procs.main and args.heldout is not None else None

    net = LayeringNet(args.width, args.depth)
    init_rec = None
    if args.init_from:  # warm start: a shipped size's layering network (same architecture)
        src = Path(args.model_dir or MODEL_DIR) / f"layering_{args.init_from}.onnx"
        net = net_from_onnx(src, json.loads(src.with_suffix(".json").read_text()))
        if (net.width, net.depth) != (args.width, args.depth):  # the command must say what was trained
            raise ValueError(f"{src.name} is {net.width} x {net.depth}: give --width {net.width} --depth {net.depth}")
        net.train()
        prev = json.loads(src.with_suffix(".json").read_text()).get("training", {})  # how the start was made
        init_rec = {
            "model": src.name,
            "sha256": file_digest(src),
            "command": prev.get("command"),
            "decoded": prev.get("decoded"),
            "init_from": prev.get("init_from"),
        }
        log(f"starting from {src.name}")
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    step, hist = 0, ({"init_from": init_rec} if init_rec else {})
    if resumed is not None:
        net.load_state_dict(resumed["net"])
        opt.load_state_dict(resumed["opt"])
        step, hist = resumed["step"], resumed.get("history", {})
        if "gen" in resumed:  # the batches continue where they stopped (checkpoints before it: drawn afresh)
            gen.set_state(resumed["gen"])
        log(f"resumed from {ckpt} at step {step}")
    total = args.steps + args.finetune

    def save(step, ema, best: bool = False, **extra):
        """``OUT/ckpt.pt`` (``best``: ``OUT/best.pt``), written whole or not at all."""
        if not procs.main:
            return
        path = out / "best.pt" if best else ckpt
        hist["data"] = [sets[c].command for c in sorted(sets)]  # the data this training has loaded
        torch.save(
            {
                "net": net.state_dict(),
                "config": net.config(),
                "opt": opt.state_dict(),
                "gen": gen.get_state(),
                "step": step,
                "trained_with": trained_with,
                "history": hist,
                "loss": ema,
                "args": {k: str(v) for k, v in vars(args).items()},
                "world_size": procs.world,
                **extra,
            },
            path.with_suffix(".tmp"),
        )
        path.with_suffix(".tmp").replace(path)

    fresh_opt = False  # a stage below ran in this call: the stages after it start with a fresh optimiser
    # stage 0 is done once the checkpoint records it ("projected"; older ones: "regressed", which only a run
    # with held-out evaluations wrote)
    if args.projected and step == 0 and not {"projected", "regressed"} & hist.keys():
        targets, refit = projected_targets(args, models, sets, args.shrink)
        regress_projected(net, sets, targets, args, gen, log, procs)
        hist["projected"] = {"latents": str(args.projected), "refit": refit, "shrink": args.shrink}
        if heldout() is not None:
            hist["regressed"] = heldout_error(
                net, dec, models, heldout(), log, remainder=args.remainder, transmission=args.top_transmission
            )
        fresh_opt = True
        save(0, None)  # --steps 0 --finetune 0 (and no --decoded-steps): the regressed network is the result
    rec = hist.get("decoded")
    if args.decoded_steps and step == 0 and (rec is None or rec.get("step", rec["steps"]) < args.decoded_steps):
        dsets, targets = decoded_stage_data(args, models, sets)
        opt_state = None
        if rec is None:
            rec = hist["decoded"] = {
                "steps": args.decoded_steps,
                "target": args.decoded_target,
                "lr": args.decoded_lr,
                "step": 0,
            }
            if args.decoded_loss != "squared":
                rec["loss"] = args.decoded_loss
            if args.decoded_reciprocal:
                rec["reciprocal"] = True
            if args.decoded_target == "latents":
                rec["shrink"] = args.decoded_shrink
            else:
                rec["data"] = [dsets[c].command for c in dsets]
        else:  # the same stage resumed (check_resume: with the same --decoded-steps, its schedule's length)
            opt_state = resumed["decoded_opt"]
            gen.set_state(resumed["decoded_gen"])
            log(f"function-space stage resumed at step {rec['step']}")
        regress_decoded(
            net,
            dec,
            dsets,
            targets,
            args,
            gen,
            log,
            rec,
            checkpoint=lambda o: save(0, None, decoded_opt=o.state_dict(), decoded_gen=gen.get_state()),
            evaluate=lambda: (
                heldout_error(net, dec, models, ho, log, remainder=args.remainder, transmission=args.top_transmission)
                if (ho := heldout()) is not None
                else None
            ),
            opt_state=opt_state,
            procs=procs,
        )
        if heldout() is not None:
            rec["heldout"] = heldout_error(
                net, dec, models, heldout(), log, remainder=args.remainder, transmission=args.top_transmission
            )
        fresh_opt = True
        save(0, None)
    if fresh_opt:
        opt = torch.optim.Adam(net.parameters(), lr=args.lr)  # the stages below start afresh
    log(f"layering net {net.config()} params {n_params(net)}; one-coating stacks {sets[1].n}; loss {args.loss}")
    t0 = time.perf_counter()
    ema = resumed.get("loss") if resumed is not None and step > 0 else None
    while step < total:
        stage2 = step >= args.steps
        if stage2:
            lr = cosine_lr(step - args.steps, args.finetune, args.lr * args.finetune_lr_scale, warmup=20)
        else:
            lr = cosine_lr(step, args.steps, args.lr)
        for g in opt.param_groups:
            g["lr"] = lr
        if stage2:  # equal shares of the batch: the recursion (2 to 4 coatings), and one coating (keep stage 1)
            deeper = recursion_counts(args)
            for c in deeper:
                if c not in sets:
                    sets[c] = stack_set(args, models, coating_data(args, c))
                    log(f"stage 2: {sets[c].n} stacks with {c} coatings")
            loss = sum(
                w
                * layering_loss(
                    *sets[c].batch(net, dec, b, args.pairs, gen, procs), args.loss, procs, args.grazing_floor
                )
                for c, (b, w) in stage2_shares(args).items()
            )
        else:
            part = sets[1].batch(net, dec, args.batch, args.pairs, gen, procs)
            loss = layering_loss(*part, args.loss, procs, args.grazing_floor)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        procs.average_gradients(net.parameters())
        nn.utils.clip_grad_norm_(net.parameters(), args.clip)
        opt.step()
        step += 1
        lv = procs.mean(loss)
        ema = lv if ema is None else 0.98 * ema + 0.02 * lv
        if step % args.log_every == 0:
            log(f"step {step}/{total} loss {ema:.5f} lr {lr:.2e} {time.perf_counter() - t0:.0f} s")
        end_of_stage = step == args.steps or step == total
        if (end_of_stage or (args.eval_every and step % args.eval_every == 0)) and (ho := heldout()) is not None:
            m = heldout_error(net, dec, models, ho, log, remainder=args.remainder, transmission=args.top_transmission)
            hist[f"step_{step}"] = m
            if end_of_stage:
                hist["stage2" if stage2 else "stage1"] = m
            if args.keep_best and selection_score(m) < hist.get("best", {}).get("score", np.inf):
                hist["best"] = {"step": step, "score": selection_score(m)}
                save(step, ema, best=True)  # OUT/best.pt, the network of the best evaluation so far
        if step % args.every == 0 or end_of_stage:
            save(step, ema)
    return {"loss": ema, "step": step, "history": hist}


# ----------------------------------------------------------------------------- export


def export_onnx(net: LayeringNet, path: Path) -> None:
    net.eval()
    b = 8
    args = (torch.zeros(b, LATENT), torch.zeros(b, LATENT), torch.zeros(b), torch.zeros(b))
    torch.onnx.export(
        net,
        args,
        str(path),
        input_names=["z_top", "z_bottom", "albedo", "thickness"],
        output_names=["z"],
        dynamic_axes={k: {0: "batch"} for k in ("z_top", "z_bottom", "albedo", "thickness", "z")},
        opset_version=OPSET,
        dynamo=False,
    )


def parity(net: LayeringNet, path: Path, n: int = 4096, seed: int = 0) -> float:
    """Max relative difference (floor 1e-3) of ONNX Runtime against torch on random inputs."""
    import onnxruntime as ort

    from onnx_export.export import max_relative_difference

    rng = np.random.default_rng(seed)
    feeds = {
        "z_top": (rng.standard_normal((n, LATENT)) * 0.5).astype(np.float32),
        "z_bottom": (rng.standard_normal((n, LATENT)) * 0.5).astype(np.float32),
        "albedo": rng.random(n).astype(np.float32),
        "thickness": (rng.random(n) * THICKNESS_MAX).astype(np.float32),
    }
    with torch.no_grad():
        ref = net(*(torch.from_numpy(feeds[k]) for k in ("z_top", "z_bottom", "albedo", "thickness"))).numpy()
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(["z"], feeds)[0]
    return max_relative_difference(got, ref, floor=1e-3)


def net_from_onnx(path: Path, card: dict) -> LayeringNet:
    """The torch module of an exported layering model, rebuilt from the ONNX weights and the card."""
    import onnx
    from onnx import numpy_helper

    net = LayeringNet(card["architecture"]["width"], card["architecture"]["depth"])
    w = {t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in onnx.load(str(path)).graph.initializer}
    net.load_state_dict(w)
    return net.eval()


def training_data(s: dict) -> list[str]:
    """The commands of the data checkpoint ``s`` was trained on, as the training recorded them when it
    loaded them (the directories may have grown since); older checkpoints: the function-space stage's
    record, else the directories as they are now."""
    hist, a = s.get("history", {}), s["args"]
    if "data" in hist:
        return hist["data"]
    decoded = hist.get("decoded") or {}
    if decoded.get("target") == "data" and a.get("decoded_data") in (None, "None"):
        return decoded["data"]
    return [
        data_command(Path(d), c, n)
        for c, d, n in (
            (1, a.get("c1", "cache/data/layering_c1"), 4096),
            (2, a.get("c2", "cache/data/layering_c2"), 1536),
        )
    ]


def training_loss(s: dict) -> str:
    """The card's words for what checkpoint ``s`` was trained against, stage by stage."""
    hist, a = s.get("history", {}), s["args"]
    decoded = hist.get("decoded") or {}
    parts = [f"started from {hist['init_from']['model']} (init_from)"] if "init_from" in hist else []
    if "projected" in hist or "regressed" in hist:
        parts.append("MSE against the latents of --projected")
    if decoded:
        parts.append(
            ("the relative RMSE" if decoded.get("loss") == "rmse" else "the relative squared error")
            + " of the cosine-weighted lobes decoded from L's latents"
            + (" in both orders of the decoder's directions" if decoded.get("reciprocal") else "")
            + " (onnx_export.layering.decoded_lobe_loss) against "
            + (
                "the Monte Carlo values of the data in decoded.data"
                if decoded.get("target") == "data"
                else "the lobes decoded from the target latents (no step against the Monte Carlo values)"
            )
        )
    if s["step"]:
        floor = float(a.get("grazing_floor", 1.0))
        weighted = f", grazing pairs weighted (--grazing-floor {floor:g})" if floor < 1.0 else ""
        level = float(a.get("level_floor", 0.0))
        weighted += f", dim stacks weighted as bright (--level-floor {level:g})" if level > 0.0 else ""
        parts.append(f"{a.get('loss')} through the decoder against the Monte Carlo values{weighted}")
    elif not decoded:
        parts.append("(stage 0 only: no step through the decoder)")
    return ", then ".join(parts)


def export(args, log=print) -> dict:
    s = torch.load(args.ckpt, weights_only=False)
    targs = s.get("args", {})
    if targs.get("decoder_ckpt") not in (None, "None"):
        raise SystemExit(
            f"{args.ckpt} was trained through a decoder checkpoint (--decoder-ckpt): its latents belong to a "
            "decoder that is not shipped, so it cannot ship either"
        )
    from addon.core.neural.models import read_card

    on_remainder = targs.get("remainder") in (True, "True")
    dcard = read_card("decoder", args.size, Path(args.out))
    decoder_remainder = dcard.get("remainder", False) is True
    on_transmission = targs.get("top_transmission") in (True, "True")
    if on_transmission != (dcard.get("top_transmission", False) is True):
        raise SystemExit(
            f"{args.ckpt} was trained {'with' if on_transmission else 'without'} the top coat's transmission "
            f"(--top-transmission) but decoder_{args.size} {'is not' if on_transmission else 'is'} scaled by it "
            "(its card's 'top_transmission'): retrain it to match"
        )
    if on_remainder != decoder_remainder:
        raise SystemExit(
            f"{args.ckpt} was trained on {'remainders' if on_remainder else 'whole BRDFs'} but decoder_{args.size} "
            f"holds {'remainders' if decoder_remainder else 'whole BRDFs'} (its card's 'remainder'): retrain it "
            f"{'without' if on_remainder else 'with'} --remainder"
        )
    net = LayeringNet(**s["config"])
    net.load_state_dict(s["net"])
    path = Path(args.out) / f"layering_{args.size}.onnx"
    export_onnx(net, path)
    par = parity(net, path)
    a = s["args"]
    decoded = s.get("history", {}).get("decoded") or {}
    card = {
        "name": f"layering_{args.size}",
        "role": (
            f"layering network in the latent space of decoder_{args.size}/encoder_{args.size}: "
            "z = L(z_top_interface, z_bottom, albedo_c, thickness) per colour channel, applied bottom-up"
        ),
        "files": {path.name: file_digest(path)},
        "inputs": {
            "z_top": "(B, 32) float32 encoder latent of the coating's interface Dielectric(roughness, ior)",
            "z_bottom": "(B, 32) float32 latent of the base or of the lower sub-stack",
            "albedo": "(B,) float32 single-scattering albedo of the slab in this channel, [0, 1]",
            "thickness": f"(B,) float32 optical thickness, [0, {THICKNESS_MAX}]",
        },
        "outputs": {"z": "(B, 32) float32"},
        "architecture": {
            **net.config(),
            "hidden": f"{net.depth} x Linear({net.width}) + ReLU",
            "inputs": "z_top, z_bottom, albedo, 1 - exp(-thickness), albedo (1 - exp(-thickness)), thickness / 5",
        },
        "parameters": n_params(net),
        "macs_per_rgb_eval": 3 * macs_per_eval(net),
        "training": {
            "data": training_data(s),
            "command": command_line("onnx_export.layering train", a, skip=("every", "log_every", "cmd", "model_dir")),
            "steps": s["step"],
            "final_loss": s.get("loss"),
            "seeds": {"data": 11, "training": int(a.get("seed", 0))},
            "loss": training_loss(s),
            "init_from": s.get("history", {}).get(
                "init_from"
            ),  # a warm start: the model it started from, and how that was made
            "projected_latents": s.get("history", {}).get("projected"),  # the command of a re-fit of them, if any
            "decoded": {k: v for k, v in decoded.items() if k != "heldout"} or None,
        },
        "heldout": {
            **{k: v for k, v in s.get("history", {}).items() if k in ("regressed", "stage1", "stage2")},
            **({"decoded": decoded["heldout"]} if "heldout" in decoded else {}),
            "set": None
            if a.get("heldout") in (None, "None")
            else str(a.get("heldout", "tests/data/heldout_layered.npz")),
            "when": "measured at training time against the reference file of that time; "
            "heldout_runtime: the latest benchmark run",
            "metric": "relative RMSE of lobe images at 0/30/60/75 deg; albedo error = |albedo from lobe|",
        },
        "onnx_runtime_vs_torch_max_relative_difference": par,
        "opset": OPSET,
        # checkpoints from before the digests were recorded: the current files (check their dates)
        "trained_with": s.get("trained_with")
        or {f"{k}_{args.size}.onnx": file_digest(MODEL_DIR / f"{k}_{args.size}.onnx") for k in ("encoder", "decoder")},
    }
    if args.speed:
        card["speed"] = json.loads(Path(args.speed).read_text())
    path.with_suffix(".json").write_text(json.dumps(card, indent=1) + "\n")
    log(json.dumps({"model": str(path), "parity": par}))
    return card


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--size", default="tiny")
    t.add_argument("--c1", type=Path, default=Path("cache/data/layering_c1"))
    t.add_argument("--c2", type=Path, default=Path("cache/data/layering_c2"))
    t.add_argument(
        "--c3",
        type=Path,
        default=None,
        help="stacks with three coatings (onnx_export.layered_data --coatings 3): stage 2 trains the recursion "
        "three deep as well",
    )
    t.add_argument(
        "--c3-share",
        type=float,
        default=None,
        help="with --c3: this fraction of each stage-2 batch (and of its loss) has three coatings, the rest is "
        "split equally between the other counts (default: equal shares)",
    )
    t.add_argument(
        "--c4",
        type=Path,
        default=None,
        help="stacks with four coatings (onnx_export.layered_data --coatings 4): stage 2 trains the recursion "
        "four deep as well",
    )
    t.add_argument("--stacks", type=int, default=0, help="use only the first N one-coating stacks (0: all)")
    t.add_argument(
        "--heldout",
        type=heldout_path,
        default=Path("tests/data/heldout_layered.npz"),
        help="the held-out (or validation) set measured along the way (onnx_export.heldout_layered); none: no "
        "evaluation",
    )
    t.add_argument(
        "--init-from",
        default=None,
        help="start from this size's layering network (read beside the encoder and decoder, --model-dir; "
        "e.g. a decoder whose latents began in that size's latent space, or more training of the "
        "shipped one); --width and --depth must be its own",
    )
    t.add_argument("--width", type=int, default=128)
    t.add_argument("--depth", type=int, default=3)
    t.add_argument("--steps", type=int, default=4000)
    t.add_argument("--finetune", type=int, default=1500)
    t.add_argument("--finetune-lr-scale", type=float, default=0.3)
    t.add_argument("--batch", type=positive_int, default=64, help="stacks per step")
    t.add_argument("--pairs", type=positive_int, default=128, help="direction pairs per stack per step")
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--clip", type=float, default=1.0)
    t.add_argument(
        "--grazing-floor",
        type=float,
        default=1.0,
        help="< 1: each pair's loss term divided by max(min(cos_i, cos_o), FLOOR), so that grazing pairs count "
        "like the lobe-image values they are (nets.pair_loss); 1: unweighted",
    )
    t.add_argument(
        "--level-floor",
        type=float,
        default=0.0,
        help="> 0: each stack dimmer than the median weighted as if it were as bright, down to FLOOR x the median "
        "level (nets.level_weights; its level the RMS of its values f cos_i cos_o), so that near-black stacks count "
        "by their relative error as the held-out lobe error does; 0: off",
    )
    t.add_argument("--loss", default="l2rel", choices=("l2rel", "l1log"))
    t.add_argument(
        "--weighting",
        default="cosine",
        choices=("cosine", "none"),
        help="per-pair weights to the cosine measure of the lobe images (see cosine_weights)",
    )
    t.add_argument(
        "--projected",
        type=Path,
        default=None,
        help="latents of the training stacks to regress on first: an .npz of onnx_export.layering_project "
        "(one coating) or a decoder checkpoint trained on the layering data (one and two coatings)",
    )
    t.add_argument(
        "--shrink",
        type=float,
        default=1.0,
        help="with a re-fitted --projected checkpoint: regress onto z0 + SHRINK (z_refit - z0), z0 the "
        "latents it was re-fitted from (1: the re-fitted latents)",
    )
    t.add_argument(
        "--model-dir",
        type=Path,
        default=None,
        help="where the frozen encoder and decoder of --size are read (default: the shipped models)",
    )
    t.add_argument(
        "--decoder-ckpt",
        type=Path,
        default=None,
        help="decode through this train_decoder checkpoint instead of --size's exported decoder (the "
        "encoder stays --size's); for comparing decoders before one is exported",
    )
    t.add_argument(
        "--remainder",
        action="store_true",
        help="the decoder holds the remainder (train_decoder --remainder): the targets are the stacks' BRDFs "
        "minus the exact top-interface reflection, and the held-out lobes are scored with it added back",
    )
    t.add_argument(
        "--top-transmission",
        action="store_true",
        help="with --remainder: the decoder's values are times the top coat's transmission in and out "
        "(train_decoder --top-transmission)",
    )
    t.add_argument("--regress-steps", type=int, default=3000)
    t.add_argument(
        "--decoded-steps",
        type=int,
        default=0,
        help="steps of the regression in function space (after the regression onto --projected, or "
        "from --init-from): lobes decoded from L's latents against those of --decoded-target; "
        "resumable, with the held-out error every --eval-every steps",
    )
    t.add_argument(
        "--decoded-shrink",
        type=float,
        default=1.0,
        help="the target latents of --decoded-steps, as --shrink (1: the re-fit's own)",
    )
    t.add_argument(
        "--decoded-target",
        default="latents",
        choices=("latents", "data"),
        help="what --decoded-steps compare with: the lobes decoded from the target latents, or the "
        "stacks' Monte Carlo values themselves",
    )
    t.add_argument(
        "--decoded-data",
        type=Path,
        nargs="+",
        default=None,
        metavar="DIR",
        help="with --decoded-target data: the values of the one- (and two-) coating stacks of --c1 "
        "(--c2) from a run of onnx_export.layered_data with more --walks (same stacks, directions)",
    )
    t.add_argument("--decoded-lr", type=float, default=2e-4)
    t.add_argument(
        "--decoded-loss",
        default="squared",
        choices=("squared", "rmse"),
        help="per outgoing direction, the squared relative lobe error or its root (decoded_lobe_loss)",
    )
    t.add_argument(
        "--decoded-reciprocal",
        action="store_true",
        help="decode half the groups with the directions swapped (the fixed one as the decoder's incident "
        "direction), so that the latents are fitted in both orders (StackSet.decoded_batch)",
    )
    t.add_argument(
        "--decoded-coatings",
        type=int,
        nargs="+",
        default=None,
        choices=(1, 2),
        help="coating counts of the function-space stage (default: those regressed with --projected, else 1 and 2)",
    )
    t.add_argument("--threads", type=positive_int, default=1)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--every", type=positive_int, default=250)
    t.add_argument("--eval-every", type=int, default=1000, help="held-out error every N steps (0: stage ends only)")
    t.add_argument(
        "--keep-best",
        action="store_true",
        help="also keep OUT/best.pt, the network of the evaluation with the lowest selection_score (use a "
        "validation set as --heldout, never the held-out set the figures are reported on)",
    )
    t.add_argument("--log-every", type=positive_int, default=50)
    t.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("export")
    e.add_argument("--size", default="tiny")
    e.add_argument("--ckpt", type=Path, required=True)
    e.add_argument("--speed", type=Path, default=None, help="JSON of measured speed to put on the card")
    e.add_argument("--out", type=Path, default=MODEL_DIR)
    b = sub.add_parser(
        "bound",
        help="the held-out lobes projected into the decoder's latent space (an optimistic "
        "bound on any layering network), beside the shipped layering network's error",
    )
    b.add_argument("--size", default="paper")
    b.add_argument("--heldout", type=Path, default=Path("tests/data/heldout_layered.npz"))
    b.add_argument("--coatings", type=int, nargs="+", default=None, help="only these numbers of coatings")
    b.add_argument("--steps", type=int, default=400)
    b.add_argument("--pixels", type=int, default=96, help="random pixels of each lobe image per step")
    b.add_argument("--threads", type=int, default=1)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument(
        "--decoder-ckpt",
        type=Path,
        default=None,
        help="a train_decoder checkpoint to project into instead of the shipped decoder of --size",
    )
    b.add_argument(
        "--remainder",
        action="store_true",
        help="the decoder holds the remainder (train_decoder --remainder): project the held-out lobes minus "
        "the exact top-interface reflection, score that reflection plus the decoded lobe",
    )
    b.add_argument(
        "--top-transmission",
        action="store_true",
        help="with --remainder: the decoder's values are times the top coat's transmission in and out "
        "(train_decoder --top-transmission)",
    )
    return ap


def main(argv=None):
    a = parser().parse_args(argv)
    lg = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    if a.cmd == "train":
        res = train(a, log=lg)
        if processes().main:
            (Path(a.out) / "train.json").write_text(json.dumps(res, default=str, indent=1))
    elif a.cmd == "bound":
        from onnx_export.heldout_layered import load as load_heldout

        torch.set_num_threads(a.threads)
        ho = load_heldout(a.heldout)
        if a.coatings:
            keep = [i for i, st in enumerate(ho["stacks"]) if len(st.coatings) in a.coatings]
            if not keep:
                raise SystemExit(f"{a.heldout} holds no stack with {a.coatings} coatings")
            ho = ho | {"stacks": [ho["stacks"][i] for i in keep], "lobe": ho["lobe"][keep]}
        src = MODEL_DIR / f"layering_{a.size}.onnx"
        net = net_from_onnx(src, json.loads(src.with_suffix(".json").read_text()))
        if a.decoder_ckpt is not None:
            from onnx_export.evaluate import load_decoder

            dec = load_decoder(a.decoder_ckpt)[0]
            for prm in dec.parameters():
                prm.requires_grad_(False)
        else:
            dec = frozen_decoder(a.size)
        models = ModelSet(a.size, threads=a.threads)
        shipped = a.decoder_ckpt is None  # the shipped decoder: its card says which design it holds
        res = lobe_bound(
            net,
            dec,
            models,
            ho,
            a.steps,
            a.pixels,
            seed=a.seed,
            log=lg,
            remainder=a.remainder or (shipped and models.remainder),
            transmission=a.top_transmission or (shipped and models.top_transmission),
        )
        print(json.dumps(res))
    else:
        export(a, log=lg)


if __name__ == "__main__":
    main()

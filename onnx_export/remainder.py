"""Exact top coat + neural remainder, measured against the whole-BRDF latent design.

The first reflection at a stack's top interface is an analytic rough-dielectric lobe (GGX,
Fresnel): the interface between air and the top coating's medium, ``RoughDielectric(alpha, ior,
reflection_only=True)`` with the top coating's roughness and index (the walk's top event,
``addon.core.reference.walk``). In the *remainder* design the decoder represents only the rest of
the stack's BRDF (the light that entered the coat), and the two are summed.

This module holds the lobe (``top_reflection``) and the lobe images of it that the comparison
scores against the whole reference (``top_lobes``); ``train_decoder --remainder`` trains a decoder
on remainders (reference minus the top lobe) and ``layering bound --remainder`` projects held-out
remainders into such a decoder's latent space and scores top lobe + decoded remainder against the
whole reference (docs/layering_training.md, "Exact top coat + neural remainder").
"""

from __future__ import annotations

import numpy as np

from addon.core import lobe
from addon.core.neural.top_lobe import eval_top, remainder_scale, top_coats
from addon.core.stack import StackArrays


def top_reflection(arrays: StackArrays, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """f (S, P, 3) of the top interface's reflection for stacks ``arrays`` (S rows) at the pairs
    ``wi``, ``wo`` (S, P, 3) (unit, local frame): the runtime's lobe (``addon.core.neural.top_lobe``).
    Stacks without coatings give 0 (the base is the whole BRDF); a smooth top interface gives 0 (its
    mirror is a delta lobe, not part of f)."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    s, p = wi.shape[:2]
    if wi.shape != (s, p, 3) or wo.shape != (s, p, 3) or len(arrays) != s:
        raise ValueError(f"wi, wo must be (S, P, 3) for {len(arrays)} stacks, got {wi.shape} and {wo.shape}")
    top = np.repeat(top_coats(arrays), p, axis=0)
    f = eval_top(top, wi.reshape(-1, 3), wo.reshape(-1, 3))
    return np.repeat(f.reshape(s, p, 1), 3, axis=2)


def remainder_scales(arrays: StackArrays, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """(S, P, 1) the top coat's transmission in and out (``top_lobe.remainder_scale``) at the pairs ``wi``,
    ``wo`` (S, P, 3): what a ``--top-transmission`` decoder's output is multiplied by; 1 without coatings."""
    wi = np.asarray(wi, dtype=np.float64)
    s, p = wi.shape[:2]
    top = np.repeat(top_coats(arrays), p, axis=0)
    return remainder_scale(top, wi.reshape(-1, 3), np.asarray(wo, dtype=np.float64).reshape(-1, 3)).reshape(s, p, 1)


def _on_lobe_grid(arrays: StackArrays, res: int, angles, values, fill: float, channels: int) -> np.ndarray:
    """(S, A, res, res, channels) ``values(wi, wo)`` (S, P, channels) on the lobe grid of each incident
    angle (``addon.core.lobe``), ``fill`` off the disk."""
    wo_grid, mask = lobe.lobe_grid(res)
    wo_m = wo_grid[mask]
    s, npx = len(arrays), wo_m.shape[0]
    out = np.full((s, len(angles), res * res, channels), fill)
    for a, t in enumerate(angles):  # a loop over the few incident angles
        wi = np.broadcast_to(lobe.incident_direction(t), (s, npx, 3))
        out[:, a][:, mask] = values(wi, np.broadcast_to(wo_m, (s, npx, 3)))
    return out.reshape(s, len(angles), res, res, channels)


def scale_lobes(arrays: StackArrays, res: int, angles) -> np.ndarray:
    """(S, A, res, res, 1) :func:`remainder_scales` on the lobe grid of each incident angle (1 off the disk)."""
    return _on_lobe_grid(arrays, res, angles, lambda wi, wo: remainder_scales(arrays, wi, wo), 1.0, 1)


def top_lobes(arrays: StackArrays, res: int, angles) -> np.ndarray:
    """(S, A, res, res, 3) lobe images (f cos(theta_o), as ``addon.core.lobe``) of the top
    interface's reflection, for the held-out set's incident angles."""

    def image(wi, wo):
        return top_reflection(arrays, wi, wo) * wo[..., 2:3]

    return _on_lobe_grid(arrays, res, angles, image, 0.0, 3)


def torch_path_brdfs(
    layering_ckpt, decoder_ckpt, stacks, size: str = "tiny", remainder: bool = False, transmission: bool = False
) -> list:
    """One ``f(wi, wo) -> (N, 3)`` per stack through a layering network and a decoder still in their
    training checkpoints (torch), the encoder of ``size`` giving the layering network's inputs as in
    ``layering train``; ``remainder``: plus the exact top-interface reflection (``transmission``: the
    decoded part times the top coat's transmission)."""
    import torch

    from addon.core.neural import load_models
    from onnx_export.evaluate import load_decoder
    from onnx_export.layering import LayeringNet, compose, encoder_latents

    ck = torch.load(layering_ckpt, weights_only=False)
    net = LayeringNet(**ck["config"])
    net.load_state_dict(ck["net"])
    net.eval()
    dec = load_decoder(decoder_ckpt)[0]
    models = load_models(size, threads=1)
    z = torch.zeros(len(stacks), 3, 32)
    for c in sorted({len(s.coatings) for s in stacks}):
        idx = [i for i, s in enumerate(stacks) if len(s.coatings) == c]
        a = StackArrays.from_stacks([stacks[i] for i in idx])
        zb, zt = encoder_latents(models, a)
        with torch.no_grad():
            z[idx] = compose(
                net,
                torch.from_numpy(zb),
                torch.from_numpy(zt),
                torch.from_numpy(a.coat_albedo.astype(np.float32)),
                torch.from_numpy(a.coat_thickness.astype(np.float32)),
            )

    def brdf(k: int):
        arrays = StackArrays.from_stacks([stacks[k]])

        def f(wi, wo):
            n = len(wi)
            with torch.no_grad():
                t = lambda v: torch.as_tensor(np.repeat(np.asarray(v, np.float32), 3, 0))  # noqa: E731
                out = dec(z[k].repeat(n, 1), t(wi), t(wo)).reshape(n, 3).double().numpy()
            if transmission:
                out = out * remainder_scales(arrays, wi[None], wo[None])[0]
            return out + top_reflection(arrays, wi[None], wo[None])[0] if remainder else out

        return f

    return [brdf(k) for k in range(len(stacks))]


def grazing_summary(ratios: dict) -> dict:
    """The issue's grazing figures of ``heldout_grazing.ratios_to_reference``: the largest albedo and
    f cos ratios at 80-89.5 degrees, and the median albedo ratio at 75 and 85 degrees per coating count."""
    from onnx_export.heldout_grazing import medians_by_coatings

    near = ratios["angles"] >= 80
    out = {"albedo_max": float(ratios["albedo"][:, near].max()), "fcos_max": float(ratios["fcos"][:, near].max())}
    for (t, c), m in medians_by_coatings(ratios).items():
        out[f"albedo_median_{t:g}deg_{c}coat"] = m
    return out


def main(argv=None) -> None:
    import argparse
    import json
    from pathlib import Path

    from onnx_export import heldout_grazing as hg

    ap = argparse.ArgumentParser(
        description="grazing ratios (docs/layering_training.md) of a layering network and decoder checkpoint"
    )
    ap.add_argument("--layering-ckpt", type=Path, required=True)
    ap.add_argument("--decoder-ckpt", type=Path, required=True)
    ap.add_argument("--size", default="tiny", help="the encoder that feeds the layering network")
    ap.add_argument("--remainder", action="store_true", help="the decoder holds the remainder: add the top lobe")
    ap.add_argument(
        "--top-transmission", action="store_true", help="the decoded remainder is times the top coat's transmission"
    )
    ap.add_argument("--grazing", type=Path, default=Path("tests/data/heldout_grazing.npz"))
    a = ap.parse_args(argv)
    data = hg.load(a.grazing)
    brdfs = torch_path_brdfs(a.layering_ckpt, a.decoder_ckpt, data["stacks"], a.size, a.remainder, a.top_transmission)
    alb, fcos = hg.brdf_grazing(brdfs, data["angles"], int(data["res"]))
    print(json.dumps(grazing_summary(hg.ratios_to_reference(data, alb, fcos))))


if __name__ == "__main__":
    main()

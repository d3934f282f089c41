"""The numpy decoder of ``addon.core.neural.refine`` against torch: its forward pass against the torch
module rebuilt from the same ONNX weights, and its backward pass (and that of the refinement loss)
against torch autograd."""

import numpy as np
import pytest
import torch

from addon.core.neural import MODEL_DIR, SIZES, read_card
from addon.core.neural import refine as rf
from onnx_export.export import torch_from_onnx

SHIPPED = [s for s in SIZES if (MODEL_DIR / f"decoder_{s}.onnx").exists()]


def _directions(rng, n, grazing=False):
    u = rng.random((n, 2))
    z = u[:, 0] * (0.05 if grazing else 1.0) + 1e-4
    r = np.sqrt(1 - z * z)
    p = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(p), r * np.sin(p), z], 1).astype(np.float32)


def _torch_decoder(size):
    return torch_from_onnx(MODEL_DIR / f"decoder_{size}.onnx", read_card("decoder", size)).double()


@pytest.mark.parametrize("size", SHIPPED)
def test_numpy_gradient_equals_torch_autograd(size):
    rng = np.random.default_rng(7)
    n = 128 if size == "paper" else 512
    wi = np.concatenate([_directions(rng, n // 2), _directions(rng, n // 2, grazing=True)])
    wo = _directions(rng, n)
    z = (rng.standard_normal((3, 32)) * 0.3).astype(np.float64)
    g_f = rng.standard_normal((n, 3))
    dec = _torch_decoder(size)
    zt = torch.tensor(z, requires_grad=True)
    f_t = dec(
        zt.repeat(n, 1), torch.from_numpy(np.repeat(wi, 3, 0)).double(), torch.from_numpy(np.repeat(wo, 3, 0)).double()
    ).reshape(n, 3)
    (f_t * torch.from_numpy(g_f)).sum().backward()
    npd = rf.NumpyDecoder.load(size, dtype=np.float64)
    p = npd.run(z, wi, wo)
    assert np.allclose(p.f, f_t.detach().numpy(), rtol=1e-6, atol=1e-12)
    grad = npd.backward(p, g_f)
    ref = zt.grad.numpy()
    assert np.max(np.abs(grad - ref)) <= 1e-6 * max(1.0, np.max(np.abs(ref)))


def test_refinement_loss_gradient_equals_torch_autograd():
    rng = np.random.default_rng(2)
    groups, per = 6, 16
    wi, wo, w = rf.refinement_pairs(_coated(), groups, per, seed=3)
    rows_wi = np.repeat(wi, per, axis=0).astype(np.float32)  # the directions the decoders see
    wo = wo.reshape(-1, 3).astype(np.float32)
    target = rng.random((groups * per, 3)) * 2.0
    level = target * (1.0 + 0.2 * rng.standard_normal(target.shape))
    pairs = rf.PairSet(rows_wi, wo, target, np.zeros_like(target), w.reshape(-1), groups, level)
    dec = _torch_decoder("tiny")
    z = rng.standard_normal((3, 32)) * 0.3
    zt = torch.tensor(z, requires_grad=True)
    m = rows_wi.shape[0]
    f_t = dec(
        zt.repeat(m, 1),
        torch.from_numpy(np.repeat(rows_wi, 3, 0)).double(),
        torch.from_numpy(np.repeat(wo, 3, 0)).double(),
    ).reshape(m, 3)
    cos_o = torch.from_numpy(np.maximum(wo[:, 2], 0.0).astype(np.float64))[:, None]
    wt = torch.from_numpy(pairs.weight)[:, None]
    tt = torch.from_numpy(target)
    lt = torch.from_numpy(np.maximum(level, 0.0))
    wsum = wt.reshape(groups, per).sum(1)
    scale = (wt * cos_o * lt).reshape(groups, -1).sum(1) / (3 * wsum)
    den = scale.repeat_interleave(per)[:, None] + cos_o * lt / rf.PEAK_RATIO
    d = cos_o * (f_t - tt) / den
    loss_t = ((wt * d**2).reshape(groups, -1).sum(1) / (3 * wsum)).mean()
    loss_t.backward()
    npd = rf.NumpyDecoder.load("tiny", dtype=np.float64)
    p = npd.run(z, rows_wi, wo)
    loss, grad_f, _ = rf.lobe_loss(p.f, pairs)
    assert np.isclose(loss, loss_t.item(), rtol=1e-9)
    assert np.allclose(npd.backward(p, grad_f), zt.grad.numpy(), rtol=1e-6, atol=1e-10)


def _coated():
    from addon.core.stack import Coating, Conductor, Stack

    return Stack(
        Conductor(eta=(0.2, 0.4, 1.4), k=(3.9, 2.4, 1.6), roughness=0.3),
        (Coating(roughness=0.05, ior=1.5, thickness=0.5, albedo=(0.8, 0.5, 0.3)),),
    )

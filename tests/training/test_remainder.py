"""The exact top coat of the remainder design (onnx_export/remainder.py) against the reference."""

import numpy as np
import pytest

from addon.core import reference
from addon.core.stack import Coating, Conductor, Diffuse, Stack, StackArrays
from onnx_export.remainder import top_lobes, top_reflection


def _pairs(rng, n):
    w = rng.normal(size=(n, 3))
    w[:, 2] = np.abs(w[:, 2]) + 0.05
    return w / np.linalg.norm(w, axis=1, keepdims=True)


@pytest.mark.parametrize("alpha, ior", [(0.3, 1.6), (0.08, 1.45), (0.6, 2.0)])
def test_top_reflection_is_the_whole_brdf_of_a_coat_over_black(alpha, ior):
    """A coat over a black base with a clear, thin medium reflects only at its top interface: the
    reference walk's f is then exactly the analytic lobe (no light comes back out of the coat)."""
    stack = Stack(base=Diffuse((0.0, 0.0, 0.0)), coatings=(Coating(roughness=alpha, ior=ior, thickness=0.0),))
    rng = np.random.default_rng(4)
    wi, wo = _pairs(rng, 64), _pairs(rng, 64)
    f, _ = reference.eval_brdf(stack, wi, wo, walks=16)
    top = top_reflection(StackArrays.from_stacks([stack] * 64), wi[:, None], wo[:, None])[:, 0]
    np.testing.assert_allclose(top, f, rtol=1e-9, atol=1e-12)
    assert top.max() > 0.0


def test_top_reflection_is_part_of_a_layered_brdf_and_zero_without_coatings():
    coated = Stack(base=Conductor(0.2, (0.2, 0.4, 1.4), (3.9, 2.4, 1.6)), coatings=(Coating(roughness=0.2, ior=1.5),))
    rng = np.random.default_rng(5)
    wi, wo = _pairs(rng, 256), _pairs(rng, 256)
    f, se = reference.eval_brdf(coated, wi, wo, walks=64)
    top = top_reflection(StackArrays.from_stacks([coated] * 256), wi[:, None], wo[:, None])[:, 0]
    assert np.all(top <= f + 4 * se + 1e-9)  # the remainder is the rest of a non-negative sum
    assert (f - top).mean() > 0.1 * f.mean()
    bare = StackArrays.from_stacks([Stack(base=Diffuse((0.5, 0.5, 0.5)))] * 3)
    assert np.all(top_reflection(bare, wi[:3, None], wo[:3, None]) == 0.0)


def test_top_lobes_are_lobe_images_of_the_top_reflection():
    stack = Stack(base=Diffuse((0.0, 0.0, 0.0)), coatings=(Coating(roughness=0.3, ior=1.6, thickness=0.0),))
    imgs = top_lobes(StackArrays.from_stacks([stack]), 24, [0.0, 60.0])
    assert imgs.shape == (1, 2, 24, 24, 3)
    from addon.core import lobe

    ref = lobe.lobe_image(lambda wi, wo: reference.eval_brdf(stack, wi, wo, walks=4)[0], 60.0, 24)
    np.testing.assert_allclose(imgs[0, 1], ref, rtol=1e-9, atol=1e-12)


def test_bad_shapes_raise():
    stack = StackArrays.from_stacks([Stack(base=Diffuse((0.5, 0.5, 0.5)))] * 2)
    with pytest.raises(ValueError, match="must be"):
        top_reflection(stack, np.zeros((3, 4, 3)), np.zeros((3, 4, 3)))


def test_remainder_targets_of_the_trainers_are_the_brdf_minus_the_top_reflection(tmp_path):
    """``train_decoder --remainder`` and ``layering train --remainder`` train on the same remainders."""
    from addon.core.neural import load_models
    from onnx_export import layered_data
    from onnx_export.layering import StackSet
    from onnx_export.train_decoder import load_training_tensors

    layered_data.generate(tmp_path / "c1", coatings=1, stacks=3, n_wo=2, n_wi=4, walks=2, chunk=4, seed=3, log=str)
    whole = load_training_tensors([tmp_path / "c1"])
    rem = load_training_tensors([tmp_path / "c1"], remainder=True)
    top = top_reflection(whole["arrays"][0], whole["wi"].numpy(), whole["wo"].numpy())
    assert top.max() > 0.0
    np.testing.assert_allclose(rem["f"].numpy(), whole["f"].numpy() - top, rtol=1e-5, atol=1e-7)
    models = load_models("tiny", threads=1)
    a, b = StackSet(tmp_path / "c1", models), StackSet(tmp_path / "c1", models, remainder=True)
    np.testing.assert_allclose(b.f.numpy(), rem["f"].numpy(), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(a.f.numpy(), whole["f"].numpy())


def test_a_remainder_decoder_is_refused_by_the_export(tmp_path):
    """The runtime decodes every shipped decoder as a whole BRDF: a remainder checkpoint must not ship."""
    import torch

    from onnx_export import export

    ck = tmp_path / "ckpt.pt"
    torch.save({"args": {"remainder": True}}, ck)
    with pytest.raises(SystemExit):
        export.main(["--size", "tiny", "--decoder", str(ck), "--encoder", str(ck), "--out", str(tmp_path)])
    assert not list(tmp_path.glob("*.onnx"))


@pytest.mark.parametrize("args", [{"remainder": "True", "decoder_ckpt": "None"}, {"decoder_ckpt": "cache/x.pt"}])
def test_a_layering_network_of_an_unshipped_decoder_is_refused_by_its_export(tmp_path, args):
    import torch

    from onnx_export import layering

    ck = tmp_path / "ckpt.pt"
    torch.save({"args": args, "config": {"width": 128, "depth": 3}}, ck)
    with pytest.raises(SystemExit):
        layering.main(["export", "--size", "tiny", "--ckpt", str(ck), "--out", str(tmp_path)])
    assert not list(tmp_path.glob("*.onnx"))

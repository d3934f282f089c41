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


@pytest.mark.parametrize("transmission", [False, True])
def test_a_remainder_decoder_exports_with_its_card_saying_so_and_the_runtime_adds_the_top_lobe(tmp_path, transmission):
    """train_decoder --remainder [--top-transmission] -> export: the card says ``"remainder": true`` (and
    ``"top_transmission"``), and the runtime's evaluation is the decoded remainder (times the top coat's
    transmission) plus the exact top lobe of the stack's top coating."""
    import json

    from addon.core.neural import ModelSet, encode_stack, top_coat
    from addon.core.neural.top_lobe import eval_top, remainder_scale
    from onnx_export import data as datamod
    from onnx_export import export, layered_data, train_decoder, train_encoder
    from tests.training.test_neural_training import smoke_encoder_args

    datamod.generate("single", tmp_path / "single", materials=16, pairs=64, chunk=8, seed=2, log=lambda s: None)
    layered_data.generate(tmp_path / "c1", coatings=1, stacks=8, n_wo=2, n_wi=32, walks=2, chunk=8, seed=3, log=str)
    args = train_decoder.parser().parse_args(
        ["--size", "tiny", "--data", str(tmp_path / "single"), str(tmp_path / "c1"), "--data-weights", "0.5", "0.5"]
        + ["--loss", "l1", "l2rel", "--steps", "4", "--batch", "8", "--pairs", "32", "--remainder"]
        + ["--out", str(tmp_path / "run")]
        + (["--top-transmission"] if transmission else [])
    )
    train_decoder.train(args, log=lambda s: None)
    enc_args = smoke_encoder_args(tmp_path / "run" / "ckpt.pt", tmp_path / "single", tmp_path / "enc.pt", 3, 0)
    train_encoder.train(enc_args, log=lambda s: None)
    out = tmp_path / "models"
    export.main(["--size", "tiny", "--decoder", str(enc_args.ckpt), "--encoder", str(enc_args.out), "--out", str(out)])
    card = json.loads((out / "decoder_tiny.json").read_text())
    assert card["remainder"] is True and "remainder" in card["role"] and card["top_transmission"] is transmission
    m = ModelSet("tiny", model_dir=out)
    assert m.remainder and m.top_transmission is transmission
    stack = Stack(Diffuse((0.5, 0.5, 0.5)))  # no layering network exported here: a single layer's latent
    z = encode_stack(stack, m)
    rng = np.random.default_rng(6)
    wi, wo = _pairs(rng, 64), _pairs(rng, 64)
    top = top_coat(Stack(base=Diffuse((0.5, 0.5, 0.5)), coatings=(Coating(roughness=0.2, ior=1.5),)))
    scale = remainder_scale(top, wi, wo)[:, None] if transmission else 1.0
    np.testing.assert_allclose(
        m.eval_brdf(z, wi, wo, top), scale * m.eval_brdf(z, wi, wo) + eval_top(top, wi, wo)[:, None], rtol=1e-4
    )


@pytest.mark.parametrize(
    "args, decoder_remainder, decoder_transmission",
    [
        ({"remainder": "True", "decoder_ckpt": "None"}, False, False),  # a remainder network, a whole-BRDF decoder
        ({"decoder_ckpt": "None"}, True, False),  # a whole-BRDF network, a remainder decoder
        ({"remainder": "True", "top_transmission": "True", "decoder_ckpt": "None"}, True, False),  # unscaled decoder
        ({"remainder": "True", "decoder_ckpt": "None"}, True, True),  # a decoder scaled by the transmission
        ({"decoder_ckpt": "cache/x.pt"}, False, False),  # trained through a decoder that is not shipped
    ],
)
def test_a_layering_network_that_does_not_match_the_shipped_decoder_is_refused_by_its_export(
    tmp_path, args, decoder_remainder, decoder_transmission
):
    import json
    import shutil

    import torch

    from addon.core.neural import MODEL_DIR
    from onnx_export import layering

    for name in ("decoder_small.onnx", "decoder_small_rgb.onnx", "decoder_small_latents.onnx"):
        shutil.copy(MODEL_DIR / name, tmp_path / name)
    card = json.loads((MODEL_DIR / "decoder_small.json").read_text())
    card["remainder"] = decoder_remainder
    card["top_transmission"] = decoder_transmission
    (tmp_path / "decoder_small.json").write_text(json.dumps(card))
    ck = tmp_path / "ckpt.pt"
    torch.save({"args": args, "config": {"width": 128, "depth": 3}}, ck)
    with pytest.raises(SystemExit):
        layering.main(["export", "--size", "small", "--ckpt", str(ck), "--out", str(tmp_path)])
    assert not list(tmp_path.glob("layering*"))

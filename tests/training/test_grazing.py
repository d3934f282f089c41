"""Grazing incidence: the shipped networks against the reference near the horizon, and the loss that weights it."""

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from addon.core.neural import MODEL_DIR, SIZES, load_models  # noqa: E402
from onnx_export.heldout_grazing import GRAZING_ANGLES_DEG, grazing_ratios, load  # noqa: E402
from onnx_export.nets import pair_loss  # noqa: E402

GRAZING = Path(__file__).resolve().parents[1] / "data" / "heldout_grazing.npz"
SHIPPED = [s for s in SIZES if (MODEL_DIR / f"layering_{s}.onnx").exists()]

# Bounds the shipped models reach (measured with ``onnx_export.heldout_grazing.grazing_ratios``;
# docs/layering_training.md), per size: the largest network / reference ratio of the albedo and of
# f cos(theta_i) (viewer on the normal) over every held-out stack at 80-89.5 degrees, and the largest
# |median albedo bias| at 75 and 85 degrees over the coating counts. The target is 2 and 0.05.
BOUNDS = {  # far from the target: this pins what is reached so that no change makes it worse unnoticed
    # tiny on the remainder design with the top coat's transmission (docs/layering_training.md, "The
    # exact top coat ... shipped"), layering network of the validation-chosen round: largest ratios
    # 9.0 -> 5.48 and 23 -> 9.5 (both stack 7, near-black), median bias 0.47 -> 0.11 (four coatings at
    # 75 degrees; one to three coatings within 0.04); then its layering network trained on two to four
    # coatings (docs/layering_training.md, "Four coatings in training"): 5.48 -> 4.19 and 9.47 -> 7.47
    # (stack 7), median bias 0.106 -> 0.114 (four coatings at 75 degrees); then all four networks trained with
    # dim stacks weighted as bright (docs/layering_training.md, "Dim stacks weighted as bright"): 4.19 -> 2.86
    # and 7.47 -> 5.10 (stack 7 still), median bias 0.114 -> 0.072
    "tiny": {"albedo_max": 2.9, "fcos_max": 5.2, "median_bias": 0.08},
    # small on the remainder design with the top coat's transmission (10.5 -> 1.84, 38 -> 3.3, largest
    # median bias 0.51 -> 0.11), then its layering network trained on three coatings too
    # (docs/layering_training.md, "Three coatings in training"): 1.84 -> 1.90 and 3.3 -> 3.08 (stack 7,
    # near-black), largest median bias 0.11 -> 0.062 (one and four coatings at 75 degrees); then trained
    # two to four coatings deep with grazing pairs weighted (docs/layering_training.md, "Four coatings in
    # training"): 1.90 -> 1.82, 3.08 -> 3.12, largest median bias 0.062 -> 0.052
    "small": {"albedo_max": 1.85, "fcos_max": 3.2, "median_bias": 0.06},
    # medium on the remainder design with the top coat's transmission (docs/layering_training.md, "medium on
    # the remainder design"): 9.7 -> 2.06, 28.3 -> 5.9, largest median bias 0.42 -> 0.084 (two coatings at
    # 85 degrees; one and three coatings within 0.05); then its layering network trained on three coatings
    # with grazing pairs weighted (docs/layering_training.md, "Three coatings in training"): 2.06 -> 2.60
    # and 5.9 -> 8.5 (stack 7, near-black), largest median bias 0.084 -> 0.067 (two coatings at 85 degrees)
    "medium": {"albedo_max": 2.65, "fcos_max": 8.6, "median_bias": 0.07},
    # paper on the remainder design with the top coat's transmission and the level weights
    # (docs/layering_training.md, "paper on the exact top coat + neural remainder"): 7.08 -> 1.85 (stack 6),
    # 22.8 -> 3.11 (stack 20), largest median bias 0.42 -> 0.056
    "paper": {"albedo_max": 1.9, "fcos_max": 3.2, "median_bias": 0.06},
}


def test_the_grazing_reference_is_shipped_and_falls_to_zero_at_the_horizon():
    d = load(GRAZING)
    assert list(d["angles"]) == list(GRAZING_ANGLES_DEG)
    fcos = d["fcos"].mean(-1)
    assert np.isfinite(fcos).all() and (fcos >= 0).all()
    # f cos(theta_i) of every stack is smaller at 89.5 degrees than at 80 (cos falls 20-fold)
    assert (fcos[:, -1] < fcos[:, 1]).all()
    # the stored noise is small enough to tell a factor 2 apart
    assert np.median(d["fcos_stderr"] / np.maximum(d["fcos"], 1e-12)) < 0.1


@pytest.mark.parametrize("size", SHIPPED)
def test_no_shipped_size_over_reflects_near_the_horizon(size):
    r = grazing_ratios(load_models(size, threads=1), load(GRAZING))
    b = BOUNDS[size]
    near = r["angles"] >= 80
    assert r["albedo"][:, near].max() <= b["albedo_max"], r["albedo"][:, near].max()
    assert r["fcos"][:, near].max() <= b["fcos_max"], r["fcos"][:, near].max()
    for t in (75.0, 85.0):
        k = list(r["angles"]).index(t)
        for c in np.unique(r["n_coatings"]):
            bias = np.median(r["albedo"][r["n_coatings"] == c, k]) - 1.0
            assert abs(bias) <= b["median_bias"], (t, int(c), bias)


# The same, calibrated, as the renderer decodes a material's own latent by default (a factor table over
# incident and outgoing elevations, towards the light below the top interface, each target shrunk within its
# noise: docs/calibration.md). The albedo target, 2, is met by every size; f cos(theta_i) with the
# viewer on the normal reaches 2.0 (tiny) to 3.4 (paper), the separable calibration's 3.3-3.9 before.
CALIBRATED_BOUNDS = {
    "tiny": {"albedo_max": 1.35, "fcos_max": 2.2},
    "small": {"albedo_max": 1.45, "fcos_max": 2.8},
    "medium": {"albedo_max": 1.55, "fcos_max": 3.0},
    "paper": {"albedo_max": 1.55, "fcos_max": 3.5},
}


@pytest.mark.parametrize(
    "size", [pytest.param(s, marks=pytest.mark.slow) if s == "paper" else s for s in SHIPPED]
)  # paper's 32 calibrations take over two minutes on two cores
def test_calibrated_materials_stay_within_twice_the_reference_albedo_near_the_horizon(size):
    r = grazing_ratios(load_models(size, threads=2), load(GRAZING), calibrate=True)
    b = CALIBRATED_BOUNDS[size]
    near = r["angles"] >= 80
    assert r["albedo"][:, near].max() <= min(b["albedo_max"], 2.0), r["albedo"][:, near].max()
    assert r["fcos"][:, near].max() <= b["fcos_max"], r["fcos"][:, near].max()


def test_the_grazing_floor_divides_each_pairs_difference_by_its_smaller_cosine():
    grazing, steep = np.radians(87.0), np.radians(10.0)
    wi = torch.tensor(
        [[np.sin(grazing), 0.0, np.cos(grazing)], [np.sin(steep), 0.0, np.cos(steep)]], dtype=torch.float32
    )
    wo = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    pred, target = torch.tensor([2.0, 2.0]), torch.tensor([1.0, 1.0])
    for kind, power in (("l1", 1), ("l2", 2), ("l2rel", 2)):
        plain = pair_loss(pred, target, wi, wo, kind)
        weighted = pair_loss(pred, target, wi, wo, kind, grazing_floor=0.1)
        # the grazing pair (cos 0.052) is floored at 0.1, the steep one (cos 0.98 > 0.1) divided by its cosine
        np.testing.assert_allclose(weighted[0].item(), plain[0].item() / 0.1**power, rtol=1e-5)
        np.testing.assert_allclose(weighted[1].item(), plain[1].item() / float(wi[1, 2]) ** power, rtol=1e-5)
        assert weighted[0] / plain[0] > 5 * weighted[1] / plain[1]  # grazing pairs now count
    with pytest.raises(ValueError, match="grazing_floor must be in"):
        pair_loss(pred, target, wi, wo, "l1", grazing_floor=0.0)

"""Grazing incidence: the shipped networks against the reference near the horizon, and the loss that weights it."""

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from addon.core.neural import MODEL_DIR, SIZES, load_models  # noqa: E402
from onnx_export.heldout_grazing import GRAZING_ANGLES_DEG, grazing_ratios, load, medians_by_coatings  # noqa: E402
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
    # and 7.47 -> 5.10 (stack 7 still), median bias 0.114 -> 0.072; then measured against the grazing
    # reference made again with 16x the walks (its grid sums' noise 5.9% -> 1.3% at the median): 2.86 -> 2.77,
    # 5.10 -> 5.07, median bias 0.072 -> 0.031 (the four-coating stacks' 7% at 75 degrees was the old reference's)
    "tiny": {"albedo_max": 2.8, "fcos_max": 5.1, "median_bias": 0.035},
    # small on the remainder design with the top coat's transmission (10.5 -> 1.84, 38 -> 3.3, largest
    # median bias 0.51 -> 0.11), then its layering network trained on three coatings too
    # (docs/layering_training.md, "Three coatings in training"): 1.84 -> 1.90 and 3.3 -> 3.08 (stack 7,
    # near-black), largest median bias 0.11 -> 0.062 (one and four coatings at 75 degrees); then trained
    # two to four coatings deep with grazing pairs weighted (docs/layering_training.md, "Four coatings in
    # training"): 1.90 -> 1.82, 3.08 -> 3.12, largest median bias 0.062 -> 0.052; the cleaner reference: 1.76,
    # 3.06, 0.036
    "small": {"albedo_max": 1.8, "fcos_max": 3.1, "median_bias": 0.04},
    # medium on the remainder design with the top coat's transmission (docs/layering_training.md, "medium on
    # the remainder design"): 9.7 -> 2.06, 28.3 -> 5.9, largest median bias 0.42 -> 0.084 (two coatings at
    # 85 degrees; one and three coatings within 0.05); then its layering network trained on three coatings
    # with grazing pairs weighted (docs/layering_training.md, "Three coatings in training"): 2.06 -> 2.60
    # and 5.9 -> 8.5 (stack 7, near-black), largest median bias 0.084 -> 0.067 (two coatings at 85 degrees);
    # the cleaner reference: 2.55, 8.29, 0.047
    "medium": {"albedo_max": 2.6, "fcos_max": 8.4, "median_bias": 0.05},
    # paper on the remainder design with the top coat's transmission and the level weights
    # (docs/layering_training.md, "paper on the exact top coat + neural remainder"): 7.08 -> 1.85 (stack 6),
    # 22.8 -> 3.11 (stack 20), largest median bias 0.42 -> 0.056; the cleaner reference: 1.67 (stack 6), 3.83
    # (stack 20, whose old reference was 29% noise), 0.083 (the grid's sum at 85 degrees; integrated in full
    # the same medians are within 2%: the albedo targets below)
    "paper": {"albedo_max": 1.7, "fcos_max": 3.9, "median_bias": 0.085},
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
    r = grazing_ratios(load_models(size, threads=1), load(GRAZING), full=False)
    b = BOUNDS[size]
    near = r["angles"] >= 80
    assert r["albedo"][:, near].max() <= b["albedo_max"], r["albedo"][:, near].max()
    assert r["fcos"][:, near].max() <= b["fcos_max"], r["fcos"][:, near].max()
    for (t, c), m in medians_by_coatings(r, "albedo").items():
        assert abs(m - 1.0) <= b["median_bias"], (t, c, m - 1.0)


# The albedo targets where they are about, the directional albedo integrated in full (the decoded lobe by
# importance sampling, the reference by analog walks: ``albedo_full`` of the grazing set), every shipped size,
# decoder alone and calibrated: no held-out stack over 2x the reference at 80-89.5 degrees, and the median
# bias of each coating count within 5% at 75 and 85 degrees. The lobe grid's sums above miss the specular
# peaks that fall between its points (docs/calibration.md, "What the lobe grid holds"), so they pin the lobes'
# shape at those points, not these targets. FULL_MAX pins what is reached (docs/calibration.md): the largest
# ratio of any stack and size, decoder alone or calibrated, is 1.12.
TARGET_MAX, TARGET_BIAS, FULL_MAX = 2.0, 0.05, 1.2


def assert_albedo_targets(r: dict) -> None:
    near = r["angles"] >= 80
    assert r["albedo_full"][:, near].max() <= min(FULL_MAX, TARGET_MAX), r["albedo_full"][:, near].max()
    for (t, c), m in medians_by_coatings(r, "albedo_full").items():
        assert abs(m - 1.0) <= TARGET_BIAS, (t, c, m - 1.0)


def test_the_integrated_reference_is_shipped_and_clear_of_its_noise():
    d = load(GRAZING)
    full, se = d["albedo_full"].mean(-1), d["albedo_full_stderr"].mean(-1)
    assert full.shape == (len(d["stacks"]), len(GRAZING_ANGLES_DEG)) and (full > 0).all()
    # each stack's albedo is known to well within the 5% the medians are judged by
    assert (se / full).max() < 0.02, (se / full).max()
    # and the grid's sum is at most the whole (up to the noise of both): the grid holds part of each lobe
    assert (d["albedo"].mean(-1) <= 1.2 * full).all()


@pytest.mark.parametrize(
    "size", [pytest.param(s, marks=pytest.mark.slow) if s == "paper" else s for s in SHIPPED]
)  # paper's 1.8 M decoded samples take a minute on two cores
def test_every_shipped_size_meets_the_albedo_targets_near_the_horizon(size):
    assert_albedo_targets(grazing_ratios(load_models(size, threads=2), load(GRAZING)))


# The same, calibrated, as the renderer decodes a material's own latent by default (a factor table over
# incident and outgoing elevations, towards the light below the top interface, each target shrunk within its
# noise: docs/calibration.md). The albedo target, 2, is met by every size; f cos(theta_i) with the
# viewer on the normal reaches 1.96 (tiny) to 3.34 (paper; held-out stack 7 at 89.5 degrees, where the
# reference is 7e-7), the separable calibration's 3.3-3.9 before (against the cleaner reference: grid albedo
# 1.10 / 1.17 / 1.23 / 1.49, f cos 1.96 / 2.59 / 2.77 / 3.34 for tiny / small / medium / paper).
CALIBRATED_BOUNDS = {
    "tiny": {"albedo_max": 1.15, "fcos_max": 2.0},
    "small": {"albedo_max": 1.2, "fcos_max": 2.65},
    "medium": {"albedo_max": 1.3, "fcos_max": 2.85},
    "paper": {"albedo_max": 1.55, "fcos_max": 3.4},
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
    assert_albedo_targets(r)


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


@pytest.mark.parametrize(
    "argv",
    [["--walks", "0"], ["--view-walks", "0"], ["--full-walks", "0"], ["--res", "1"]],
)
def test_the_grazing_set_command_refuses_bad_counts(argv, tmp_path, capsys):
    from onnx_export.heldout_grazing import main

    with pytest.raises(SystemExit) as e:
        main([*argv, "--out", str(tmp_path / "g.npz")])
    assert e.value.code == 2 and "must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "g.npz").exists()


def test_the_integrated_reference_is_what_its_command_makes():
    """The stored ``albedo_full`` at 89.5 degrees, every stack, made again by the code with an eighth of the walks."""
    from onnx_export.heldout_grazing import GRAZING_SEED, directional_albedo_reference

    d = load(GRAZING)
    walks = int(str(d["command"]).split("--full-walks ")[1].split()[0])
    full, se = directional_albedo_reference(d["stacks"], GRAZING_ANGLES_DEG[-1:], walks // 8, GRAZING_SEED)
    stored = np.asarray(d["albedo_full"][:, -1:], dtype=np.float64)
    # an eighth of the walks: within 4 of the two estimates' joint standard error, every stack
    joint = np.sqrt(se**2 + np.asarray(d["albedo_full_stderr"][:, -1:], dtype=np.float64) ** 2)
    assert (np.abs(full - stored) <= 4 * joint + 1e-6).all(), np.abs(full - stored) / joint

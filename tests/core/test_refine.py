"""Refine on demand (addon.core.neural.refine): the numpy decoder against ONNX Runtime, its gradient,
the pairs and their weights, the keep-if-better rule, the cache and bad input."""

import shutil
import time

import numpy as np
import pytest

from addon.core.neural import MODEL_DIR, SIZES, encode_stack, load_models
from addon.core.neural import refine as rf
from addon.core.stack import Coating, Conductor, Stack

# every shipped decoder size must have its numpy weights (a missing file fails, it does not skip)
SHIPPED = [s for s in SIZES if (MODEL_DIR / f"decoder_{s}.onnx").exists()]
# a coated metal on which the tiny decoder's encoded latent is poor (held-out lobe error ~0.3)
COATED = Stack(
    Conductor(eta=(0.2, 0.4, 1.4), k=(3.9, 2.4, 1.6), roughness=0.3),
    (Coating(roughness=0.05, ior=1.5, thickness=0.5, albedo=(0.8, 0.5, 0.3)),),
)
QUICK = rf.RefineSettings(fit_groups=16, validation_groups=8, per_group=16, walks=32, steps=120)


def _directions(rng, n, grazing=False):
    u = rng.random((n, 2))
    z = u[:, 0] * (0.05 if grazing else 1.0) + 1e-4
    r = np.sqrt(1 - z * z)
    p = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(p), r * np.sin(p), z], 1)


@pytest.mark.parametrize("size", SHIPPED)
def test_numpy_decoder_equals_the_onnx_decoder(size):
    dec = rf.NumpyDecoder.load(size)
    rng = np.random.default_rng(3)
    n = 512
    wi = np.concatenate([_directions(rng, n // 2), _directions(rng, n // 2, grazing=True)])
    wo = _directions(rng, n)
    for z in (encode_stack(COATED, load_models(size, 1)), (rng.standard_normal((3, 32)) * 0.5).astype(np.float32)):
        ref = load_models(size, 1).eval_brdf(z, wi, wo)
        got = dec.forward(z, wi, wo)
        assert got.shape == (n, 3) and got.dtype == np.float32
        assert np.max(np.abs(got - ref) / np.maximum(np.abs(ref), 1e-6)) < 1e-4


def test_numpy_decoder_is_zero_below_the_horizon():
    dec = rf.NumpyDecoder.load("tiny")
    wi = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, -0.8], [0.0, 0.0, 1.0]])
    wo = np.array([[0.0, 0.6, -0.8], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    f = dec.forward(np.zeros((3, 32), np.float32), wi, wo)
    assert np.all(f[:2] == 0.0) and np.all(f[2] > 0.0)


def test_gradient_matches_central_differences():
    dec = rf.NumpyDecoder.load("small", dtype=np.float64)  # float64: differences of 1e-5 are resolved
    rng = np.random.default_rng(1)
    wi, wo = _directions(rng, 256), _directions(rng, 256)
    z = encode_stack(COATED, load_models("small", 1)).astype(np.float64)
    g_f = rng.standard_normal((256, 3))

    def loss(zz):
        return float((dec.forward(zz, wi, wo).astype(np.float64) * g_f).sum())

    grad = dec.backward(dec.run(z, wi, wo), g_f)
    h = 1e-5
    for c, k in ((0, 0), (1, 7), (2, 31), (0, 19)):
        e = np.zeros_like(z)
        e[c, k] = h
        fd = (loss(z + e) - loss(z - e)) / (2 * h)
        assert abs(fd - grad[c, k]) <= 1e-4 * max(1.0, abs(grad[c, k])), (c, k, fd, grad[c, k])


def test_lobe_loss_gradient_is_its_derivative():
    pairs = rf.PairSet.measure(COATED, 4, 8, walks=4, seed=0)
    rng = np.random.default_rng(0)
    f = (pairs.target + 0.1 * rng.random(pairs.target.shape)).astype(np.float64)
    loss, grad, per_group = rf.lobe_loss(f, pairs)
    assert per_group.shape == (4,) and np.isclose(loss, np.mean(per_group**2))
    for i in (0, 5, 17):
        e = np.zeros_like(f)
        e[i, 1] = 1e-6
        fd = (rf.lobe_loss(f + e, pairs)[0] - rf.lobe_loss(f - e, pairs)[0]) / 2e-6
        assert np.isclose(fd, grad[i, 1], rtol=1e-4, atol=1e-9)
    assert rf.lobe_loss(pairs.target, pairs)[0] == 0.0
    # the weights do not depend on the prediction: the loss is quadratic in f, minimised by the targets,
    # and the weights come from other walks than the targets
    assert pairs.level is not None and not np.array_equal(pairs.level, pairs.target)


def test_pairs_are_seeded_and_their_weights_estimate_the_projected_disk_mean():
    stack = COATED
    a = rf.refinement_pairs(stack, 400, 64, seed=5)
    b = rf.refinement_pairs(stack, 400, 64, seed=5)
    c = rf.refinement_pairs(stack, 400, 64, seed=6)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)) and not np.array_equal(a[1], c[1])
    wi, wo, w = a
    assert np.allclose(np.linalg.norm(wo, axis=-1), 1.0) and np.allclose(np.linalg.norm(wi, axis=-1), 1.0)
    # grazing incident directions (80 to 89.5 degrees) make up the requested share
    theta = np.degrees(np.arccos(wi[:, 2]))
    assert np.isclose(np.mean(theta > 80.0), 0.2, atol=0.01) and theta.max() <= 89.5 + 1e-9
    # a weighted mean of g(wo) estimates its mean over the projected disk: E_cos[cos^2] = 1/2, E_cos[1] = 1
    assert np.isclose(np.mean(w), 1.0, atol=0.03)
    assert np.isclose(np.mean(w * wo[..., 2] ** 2), 0.5, atol=0.02)
    # half or more of the outgoing directions lie in the lobes about the mirror direction
    mirror = wi * [-1, -1, 1]
    assert np.mean(np.einsum("gmk,gk->gm", wo, mirror) > 0.95) > 0.3


def test_refinement_fits_the_reference_better_on_separate_validation_pairs_and_is_cached(tmp_path):
    rf._MEMORY.clear()
    z0 = encode_stack(COATED, load_models("tiny", 1))
    z, rep = rf.refine_latent(COATED, "tiny", budget_s=30.0, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert rep.kept and rep.validation_loss_after < rep.validation_loss_before
    assert rep.fit_loss_after < rep.fit_loss_before and rep.steps > 1 and not rep.cached
    assert z.shape == (3, 32) and z.dtype == np.float32 and np.all(np.isfinite(z)) and not np.array_equal(z, z0)
    # the validation pairs are not the fitted ones
    fit = rf.refinement_pairs(COATED, QUICK.fit_groups, QUICK.per_group, 2 * QUICK.seed)
    val = rf.refinement_pairs(COATED, QUICK.validation_groups, QUICK.per_group, 2 * QUICK.seed + 1)
    assert not np.any(np.all(np.isclose(fit[0][:, None], val[0][None]), axis=-1))
    # the same stack, models and settings: the cached latent, in memory and then from the folder
    t = time.perf_counter()
    z2, rep2 = rf.refine_latent(COATED, "tiny", budget_s=30.0, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert rep2.cached and np.array_equal(z2, z) and time.perf_counter() - t < rep.total_s
    rf._MEMORY.clear()
    z3, rep3 = rf.refine_latent(COATED, "tiny", budget_s=30.0, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert rep3.cached and np.array_equal(z3, z) and rep3.key == rep.key
    assert len(list(tmp_path.glob("refine_*.npz"))) == 1 and not list(tmp_path.glob(".refine_*"))
    # a file damaged on disk is a miss (refined again), not an error
    next(tmp_path.glob("refine_*.npz")).write_bytes(b"damaged")
    rf._MEMORY.clear()
    assert rf._cache_get(rep.key, tmp_path) is None


def test_a_refinement_its_budget_cut_short_is_refined_again_for_a_larger_budget(tmp_path):
    """The budget is not in the cache key (a finished refinement serves any budget); one the budget stopped was
    served to every larger budget too, so Refine's redo panel could never improve it."""
    rf._MEMORY.clear()
    _, short = rf.refine_latent(COATED, "tiny", budget_s=0.05, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert short.stopped == "budget" and not short.cached
    _, longer = rf.refine_latent(COATED, "tiny", budget_s=30.0, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert not longer.cached and longer.steps > short.steps and longer.stopped != "budget"
    rf._MEMORY.clear()
    _, again = rf.refine_latent(COATED, "tiny", budget_s=0.05, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert again.cached and again.steps == longer.steps  # the finished one serves a smaller budget


def test_a_refinement_its_budget_cut_short_is_refined_again_for_the_same_budget(tmp_path):
    """One the budget stopped served the same budget too: pressing Refine again answered "did not improve" from the
    cache, where the first had made no step of the fit. A smaller budget, which would stop sooner still, it serves."""
    rf._MEMORY.clear()
    _, short = rf.refine_latent(COATED, "tiny", budget_s=0.05, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert short.stopped == "budget" and short.steps == 0 and not short.cached  # the walks took the budget
    assert short.fit_loss_after == short.fit_loss_before
    _, again = rf.refine_latent(COATED, "tiny", budget_s=0.05, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert not again.cached and again.stopped == "budget"
    _, smaller = rf.refine_latent(COATED, "tiny", budget_s=0.04, settings=QUICK, threads=1, cache_dir=tmp_path)
    assert smaller.cached and smaller.budget_s == 0.05


def test_a_refinement_refined_again_keeps_the_better_of_the_two_tries():
    """The same budget buys fewer steps on a busier machine: refined again, a try that went less far replaced the
    better latent of the one before. The one better on the validation pairs is kept, and returned."""
    rf._MEMORY.clear()
    _, first = rf.refine_latent(COATED, "tiny", budget_s=0.05, settings=QUICK, threads=1)
    assert first.stopped == "budget" and not first.kept
    better = np.full((3, 32), 0.5, np.float32)  # stands for a try that went further: kept, validation loss 0
    rf._MEMORY[first.key] = (better, rf.RefineReport(**{**first.to_dict(), "kept": True, "validation_loss_after": 0.0}))
    seen = []
    z, again = rf.refine_latent(COATED, "tiny", budget_s=0.05, settings=QUICK, threads=1, progress=seen.append)
    assert seen  # refined again
    assert again.cached and again.kept and np.array_equal(z, better)
    assert np.array_equal(rf._MEMORY[first.key][0], better)  # and it stays the answer


def test_what_a_session_makes_once_is_not_counted_in_a_refinements_budget(monkeypatch):
    """The top lobe's loops compile on their first call (with a remainder decoder's transmission table, 2.5 s in a
    new session), which came after the reference walks, inside the budget: a first refinement with a budget of a few
    seconds spent it there and made no step of the fit. Here a first call that takes 3 s stands for it."""
    rf._MEMORY.clear()
    real, calls = rf.eval_top, []

    def compiled_on_first_call(*args, **kwargs):
        if not calls:
            time.sleep(3.0)
        calls.append(len(args[1]))
        return real(*args, **kwargs)

    monkeypatch.setattr(rf, "eval_top", compiled_on_first_call)
    _, rep = rf.refine_latent(COATED, "tiny", budget_s=2.5, settings=QUICK, threads=1, use_cache=False)
    assert calls[0] == 1  # made on one pair, before the budget's clock
    assert rep.steps > 0 and rep.fit_loss_after < rep.fit_loss_before
    assert rep.total_s > 3.0 + rep.reference_s + rep.optimise_s - 0.1  # the whole call's time, the 3 s in it


def test_a_refinement_reports_its_progress_and_stops_when_asked_caching_nothing(tmp_path):
    """``progress``: the share of the budget spent, after the reference walks and each step (the add-on's Refine
    runs on a worker thread with a bar and Esc; it held Blender's UI for its whole budget)."""
    rf._MEMORY.clear()
    seen = []

    def progress(fraction):
        seen.append(fraction)
        if len(seen) == 6:
            raise KeyboardInterrupt("Esc")

    with pytest.raises(KeyboardInterrupt):
        rf.refine_latent(
            COATED, "tiny", budget_s=30.0, settings=QUICK, threads=1, cache_dir=tmp_path, progress=progress
        )
    assert len(seen) == 6 and seen == sorted(seen) and 0.0 <= seen[0] and seen[-1] <= 1.0
    assert not list(tmp_path.glob("refine_*.npz")) and not rf._MEMORY


def test_a_refinement_that_is_worse_on_validation_is_not_kept():
    rf._MEMORY.clear()
    # one group of 8 pairs at 2 walks: the fit follows the noise of those few values (overfits)
    few = rf.RefineSettings(fit_groups=1, validation_groups=8, per_group=8, walks=2, steps=200, lr=0.05)
    z, rep = rf.refine_latent(COATED, "tiny", budget_s=30.0, settings=few, threads=1, use_cache=False)
    assert rep.fit_loss_after < 0.1 * rep.fit_loss_before
    assert rep.validation_loss_after > rep.validation_loss_before and not rep.kept
    assert np.array_equal(z, encode_stack(COATED, load_models("tiny", 1)))


def test_cache_key_follows_the_stack_the_settings_and_the_model_files(tmp_path):
    for name in ("decoder_tiny.onnx", "decoder_tiny_weights.npz", "encoder_tiny.onnx", "layering_tiny.onnx"):
        shutil.copy(MODEL_DIR / name, tmp_path / name)
    k = rf.refine_key(COATED, "tiny", QUICK, tmp_path)
    assert k == rf.refine_key(COATED, "tiny", QUICK, MODEL_DIR)
    other = Stack(COATED.base, (Coating(roughness=0.06, ior=1.5, thickness=0.5, albedo=(0.8, 0.5, 0.3)),))
    assert rf.refine_key(other, "tiny", QUICK, tmp_path) != k
    assert rf.refine_key(COATED, "tiny", rf.RefineSettings(seed=1), tmp_path) != rf.refine_key(
        COATED, "tiny", rf.RefineSettings(), tmp_path
    )
    from addon.core import reference

    with pytest.MonkeyPatch.context() as mp:  # the reference's eval gives the targets: a corrected one, new ones
        mp.setattr(reference, "ESTIMATOR_VERSION", reference.ESTIMATOR_VERSION + 1)
        assert rf.refine_key(COATED, "tiny", QUICK, tmp_path) != k
    with open(tmp_path / "layering_tiny.onnx", "ab") as fh:
        fh.write(b"\0")
    assert rf.refine_key(COATED, "tiny", QUICK, tmp_path) != k
    (tmp_path / "encoder_tiny.onnx").unlink()
    with pytest.raises(FileNotFoundError, match="encoder_tiny.onnx"):
        rf.refine_key(COATED, "tiny", QUICK, tmp_path)


def test_weights_of_another_decoder_version_are_refused(tmp_path):
    shutil.copy(MODEL_DIR / "decoder_tiny.onnx", tmp_path / "decoder_tiny.onnx")
    with pytest.raises(FileNotFoundError, match="onnx_export.decoder_weights --sizes tiny"):
        rf.NumpyDecoder.load("tiny", tmp_path)
    shutil.copy(MODEL_DIR / "decoder_tiny_weights.npz", tmp_path / "decoder_tiny_weights.npz")
    rf.NumpyDecoder.load("tiny", tmp_path)
    with open(tmp_path / "decoder_tiny.onnx", "ab") as fh:
        fh.write(b"\0")
    with pytest.raises(rf.StaleWeightsError, match="another version of decoder_tiny.onnx"):
        rf.NumpyDecoder.load("tiny", tmp_path)


@pytest.mark.parametrize("budget", [0.0, -1.0, float("nan"), float("inf"), True])
def test_bad_budget_is_refused(budget):
    with pytest.raises(ValueError, match="budget_s"):
        rf.refine_latent(COATED, "tiny", budget_s=budget)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="needs a Stack"):
        rf.refine_latent("gold", "tiny")
    with pytest.raises(ValueError, match="unknown decoder size"):
        rf.refine_latent(COATED, "huge")
    with pytest.raises(ValueError, match="walks"):
        rf.RefineSettings(walks=0)
    with pytest.raises(ValueError, match="lr"):
        rf.RefineSettings(lr=float("nan"))
    with pytest.raises(ValueError, match="grazing_share"):
        rf.refinement_pairs(COATED, 4, 4, 0, grazing_share=1.5)


@pytest.mark.slow
def test_refinement_lowers_the_held_out_lobe_error_of_the_tiny_decoder():
    """Held-out layered stacks (never fitted: the refinement draws its own pairs and walks): the median lobe
    error over the first six one-coating stacks and four elevations falls (about a minute here)."""
    from pathlib import Path

    from addon.core import lobe
    from onnx_export.heldout_layered import load

    data = load(Path(__file__).resolve().parents[1] / "data" / "heldout_layered.npz")
    models = load_models("tiny", 1)
    idx = [i for i, s in enumerate(data["stacks"]) if len(s.coatings) == 1][:6]
    before, after = [], []
    for i in idx:
        s = data["stacks"][i]
        z, rep = rf.refine_latent(s, "tiny", budget_s=120.0, threads=1, use_cache=False)
        for zz, out in ((encode_stack(s, models), before), (z, after)):
            img = np.array(
                [
                    lobe.lobe_image(lambda wi, wo, zz=zz: models.eval_brdf(zz, wi, wo), float(t), 24)
                    for t in data["angles"]
                ]
            )
            out.append(lobe.relative_rmse(img, data["lobe"][i], image_axes=3))
    assert np.median(after) < 0.9 * np.median(before), (np.median(before), np.median(after))

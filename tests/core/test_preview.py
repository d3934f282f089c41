"""Preview images (sphere, lobe), BRDF choice and chunked evaluation, with analytic BRDFs."""

from __future__ import annotations

import numpy as np
import pytest

from addon.core import preview
from addon.core.bsdf.lambert import Lambertian
from addon.core.stack import PRESETS, Coating, Diffuse, Stack


def lambert(albedo):
    bsdf = Lambertian(np.asarray(albedo, dtype=np.float64))
    return lambda wi, wo: bsdf.eval(wi, wo)


def test_sphere_white_furnace_is_one():
    """A white Lambertian under a white sky: 1 everywhere on average (the MIS weights of the cosine
    proxy and the sky's uniform distribution are not 1 sample by sample) and at many samples."""
    env = preview.Environment(zenith=(1, 1, 1), horizon=(1, 1, 1), ground=(1, 1, 1), sun_irradiance=(0, 0, 0))
    img = preview.sphere_preview(lambert((1, 1, 1)), res=48, env=env, env_samples=7)
    assert img.shape == (48, 48, 4) and img.dtype == np.float32
    on = img[..., 3] > 0
    assert on.sum() == pytest.approx(np.pi * 24**2, rel=0.05)
    assert img[on][:, :3].mean() == pytest.approx(1.0, abs=0.01)
    assert np.all(img[~on] == 0.0)
    many = preview.sphere_preview(lambert((1, 1, 1)), res=16, env=env, env_samples=512)
    np.testing.assert_allclose(many[many[..., 3] > 0][:, :3], 1.0, atol=0.08)


def test_the_sphere_sky_term_goes_a_block_of_pixels_at_a_time_with_progress(monkeypatch):
    """All the sky's directions at once, a 512-pixel sphere of 64 samples held 4.6 GB and called no progress for
    12 s (Esc unheard). A block at a time: the same furnace, and progress between the blocks."""
    env = preview.Environment(zenith=(1, 1, 1), horizon=(1, 1, 1), ground=(1, 1, 1), sun_irradiance=(0, 0, 0))
    monkeypatch.setattr(preview, "SPHERE_BLOCK_ROWS", 700)
    seen = []
    img = preview.sphere_preview(lambert((1, 1, 1)), res=48, env=env, env_samples=7, progress=seen.append)
    on = img[..., 3] > 0
    assert img[on][:, :3].mean() == pytest.approx(1.0, abs=0.01)
    assert len(seen) >= 20 and seen == sorted(seen) and seen[-1] == pytest.approx(1.0)  # 19 blocks and the sun


def test_sky_distribution_is_normalised_and_matches_its_samples():
    env = preview.DEFAULT_ENVIRONMENT
    d, pdf = env.sample_sky(np.random.default_rng(3).random((200_000, 2)))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(pdf, env.sky_pdf(d), rtol=1e-9)
    # E[1 / pdf] over its own samples is the sphere's solid angle
    assert np.mean(1.0 / pdf) == pytest.approx(4 * np.pi, rel=0.01)
    # brighter heights are drawn more often: the horizon (0.85) over the ground (0.16)
    assert np.mean(d[:, 1] > 0) > 0.75


def _sky_term(choice, samples, res=48):
    from benchmarks.bench_previews import sky_term

    return sky_term(choice, res, samples)


def test_neural_sphere_has_no_fireflies_at_the_default_samples():
    """Red car paint on the neural decoder at the default 8 sky directions: the cosine pattern gave
    a sky term with pixels to 1848 times the median (128 px); the material's sampler (the proxy, and for a
    remainder decoder the exact top lobe) and the sky's distribution keep it within a few tens of the
    median and on the 256-sample mean."""
    from addon.core.neural.top_lobe import top_share

    choice = preview.choose_brdf(PRESETS["red_car_paint"], "NEURAL", size="auto")
    assert choice.proposal is not None
    if choice.proposal.top is not None:  # a glossy coat: its exact lobe gets samples
        assert top_share(choice.proposal.top[None], np.array([[0.0, 0.0, 1.0]]))[0] > 0.1
    else:  # a glossy coat: a narrow proxy lobe
        assert choice.proxy[0] < 0.1
    lum = _sky_term(choice, 8)
    converged = _sky_term(choice, 256)
    assert lum.max() / np.median(lum) < 100.0, lum.max() / np.median(lum)
    assert lum.mean() == pytest.approx(converged.mean(), rel=0.05)


def test_sphere_sun_term_matches_lambert_cosine():
    sun = np.array([-0.3, 0.5, 0.8])
    env = preview.Environment(
        zenith=(0, 0, 0), horizon=(0, 0, 0), ground=(0, 0, 0), sun_direction=tuple(sun), sun_irradiance=(2.0, 1.0, 0.5)
    )
    res = 40
    img = preview.sphere_preview(lambert((0.5, 0.5, 0.5)), res=res, env=env, env_samples=3)
    c = (np.arange(res) + 0.5) / res * 2 - 1
    x, y = np.meshgrid(c, -c)
    z = np.sqrt(np.clip(1 - x * x - y * y, 0, 1))
    cos = np.clip((x * sun[0] + y * sun[1] + z * sun[2]) / np.linalg.norm(sun), 0, None)
    expect = 0.5 / np.pi * cos[..., None] * np.array([2.0, 1.0, 0.5])
    on = img[..., 3] > 0
    np.testing.assert_allclose(img[on][:, :3], expect[on], rtol=1e-4, atol=1e-6)
    # rows run top to bottom: the sun is up, so the top half is brighter
    assert img[: res // 2, :, 0].sum() > 2 * img[res // 2 :, :, 0].sum()


def test_default_environment_is_finite_nonnegative_and_deterministic():
    a = preview.sphere_preview(lambert((0.8, 0.4, 0.2)), res=32)
    b = preview.sphere_preview(lambert((0.8, 0.4, 0.2)), res=32)
    assert np.all(np.isfinite(a)) and np.all(a >= 0)
    np.testing.assert_array_equal(a, b)


def test_lobe_preview_alpha_marks_the_disk_and_matches_albedo():
    img = preview.lobe_preview(lambert((0.6, 0.6, 0.6)), 30.0, res=64)
    assert img.shape == (64, 64, 4)
    from addon.core.lobe import albedo_from_lobe

    np.testing.assert_allclose(albedo_from_lobe(img[..., :3]), 0.6, rtol=0.02)
    assert img[0, 0, 3] == 0 and img[32, 32, 3] == 1
    with pytest.raises(ValueError, match="incident angle"):
        preview.lobe_preview(lambert((1, 1, 1)), 95.0)


def test_chunked_calls_progress_and_can_cancel():
    seen = []
    f = preview.chunked(lambert((1, 1, 1)), chunk=10, progress=seen.append)
    wi = np.tile([0.0, 0.0, 1.0], (35, 1))
    out = f(wi, wi)
    assert out.shape == (35, 3) and seen == pytest.approx([10 / 35, 20 / 35, 30 / 35, 1.0])

    def stop(fraction):
        if fraction > 0.5:
            raise preview.Cancelled()

    with pytest.raises(preview.Cancelled):
        preview.chunked(lambert((1, 1, 1)), chunk=10, progress=stop)(wi, wi)


def test_stack_hash_changes_with_any_parameter():
    a = PRESETS["coated_gold"]
    b = Stack(a.base, (Coating(roughness=0.021, ior=1.5),))
    assert preview.stack_hash(a) == preview.stack_hash(Stack.from_json(a.to_json()))
    assert preview.stack_hash(a) != preview.stack_hash(b)


def test_choose_brdf_falls_back_with_a_note(monkeypatch):
    def missing():
        raise preview.NeuralUnavailable("decoder_small.onnx not found in addon/models")

    monkeypatch.setattr(preview, "_neural_module", missing)
    stack = Stack(Diffuse((0.5, 0.5, 0.5)))
    choice = preview.choose_brdf(stack, "AUTO")
    assert choice.method == "REFERENCE"
    assert "neural models not available" in choice.notes[0] and "decoder_small.onnx" in choice.notes[0]
    with pytest.raises(preview.NeuralUnavailable, match="decoder_small.onnx"):
        preview.choose_brdf(stack, "NEURAL")
    with pytest.raises(ValueError, match="method must be one of"):
        preview.choose_brdf(stack, "FAST")


def lambert_sampler(albedo, seed=1):
    bsdf = Lambertian(np.asarray(albedo, dtype=np.float64))
    rng = np.random.default_rng(seed)

    def sample(wo):
        n = len(wo)
        out = bsdf.sample(wo, rng.random(n), rng.random((n, 2)))
        return out.wi, out.weight

    return sample


def test_sphere_with_a_sampler_matches_the_fixed_pattern_on_average():
    white = preview.Environment(zenith=(1, 1, 1), horizon=(1, 1, 1), ground=(1, 1, 1), sun_irradiance=(0, 0, 0))
    img = preview.sphere_preview(
        lambert((0.7, 0.7, 0.7)), res=24, env=white, env_samples=5, sampler=lambert_sampler((0.7, 0.7, 0.7))
    )
    on = img[..., 3] > 0
    np.testing.assert_allclose(img[on][:, :3], 0.7, rtol=1e-5)  # furnace: weight = albedo exactly

    sampled = preview.sphere_preview(
        lambert((0.5, 0.5, 0.5)), res=24, env_samples=256, sampler=lambert_sampler((0.5, 0.5, 0.5))
    )
    pattern = preview.sphere_preview(lambert((0.5, 0.5, 0.5)), res=24, env_samples=256)
    on = sampled[..., 3] > 0
    assert sampled[on][:, :3].mean(0) == pytest.approx(pattern[on][:, :3].mean(0), rel=0.02)
    # the sky is brighter than the ground: the top half of the sphere is brighter
    assert sampled[:12, :, 2].sum() > sampled[12:, :, 2].sum()


def test_reference_choice_samples_delta_reflections_of_a_smooth_coat():
    """eval_brdf leaves out the mirror reflection of a smooth coat; the sampler carries it."""
    stack = Stack(Diffuse((0.0, 0.0, 0.0)), (Coating(roughness=0.0, ior=1.5),))
    choice = preview.choose_brdf(stack, "REFERENCE", walks=4)
    assert choice.sampler is not None
    env = preview.Environment(zenith=(1, 1, 1), horizon=(1, 1, 1), ground=(1, 1, 1), sun_irradiance=(0, 0, 0))
    img = preview.sphere_preview(choice.brdf, res=16, env=env, env_samples=32, sampler=choice.sampler)
    on = img[..., 3] > 0
    centre = img[8, 8, :3]  # normal incidence: Fresnel reflectance of ior 1.5 is 0.04
    assert centre == pytest.approx(0.04, abs=0.03)
    # grazing pixels reflect more (Fresnel), and nothing is negative or infinite
    assert img[on][:, 0].max() > 0.2 and np.all(np.isfinite(img)) and np.all(img >= 0)


def _row_band_ratio(a, b):
    """Variance of the row means of ``a - b`` times the pixels per row, over the per-pixel variance:
    about 1 when the pixels' noise is independent, much more when rows share it."""
    on = (a > 0) & (b > 0)
    d = a - b
    rows = [d[r][on[r]] for r in range(a.shape[0]) if on[r].sum() > 8]
    return np.mean([r.mean() ** 2 * len(r) for r in rows]) / d[on].var()


def test_reference_half_of_the_comparison_has_independent_noise_per_pixel():
    """Two comparisons with different seeds: their reference halves differ by noise alone. With
    walks shared by the pixels of a chunk (the amortised estimator: 21 image rows per chunk here)
    the band ratio measured 12.6; independent walks per pixel give about 1."""
    stack = PRESETS["lacquered_plastic"]
    halves = [
        preview.compare_with_reference(stack, 30.0, res=48, walks=64, seed=seed).reference[..., 0] for seed in (0, 1)
    ]
    assert _row_band_ratio(*halves) < 2.0


def test_reference_lobe_preview_has_independent_noise_per_pixel():
    stack = PRESETS["lacquered_plastic"]
    lobes = []
    for seed in (0, 1):
        choice = preview.choose_brdf(stack, "REFERENCE", walks=16, seed=seed)
        lobes.append(preview.lobe_preview(choice.brdf, 30.0, 48, chunk=choice.chunk)[..., 0])
    assert _row_band_ratio(*lobes) < 2.0


def test_every_neural_preview_shows_the_calibration_f12_applies_and_none_when_it_is_off():
    """Lobe and Sphere applied a render's albedo calibration (even with Calibrate Albedo off), Compare with
    Reference never did: its error was not that of what F12 renders. All three now follow the scene's setting."""
    from addon.core.neural import calibrate, encode_stack, load_models

    stack = PRESETS["red_car_paint"]
    models = load_models("tiny")
    z = encode_stack(stack, models)
    calibrate.calibrate(stack, models, z, models.proxy_params(z[None])[0])  # what a render makes and keeps
    note = "albedo calibration of the last render applied"
    shown = {on: preview.choose_brdf(stack, "NEURAL", size="tiny", calibrated=on) for on in (True, False)}
    compared = {
        on: preview.compare_with_reference(stack, 60.0, 16, walks=2, size="tiny", calibrated=on) for on in (True, False)
    }
    assert note in shown[True].notes and note not in shown[False].notes
    assert note in compared[True].notes and note not in compared[False].notes
    for on in (True, False):  # the comparison's neural lobe is the one the lobe preview shows
        lobe = preview.lobe_preview(shown[on].brdf, 60.0, 16)
        np.testing.assert_allclose(
            compared[on].neural[..., :3], preview.sanitize(lobe)[0][..., :3], rtol=1e-5, atol=1e-7
        )
    assert not np.allclose(compared[True].neural, compared[False].neural)


def test_a_smooth_coat_is_compared_with_the_reference_of_the_stack_the_networks_see_and_the_clamp_is_said():
    """A roughness-0 coat is clamped to the trained 0.01 for the networks: its sharp lobe against the reference's
    delta reflection (which no lobe image shows) read a relative RMSE of 4.95 for a network within 0.03 of its
    clamped stack, and with a stored latent nothing said why. The comparison now takes the clamped stack's
    reference and says so, and the clamp is said with a stored latent too."""
    from addon.core import preview
    from addon.core.stack import Coating, Diffuse, Stack

    smooth = Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.0, 1.5),))
    z, size, notes = preview.encode_latent(smooth, "tiny")
    assert any("clamped" in n for n in notes)
    cmp = preview.compare_with_reference(smooth, res=24, walks=64, latent=(z, size), size="tiny", calibrated=False)
    assert any("clamped" in n for n in cmp.notes) and any("networks see" in n for n in cmp.notes)
    assert cmp.relative_rmse < 0.5, cmp.relative_rmse
    # the neural side's time is its lobe's evaluation, not the first call's loading and tables
    assert cmp.seconds_neural < cmp.seconds_reference

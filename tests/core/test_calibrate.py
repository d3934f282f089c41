"""Albedo calibration of decoded materials against the reference (addon.core.neural.calibrate)."""

import numpy as np
import pytest

from addon.core import kernels, reference
from addon.core.neural import calibrate as cal
from addon.core.neural import encode_stack, load_models, top_coat
from addon.core.neural.top_lobe import eval_top, remainder_scale
from addon.core.render import neural_material
from addon.core.render.integrator import RenderSettings
from addon.core.stack import Coating, Conductor, Dielectric, Diffuse, Stack, StackArrays, preset


def test_factors_solve_the_symmetric_scaling_and_leave_a_matching_albedo_alone():
    rng = np.random.default_rng(3)
    k = len(cal.COSINES)
    m = rng.uniform(0.01, 0.2, size=(k, k, 3))
    c_true = rng.uniform(0.5, 2.0, size=(k, 3))
    target = c_true * np.einsum("klc,lc->kc", m, c_true)
    c = cal.solve_factors(m, target)
    np.testing.assert_allclose(c * np.einsum("klc,lc->kc", m, c), target, rtol=1e-6)
    np.testing.assert_allclose(c, c_true, rtol=1e-5)  # the positive solution is unique
    # an albedo that already matches needs no factor
    np.testing.assert_allclose(cal.solve_factors(m, m.sum(axis=1)), 1.0, rtol=1e-6)
    # factors stay in range even for a target the lobe cannot reach
    c = cal.solve_factors(m, np.full((k, 3), 1e6))
    assert c.max() <= cal.FACTOR_RANGE[1] and c.min() >= cal.FACTOR_RANGE[0]


def test_hat_weights_interpolate_like_the_factor():
    grid = np.asarray(cal.COSINES)
    x = np.concatenate([np.linspace(0.0, 1.0, 101), grid])
    y = np.random.default_rng(1).permutation(x)
    hats_x, hats_y = cal._hats(x, grid), cal._hats(y, grid)
    np.testing.assert_allclose(hats_x.sum(axis=1), 1.0)
    rng = np.random.default_rng(0)
    scale = rng.uniform(0.5, 2.0, size=(len(grid), 3))
    separable = scale[:, None, :] * scale[None, :, :]

    def calibration(table):
        return cal.AlbedoCalibration(grid, scale, table, scale, scale, scale, scale)

    # a separable table is the product of the two piecewise-linear factors
    c = calibration(separable)
    np.testing.assert_allclose(c.factor(x, y), (hats_x @ scale) * (hats_y @ scale), rtol=1e-12)
    # any table: bilinear in the hats, and symmetric when the table is
    d = rng.uniform(0.5, 1.5, size=separable.shape)
    table = separable * (d + d.transpose(1, 0, 2)) / 2
    c = calibration(table)
    np.testing.assert_allclose(c.factor(x, y), np.einsum("nk,nl,klc->nc", hats_x, hats_y, table), rtol=1e-12)
    np.testing.assert_allclose(c.factor(x, y), c.factor(y, x), rtol=1e-12)
    # constant beyond the grid's ends (grazing beyond 88.6 degrees keeps the last factor)
    np.testing.assert_allclose(c.factor(np.array([0.0, 0.01]), np.array([1.0, 1.0])), table[[-1, -1], 0])


def test_the_table_follows_the_binned_reference_where_it_is_clear_of_the_noise_and_nowhere_else():
    rng = np.random.default_rng(4)
    k = len(cal.COSINES)
    pairs = rng.uniform(0.001, 0.02, size=(k, k, k, 3))
    moments = cal.DecodedMoments(pairs, np.zeros((k, k, 3)))
    scale = rng.uniform(0.8, 1.2, size=(k, 3))
    d = rng.uniform(-0.3, 0.3, size=(k, k, 3))
    truth = scale[:, None, :] * scale[None, :, :] * (1.0 + (d + d.transpose(1, 0, 2)) / 2)
    target = cal.table_energy(pairs, truth)
    # a precise reference: the table is found (the small pull of the regulariser aside)
    table = cal.solve_table(moments, scale, target, 1e-5 * target)
    np.testing.assert_allclose(table, truth, rtol=0.02)
    np.testing.assert_array_equal(table, table.transpose(1, 0, 2))
    # a reference whose every bin is within its noise: the separable factors stand
    loose = cal.solve_table(moments, scale, target, 10.0 * target)
    np.testing.assert_allclose(loose, scale[:, None, :] * scale[None, :, :], rtol=1e-9)


@pytest.fixture(scope="module")
def plastic():
    stack = preset("lacquered_plastic")
    models = load_models("tiny", threads=2)
    z = encode_stack(stack, models)
    proxy = models.proxy_params(z)[0]
    return stack, models, z, proxy, cal.calibrate(stack, models, z, proxy)


def test_calibrated_albedo_matches_an_independent_reference_better_than_the_decoder(plastic):
    """The calibrated material's albedo (other importance samples than the factors were solved with)
    against reference walks with other seeds, at angles on and between the grid's."""
    stack, models, z, proxy, c = plastic
    cosines = np.cos(np.radians([0.0, 40.0, 65.0, 80.0, 85.0, 88.0]))
    ref, se = reference.albedo(stack, cal.grid_directions(cosines), samples=32768, seed=99)
    top = top_coat(stack)  # a remainder decoder's exact top lobe is part of the material's albedo
    a_cal = cal.decoded_albedo(models, z, *proxy, cosines, calibration=c, samples=32768, seed=7, top=top)
    a_plain = cal.decoded_albedo(models, z, *proxy, cosines, samples=32768, seed=7, top=top)
    err_cal = np.abs(a_cal / ref - 1).mean(axis=1)
    err_plain = np.abs(a_plain / ref - 1).mean(axis=1)
    # within a few percent at every angle (reference noise 1-2%, interpolation between grid angles)
    assert err_cal.max() < 0.05, err_cal
    assert err_cal.mean() < 0.5 * err_plain.mean(), (err_cal, err_plain)


def test_shrunk_targets_keep_the_decoded_albedo_within_the_noise_and_the_reference_beyond_it():
    decoded = np.full((4, 3), 0.2)
    stderr = np.full((4, 3), 0.01)
    gaps = np.array([0.0, 0.015, 0.1, 1.0])[:, None] * np.array([1.0, -1.0, 0.5])
    out = cal.shrink_target(decoded + gaps, decoded, stderr, k=2.0)
    np.testing.assert_allclose(out[:2], decoded[:2])  # within 2 sigma: the decoder stands
    moved = (out - decoded)[2:] / gaps[2:]
    assert (moved > 0.8).all() and (moved <= 1.0).all()  # clear gaps are followed (garrote, nearly unbiased)
    assert moved[1, 0] > moved[0, 0]  # the further off, the closer to the reference
    np.testing.assert_allclose(cal.shrink_target(decoded + gaps, decoded, stderr, k=0.0), decoded + gaps)
    with pytest.raises(ValueError, match="noise threshold"):
        cal.shrink_target(decoded, decoded, stderr, k=-1.0)


def test_remainder_calibration_targets_the_light_below_the_top_interface():
    """A remainder decoder's target comes from the walks without the top interface's first reflections:
    those walks carry the exact top lobe's albedo, and what is left is far less noisy than the difference
    of the full albedo and the top lobe's. The parts by exit direction add up to the whole."""
    from addon.core.neural.top_lobe import top_albedo

    stack = preset("lacquered_plastic")
    ref = cal.reference_parts(stack, seed=3)
    top = top_albedo(top_coat(stack), cal.COSINES, 65536, 0)[:, None]
    np.testing.assert_array_less(np.abs(ref.albedo - ref.below_top - top), 4 * ref.albedo_stderr + 0.002)
    assert (ref.below_top_stderr < ref.albedo_stderr).all()
    np.testing.assert_allclose(ref.by_exit.sum(axis=1), ref.albedo, rtol=1e-9)
    np.testing.assert_allclose(ref.below_top_by_exit.sum(axis=1), ref.below_top, rtol=1e-9)
    # a coating-free stack has no top lobe: the light below the top is all of it
    single = preset("frosted_copper")
    single = type(single)(base=single.base, coatings=())
    one = cal.reference_parts(single, walks=[64] * len(cal.COSINES), seed=1)
    np.testing.assert_array_equal(one.albedo, one.below_top)
    np.testing.assert_array_equal(one.by_exit, one.below_top_by_exit)


def test_the_renderer_evaluates_the_calibrated_lobe(plastic):
    stack, models, z, proxy, c = plastic
    rng = np.random.default_rng(2)
    wi = rng.normal(size=(64, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo = wi[::-1].copy()
    top = top_coat(stack)
    f = neural_material.NeuralMaterial(models, z, proxy, calibration=c, top=top).bind(None).eval(wi, wo)
    cos_phi = kernels.relative_azimuth_cosines(np.asarray(wi, float), np.asarray(wo, float))
    expected = models.eval_brdf(z, wi, wo) * c.factor(wi[:, 2], wo[:, 2], cos_phi)
    if models.top_transmission:  # the structural prior of the decoded remainder
        expected = expected * remainder_scale(top, wi, wo)[:, None]
    if models.remainder:  # the factors scale the decoded remainder; the exact top lobe is added as it is
        expected = expected + eval_top(top, wi, wo)[:, None]
    np.testing.assert_allclose(f, expected, rtol=1e-5)


def test_calibration_keeps_reciprocity_and_non_negative_finite_values(plastic):
    stack, models, z, proxy, c = plastic
    rng = np.random.default_rng(5)
    n = 4096
    wi = rng.normal(size=(n, 3))
    wo = rng.normal(size=(n, 3))
    wi[:, 2] = np.abs(wi[:, 2]) * rng.choice([1.0, 1e-4], size=n)  # many at the horizon
    wo[:, 2] = np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    cal_b = neural_material.NeuralMaterial(models, z, proxy, calibration=c).bind(None)
    plain = neural_material.NeuralMaterial(models, z, proxy).bind(None)
    f, g = cal_b.eval(wi, wo), cal_b.eval(wo, wi)
    assert np.isfinite(f).all() and (f >= 0).all()
    # the factor is symmetric in the two directions: the calibrated ratio f(wi, wo) / f(wo, wi) is the decoder's
    f0, g0 = plain.eval(wi, wo), plain.eval(wo, wi)
    ok = (f0 > 1e-6) & (g0 > 1e-6)
    np.testing.assert_allclose((f / g)[ok], (f0 / g0)[ok], rtol=1e-5)


def test_make_calibrates_on_request_and_reuses_only_what_the_session_made():
    stack = preset("frosted_copper")
    cal.clear_cache()
    assert neural_material.make(stack, size="tiny").calibration is None
    assert neural_material.make(stack, size="tiny", calibrate="cached").calibration is None  # nothing made yet
    made = neural_material.make(stack, size="tiny", calibrate=True).calibration
    assert made is not None
    assert neural_material.make(stack, size="tiny", calibrate="cached").calibration is made
    # the calibration belongs to the latent: another size has its own
    assert neural_material.make(stack, size="small", calibrate="cached").calibration is None


def test_bad_calibrate_settings_are_refused():
    stack = preset("frosted_copper")
    for bad in ("yes", 1, None, "Cached"):
        with pytest.raises(ValueError, match="calibrate must be True, False or 'cached'"):
            neural_material.make(stack, size="tiny", calibrate=bad)
        with pytest.raises(ValueError, match="calibrate must be True, False or 'cached'"):
            RenderSettings(calibrate=bad)
    with pytest.raises(ValueError, match="calibrate needs a Stack"):
        cal.calibrate("frosted_copper", None, None, (0.1, 0.5))
    models = load_models("tiny")
    z = encode_stack(stack, models)
    c = cal.calibrate(stack, models, z, models.proxy_params(z)[0])
    from addon.core.textures import LatentTexture

    tex = LatentTexture.from_texels(np.zeros((2, 2, 100), np.float32))
    with pytest.raises(ValueError, match="a latent texture takes a TextureCalibration"):
        neural_material.NeuralMaterial(models, None, (0.1, 0.5), tex, calibration=c)


def test_previews_use_the_calibration_a_render_made_and_make_none_themselves():
    from addon.core import preview

    stack = preset("varnished_wood")
    cal.clear_cache()
    wi = cal.grid_directions([0.9, 0.3, 0.05])
    wo = cal.grid_directions([0.5, 0.5, 0.5])
    before = preview.choose_brdf(stack, "NEURAL", size="tiny")
    assert cal._CACHE == {}  # a preview computes no calibration
    material = neural_material.make(stack, size="tiny", calibrate=True)
    after = preview.choose_brdf(stack, "NEURAL", size="tiny")
    # the preview shades as the renderer does: the calibrated decoded part (plus a remainder decoder's top lobe)
    np.testing.assert_allclose(after.brdf(wi, wo), material.bind(None).eval(wi, wo), rtol=1e-6)
    assert not np.allclose(after.brdf(wi, wo), before.brdf(wi, wo), rtol=1e-3)
    assert any("calibration" in n for n in after.notes)


def test_calibrated_albedo_of_held_out_stacks_is_within_five_percent_near_grazing():
    """The issue's albedo target at 75 and 85 degrees (median within 5%, no stack over 2x) on held-out
    stacks the calibration never saw, with independent reference walks (the set's directional albedo from
    analog walks of other seeds) and decoded samples (every fourth stack of tests/data/heldout_grazing.npz: one
    to four coatings)."""
    from pathlib import Path

    from addon.core.stack import Stack

    data = np.load(Path(__file__).resolve().parents[1] / "data" / "heldout_grazing.npz")
    stacks = [Stack.from_json(str(s)) for s in data["stacks"]][::4]
    angles = [list(data["angles"]).index(t) for t in (75.0, 85.0)]
    models = load_models("tiny")
    cosines = np.cos(np.radians([75.0, 85.0]))
    before, after = [], []
    for k, stack in enumerate(stacks):
        z = encode_stack(stack, models)
        proxy = models.proxy_params(z)[0]
        c = cal.calibrate(stack, models, z, proxy)
        ref = np.asarray(data["albedo_full"][4 * k, angles], dtype=np.float64)
        for out, calib in ((before, None), (after, c)):
            dec = cal.decoded_albedo(
                models, z, *proxy, cosines, calibration=calib, samples=8192, seed=9, top=top_coat(stack)
            )
            out.append(dec.mean(-1) / ref.mean(-1))
    before, after = np.array(before), np.array(after)
    assert np.all(np.abs(np.median(after, axis=0) - 1) < 0.05), np.median(after, axis=0)
    assert after.max() < 1.25 and after.min() > 0.8, after
    assert np.abs(after - 1).mean() < 0.5 * np.abs(before - 1).mean(), (after, before)


def test_a_calibration_stops_at_its_step_and_caches_nothing(plastic):
    """``step`` is called between the parts of a calibration (the viewport stops a stale one there): before each
    call of the decoder and each event of the reference walks. A step that raises stops the calibration, which
    caches nothing; a step that does not changes no figure."""
    stack, models, z, proxy, made = plastic
    decoder_calls = -(-len(cal.COSINES) * cal.DECODED_SAMPLES // cal.STEP_ROWS)

    class Stop(Exception):
        pass

    def stop_at(k):
        calls = []

        def step():
            calls.append(1)
            if len(calls) == k:
                raise Stop

        return step, calls

    walks = []
    real_parts = cal.reference_parts

    def counting_parts(*args, **kwargs):
        walks.append(1)
        return real_parts(*args, **kwargs)

    z = np.nextafter(z, np.float32(np.inf))  # a latent of its own: the fixture's calibration stays in the cache
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cal, "reference_parts", counting_parts)
        for k, walked in ((3, False), (decoder_calls + 2, True)):  # while decoding; at the walks' second event
            step, calls = stop_at(k)
            with pytest.raises(Stop):
                cal.calibrate(stack, models, z, proxy, step=step)
            assert len(calls) == k and bool(walks) == walked
            assert cal.cached(stack, models, z) is None
    steps = []
    again = cal.calibrate(stack, models, z, proxy, step=lambda: steps.append(1))
    assert cal.cached(stack, models, z) is again
    assert len(steps) > decoder_calls + 2  # the walks' events too
    np.testing.assert_allclose(again.table, made.table, rtol=1e-4)  # the latent moved by one float32 step
    np.testing.assert_allclose(again.calibrated, made.calibrated, rtol=1e-4)


def test_calibrations_on_disk_serve_a_later_session_and_a_damaged_one_is_made_again(plastic, tmp_path, monkeypatch):
    """With a disk cache (the add-on's: its extension's user folder) a calibration made once is found by a later
    session (an empty memory cache) without walks, as ``cached`` (the viewport's and thumbnails' mode) and as
    ``calibrate``; a damaged file is a miss, made again; the folder keeps the most recently used entries."""
    stack, models, z, proxy, _made = plastic
    z = np.nextafter(z, np.float32(-np.inf))  # a latent of its own
    monkeypatch.setattr(cal, "_CACHE", {})
    monkeypatch.setattr(cal, "_DISK_FOLDER", None)
    cal.use_disk_cache(tmp_path / "calibrations")
    first = cal.calibrate(stack, models, z, proxy)
    (entry,) = (tmp_path / "calibrations").glob("calibration_*.npz")

    walks = []
    real_parts = cal.reference_parts
    monkeypatch.setattr(cal, "reference_parts", lambda *a, **k: walks.append(1) or real_parts(*a, **k))
    monkeypatch.setattr(cal, "_CACHE", {})  # a new session
    again = cal.cached(stack, models, z)
    assert again is not None and cal.calibrate(stack, models, z, proxy) is again and not walks
    for name in ("table", "scale", "reference", "reference_stderr", "decoded", "calibrated", "top"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))

    entry.write_bytes(b"not a calibration")
    monkeypatch.setattr(cal, "_CACHE", {})
    assert cal.cached(stack, models, z) is None
    remade = cal.calibrate(stack, models, z, proxy)
    assert len(walks) == 1 and np.array_equal(remade.table, first.table)
    monkeypatch.setattr(cal, "_CACHE", {})
    assert cal.cached(stack, models, z) is not None  # written again, whole

    monkeypatch.setattr(cal, "MAX_DISK_ENTRIES", 2)
    for k in range(3):
        cal._to_disk(f"{k:064x}", first)
    kept = sorted(p.name for p in (tmp_path / "calibrations").glob("calibration_*.npz"))
    assert len(kept) == 2 and f"calibration_{0:064x}.npz" not in kept

    plain = tmp_path / "plain"
    plain.write_text("a file, not a folder")
    cal.use_disk_cache(plain)  # nothing can be stored there: the calibration is still made and used
    monkeypatch.setattr(cal, "_CACHE", {})
    assert cal.calibrate(stack, models, z, proxy) is not None and plain.is_file()
    cal.use_disk_cache(None)


def test_the_calibration_folder_loses_what_a_killed_writer_left(tmp_path, monkeypatch):
    """A session killed while it wrote a calibration left its temporary file in the folder for good."""
    import subprocess
    import sys

    from addon.core.textures import files

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".calibration_{0:064x}.npz.{files._HOST}-{dead.pid}-0123abcd.partial.npz"
    stale.write_bytes(b"")
    monkeypatch.setattr(cal, "_DISK_FOLDER", None)
    cal.use_disk_cache(tmp_path)
    assert not stale.exists()
    cal.use_disk_cache(None)


@pytest.mark.parametrize("threads", [1, 2])
def test_a_render_stopped_while_its_materials_calibrate_stops_there_and_caches_nothing(threads, monkeypatch):
    """A session's first render of a stack calibrates it (about a second of reference walks a stack) before its
    first path. A stop then (F12's Esc: Blender's ``test_break``, a function of the calling thread only) is heard
    between the calibration's steps, on whichever thread calibrates: the render raises ``Cancelled`` with its empty
    film, and no calibration is cached half made. Before, the render heard it only once every stack was
    calibrated."""
    import threading

    from addon.core.render import Cancelled, RenderSettings, render
    from tests.core.test_render import mixed_scene

    monkeypatch.setattr(cal, "_CACHE", {})
    monkeypatch.setattr(cal, "_DISK_FOLDER", None)  # this session's memory only
    started = []  # the calibrations begun (their decoded moments), and on which thread
    real_moments = cal.decoded_moments

    def moments(*args, **kwargs):
        started.append(threading.get_ident())
        return real_moments(*args, **kwargs)

    monkeypatch.setattr(cal, "decoded_moments", moments)
    home, polls = threading.get_ident(), []

    def test_break():  # says stop once a calibration has begun
        polls.append(threading.get_ident())
        return bool(started)

    scene = mixed_scene(8, 6, env=False)
    scene.materials = [preset("lacquered_plastic"), preset("red_car_paint")]
    with pytest.raises(Cancelled) as info:
        render(scene, RenderSettings(samples=2, max_bounces=2, threads=threads), stop=test_break)
    assert started and set(polls) == {home}  # stopped inside a calibration; polled on this thread only
    assert (threading.get_ident() in started) == (threads == 1)  # two stacks, two threads: calibrated on workers
    assert info.value.film.passes == 0 and info.value.film.count.sum() == 0
    assert cal._CACHE == {}
    # Not stopped, the same render calibrates both stacks and renders its passes.
    film, _ = render(scene, RenderSettings(samples=2, max_bounces=2, threads=threads), stop=lambda: False)
    assert film.passes == 2 and len(cal._CACHE) == 2


def test_a_coat_outside_the_trained_ior_range_calibrates_to_the_references_albedo():
    """A remainder decoder's material is the exact top lobe at the coat the decoders see (clamped into the trained
    ior range 1.05-2) plus the calibrated remainder, whose target was the light below the stack's *own* top. The two
    did not add up: a white base under an ior 3 coat read 0.68x the reference at normal incidence, under an ior
    1.02 coat 1.08x at grazing. The renderer's top lobe now keeps the coating's own ior."""
    models = load_models("tiny", threads=2)
    for ior in (3.0, 1.02):
        stack = Stack(Diffuse((0.8, 0.8, 0.8)), (Coating(roughness=0.1, ior=ior),))
        assert not cal.top_clamped(StackArrays.from_stacks([stack])).any()
        material = neural_material.make(stack, size="tiny", calibrate=True)
        got = cal.decoded_albedo(
            models, material.z, material.sigma, material.w, cal.COSINES, material.calibration, seed=7, top=material.top
        )
        ref = cal.reference_parts(stack, seed=11).albedo  # other walks than the calibration's
        ratio = got / ref
        assert np.all(np.abs(ratio - 1) < 0.05), (ior, ratio[:, 1])


def test_an_index_matched_coat_over_a_black_base_renders_black_at_grazing():
    """A coat of ior 1 reflects nothing; the renderer added its top lobe at the trained 1.05, which reflects much at
    grazing, and no calibration of the remainder can take light away from the exact lobe: a black base under it
    rendered 0.066 at 80 degrees and 0.147 at 87 (the reference: 0). The top lobe is the stack's own below 1.05."""
    from benchmarks.bench_stack_sweep import white_sky_albedo

    stack = Stack(Diffuse((0.0, 0.0, 0.0)), (Coating(roughness=0.1, ior=1.0),))
    assert white_sky_albedo(stack, 80.0, "neural", 64, seed=2).max() < 0.01


def test_an_opaque_coat_of_ior_3_renders_its_interfaces_reflection():
    """Under an opaque absorbing coat only the coat's interface reflects. The renderer's top lobe took the trained
    ior 2, which reflects less, and the calibration cannot brighten a remainder of nothing: the coat rendered 0.56
    of the reference at 20 degrees (the calibration's factors at their bound, 10). The lobe keeps the own ior."""
    import math

    from addon.core import reference
    from benchmarks.bench_stack_sweep import white_sky_albedo

    stack = Stack(Dielectric(0.0, 1.43), (Coating(roughness=0.37, ior=3.08, thickness=17.7),))
    t = math.radians(20.0)
    truth, _ = reference.albedo(stack, np.array([[0.0, -math.sin(t), math.cos(t)]]), samples=20000, seed=4)
    np.testing.assert_allclose(white_sky_albedo(stack, 20.0, "neural", 64, seed=2), truth[0], rtol=0.05)


def test_calibrations_of_a_top_outside_the_trained_ior_made_with_the_lobe_at_the_bound_are_not_found():
    """A calibration on disk is found by its key. The top lobe takes the coating's own ior now; calibrations made
    with it at the trained bound (a rough ior-3 coat's key had lost the clamped-top rule and became the one of
    before that rule: rendered 0.89-0.97 of the reference) must not be found again."""
    from addon.core.neural import top_lobe

    inside = Stack(Diffuse((0.8, 0.8, 0.8)), (Coating(roughness=0.1, ior=1.5),))
    assert not cal.stack_settings_key(inside).endswith(top_lobe.OWN_TOP_IOR)
    for ior, roughness in ((3.0, 0.1), (3.0, 0.0), (1.02, 0.1)):
        stack = Stack(Diffuse((0.8, 0.8, 0.8)), (Coating(roughness=roughness, ior=ior),))
        key = cal.stack_settings_key(stack)
        assert key.endswith(top_lobe.OWN_TOP_IOR) and key not in (cal.settings_key(), cal.settings_key() + cal.TOP_RULE)


def _assert_albedo_as_the_reference(stack, material, views, calibration, rtol=0.06):
    """The material's decoded albedo under ``calibration`` equals the reference's at each view (degrees)."""
    import math

    from addon.core import reference

    for view in views:
        t = math.radians(view)
        wo = np.array([[0.0, -math.sin(t), math.cos(t)]])
        got = cal.decoded_albedo(
            material.models, material.z, material.sigma, material.w, wo[:, 2], calibration, seed=7, top=material.top
        )
        truth, _ = reference.albedo(stack, wo, samples=20000, seed=1)
        np.testing.assert_allclose(got[0], truth[0], rtol=rtol, err_msg=f"{view} degrees")


def test_a_near_mirror_metal_under_a_clear_coat_keeps_its_albedo_between_the_grids_angles():
    """The table's exit bins split a near-mirror lobe between two grid nodes, and the entries off the diagonal went
    to their bounds: between the nodes the calibrated material lost its light (a conductor of alpha 0.01 under a
    coat of 0.01: 39% dark at 20 degrees, its render too). Such a narrow lobe keeps the separable factors within 70
    degrees of the normal, where the grid is coarse."""
    from addon.core.stack import Conductor

    stack = Stack(Conductor(0.01, eta=(1.23, 1.77, 1.62), k=(3.08, 5.15, 4.33)), (Coating(roughness=0.01, ior=1.47),))
    material = neural_material.make(stack, size="tiny", calibrate=True)
    assert cal.narrow_lobe(material.sigma)
    _assert_albedo_as_the_reference(stack, material, (10.0, 20.0, 60.0), material.calibration)
    wide = neural_material.make(preset("coated_gold"), size="tiny", calibrate=False)
    assert not cal.narrow_lobe(wide.sigma)  # the presets keep the table
    # a latent texture of it, calibrated as a bake calibrates a cluster (it kept the table: 41% dark at 20 degrees)
    rows = 4
    texels = cal.calibrate_texels(
        StackArrays.from_stacks([stack] * rows), material.models, np.repeat(material.z[None], rows, axis=0),
        np.tile([material.sigma, material.w], (rows, 1)), np.tile(material.top, (rows, 1)),
    )  # fmt: skip
    _assert_albedo_as_the_reference(stack, material, (20.0,), texels)


def test_a_polished_metal_under_a_dense_clear_coat_keeps_its_albedo_between_the_grids_angles():
    """The sampling network sees a coat's ior clamped to 2, so a narrow lobe under an ior-3 coat has a wide proxy;
    its table went far from separable along the diagonal, and between the nodes the material read 1.24 of the
    reference (20 degrees). Such a table keeps the separable factors where the grid is coarse."""
    from addon.core.stack import Conductor

    stack = Stack(Conductor(0.04, eta=(1.23, 1.77, 1.62), k=(3.08, 5.15, 4.33)), (Coating(roughness=0.05, ior=3.0),))
    material = neural_material.make(stack, size="tiny", calibrate=True)
    coarse = np.flatnonzero(np.asarray(cal.COSINES) >= cal.COARSE_COS)
    assert cal.diagonal_mismatch(material.calibration.table, coarse) < 1e-9
    _assert_albedo_as_the_reference(stack, material, (10.0, 20.0, 45.0), material.calibration)


@pytest.mark.parametrize(
    "stack",
    [
        Stack(Diffuse(1.0), (Coating(0.0, 1.5, 1.0, 0.0, 0.0),)),
        Stack(Diffuse(0.8), (Coating(0.0, 1.5, 1.0, 0.0, 0.0),)),
        Stack(Conductor(0.0, (0.2, 0.2, 0.2), (8.0, 8.0, 8.0)), (Coating(0.0, 1.5, 1.0, 0.0, 0.0),)),
    ],
    ids=["white-under-smooth-clear", "grey-under-smooth-clear", "smooth-metal-under-smooth-clear"],
)
def test_a_smooth_top_coat_calibrates_to_its_reference_albedo_not_above(stack):
    """A clear coat of roughness 0, the usual lacquer: the renderer's top lobe is the clamped one (alpha 0.01), whose
    reflection near grazing spreads over the exit bins beside the mirror's. Taken bin by bin, the difference asked
    the remainder for negative light beside the mirror bin and more in it: the calibration's own albedo was 1.115 of
    the reference over white (1.10 rendered at 80 degrees), and 1.32 over a smooth metal, its table at its bounds."""
    material = neural_material.make(stack, calibrate=True)
    c = material.calibration
    ratio = c.calibrated / np.maximum(c.reference, 1e-6)
    assert ratio.max() < 1.04 and ratio.min() > 0.95, ratio.round(3)

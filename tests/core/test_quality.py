"""The "auto" quality setting: decoder choice by measured error, texture resolution by footprint."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from addon.core import quality
from addon.core.neural import MODEL_DIR
from addon.core.neural import SIZES as ALL_SIZES
from addon.core.render import shapes
from addon.core.render.demo_scene import demo_scene
from addon.core.render.materials import LambertMaterial
from addon.core.render.scene import Camera, Mesh, Scene
from addon.core.stack import PRESETS, Dielectric, Diffuse, Stack

SIZES = quality.available_sizes()

SIMPLE = Stack(Diffuse((0.8, 0.8, 0.8)))
# A near-mirror dielectric: a sharp lobe with a strong Fresnel rise, the hardest single layer.
DEMANDING = Stack(Dielectric(roughness=0.02, ior=1.5))


def test_available_sizes_are_shipped_and_ordered_by_parameters():
    assert sorted(SIZES) == sorted(ALL_SIZES), f"shipped: {SIZES}"  # the models are committed
    params = [json.loads((MODEL_DIR / f"decoder_{s}.json").read_text())["parameters"] for s in SIZES]
    assert params == sorted(params)
    for s in SIZES:
        assert (MODEL_DIR / f"decoder_{s}.onnx").exists() and (MODEL_DIR / f"encoder_{s}.onnx").exists()


def test_simple_stack_picks_the_smallest_decoder():
    choice = quality.choose_decoder(SIMPLE, tolerance=0.15, cache=quality.ErrorCache())
    assert choice.size == SIZES[0]
    assert choice.met
    assert list(choice.errors) == [SIZES[0]]  # the search stops at the first size that fits
    assert 0.0 <= choice.errors[SIZES[0]] <= 0.15


def test_only_cached_reads_what_was_measured_and_never_measures(monkeypatch):
    """The viewport's choice (``only_cached``): no reference walks at an edit (1-2 s each, on Blender's main
    thread, at every tick of a slider); the default size with a note until a render measured the stack, then
    the measured choice."""
    from addon.core.neural.models import resolve_size

    cache = quality.ErrorCache()
    measuring = quality.reference_lobes
    monkeypatch.setattr(quality, "reference_lobes", lambda *a, **k: pytest.fail("measured in only_cached"))
    first = quality.choose_decoder(DEMANDING, 0.15, cache=cache, only_cached=True)
    assert first.size == resolve_size() and not first.met and math.isnan(first.errors[SIZES[0]])
    assert "not measured yet" in quality.choice_reason("m", first)
    monkeypatch.setattr(quality, "reference_lobes", measuring)
    measured = quality.choose_decoder(DEMANDING, 0.15, cache=cache)
    monkeypatch.setattr(quality, "reference_lobes", lambda *a, **k: pytest.fail("measured in only_cached"))
    assert quality.choose_decoder(DEMANDING, 0.15, cache=cache, only_cached=True) == measured


def test_demanding_stack_needs_more_than_the_simple_one():
    cache = quality.ErrorCache()
    e_simple = quality.measured_error(SIMPLE, SIZES[0], cache=cache)
    e_hard = quality.measured_error(DEMANDING, SIZES[0], cache=cache)
    assert e_hard > 2 * e_simple
    tol = math.sqrt(e_simple * e_hard)  # between the two: the smallest size serves only the simple stack
    assert quality.choose_decoder(SIMPLE, tol, cache=cache).size == SIZES[0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        hard = quality.choose_decoder(DEMANDING, tol, cache=cache)
    assert hard.size != SIZES[0] or not hard.met
    if hard.met:  # a larger shipped size meets it: the smallest such one
        assert SIZES.index(hard.size) > 0
        assert all(hard.errors[s] > tol for s in SIZES[: SIZES.index(hard.size)])
    else:  # none does: the most accurate measured size, and the user is told
        assert hard.size == min(hard.errors, key=hard.errors.get)
        assert list(hard.errors) == SIZES
        assert any(issubclass(w.category, quality.QualityWarning) for w in caught)


def test_an_error_measured_against_an_earlier_reference_estimator_is_measured_again(monkeypatch):
    """The cache keys on what the reference estimates: errors measured before a fix of its expectation (the light a
    mirror brings back to a medium vertex) were measured against a wrong lobe."""
    from addon.core import reference

    before = quality.error_key(DEMANDING, "tiny")
    monkeypatch.setattr(reference, "ESTIMATOR_VERSION", reference.ESTIMATOR_VERSION + 1)
    assert quality.error_key(DEMANDING, "tiny") != before


def test_rule_smallest_size_under_tolerance_from_cached_measurements(tmp_path):
    """The selection rule on recorded errors (as read back from the on-disk cache)."""
    cache = quality.ErrorCache(tmp_path)
    errors = {"tiny": 0.30, "small": 0.12, "medium": 0.05, "paper": 0.04}
    for size, err in errors.items():
        cache.put(quality.error_key(DEMANDING, size), err)
    reread = quality.ErrorCache(tmp_path)
    sizes = list(errors)
    assert quality.choose_decoder(DEMANDING, 0.2, sizes=sizes, cache=reread).size == "small"
    assert quality.choose_decoder(DEMANDING, 0.06, sizes=sizes, cache=reread).size == "medium"
    assert quality.choose_decoder(DEMANDING, 0.5, sizes=sizes, cache=reread).size == "tiny"
    with pytest.warns(quality.QualityWarning, match="most accurate one, paper"):
        c = quality.choose_decoder(DEMANDING, 0.01, sizes=sizes, cache=reread)
    assert c.size == "paper" and not c.met
    with pytest.warns(quality.QualityWarning, match="reference estimator"):
        c = quality.choose_decoder(DEMANDING, 0.01, sizes=sizes, cache=reread, fallback="reference")
    assert c.size is None and not c.met


def test_measured_errors_are_cached_on_disk_and_a_damaged_cache_is_ignored(tmp_path):
    c1 = quality.choose_decoder(SIMPLE, 0.5, cache_dir=tmp_path)
    data = json.loads((tmp_path / "decoder_errors.json").read_text())
    assert list(data.values()) == [pytest.approx(c1.errors[SIZES[0]])]
    c2 = quality.choose_decoder(SIMPLE, 0.5, cache=quality.ErrorCache(tmp_path))
    assert c2.errors == c1.errors
    for damaged in ("{not json", '{"k": null}', '{"k": [1]}', "[1, 2]"):  # the add-on reads it as it registers
        (tmp_path / "decoder_errors.json").write_text(damaged)
        assert quality.ErrorCache(tmp_path).data == {}


def test_the_default_cache_kept_on_disk_serves_a_later_session(tmp_path, monkeypatch):
    """``use_disk_cache`` (the add-on's: its extension's user folder) keeps what Auto measures without a cache of
    its own: a later session (the cache read again) chooses without measuring; an unwritable folder only loses
    the file."""
    monkeypatch.setattr(quality, "_DEFAULT_CACHE", quality.ErrorCache())
    quality.use_disk_cache(tmp_path / "quality")
    try:
        first = quality.choose_decoder(SIMPLE, 0.5)
        assert (tmp_path / "quality" / "decoder_errors.json").is_file()
        quality.use_disk_cache(tmp_path / "quality")  # a new session

        def no_measuring(*args, **kwargs):
            raise AssertionError("measured again")

        monkeypatch.setattr(quality, "decoder_lobes", no_measuring)
        assert quality.choose_decoder(SIMPLE, 0.5).errors == first.errors
        plain = tmp_path / "plain"
        plain.write_text("a file, not a folder")
        quality.use_disk_cache(plain)
        quality._DEFAULT_CACHE.put("key", 0.1)
        assert quality._DEFAULT_CACHE.get("key") == 0.1 and plain.is_file()
    finally:
        quality.use_disk_cache(None)


def test_sizes_that_cannot_encode_the_stack_fall_back_to_the_reference(tmp_path, monkeypatch):
    """A size whose models are not shipped (or cannot encode the stack) is never chosen, nor cached."""
    from addon.core.neural import models

    missing = "paper"  # every size is shipped: take the paper size's models away for this test
    empty = tmp_path / "models"
    empty.mkdir()
    monkeypatch.setattr(models, "MODEL_DIR", empty)
    monkeypatch.setattr(models, "_CACHE", {})
    with pytest.warns(quality.QualityWarning, match="reference estimator"):
        c = quality.choose_decoder(PRESETS["coated_gold"], 0.2, sizes=[missing], cache=quality.ErrorCache(tmp_path))
    assert c.size is None and not c.met and math.isinf(c.errors[missing])
    assert not (tmp_path / "decoder_errors.json").exists()


def test_layered_stacks_get_a_measured_error():
    err = quality.measured_error(PRESETS["coated_gold"], SIZES[0], cache=quality.ErrorCache())
    assert math.isfinite(err) and err > 0.0


def test_auto_measures_the_material_as_the_renderer_shades_it_calibrated():
    """A default render shades the calibrated material, so Auto measures that one: the error is that of
    the renderer's material, "cached" measures it only once a render has made the calibration, each has
    its own cache entry, and the calibrated lobes carry the reference's brightness more closely."""
    from addon.core import lobe
    from addon.core.neural import calibrate as cal

    stack = PRESETS["varnished_wood"]
    cal.clear_cache()
    cache = quality.ErrorCache()
    plain = quality.measured_error(stack, "tiny", cache=cache)
    assert quality.measured_error(stack, "tiny", cache=cache, calibrate="cached") == plain  # none made yet
    calibrated = quality.measured_error(stack, "tiny", cache=cache, calibrate=True)
    assert quality.measured_error(stack, "tiny", cache=cache, calibrate="cached") == calibrated
    assert len(cache.data) == 2 and calibrated != plain
    shaded = quality.neural_material(stack, "tiny", calibrate=True).bind(None)  # what the renderer shades
    ref, se = quality.reference_lobes(stack)
    pred = np.stack([lobe.lobe_image(shaded.eval, t, quality.LOBE_RES) for t in lobe.INCIDENT_ANGLES_DEG])
    assert calibrated == pytest.approx(quality.noise_corrected_error(pred, ref, se), rel=1e-9)
    assert quality.choose_decoder(stack, 1.0, sizes=["tiny"], cache=cache, calibrate=True).errors == {
        "tiny": calibrated
    }
    # brightness per incidence (a lobe image's sum against the reference's), over the layered presets
    off = {False: [], True: []}
    for st in PRESETS.values():
        if st.coatings:
            r = quality.reference_lobes(st)[0].sum(axis=(1, 2, 3))
            for c in off:
                off[c].append(np.abs(quality.decoder_lobes(st, "tiny", calibrate=c).sum(axis=(1, 2, 3)) / r - 1))
    # (the calibration scales a remainder decoder's decoded part only: its exact top lobe was right already)
    assert np.mean(off[True]) < 0.95 * np.mean(off[False]), (np.mean(off[True]), np.mean(off[False]))
    with pytest.raises(ValueError, match="calibrate must be"):
        quality.measured_error(stack, "tiny", cache=cache, calibrate="yes")


def test_out_of_range_parameters_are_clamped_and_the_note_is_kept():
    stack = Stack(Dielectric(roughness=0.3, ior=3.0))  # above the trained ior range [1.05, 2]
    c = quality.choose_decoder(stack, 100.0, cache=quality.ErrorCache())
    assert c.met and any("clamped" in n and "ior" in n for n in c.notes)
    # the clamp's cost is part of the measured error: the same stack at ior 2 is closer
    assert c.errors[SIZES[0]] > quality.measured_error(Stack(Dielectric(roughness=0.3, ior=2.0)), SIZES[0])


@pytest.mark.parametrize("tol", [0.0, -0.1, float("nan"), "abc", None])
def test_bad_tolerance_is_rejected(tol):
    with pytest.raises(ValueError, match="tolerance"):
        quality.choose_decoder(SIMPLE, tol)


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError, match="Stack"):
        quality.choose_decoder({"base": "Diffuse"}, 0.2)
    with pytest.raises(ValueError, match="fallback"):
        quality.choose_decoder(SIMPLE, 0.2, fallback="largest")


def test_noise_corrected_error_removes_the_reference_noise():
    rng = np.random.default_rng(0)
    truth = rng.random((4, 16, 16, 3)) + 0.5
    se = np.full_like(truth, 0.1)
    noisy_ref = truth + rng.normal(size=truth.shape) * se
    raw = quality.noise_corrected_error(truth, noisy_ref)
    corrected = quality.noise_corrected_error(truth, noisy_ref, se)
    assert raw > 0.08  # the noise alone, about 0.1 / rms(truth)
    assert corrected < 0.25 * raw
    off = truth * 1.2  # a real 20% error survives the correction
    assert quality.noise_corrected_error(off, noisy_ref, se) == pytest.approx(0.2, rel=0.15)


def test_reference_lobes_of_a_single_layer_stack_are_exact():
    ref, se = quality.reference_lobes(Stack(Diffuse((0.5, 0.5, 0.5))), res=8)
    assert ref.shape == (4, 8, 8, 3) and np.all(se == 0)
    from addon.core import lobe

    # a Lambertian's directional albedo is its albedo at every incidence
    for img in ref:
        assert lobe.albedo_from_lobe(img) == pytest.approx([0.5] * 3, rel=0.05)


# --------------------------------------------------------------------------- textures


@pytest.mark.parametrize(
    "fp, source, expected",
    [
        (1 / 300, (2048, 2048), (512, 512)),
        (1 / 256, (2048, 2048), (256, 256)),
        (1 / 300, (256, 256), (256, 256)),  # never finer than the source
        (1 / 100, (1024, 2048), (64, 128)),  # aspect kept, longer side decides
        (1 / 100, (999, 1000), (128, 128)),  # rounded up on the short side
        (2.0, (512, 512), (1, 1)),  # a footprint larger than the texture
        (math.inf, (512, 512), (1, 1)),  # not seen
    ],
)
def test_texture_resolution_for_footprint(fp, source, expected):
    assert quality.texture_resolution_for_footprint(fp, source) == expected


def test_texture_resolution_min_size_and_bad_input():
    assert quality.texture_resolution_for_footprint(math.inf, (512, 512), min_size=16) == (16, 16)
    for fp in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="footprint"):
            quality.texture_resolution_for_footprint(fp, (64, 64))
    with pytest.raises(ValueError, match="source"):
        quality.texture_resolution_for_footprint(0.1, (0, 64))


def test_primary_footprints_follow_the_image_resolution():
    lo = quality.primary_footprints(demo_scene(80, 45))
    hi = quality.primary_footprints(demo_scene(160, 90))
    assert lo.shape == hi.shape == (6,)
    assert np.all(np.isfinite(lo)) and np.all(lo > 0)
    # twice the pixels across: half the footprint, hence twice the texels (up to sampling of the minimum)
    assert np.allclose(hi / lo, 0.5, rtol=0.15)
    res = [quality.texture_resolution_for_footprint(f, (4096, 4096)) for f in hi]
    assert all(r[0] <= 4096 for r in res)


def test_primary_footprints_of_an_unseen_material_are_infinite():
    cam = Camera.look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), fov_deg=40.0, width=32, height=32)
    seen = shapes.uv_sphere((0.0, 0.0, 0.0), 0.5, 16, 8, material=0)
    behind = shapes.uv_sphere((0.0, -8.0, 0.0), 0.5, 16, 8, material=1)
    scene = Scene(
        cam, Mesh.concatenate([seen, behind]), [LambertMaterial(), LambertMaterial()], [], None, ["seen", "behind"]
    )
    fp = quality.primary_footprints(scene)
    assert math.isfinite(fp[0]) and fp[0] > 0 and math.isinf(fp[1])


# --------------------------------------------------------------------------- renderer materials


def test_assign_decoders_auto_gives_every_encodable_layered_material_its_decoder():
    from addon.core.render import RenderSettings, render
    from addon.core.render.materials import LayeredSpec
    from addon.core.render.neural_material import NeuralMaterial

    scene = demo_scene(16, 9)
    mats, choices, notes = quality.assign_decoders(scene, "auto", 0.3, res=8, walks=16, cache=quality.ErrorCache())
    assert mats[0] is scene.materials[0]  # the textured floor is not a stack
    assert set(choices) == set(scene.material_names[1:])
    for name, m in zip(scene.material_names[1:], mats[1:], strict=True):
        c = choices[name]
        if c.size is None:
            assert isinstance(m, LayeredSpec)
        else:
            assert isinstance(m, NeuralMaterial) and m.models.size == c.size
            assert c.met or any(name in n and "tolerance" in n for n in notes)
    scene.materials = mats
    film, stats = render(scene, RenderSettings(samples=1, max_bounces=2))
    assert np.isfinite(film.mean()).all()
    assert {stats.material_kinds[i] for i in range(1, 6)} <= {"neural", "reference"}


def test_assign_decoders_with_the_reference_as_fallback_renders_the_reference():
    """fallback="reference": a stack no size fits renders with the reference estimator, as its note says (it
    rendered on the default decoder: the spec went back as it was, and neural mode encoded it)."""
    from addon.core.render.materials import ReferenceLayered, resolve

    scene = demo_scene(16, 9)
    mats, choices, notes = quality.assign_decoders(
        scene, "auto", 1e-4, fallback="reference", res=8, walks=16, cache=quality.ErrorCache()
    )
    assert any("reference estimator" in n for n in notes)
    fell_back = [m for name, m in zip(scene.material_names[1:], mats[1:], strict=True) if choices[name].size is None]
    assert fell_back  # (a lobe whose measured error is within the reference's noise fits any tolerance)
    assert all(isinstance(resolve(m, "neural"), ReferenceLayered) for m in fell_back)


def test_assign_decoders_fixed_size_and_what_stays_untouched():

    scene = demo_scene(16, 9, presets=["coated_gold", "white_diffuse"])
    mats, choices, notes = quality.assign_decoders(scene, SIZES[0])
    assert mats[2] is scene.materials[2]  # no coating: rendered exactly by its analytic BSDF
    assert type(mats[1]).__name__ == "NeuralMaterial" and mats[1].models.size == SIZES[0]
    with pytest.raises(ValueError, match="quality"):
        quality.assign_decoders(scene, "huge")


def test_camera_hits_give_the_renderers_footprint_on_a_facing_quad():
    """A 2 x 2 quad (uvs span [0, 1]: 0.5 uv units per world unit) 4 units in front of the camera:
    the footprint at the image centre is 4 x pixel spread x 0.5; tilting the quad by 60 degrees
    stretches it by 1 / sqrt(cos 60); a miss is -1 / inf."""
    from addon.core.kernels import texture_footprint
    from addon.core.render.integrator import camera_hits

    cam = Camera.look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), fov_deg=30.0, width=33, height=33)
    facing = shapes.quad((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    scene = Scene(cam, facing, [LambertMaterial()], [], None, ["quad"])
    prim, fp = camera_hits(scene, [16, 0], [16, 0])
    assert prim[0] >= 0 and prim[1] == -1 and math.isinf(fp[1])
    np.testing.assert_allclose(fp[0], 4.0 * cam.pixel_spread * 0.5, rtol=1e-6)
    c, s = math.cos(math.radians(60.0)), math.sin(math.radians(60.0))
    tilted = shapes.quad((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, -s, c))  # normal 60 deg from the view ray
    prim, fp = camera_hits(Scene(cam, tilted, [LambertMaterial()], [], None, ["quad"]), [16], [16])
    np.testing.assert_allclose(fp[0], 4.0 * cam.pixel_spread * 0.5 / math.sqrt(c), rtol=1e-6)
    # the grazing floor: |cos| below 0.05 counts as 0.05
    np.testing.assert_allclose(texture_footprint(1.0, 1e-9, 2.0), 2.0 / math.sqrt(0.05))
    # A plane facing a pinhole camera is the same number of texels a pixel everywhere: a wide view's corner has the
    # centre's footprint (one spread for every ray made it 2.3x larger at 90 degrees, 4.3x at 120).
    for fov in (40.0, 90.0, 120.0):
        wide = Camera.look_at((0.0, -1.0, 0.0), (0.0, 0.0, 0.0), fov_deg=fov, width=33, height=33)
        plane = shapes.quad((-50.0, 0.0, -50.0), (100.0, 0.0, 0.0), (0.0, 0.0, 100.0))
        prim, fp = camera_hits(Scene(wide, plane, [LambertMaterial()], [], None, ["plane"]), [16, 0, 32], [16, 0, 0])
        assert (prim >= 0).all()
        np.testing.assert_allclose(fp[1:], fp[0], rtol=1e-3)


def test_a_size_with_a_damaged_card_is_not_available_and_says_why(tmp_path):
    import shutil

    for f in MODEL_DIR.glob("*"):
        if f.name.startswith(("decoder_", "encoder_")) and ("tiny" in f.name or "small" in f.name):
            shutil.copy(f, tmp_path / f.name)
    (tmp_path / "decoder_tiny.json").write_text("{")
    with pytest.warns(quality.QualityWarning, match="decoder size tiny is not available: .*decoder_tiny.json"):
        assert quality.available_sizes(tmp_path) == ["small"]


def test_a_disk_backed_error_cache_keeps_every_entry_put_from_two_threads(tmp_path, monkeypatch):
    """The viewport and an F12 render may measure at once: an entry put while another thread is still writing its
    file reaches the file. Thread A's write is held until thread B's put has returned (or 0.5 s have passed): without
    the cache's lock, A's older snapshot would replace B's newer file and B's entry would be lost on disk."""
    import threading

    from addon.core.textures import files

    real_write = files.write_bytes
    a_writing, b_done = threading.Event(), threading.Event()

    def held_write(path, data):
        if threading.current_thread().name == "A":
            a_writing.set()
            b_done.wait(0.5)
        real_write(path, data)

    monkeypatch.setattr(files, "write_bytes", held_write)
    cache = quality.ErrorCache(tmp_path)
    a = threading.Thread(target=cache.put, args=("a", 1.0), name="A")
    a.start()
    assert a_writing.wait(5.0)
    cache.put("b", 2.0)
    b_done.set()
    a.join()
    assert quality.ErrorCache(tmp_path).data == {"a": 1.0, "b": 2.0}


def test_a_stopped_choice_raises_cancelled_before_it_measures(monkeypatch):
    """F12's Esc during "Choosing decoders" (seconds a new stack): heard before each size's measurement."""
    from addon.core.render import Cancelled

    monkeypatch.setattr(quality, "reference_lobes", lambda *a, **k: pytest.fail("measured after the stop"))
    with pytest.raises(Cancelled, match="decoder choice was stopped"):
        quality.choose_decoder(DEMANDING, 0.15, cache=quality.ErrorCache(), stop=lambda: True)


def test_a_reason_says_an_error_below_the_references_noise_as_such():
    """The measured error is less the reference's noise: a thick coat's noisy walks made it 0, said as "measured
    error 0", which reads as exact."""
    choice = quality.DecoderChoice("tiny", 0.2, {"tiny": 0.0}, True)
    reason = quality.choice_reason("thick", choice)
    assert "within the reference's own noise" in reason and "error 0" not in reason
    assert "measured error 0.05" in quality.choice_reason("m", quality.DecoderChoice("tiny", 0.2, {"tiny": 0.05}, True))


def test_a_choice_hears_its_stop_inside_a_measurement(monkeypatch):
    """A thick scattering coat's reference walks took minutes, and the stop was heard only before each size: F12's
    Esc went unheard for 19-108 s. The walks now call the choice's stop between their events."""
    from addon.core.render import Cancelled
    from addon.core.stack import Coating, Diffuse, Stack

    thick = Stack(Diffuse((0.8, 0.8, 0.8)), (Coating(roughness=0.3, ior=1.5, albedo=(1.0, 1.0, 1.0), thickness=5.0),))
    calls = []

    def stop():
        calls.append(1)
        return len(calls) > 3  # after the first size's check, inside its measurement

    monkeypatch.setattr(quality, "decoder_lobes", lambda *a, **k: np.zeros((4, 8, 8, 3)))
    with pytest.raises(Cancelled, match="decoder choice was stopped"):
        quality.choose_decoder(thick, 0.15, sizes=[SIZES[0]], cache=quality.ErrorCache(), res=8, stop=stop)
    assert len(calls) == 4  # stopped at the walks' third event, not after the measurement


def test_a_reference_render_hears_its_stop_between_the_walks_events(monkeypatch):
    """A reference-mode render of a thick coat heard Esc only between bounces (50 s at 96 x 64): the chunks' walks
    now call the render's stop between their events."""
    import threading

    from addon.core.reference import walk
    from addon.core.render import Camera, Cancelled, Environment, RenderSettings, Scene, render
    from addon.core.stack import Coating, Diffuse, Stack

    thick = Stack(Diffuse((0.8, 0.8, 0.8)), (Coating(roughness=0.3, ior=1.5, albedo=(1.0, 1.0, 1.0), thickness=5.0),))
    cam = Camera.look_at((0, -3, 0), (0, 0, 0), fov_deg=30, width=8, height=8)
    scene = Scene(cam, shapes.uv_sphere((0, 0, 0), 1.0, 12, 6), [thick], [])
    scene.environment = Environment((1.0, 1.0, 1.0))
    events = []
    run = walk._RandomWalk.run

    def counted(self, alive_per_event=None, step=None):
        def check():
            events.append(1)
            if len(events) == 5:
                stopped.set()
            if step is not None:
                step()

        return run(self, alive_per_event, check)

    stopped = threading.Event()
    monkeypatch.setattr(walk._RandomWalk, "run", counted)
    with pytest.raises(Cancelled):
        render(scene, RenderSettings(samples=4, max_bounces=1, mode="reference", threads=1), stop=stopped.is_set)
    assert len(events) < 50  # ended within the walks, a few events after the stop


def test_the_error_cache_keeps_the_most_recent_entries_and_cleans_a_killed_writers_files(tmp_path, monkeypatch):
    """decoder_errors.json grew for good (one entry a stack, size and setting: the file is written whole at each)
    and a session killed while writing it left its temporary file there."""
    import subprocess
    import sys

    from addon.core.textures import files

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".decoder_errors.json.{files._HOST}-{dead.pid}-0123abcd.partial.json"
    stale.write_text("{")
    monkeypatch.setattr(quality, "MAX_ERROR_ENTRIES", 3)
    cache = quality.ErrorCache(tmp_path)
    assert not stale.exists()
    for i in range(5):
        cache.put(f"k{i}", float(i))
    cache.put("k2", 2.5)  # measured again: the most recent now
    assert list(quality.ErrorCache(tmp_path).data.items()) == [("k3", 3.0), ("k4", 4.0), ("k2", 2.5)]


def test_a_black_stack_measures_a_finite_error_and_is_not_called_unencodable():
    """A black base under an index-matched coat reflects nothing: every relative error was infinite, and Auto said
    no shipped decoder could encode the stack (it renders with the reference). The error is now relative to at
    least ``ERROR_FLOOR`` a value: finite, and the chosen size is a decoder."""
    from addon.core.stack import Coating, Diffuse, Stack

    black = Stack(Diffuse((0.0, 0.0, 0.0)), (Coating(roughness=0.3, ior=1.0),))
    ref, _ = quality.reference_lobes(black)
    assert float(np.abs(ref).sum()) == 0.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        choice = quality.choose_decoder(black, 0.2, sizes=[SIZES[0]], cache=quality.ErrorCache())
    assert choice.size == SIZES[0] and math.isfinite(choice.errors[SIZES[0]])
    assert not any("can encode" in str(w.message) for w in caught)
    # The floor: an error below it is absolute (its RMSE over ERROR_FLOOR), above it relative as before.
    pred = np.full((4, 3), 0.002)
    assert quality.noise_corrected_error(pred, np.zeros((4, 3))) == pytest.approx(0.2)
    bright = np.full((4, 3), 0.5)
    assert quality.noise_corrected_error(bright * 1.1, bright) == pytest.approx(0.1)


def test_the_error_cache_keeps_what_another_session_wrote_and_knows_reinstalled_files(tmp_path):
    """Two sessions sharing decoder_errors.json each wrote their whole dictionary: the last lost the other's new
    entries. Now each write merges what is on disk. And the files' identity is their content (the cards' digests),
    not their modification times: the same files installed again keep their measured errors."""
    import os
    import shutil

    a, b = quality.ErrorCache(tmp_path), quality.ErrorCache(tmp_path)
    a.put("stack-a", 0.1)
    b.put("stack-b", 0.2)
    assert quality.ErrorCache(tmp_path).data == {"stack-a": 0.1, "stack-b": 0.2}
    models = tmp_path / "models"
    shutil.copytree(MODEL_DIR, models, ignore=shutil.ignore_patterns("*_weights.npz", "sampling_*"))
    before = quality._fingerprint("tiny", models)
    for f in models.iterdir():
        os.utime(f, ns=(1, 1))  # a reinstall: the same bytes, new times
    assert quality._fingerprint("tiny", models) == before
    card = models / "decoder_tiny.json"
    data = json.loads(card.read_text())
    data["remainder"] = not data["remainder"]  # how the decoder's output is used changes what it renders
    card.write_text(json.dumps(data))
    assert quality._fingerprint("tiny", models) != before


def test_a_stack_the_networks_see_clamped_is_said_at_every_render():
    """The encoding is cached, so its ClampWarning reached the console once a session, and F12 and Render Preview
    said nothing: the decoder choice now says it for each material, once, whatever the decoder size setting."""
    from addon.core.stack import Coating

    smooth = Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.0, 1.5),))
    scene = demo_scene(8, 6, [smooth])
    for _ in range(2):  # the second time from the caches
        _, _, notes = quality.assign_decoders(scene, SIZES[0])
        clamped = [n for n in notes if "clamped" in n]
        assert len(clamped) == 1 and "coatings[0].roughness" in clamped[0], notes


def test_a_fixed_sizes_calibrations_hear_the_stop():
    """A fixed Decoder size (Tiny..Paper, Calibrate Albedo on) calibrates each new stack before the first pass, a
    second or two each: F12 returned 14.8-22.4 s after Esc, against 1.5 s for Auto, whose measurements heard it.
    The calibrations now hear the same stop, between their parts."""
    from addon.core.neural import calibrate as cal
    from addon.core.neural import encode_stack, load_models
    from addon.core.render import Cancelled

    stack = PRESETS["varnished_wood"]
    cal.clear_cache()
    calls = []

    def stop():
        calls.append(1)
        return len(calls) > 2  # after the check before the material, inside its calibration

    with pytest.raises(Cancelled, match="decoder choice was stopped"):
        quality.assign_decoders(demo_scene(8, 6, [stack]), SIZES[0], calibrate=True, stop=stop)
    assert len(calls) == 3  # stopped at the calibration's second step, not after it
    models = load_models(SIZES[0])
    assert cal.cached(stack, models, encode_stack(stack, models)) is None  # nothing half made was kept


def test_the_error_bounds_hold_the_true_error_under_heavy_tailed_correlated_noise():
    """The reference's walks serve every pixel, and under a glossy coat the few that find its peak decide how bright
    it is: noise heavy-tailed and along one direction of the lobe. An estimate from one set of walks is then below
    the truth about half the time and far below it often (a lacquered plastic's tiny decoder: 0.011-0.042 over ten
    seeds, 0.032 converged). The bounds (a jackknife over the walks' batches) hold the true error in about 9 of 10
    sets, and are not so wide that they say nothing."""
    rng = np.random.default_rng(1)
    n = 600
    truth = rng.random(n) + 0.2
    along = rng.random(n)  # the direction the walks err along (a lobe's peak)
    pred = truth * 1.03 + 0.02 * along
    true_error = math.sqrt(np.sum((pred - truth) ** 2) / np.sum(truth**2))
    held, below, width = [], [], []
    for _ in range(200):
        refs, ses = [], []
        for _batch in range(quality.REFERENCE_BATCHES):  # 16 walks a batch, as 256 walks are run
            scale = rng.lognormal(-0.5, 1.0, 16)  # mean 1, a heavy tail
            walks = truth[None] + (scale - 1)[:, None] * 0.3 * along[None] + rng.normal(0.0, 0.1, (16, n))
            refs.append(walks.mean(axis=0))
            ses.append(walks.std(axis=0, ddof=1) / 4.0)
        error, low, high = quality.error_bounds(pred, np.array(refs), np.array(ses))
        assert error == pytest.approx(quality.noise_corrected_error(pred, np.mean(refs, axis=0), _mean_se(ses)))
        held.append(low <= true_error <= high)
        below.append(error < true_error)
        width.append(high / true_error)
    assert np.mean(below) > 0.35  # the estimate alone is no bound: what the choice compared with the tolerance
    assert np.mean(held) >= 0.85, np.mean(held)
    assert np.median(width) < 2.5, np.median(width)
    # an exact reference (one batch, no noise) bounds the error by itself
    assert quality.error_bounds(pred, truth[None], np.zeros((1, n))) == (pytest.approx(true_error),) * 3


def _mean_se(ses):
    """The standard error of the mean of equal batches with these standard errors."""
    ses = np.asarray(ses)
    return np.sqrt(np.sum(ses**2, axis=0)) / len(ses)


def test_auto_does_not_claim_a_glossy_coat_meets_a_tolerance_the_noise_cannot_show():
    """lacquered_plastic on the tiny decoder measures 0.032 with 8192 walks; Auto's 256 walks (seed 0) measured
    0.0164 and took tiny as meeting a tolerance of 0.02. The choice now compares the tolerance with the error's
    upper bound, measures again with more walks where the bounds hold it, and says the error with its bound."""
    stack = PRESETS["lacquered_plastic"]
    cache = quality.ErrorCache()
    with pytest.warns(quality.QualityWarning, match="meets the tolerance 0.02 .*as far as the reference's noise"):
        choice = quality.choose_decoder(stack, 0.02, sizes=["tiny"], calibrate=True, cache=cache)
    assert not choice.met and choice.bound("tiny")[1] > 0.02
    low, high = choice.bound("tiny")
    assert low <= choice.errors["tiny"] <= high
    reason = quality.choice_reason("plastic", choice)
    assert f"at most {high:.2g}" in reason and "none shown within 0.02" in reason, reason
    # the bounds are kept with the error (a later session reads them), and the wider first measurement too
    assert any(isinstance(v, tuple) for v in cache.data.values()) and len(cache.data) == 2
    assert quality.choose_decoder(stack, 0.02, sizes=["tiny"], calibrate=True, cache=cache) == choice


def test_a_refined_latent_or_a_baked_texture_says_it_keeps_its_decoder_size():
    """After Refine (tiny) was kept, F12 with Decoder = Paper rendered that material on tiny without a word: a line
    now says why it is on tiny, and that the Decoder setting says otherwise."""
    from dataclasses import replace

    from addon.core.neural import encode_stack, load_models

    stack = PRESETS["red_car_paint"]
    scene = demo_scene(8, 6, [stack, "coated_gold"])
    z = encode_stack(stack, load_models("tiny"))
    scene.materials[1] = replace(scene.materials[1], latent=(z, "tiny"))
    name = scene.material_names[1]
    for setting, said in (
        ("paper", f"material {name!r}: decoder tiny (its refined latent; Decoder: Paper)"),
        ("tiny", f"material {name!r}: decoder tiny (its refined latent)"),
    ):
        info = []
        mats, choices, _ = quality.assign_decoders(scene, setting, info=info)
        assert mats[1] is scene.materials[1] and name not in choices  # rendered from its latent, on its size
        assert info == [said]
        assert "as set" in quality.choice_reason("coated_gold", choices["coated_gold"])

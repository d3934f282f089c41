"""Progressive sessions (the viewport's renderer): first image, accumulation, restart, cancel."""

import time
from dataclasses import replace

import numpy as np
import pytest

from addon.core.render import Camera, Environment, LambertMaterial, PointLight, RenderSettings, Scene, render, shapes
from addon.core.render.progressive import (
    PREVIEW_PIXELS,
    ProgressiveSession,
    predicted_pass_seconds,
    preview_divisors,
    reduced_camera,
)


def small_scene(sky=(0.3, 0.4, 0.5), width=24, height=16):
    cam = Camera.look_at((0.0, -3.0, 1.0), (0.0, 0.0, 0.3), width=width, height=height)
    mesh = shapes.uv_sphere((0.0, 0.0, 0.4), 0.4, segments=12, rings=6)
    return Scene(cam, mesh, [LambertMaterial((0.7, 0.5, 0.3))], [PointLight((1.0, -2.0, 2.0), 80.0)], Environment(sky))


def plastic_scene(roughness: float) -> Scene:
    """A small scene with its sphere in lacquered plastic of a coat ``roughness`` of its own (one that no other
    test calibrates in this session)."""
    from addon.core.render.materials import LayeredSpec
    from addon.core.stack import preset

    plastic = preset("lacquered_plastic")
    stack = replace(plastic, coatings=[replace(plastic.coatings[0], roughness=roughness)] + list(plastic.coatings[1:]))
    base = small_scene(width=12, height=8)
    return Scene(base.camera, base.mesh, [LayeredSpec(stack, None, "plastic")], base.lights, base.environment)


def rendered_once(scene, settings, preview_divisor, **options):
    """Every image a session shows of ``scene`` until its last sample, and the last."""
    seen = []
    session = ProgressiveSession(settings, preview_divisor=preview_divisor, on_image=seen.append, **options)
    try:
        session.restart(scene)
        return seen, session.wait()
    finally:
        session.close()


def test_accumulation_equals_an_offline_render_of_the_same_samples():
    scene = small_scene()
    settings = RenderSettings(samples=5, max_bounces=3, seed=4)
    seen, image = rendered_once(scene, settings, 2)
    offline, _ = render(scene, settings)
    assert image.samples == 5 and not image.reduced
    assert np.array_equal(image.rgba, offline.rgba())
    # The first image is one sample at half the resolution on each side.
    assert seen[0].reduced and seen[0].samples == 1 and seen[0].rgba.shape == (8, 12, 4)
    assert [im.samples for im in seen[1:]] == [1, 2, 3, 4, 5]


def test_restart_renders_only_the_newest_scene():
    settings = RenderSettings(samples=3, max_bounces=2, seed=1)
    session = ProgressiveSession(settings, preview_divisor=1)
    try:
        session.restart(small_scene((1.0, 0.0, 0.0)))
        generation = session.restart(small_scene((0.0, 0.0, 1.0)))
        image = session.wait()
    finally:
        session.close()
    assert image.generation == generation == 2
    offline, _ = render(small_scene((0.0, 0.0, 1.0)), settings)
    assert np.array_equal(image.rgba, offline.rgba())


def test_cancel_stops_within_a_pass_and_keeps_the_last_image():
    settings = RenderSettings(samples=100_000, max_bounces=2)
    session = ProgressiveSession(settings, preview_divisor=4)
    try:
        session.restart(small_scene(width=64, height=48))
        first = session.wait(samples=2, timeout=60)
        assert first is not None and first.samples >= 2
        t0 = time.monotonic()
        session.cancel()
        while not session.idle and time.monotonic() - t0 < 30:
            time.sleep(0.01)
        assert session.idle
        stopped = session.latest().samples
        time.sleep(0.3)
        assert session.latest().samples == stopped < 100_000
    finally:
        session.close()


def test_a_restart_ends_the_old_pass_at_its_next_bounce_not_at_its_end():
    import threading

    from addon.core.render import Mesh

    entered, release = threading.Event(), threading.Event()
    binds = []

    class HeldOnce(LambertMaterial):  # the old scene's first bounce waits until the restart has come
        def bind(self, hits):
            binds.append(len(hits.uv))
            if len(binds) == 1:
                entered.set()
                release.wait(30)
            return super().bind(hits)

    old = small_scene(width=32, height=24)
    floor = shapes.quad((0.0, 0.0, 0.0), (3.0, 0.0, 0.0), (0.0, 3.0, 0.0))
    old = replace(old, mesh=Mesh.concatenate([old.mesh, floor]), materials=[HeldOnce((0.7, 0.5, 0.3))])
    # One thread: no other chunk of the old scene runs beside the one held (two would race the restart).
    session = ProgressiveSession(RenderSettings(samples=50, max_bounces=6, threads=1), preview_divisor=1)
    try:
        session.restart(old)
        assert entered.wait(30)
        generation = session.restart(small_scene((0.0, 0.0, 1.0)))
        release.set()
        image = session.wait(samples=1, timeout=60)
    finally:
        release.set()
        session.close()
    assert image.generation == generation
    # Its paths went on bouncing between the sphere and the floor, but the old scene shaded no bounce after the
    # restart: its pass stopped at the next bounce, not at its end.
    assert len(binds) == 1
    full, _ = render(old, RenderSettings(samples=1, max_bounces=6, threads=1))
    assert len(binds) > 2


def test_a_failing_render_is_reported_not_lost():
    class Broken(LambertMaterial):
        def bind(self, hits):
            raise RuntimeError("texture file vanished")

    scene = small_scene()
    scene.materials = [Broken()]
    errors = []
    session = ProgressiveSession(RenderSettings(samples=2), preview_divisor=1, on_error=errors.append)
    try:
        session.restart(scene)
        session.wait(timeout=30)
    finally:
        session.close()
    assert isinstance(session.error, RuntimeError) and errors == [session.error]


def test_a_large_view_starts_smaller_and_doubles_up_to_the_divisor():
    assert PREVIEW_PIXELS == 64 * 64
    assert preview_divisors(320, 180, 4) == [4]  # 80 x 45: within the first image's pixels already
    assert preview_divisors(1280, 720, 4) == [16, 8, 4]  # 80 x 45 first, then 160 x 90 and 320 x 180
    assert preview_divisors(3840, 2160, 4) == [64, 32, 16, 8, 4]
    assert preview_divisors(3840, 2160, 1) == [] and preview_divisors(24, 16, 2) == [2]
    assert preview_divisors(400, 300, 3) == [6, 3]  # 66 x 50 first: a divisor need not be a power of two
    for w, h in ((1280, 720), (3840, 2160), (7, 5000), (1, 40000), (40000, 1), (1, 1)):
        cam = Camera.look_at((0, -3, 1), (0, 0, 0), width=w, height=h)
        first = reduced_camera(cam, preview_divisors(w, h, 4)[0])
        assert first.width * first.height <= PREVIEW_PIXELS

    scene = small_scene(width=200, height=150)
    settings = RenderSettings(samples=2, max_bounces=2, seed=3)
    seen, image = rendered_once(scene, settings, 2)
    assert [im.rgba.shape[:2] for im in seen if im.reduced] == [(37, 50), (75, 100)]
    assert [im.samples for im in seen] == [1, 1, 1, 2]
    # The reduced images are previews only: the accumulation is the offline render's.
    assert np.array_equal(image.rgba, render(scene, settings)[0].rgba())


def test_a_view_whose_pass_is_predicted_slow_gets_a_half_resolution_image_before_it():
    """After the reduced images down to the divisor, one at half the view's resolution when the full pass is
    predicted to take longer than ``half_image_seconds``: from the last full pass's seconds a pixel, or from the
    last two reduced images before any full pass; a view with one reduced image waits for a full pass to know."""
    scene = small_scene(width=200, height=150)  # one reduced image at the divisor 4: 50 x 37
    settings = RenderSettings(samples=2, max_bounces=2, seed=3)
    offline = render(scene, settings)[0].rgba()
    for seconds, shapes_seen in ((0.0, [(37, 50), (75, 100)]), (float("inf"), [(37, 50)])):
        seen, image = rendered_once(scene, settings, 4, half_image_seconds=seconds)
        assert [im.rgba.shape[:2] for im in seen if im.reduced] == shapes_seen
        assert np.array_equal(image.rgba, offline)  # previews only: the accumulation is the offline render's

    seen = []
    session = ProgressiveSession(settings, preview_divisor=4, on_image=seen.append, half_image_seconds=1e-9)
    try:
        session.restart(scene)
        session.wait()
        assert [im.rgba.shape[:2] for im in seen if im.reduced] == [(37, 50)]  # nothing to predict from yet
        per_pixel = session.pass_seconds_per_pixel
        assert per_pixel is not None and per_pixel > 0.0  # the first full pass, timed
        predicted = per_pixel * 200 * 150
        for seconds, shapes_seen in ((2.0 * predicted, [(37, 50)]), (0.5 * predicted, [(37, 50), (75, 100)])):
            session.half_image_seconds = seconds
            session.pass_seconds_per_pixel = per_pixel  # as the last generation measured it
            seen.clear()
            generation = session.move_camera(scene.camera)
            image = session.wait()
            assert image.generation == generation
            assert [im.rgba.shape[:2] for im in seen if im.reduced] == shapes_seen
    finally:
        session.close()
    with pytest.raises(ValueError, match="half_image_seconds"):
        ProgressiveSession(settings, half_image_seconds=-1.0)
    with pytest.raises(ValueError, match="half_image_seconds"):
        ProgressiveSession(settings, half_image_seconds=float("nan"))


def test_a_full_pass_is_predicted_from_the_last_one_or_the_reduced_images_marginal_cost():
    # the last full pass's seconds a pixel first
    assert predicted_pass_seconds(1000, 2e-3, [(100, 9.0), (400, 9.5)]) == pytest.approx(2.0)
    # before any: the seconds per pixel more of the last two reduced images, their fixed costs left out
    assert predicted_pass_seconds(1000, None, [(25, 0.5), (100, 0.6), (400, 0.9)]) == pytest.approx(1.0)
    assert predicted_pass_seconds(1000, None, [(100, 0.6), (400, 0.5)]) == 0.0  # noise: never below 0
    assert predicted_pass_seconds(1000, None, [(100, 0.6)]) is None and predicted_pass_seconds(10, None, []) is None


def test_reduced_camera_and_bad_divisor():
    cam = Camera.look_at((0, -3, 1), (0, 0, 0), width=320, height=180)
    small = reduced_camera(cam, 4)
    assert (small.width, small.height) == (80, 45) and small.tan_half_fov == cam.tan_half_fov
    assert (reduced_camera(cam, 1000).width, reduced_camera(cam, 1000).height) == (1, 1)
    with pytest.raises(ValueError, match="preview_divisor"):
        ProgressiveSession(RenderSettings(), preview_divisor=0)


def test_move_camera_renders_the_last_scene_from_the_new_view():
    """The viewport's navigation: the scene of the last restart, its materials as resolved then, from another
    camera; the image is the offline render of that view."""
    settings = RenderSettings(samples=2, max_bounces=2, seed=3)
    scene = small_scene()
    moved = Camera.look_at((1.5, -2.5, 1.2), (0.0, 0.0, 0.3), width=24, height=16)
    session = ProgressiveSession(settings, preview_divisor=1)
    try:
        with pytest.raises(ValueError, match="call restart first"):
            session.move_camera(moved)
        session.restart(scene)
        session.wait()
        resolved = session._last.materials
        assert resolved[0] is scene.materials[0]  # a renderer material resolves to itself
        generation = session.move_camera(moved)
        image = session.wait()
    finally:
        session.close()
    assert image.generation == generation == 2
    offline, _ = render(Scene(moved, scene.mesh, scene.materials, scene.lights, scene.environment), settings)
    assert np.array_equal(image.rgba, offline.rgba())


def test_layered_materials_are_calibrated_as_an_offline_render_calibrates_them():
    """The session resolves the scene's stacks with the settings' calibration, as ``render`` does: its image is
    the offline render's (it used to leave them uncalibrated)."""
    from addon.core.render.materials import LayeredSpec
    from addon.core.stack import preset

    base = small_scene(width=12, height=8)
    scene = Scene(
        base.camera, base.mesh, [LayeredSpec(preset("coated_gold"), None, "gold")], base.lights, base.environment
    )
    settings = RenderSettings(samples=2, max_bounces=2, seed=5, calibrate=True)
    session = ProgressiveSession(settings, preview_divisor=1)
    try:
        session.restart(scene)
        image = session.wait()
        assert session._last.materials[0].calibration is not None
    finally:
        session.close()
    offline, _ = render(scene, settings)
    assert np.array_equal(image.rgba, offline.rgba())


def test_the_viewport_calibrates_what_cached_left_out_after_its_first_image():
    """``calibrate="cached"`` (the viewport's setting) makes no reference walks before the first images; after
    the first full-resolution pass the session calibrates the materials that had none and accumulates as a
    calibrating offline render does."""
    from addon.core.render.materials import resolve

    scene = plastic_scene(0.0731)
    spec = scene.materials[0]
    settings = RenderSettings(samples=2, max_bounces=2, seed=6, calibrate="cached")
    assert resolve(spec, "neural", calibrate="cached").calibration is None  # nothing made yet
    seen = []
    session = ProgressiveSession(settings, preview_divisor=2, on_image=seen.append)
    try:
        session.restart(scene)
        image = session.wait()
        material = session._last.materials[0]
    finally:
        session.close()
    assert seen[0].reduced and material.calibration is not None and material.uncalibrated_stack is None
    # one full-resolution pass uncalibrated (an edit that comes now does not wait for walks), then the calibrated
    # accumulation from its first sample
    assert [im.samples for im in seen if not im.reduced] == [1, 1, 2]
    offline, _ = render(scene, replace(settings, calibrate=True))
    assert np.array_equal(image.rgba, offline.rgba())


def test_the_viewport_calibrates_several_stacks_side_by_side_as_an_offline_render_does():
    """Every stack the view left uncalibrated is calibrated after its first full pass, on the render's threads;
    each as a lone calibration makes it, so the accumulation equals the offline render's."""
    from addon.core.neural import calibrate
    from addon.core.render.demo_scene import demo_scene

    calibrate.clear_cache()
    scene = demo_scene(24, 14)
    settings = RenderSettings(samples=2, max_bounces=2, seed=8, calibrate="cached", threads=2)
    session = ProgressiveSession(settings, preview_divisor=2)
    try:
        session.restart(scene)
        image = session.wait()
        made = [m for m in session._last.materials if getattr(m, "calibration", None) is not None]
    finally:
        session.close()
    assert len(made) == 5 and all(m.uncalibrated_stack is None for m in made)
    calibrate.clear_cache()  # the offline render makes its own, one stack after another
    offline, _ = render(scene, replace(settings, calibrate=True, threads=1))
    assert np.array_equal(image.rgba, offline.rgba())


def test_a_calibration_that_fails_leaves_the_view_rendering_uncalibrated(monkeypatch):
    """The viewport's calibration runs reference walks the user did not ask for: if it fails, the view goes on
    with the material uncalibrated (what it showed before the calibration existed) and keeps the failure for a
    warning, instead of stopping with an error."""
    from addon.core.render import neural_material

    def failing(self, step=None):
        raise ValueError("walks failed")

    monkeypatch.setattr(neural_material.NeuralMaterial, "calibrated", failing)
    scene = plastic_scene(0.0913)
    settings = RenderSettings(samples=2, max_bounces=2, seed=7, calibrate="cached")
    session = ProgressiveSession(settings, preview_divisor=2)
    try:
        session.restart(scene)
        image = session.wait()
    finally:
        session.close()
    assert session.error is None and "walks failed" in str(session.calibration_failure)
    assert image.samples == 2 and np.isfinite(image.rgba).all()
    offline, _ = render(scene, replace(settings, calibrate=False))
    assert np.array_equal(image.rgba, offline.rgba())


def test_a_restart_stops_the_calibration_of_the_scene_before_it(monkeypatch):
    """An edit during the viewport's calibration renders the new scene at once: the stale calibration stops at its
    next step (it used to run to its end first: about 2.5 s with the paper decoder), caches nothing and is not
    reported as a failure."""
    import threading

    from addon.core.render import neural_material
    from addon.core.render.integrator import Cancelled

    started, stopped_by = threading.Event(), []

    def endless(self, step=None):  # a calibration that would take 60 s, checking its step as the real one does
        started.set()
        end = time.monotonic() + 60.0
        while time.monotonic() < end:
            try:
                step()
            except Cancelled as e:
                stopped_by.append(e)
                raise
            time.sleep(0.005)
        raise AssertionError("the calibration was not stopped")

    monkeypatch.setattr(neural_material.NeuralMaterial, "calibrated", endless)
    layered = plastic_scene(0.0871)
    settings = RenderSettings(samples=2, max_bounces=2, seed=8, calibrate="cached")
    session = ProgressiveSession(settings, preview_divisor=2)
    try:
        session.restart(layered)
        assert started.wait(60.0)
        t0 = time.monotonic()
        session.restart(small_scene(width=12, height=8))
        image = session.wait(timeout=60.0)
        elapsed = time.monotonic() - t0
    finally:
        session.close()
    assert len(stopped_by) == 1 and elapsed < 30.0
    assert session.error is None and session.calibration_failure is None
    assert image.samples == 2 and not image.reduced
    offline, _ = render(small_scene(width=12, height=8), settings)
    assert np.array_equal(image.rgba, offline.rgba())

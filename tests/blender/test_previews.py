"""Latent, lobe and sphere previews, and the reference comparison, run as operators in bpy.

Previews with the Monte Carlo reference use tiny images and few walks to stay fast. Tests of the
operators' plumbing (latent storage, comparison layout) use a stand-in neural module (a Lambertian
decoder whose latent holds the base albedo), so they run whether or not trained models are
shipped; the real models are exercised where they exist.
"""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from addon.core import preview
from tests.blender.helpers import run_operator

pytest.importorskip("bpy")


def _pixels(image):
    w, h = image.size
    px = np.empty(w * h * 4, dtype=np.float32)
    image.pixels.foreach_get(px)
    return px.reshape(h, w, 4)


def _area_types(context):
    return [a.type for w in context.window_manager.windows for a in w.screen.areas]


def _shown(context, image):
    """Where an Image Editor is open it shows ``image``; with none (background mode), the preview
    changed no area and the image is in ``bpy.data.images``."""
    editors = [a for w in context.window_manager.windows for a in w.screen.areas if a.type == "IMAGE_EDITOR"]
    if not editors:
        return image.name in __import__("bpy").data.images and "VIEW_3D" in _area_types(context)
    return editors[0].spaces.active.image == image


def stand_in_neural():
    """A fake neural runtime: latent row c starts with the base albedo of channel c."""

    def encode_stack(stack, size="small"):
        z = np.zeros((3, 32), dtype=np.float32)
        z[:, 0] = getattr(stack.base, "albedo", (0.5, 0.5, 0.5))
        z[:, 1] = sum(getattr(l, "roughness", 0.0) for l in stack.layers)
        z[:, 2] = len(stack.coatings)
        return z

    def eval_brdf(z, wi, wo, size="small", top=None, calibration=None):
        up = (wi[:, 2:3] > 0) & (wo[:, 2:3] > 0)
        return np.where(up, np.asarray(z)[:, 0][None, :] / math.pi, 0.0)

    return types.SimpleNamespace(load_models=lambda size="small": None, encode_stack=encode_stack, eval_brdf=eval_brdf)


@pytest.fixture()
def fake_neural(monkeypatch):
    module = stand_in_neural()
    monkeypatch.setattr(preview, "_neural_module", lambda: module)
    return module


@pytest.fixture()
def no_neural(monkeypatch):
    def missing():
        raise preview.NeuralUnavailable("decoder_small.onnx is missing from addon/models")

    monkeypatch.setattr(preview, "_neural_module", missing)


def _small_previews(mat, **extra):
    s = mat.neural_layers
    s.lobe_resolution = 24
    s.sphere_resolution = 20
    s.env_samples = 4
    s.walks = 4
    for k, v in extra.items():
        setattr(s, k, v)


@pytest.mark.parametrize(
    "op, prefix, size_attr",
    [("preview_lobe", "Lobe", "lobe_resolution"), ("preview_sphere", "Sphere", "sphere_resolution")],
)
def test_reference_preview_lands_in_image_editor(
    bpy_addon, fresh_scene, material, no_neural, op, prefix, size_attr, capfd
):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="lacquered_plastic").finished
    _small_previews(material)
    r = run_operator(getattr(bpy.ops.neural_layers, op))
    assert r.finished, r.error
    image = bpy.data.images[f"{prefix} {material.name}"]
    res = getattr(material.neural_layers, size_attr)
    assert tuple(image.size) == (res, res)
    px = _pixels(image)
    assert np.all(np.isfinite(px)) and np.all(px >= 0)
    assert px[..., :3].max() > 0
    assert image["method"] == "REFERENCE"
    assert _shown(fresh_scene, image)
    assert "neural models not available" in capfd.readouterr().out


def test_image_rows_run_bottom_to_top(bpy_addon, fresh_scene, material, fake_neural):
    """Blender stores rows bottom to top: the sphere, lit from above, is brighter in the last rows."""
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    _small_previews(material, sphere_resolution=32, env_samples=8)
    assert run_operator(bpy.ops.neural_layers.preview_sphere).finished
    px = _pixels(bpy.data.images[f"Sphere {material.name}"])  # Blender order: row 0 = bottom
    assert px[16:, :, :3].sum() > 1.5 * px[:16, :, :3].sum()


def test_invoke_in_background_runs_blocking(bpy_addon, fresh_scene, material, fake_neural):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    _small_previews(material)
    assert run_operator(bpy.ops.neural_layers.preview_lobe, "INVOKE_DEFAULT").finished
    image = bpy.data.images[f"Lobe {material.name}"]
    assert image["method"] == "NEURAL"
    from addon.core.lobe import albedo_from_lobe

    lobe = _pixels(image)[::-1, :, :3]
    np.testing.assert_allclose(albedo_from_lobe(lobe), 0.8, rtol=0.05)  # stand-in decoder = white diffuse


def test_neural_only_method_reports_missing_models(bpy_addon, fresh_scene, material, no_neural):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    _small_previews(material, preview_method="NEURAL")
    for op in (
        bpy.ops.neural_layers.preview_lobe,
        bpy.ops.neural_layers.preview_sphere,
        bpy.ops.neural_layers.evaluate_latent,
        bpy.ops.neural_layers.compare_reference,
    ):
        r = run_operator(op)
        assert r.error and "neural models not available" in r.error and "decoder_small.onnx" in r.error


def test_latent_is_stored_and_recomputed_when_the_stack_changes(bpy_addon, fresh_scene, material, fake_neural):
    bpy = bpy_addon
    from addon.blender import stack_io

    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="varnished_wood").finished
    assert stack_io.latent_is_current(material)  # automatic on edit
    z0 = stack_io.latent_of(material)
    assert z0[:, 0] == pytest.approx((0.45, 0.22, 0.08))

    material.neural_layers.layers[0].albedo = (0.1, 0.2, 0.3)  # an edit in the sidebar
    assert stack_io.latent_is_current(material)
    assert stack_io.latent_of(material)[:, 0] == pytest.approx((0.1, 0.2, 0.3))
    assert material.neural_layers.latent_hash == preview.stack_hash(stack_io.stack_from_material(material))

    material.neural_layers.auto_latent = False
    material.neural_layers.layers[1].thickness = 2.0
    assert not stack_io.latent_is_current(material)  # stale until evaluated
    assert run_operator(bpy.ops.neural_layers.evaluate_latent).finished
    assert stack_io.latent_is_current(material)

    material.neural_layers.active_index = 1
    assert run_operator(bpy.ops.neural_layers.layer_remove).finished
    assert not stack_io.latent_is_current(material)


def test_latent_goes_stale_when_models_are_missing(bpy_addon, fresh_scene, material, no_neural):
    from addon.blender import stack_io

    assert run_operator(bpy_addon.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    assert not stack_io.latent_is_current(material)
    r = run_operator(bpy_addon.ops.neural_layers.evaluate_latent)
    assert r.error and "neural models not available" in r.error


def test_out_of_trained_range_is_clamped_with_a_warning(bpy_addon, fresh_scene, material, fake_neural, capfd):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    material.neural_layers.layers[1].ior = 3.0  # valid, above the trained 2.0
    material.neural_layers.layers[1].thickness = 40.0
    capfd.readouterr()
    assert run_operator(bpy.ops.neural_layers.evaluate_latent).finished
    out = capfd.readouterr().out
    assert "ior = 3.0 clamped to 2.0" in out and "thickness = 40.0 clamped to 5.0" in out


def test_compare_shows_neural_reference_and_error_with_timings(bpy_addon, fresh_scene, material, fake_neural):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    _small_previews(material, walks=8)
    assert run_operator(bpy.ops.neural_layers.compare_reference).finished
    image = bpy.data.images[f"Compare {material.name}"]
    res = material.neural_layers.lobe_resolution
    assert tuple(image.size) == (3 * res + 4, res)
    px = _pixels(image)
    assert np.all(np.isfinite(px)) and np.all(px >= 0)
    assert image["seconds_neural"] > 0 and image["seconds_reference"] > 0
    # the stand-in decoder is the exact white Lambertian: the reference agrees up to its noise
    assert image["relative_rmse"] < 0.2
    assert _shown(fresh_scene, image)


def test_real_models_preview_when_shipped(bpy_addon, fresh_scene, material):
    from addon.core.stack import Diffuse, Stack

    try:
        preview.encode_latent(Stack(Diffuse((0.5, 0.5, 0.5))))
    except preview.NeuralUnavailable as e:
        pytest.skip(f"trained models not shipped yet: {e}")
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    _small_previews(material, preview_method="NEURAL")
    from addon.blender import stack_io

    assert stack_io.latent_is_current(material)
    assert run_operator(bpy.ops.neural_layers.preview_lobe).finished
    px = _pixels(bpy.data.images[f"Lobe {material.name}"])
    assert np.all(np.isfinite(px)) and np.all(px >= 0) and px[..., :3].max() > 0


def test_job_reports_progress_result_and_cancel():
    """The worker-thread job behind the modal operators (timers never fire headless)."""
    import threading

    from addon.blender.jobs import Job

    done = Job(lambda progress: [progress(f) for f in (0.5, 1.0)] and "image").start()
    done.wait(10)
    assert done.done and done.result == "image" and done.fraction == 1.0 and not done.cancelled

    started = threading.Event()

    def long_work(progress):
        started.set()
        while True:
            progress(0.1)

    job = Job(long_work).start()
    assert started.wait(10)
    job.cancel()
    job.wait(10)
    assert job.done and job.cancelled and job.result is None and job.error is None

    failing = Job(lambda progress: 1 / 0).start()
    failing.wait(10)
    assert isinstance(failing.error, ZeroDivisionError)


def _modal_operator(op_cls):
    """The operator's modal logic on a plain object (Blender's event loop does not run headless)."""
    from addon.blender import operator_base

    class Driven(operator_base.LongOperator):
        bl_label = op_cls.bl_label
        material = ""
        prepare = op_cls.prepare

        def __init__(self):
            self.reports = []

        def report(self, kind, message):
            self.reports.append((set(kind), message))

    return Driven()


def _drive(op, context, events, limit=600):
    import time
    import types

    from addon.blender.jobs import Job

    work, op._finish = op.prepare(context)
    op._job = Job(work).start()
    result = {"RUNNING_MODAL"}
    for event in events:
        result = op.modal(context, types.SimpleNamespace(type=event))
        assert result == ({"PASS_THROUGH"} if event == "MOUSEMOVE" else {"RUNNING_MODAL"}), (event, result)
        result = {"RUNNING_MODAL"}
    for _ in range(limit):
        if result != {"RUNNING_MODAL"}:
            break
        time.sleep(0.05)
        result = op.modal(context, types.SimpleNamespace(type="TIMER"))
    return result


def test_modal_preview_finishes_with_the_image(bpy_addon, fresh_scene, material, fake_neural):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    _small_previews(material)
    op = _modal_operator(bpy.types.NEURAL_LAYERS_OT_preview_sphere)
    result = _drive(op, fresh_scene, ["MOUSEMOVE"])  # other events pass through to the UI
    assert result == {"FINISHED"}, op.reports
    image = bpy.data.images[f"Sphere {material.name}"]
    assert tuple(image.size) == (20, 20) and _shown(fresh_scene, image)
    assert any("INFO" in kind and "sphere" in msg for kind, msg in op.reports)


def test_modal_preview_cancels_on_escape(bpy_addon, fresh_scene, material, no_neural):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    _small_previews(material, lobe_resolution=512, walks=256)  # minutes of reference work
    op = _modal_operator(bpy.types.NEURAL_LAYERS_OT_preview_lobe)
    result = _drive(op, fresh_scene, ["ESC"])
    assert result == {"CANCELLED"}
    assert op._job.cancelled and op._job.fraction < 1.0
    assert any("cancelled" in msg for _, msg in op.reports)
    assert f"Lobe {material.name}" not in bpy.data.images


def test_modal_preview_reports_worker_errors(bpy_addon, fresh_scene, material, monkeypatch):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="white_diffuse").finished
    _small_previews(material, preview_method="NEURAL")

    def broken():
        raise preview.NeuralUnavailable("decoder_small.onnx is corrupt")

    monkeypatch.setattr(preview, "_neural_module", broken)
    op = _modal_operator(bpy.types.NEURAL_LAYERS_OT_preview_lobe)
    assert _drive(op, fresh_scene, []) == {"CANCELLED"}
    assert any("ERROR" in kind and "neural models not available" in msg for kind, msg in op.reports)


def test_background_previews_leave_the_screen_alone_and_use_an_open_image_editor(
    bpy_addon, fresh_scene, material, no_neural
):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="lacquered_plastic").finished
    _small_previews(material)
    before = _area_types(fresh_scene)
    assert "IMAGE_EDITOR" not in before
    assert run_operator(bpy.ops.neural_layers.preview_lobe).finished
    assert _area_types(fresh_scene) == before  # the 3D viewport is not turned into an Image Editor
    area = next(a for a in fresh_scene.window_manager.windows[0].screen.areas if a.type == "PROPERTIES")
    area.type = "IMAGE_EDITOR"
    assert run_operator(bpy.ops.neural_layers.preview_sphere).finished
    assert area.spaces.active.image == bpy.data.images[f"Sphere {material.name}"]


def test_a_preview_image_keeps_its_pixels_through_a_save_and_a_reload(bpy_addon, fresh_scene, tmp_path):
    """A preview is a generated float image, whose pixels a .blend does not keep: one shown in the Image Editor came
    back black after a reload. The previews are packed as the file is saved (OpenEXR), and written again after. A
    transparent film's Render Preview has partial alpha over premultiplied colour: marked Straight, its colour came
    back multiplied by its alpha once more."""
    from addon.blender import images

    bpy = bpy_addon
    rng = np.random.default_rng(3)
    path = str(tmp_path / "previews.blend")
    for _ in range(2):  # a preview, and a preview again after the file packed the first
        rgba = rng.random((6, 8, 4)).astype(np.float32) * 4.0  # beyond 1: float pixels
        rgba[..., 3] = np.where(rng.random((6, 8)) < 0.5, 1.0, rng.uniform(0.1, 0.9, (6, 8)))  # some half covered
        rgba[..., :3] *= rgba[..., 3:]  # premultiplied, as Film.rgba is
        image = images.store_image("NLM Preview Test", rgba)
        image.use_fake_user = True  # as the Image Editor's user keeps it
        bpy.ops.wm.save_as_mainfile(filepath=path)
        bpy.ops.wm.open_mainfile(filepath=path)
        image = bpy.data.images["NLM Preview Test"]
        assert image.packed_file is not None
        np.testing.assert_allclose(images.read_pixels(image), rgba, rtol=1e-3)


def test_previews_no_editor_shows_survive_saves_and_reloads(bpy_addon, fresh_scene, tmp_path):
    """Only the image an Image Editor shows had a user: the sidebar's other previews were dropped at the second
    save and reload, and their pictures in the panel with them."""
    from addon.blender import images

    bpy = bpy_addon
    rgba = np.ones((4, 4, 4), np.float32)
    images.store_image("NLM Unshown Preview", rgba)
    path = str(tmp_path / "kept.blend")
    for _ in range(3):
        bpy.ops.wm.save_as_mainfile(filepath=path)
        bpy.ops.wm.open_mainfile(filepath=path)
    assert "NLM Unshown Preview" in bpy.data.images


def test_a_preview_stored_again_at_another_size_takes_its_new_pixels(bpy_addon, fresh_scene):
    """Changing Lobe Size between two previews failed: the image was scaled, then its colour space was set, which
    put its buffer back at the generated size ("expected sequence size 2304, got 1024")."""
    from addon.blender import images

    rng = np.random.default_rng(4)
    for side in (24, 16, 40):
        rgba = rng.random((side, side, 4)).astype(np.float32)
        rgba[..., 3] = 1.0
        image = images.store_image("NLM Resized Preview", rgba)
        assert tuple(image.size) == (side, side)
        np.testing.assert_allclose(images.read_pixels(image), rgba, rtol=1e-6)

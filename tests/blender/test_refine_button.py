"""The Refine button (neural_layers.refine_latent) in bpy: it stores the refined latent on the material
with what it measured, it is the latent the core refinement returns, and bad targets are reported."""

from __future__ import annotations

import numpy as np
import pytest

from tests.blender.helpers import run_operator

pytest.importorskip("bpy")


def test_refine_stores_the_refined_latent_and_its_measurements(bpy_addon, material):
    bpy = bpy_addon
    from addon.blender import stack_io
    from addon.core.neural.refine import refine_latent

    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    material.neural_layers.model_size = "TINY"
    encoded = stack_io.latent_of(material).copy()
    r = run_operator(bpy.ops.neural_layers.refine_latent, budget=20.0)
    assert r.finished, r.error
    res = material.neural_refine
    assert res.size == "tiny" and len(res.key) == 64 and res.kept in ("yes", "no") and res.seconds > 0.0
    # the material is tagged: its evaluated copy (what the viewport is told changed) has the result too
    bpy.context.view_layer.update()
    assert material.evaluated_get(bpy.context.evaluated_depsgraph_get()).neural_refine.key == res.key
    assert stack_io.latent_is_current(material) and material.neural_layers.latent_size == "tiny"
    stored = stack_io.latent_of(material)
    # the same stack, models and settings: the core's cached result is the stored latent
    z, rep = refine_latent(stack_io.stack_from_material(material), "tiny", budget_s=20.0)
    assert rep.cached and rep.key == res.key and np.allclose(stored, z)
    if res.kept == "yes":  # kept: better on the validation pairs' loss (its median error is reported beside it)
        assert rep.validation_loss_after < rep.validation_loss_before and not np.allclose(stored, encoded)
    else:
        assert np.allclose(stored, encoded)
    # an edit of the stack makes the refined latent stale (the automatic update encodes it again)
    material.neural_layers.layers[-1].roughness = 0.2
    assert stack_io.latent_is_current(material) and not np.allclose(stack_io.latent_of(material), stored)


def _reports(capfd) -> dict:
    """The reports printed since the last call (background Blender prints them), by kind ("Warning", "Info")."""
    lines = capfd.readouterr().out.splitlines()
    return {
        kind: [ln.removeprefix(f"{kind}: ") for ln in lines if ln.startswith(f"{kind}: ")]
        for kind in ("Warning", "Info")
    }


@pytest.mark.parametrize("steps, kept", [(0, False), (12, False), (37, True)])
def test_a_refinement_its_budget_stopped_says_so_and_asks_for_more_time(
    bpy_addon, material, monkeypatch, capfd, steps, kept
):
    """A fit the time budget stopped read "did not improve on the validation pairs", where it had made no step: the
    reference walks had taken the budget. It says the budget ran out, after how many steps, and what to do."""
    from addon.blender import stack_io
    from addon.core.neural import refine

    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    material.neural_layers.model_size = "TINY"
    encoded = stack_io.latent_of(material).copy()

    def cut_short(stack, size, budget_s, progress=None):
        loss_after = 0.1 if kept else 0.2
        report = refine.RefineReport(
            size=size, key="0" * 64, kept=kept, validation_error_before=0.3, validation_error_after=0.25,
            validation_loss_before=0.2, validation_loss_after=loss_after, fit_loss_before=0.2, fit_loss_after=0.15,
            steps=steps, stopped="budget", budget_s=budget_s, reference_s=1.4, optimise_s=0.0, total_s=1.5,
        )  # fmt: skip
        return encoded + (0.1 if kept else 0.0), report

    monkeypatch.setattr(refine, "refine_latent", cut_short)
    capfd.readouterr()
    assert run_operator(bpy.ops.neural_layers.refine_latent, budget=1.0).finished
    reports = _reports(capfd)
    warnings, infos = reports["Warning"], reports["Info"]
    if steps == 0:
        (line,) = warnings
        assert "its time budget of 1 s ran out before the fit made a step (its reference walks took 1.4 s)" in line
        assert line.endswith("the encoded latent is kept; give Refine more time (Refine Budget)")
    elif not kept:
        (line,) = warnings
        assert "its time budget of 1 s ran out after 12 step(s) of the fit" in line
        assert line.endswith("the encoded latent is kept; give Refine more time (Refine Budget)")
    else:
        (line,) = [line for line in infos if "refined" in line]
        assert "ran out after 37 step(s) of the fit" in line and "a larger Refine Budget may refine it further" in line
    assert "did not improve" not in line
    assert material.neural_refine.kept == ("yes" if kept else "no")


def test_refine_reports_a_missing_material_or_an_empty_stack(bpy_addon, fresh_scene, material):
    bpy = bpy_addon
    r = run_operator(bpy.ops.neural_layers.refine_latent, material="no such material")
    assert r.error and "no material named 'no such material'" in r.error
    r = run_operator(bpy.ops.neural_layers.refine_latent)
    assert r.error and "empty layer stack" in r.error
    fresh_scene.view_layer.objects.active = None
    r = run_operator(bpy.ops.neural_layers.refine_latent)
    assert r.error and "no active object" in r.error


def test_bake_command_refine_flag_refines_and_keys_the_bake_apart(tmp_path):
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bake"))
    import bake as bake_cli
    from addon.core.textures import LatentTexture

    out = tmp_path / "out"
    argv = ["--preset", "coated_gold", "--resolution", "1", "1", "--model", "tiny", "--out", str(out)]
    assert bake_cli.main([*argv, "--refine", "0.01"]) == 0  # the one distinct texel is refined
    meta = LatentTexture.read_exr(out / "coated_gold.exr").metadata
    assert meta["refined"] == "1" and float(meta["refine_s"]) == 0.01 and meta["model"] == "tiny"
    assert len(list((out / ".refine").glob("refine_*.npz"))) == 1
    key = json.loads((out / "coated_gold.json").read_text())["key"]
    # without the flag: another key, baked again, unrefined
    assert bake_cli.main(argv) == 0
    plain = LatentTexture.read_exr(out / "coated_gold.exr")
    assert "refined" not in plain.metadata and json.loads((out / "coated_gold.json").read_text())["key"] != key
    assert bake_cli.main(["--preset", "coated_gold", "--out", str(out), "--refine", "-1"]) == 2


def _f12(bpy, scene, path):
    scene.render.filepath = str(path)
    scene.render.image_settings.file_format = "OPEN_EXR"
    bpy.ops.render.render(write_still=True)
    bpy.utils.expose_bundled_modules()
    import OpenImageIO as oiio  # noqa: N813

    buf = oiio.ImageBuf(str(path))
    assert not buf.has_error, buf.geterror()
    return buf.get_pixels(oiio.FLOAT)[..., :3]


def test_f12_renders_the_refined_latent_the_preview_shows_and_ignores_a_stale_one(bpy_addon, material, tmp_path):
    bpy = bpy_addon
    from addon.blender import scene_export, stack_io
    from addon.core import preview
    from addon.core.render.materials import resolve

    scene = bpy.context.scene
    scene.render.engine = "NEURAL_LAYERED"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 24, 16, 100
    scene.neural_render.samples, scene.neural_render.max_bounces = 2, 2
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    material.neural_layers.model_size = "TINY"
    plain = _f12(bpy, scene, tmp_path / "encoded.exr")
    assert run_operator(bpy.ops.neural_layers.refine_latent, budget=20.0).finished
    assert material.neural_refine.kept == "yes", "coated gold on the tiny decoder is one the refinement improves"
    # the exported material carries the stored (refined) latent; the renderer decodes exactly it, as the preview
    info = []
    core_scene, _ = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), info=info)
    (spec,) = [m for m, n in zip(core_scene.materials, core_scene.material_names, strict=True) if n == material.name]
    shown = preview.choose_brdf(
        stack_io.stack_from_material(material),
        "NEURAL",
        latent=stack_io.current_latent(material),
        size=stack_io.model_size(material),
    )
    z_shown = stack_io.current_latent(material)[0]
    made = resolve(spec, "neural")
    assert made.size == "tiny" and np.array_equal(made.z, z_shown) and not info
    wi, wo = np.array([[0.3, 0.1, 0.95]]), np.array([[-0.2, 0.4, 0.9]])
    wi, wo = wi / np.linalg.norm(wi, axis=1, keepdims=True), wo / np.linalg.norm(wo, axis=1, keepdims=True)
    from addon.core import neural

    np.testing.assert_allclose(
        neural.eval_brdf(made.z, wi, wo, size=made.size, top=made.top), shown.brdf(wi, wo), rtol=1e-6
    )
    refined = _f12(bpy, scene, tmp_path / "refined.exr")
    assert np.isfinite(refined).all() and np.abs(refined - plain).max() > 1e-3  # F12 changed with Refine
    # a latent refined by an earlier version (another key for the same stack and files): F12 encodes the stack
    # again and says why (an earlier version's, fitted to other targets, was rendered silently)
    key = material.neural_refine.key
    material.neural_refine.key = "0" * 64
    info = []
    core_scene, _ = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), info=info)
    assert all(getattr(m, "latent", None) is None for m in core_scene.materials)
    assert any("refined by an earlier version" in line for line in info), info
    assert stack_io.current_latent(material) is None  # the previews encode the stack again too, as F12 renders
    material.neural_refine.key = key
    assert np.array_equal(stack_io.current_latent(material)[0], z_shown)
    # the stack edited: the refined latent is stale, F12 encodes the stack again and says why
    refined_roughness = material.neural_layers.layers[-1].roughness
    material.neural_layers.layers[-1].roughness = 0.2
    info = []
    core_scene, _ = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), info=info)
    assert all(getattr(m, "latent", None) is None for m in core_scene.materials)
    assert any("refined latent is out of date" in line for line in info)
    # and back as it was: the stack is the refined one again, but its latent is the encoded one now, which F12
    # renders and says so (it took the encoded latent for the refined one, silently)
    material.neural_layers.layers[-1].roughness = refined_roughness
    assert material.neural_refine.kept == "replaced"
    info = []
    core_scene, _ = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), info=info)
    assert all(getattr(m, "latent", None) is None for m in core_scene.materials)
    assert any("refined latent was replaced" in line for line in info), info

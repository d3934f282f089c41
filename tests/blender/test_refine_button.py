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
    assert stack_io.latent_is_current(material) and material.neural_layers.latent_size == "tiny"
    stored = stack_io.latent_of(material)
    # the same stack, models and settings: the core's cached result is the stored latent
    z, rep = refine_latent(stack_io.stack_from_material(material), "tiny", budget_s=20.0)
    assert rep.cached and rep.key == res.key and np.allclose(stored, z)
    if res.kept == "yes":
        assert res.error_after < res.error_before and not np.allclose(stored, encoded)
    else:
        assert np.allclose(stored, encoded)
    # an edit of the stack makes the refined latent stale (the automatic update encodes it again)
    material.neural_layers.layers[-1].roughness = 0.2
    assert stack_io.latent_is_current(material) and not np.allclose(stack_io.latent_of(material), stored)


def test_refine_reports_a_missing_material_or_an_empty_stack(bpy_addon, fresh_scene, material):
    bpy = bpy_addon
    r = run_operator(bpy.ops.neural_layers.refine_latent, material="no such material")
    assert r.error and "no material named 'no such material'" in r.error
    r = run_operator(bpy.ops.neural_layers.refine_latent)
    assert r.error and "empty layer stack" in r.error
    fresh_scene.view_layer.objects.active = None
    r = run_operator(bpy.ops.neural_layers.refine_latent)
    assert r.error and "no active object" in r.error

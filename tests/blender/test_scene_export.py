"""What the scene export cannot evaluate is said, not silently replaced by a flat colour."""

from __future__ import annotations

import pytest

pytest.importorskip("bpy")


def _world_with(bpy, node_type):
    world = bpy.data.worlds.new("sky")
    tree = world.node_tree
    background = tree.nodes["Background"]
    node = tree.nodes.new(node_type)
    tree.links.new(node.outputs["Color"], background.inputs["Color"])
    return world


def test_a_sky_texture_world_warns_that_it_renders_flat(bpy_addon, fresh_scene):
    bpy = bpy_addon
    from addon.blender import scene_export

    warnings: list[str] = []
    env = scene_export._world(_world_with(bpy, "ShaderNodeTexSky"), warnings)
    assert env is not None and env.image is None
    assert any("SKY" in w and "does not evaluate" in w and "flat" in w for w in warnings), warnings


def test_a_plain_background_colour_exports_without_a_warning(bpy_addon, fresh_scene):
    bpy = bpy_addon
    from addon.blender import scene_export

    world = bpy.data.worlds.new("plain")
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.1, 0.2, 0.3, 1.0)
    warnings: list[str] = []
    env = scene_export._world(world, warnings)
    assert warnings == [] and env.constant == pytest.approx((0.1, 0.2, 0.3))


def test_a_procedural_base_colour_warns(bpy_addon, fresh_scene):
    bpy = bpy_addon
    from addon.blender import scene_export

    mat = bpy.data.materials.new("noisy")
    noise = mat.node_tree.nodes.new("ShaderNodeTexNoise")
    mat.node_tree.links.new(noise.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    warnings: list[str] = []
    scene_export.unmanaged_material(mat, warnings)
    assert any("TEX_NOISE" in w and "does not evaluate" in w for w in warnings), warnings


def test_path_properties_take_blend_relative_paths_without_a_warning(bpy_addon, material, tmp_path):
    import warnings

    bpy = bpy_addon
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        material.neural_layers.bake_directory = "//textures/"
        material.neural_layers.texture_path = "//textures/Material.exr"
        bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = 8, 6
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a.blend"))
        assert bpy.ops.neural_layers.render_preview(filepath="//preview.exr", samples=1) == {"FINISHED"}
    assert (tmp_path / "preview.exr").is_file()
    assert not [str(w.message) for w in caught if "relative" in str(w.message)]

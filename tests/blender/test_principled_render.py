"""An ordinary Principled BSDF renders its specular layer over its base colour, and its metal, as Cycles renders
them: a sphere under a sun and a grey world, rendered with Cycles and with this renderer's export of it, compared
block by block (``test_cycles_settings._assert_blocks_match``: each of 4 x 4 blocks within 5% of the brightest)."""

import math

import numpy as np
import pytest

from tests.blender.test_cycles_settings import _assert_blocks_match, _blocks, _both, _empty_scene

bpy = pytest.importorskip("bpy")


def _sphere_under_sun(ctx, inputs: dict, world: float):
    """A smooth UV sphere with a Principled BSDF of ``inputs`` (the rest Blender's defaults) under a sun of
    strength 3 and a world of grey ``world``, seen from above the horizon, 64 x 64."""
    s = _empty_scene(ctx, 64, 64)
    sky = bpy.data.worlds.new("grey")
    if sky.node_tree is None:
        sky.use_nodes = True
    sky.node_tree.nodes["Background"].inputs["Color"].default_value = (world, world, world, 1.0)
    s.world = sky
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy, sun.data.angle = 3.0, 0.0
    sun.rotation_euler = (math.radians(40.0), 0.0, math.radians(30.0))
    s.collection.objects.link(sun)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.location, cam.rotation_euler = (0.0, -6.0, 2.0), (math.radians(73.0), 0.0, 0.0)
    cam.data.lens = 50.0
    s.collection.objects.link(cam)
    s.camera = cam
    bpy.ops.mesh.primitive_uv_sphere_add(segments=48, ring_count=24, radius=1.0, location=(0.0, 0.0, 0.3))
    bpy.ops.object.shade_smooth()
    mat = bpy.data.materials.new("principled")  # 5.0: a new material has a Principled BSDF on its output
    node = mat.node_tree.nodes["Principled BSDF"]
    for name, value in inputs.items():
        node.inputs[name].default_value = value
    ctx.object.data.materials.append(mat)
    return mat


# (inputs, world grey, worst block difference / brightest block before (a Lambertian of the base colour) and after,
# measured at 64 x 64, 32 samples, 2 bounces: Cycles' image against this renderer's)
CASES = {
    "black-plastic": ({"Base Color": (0.0, 0.0, 0.0, 1.0), "Roughness": 0.2}, 0.2),  # 0.203 -> 0.011
    "dark-blue": ({"Base Color": (0.02, 0.03, 0.1, 1.0), "Roughness": 0.3}, 1.0),  # 0.081 -> 0.001
    "default": ({}, 0.2),  # base 0.8, roughness 0.5: 0.018 -> 0.003 (its layer reflects 2% of its light)
    "rough-0.6": ({"Base Color": (0.1, 0.1, 0.1, 1.0), "Roughness": 0.6}, 0.2),  # 0.114 -> 0.001
    "gold": ({"Base Color": (1.0, 0.77, 0.34, 1.0), "Metallic": 1.0, "Roughness": 0.3}, 0.2),  # 0.452 -> 0.033
    "metal-0.8": ({"Metallic": 1.0}, 0.2),  # roughness 0.5: 0.360 -> 0.014 (0.063 without multiple scattering)
    "half-metal": ({"Base Color": (0.5, 0.2, 0.1, 1.0), "Metallic": 0.5, "Roughness": 0.4}, 0.2),  # 0.164 -> 0.021
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_principled_bsdf_renders_as_in_cycles(fresh_scene, tmp_path, case):
    """The specular layer over the base and the metal were left out (a Lambertian of the base colour): a black
    plastic rendered 0.03 of Cycles' object pixels, a dark blue one 0.52, a gold metal 1.52. Each now renders within
    5% of the brightest block, with no warning, the default material too (a ``PrincipledMaterial``: its specular
    layer, 2% of its light, was left out while numpy's Principled shading cost 4x the render)."""
    from addon.core.render import PrincipledMaterial

    inputs, world = CASES[case]
    _sphere_under_sun(fresh_scene, inputs, world)
    cycles, ours, warnings = _both(fresh_scene, tmp_path, samples=32, bounces=2)
    assert warnings == []
    from tests.blender.test_render_engine import export

    scene, _ = export(fresh_scene)
    assert any(type(m) is PrincipledMaterial for m in scene.materials)
    _assert_blocks_match(cycles, ours, 0.05)
    assert np.abs(_blocks(ours) - _blocks(cycles)).max() > 0.0  # two renders, not one image twice


def test_a_principled_bsdf_without_layers_stays_a_lambertian(fresh_scene):
    """Specular IOR Level 0 and Metallic 0: nothing above the base, so the export keeps the exact (and cheaper)
    Lambertian; a linked Roughness keeps it too, with the specular layer named."""
    from addon.blender import scene_export
    from addon.core.render import LambertMaterial

    mat = _sphere_under_sun(fresh_scene, {"Specular IOR Level": 0.0}, 0.2)
    warnings: list[str] = []
    assert type(scene_export.unmanaged_material(mat, warnings)) is LambertMaterial and warnings == []
    node = mat.node_tree.nodes["Principled BSDF"]
    node.inputs["Specular IOR Level"].default_value = 0.5
    noise = mat.node_tree.nodes.new("ShaderNodeTexNoise")
    mat.node_tree.links.new(noise.outputs[0], node.inputs["Roughness"])
    assert type(scene_export.unmanaged_material(mat, warnings)) is LambertMaterial
    assert warnings == ["material 'principled': its specular reflection is left out (its Roughness is linked)"]


def test_a_rendered_principled_bsdf_names_only_what_it_leaves_out(fresh_scene):
    """A Specular Tint and a Coat are left out of a rendered Principled BSDF: each is named (under the specular
    layer, the base is a Lambertian of its base colour)."""
    from addon.blender import scene_export
    from addon.core.render import PrincipledMaterial

    dark = {"Base Color": (0.05, 0.05, 0.05, 1.0), "Specular Tint": (1.0, 0.2, 0.2, 1.0), "Coat Weight": 1.0}
    mat = _sphere_under_sun(fresh_scene, dark, 0.2)
    warnings: list[str] = []
    assert isinstance(scene_export.unmanaged_material(mat, warnings), PrincipledMaterial)
    assert warnings == [
        "material 'principled': its Principled BSDF's Coat is left out; its "
        "Specular Tint is left out (an untinted specular reflection)"
    ]


def _cube_on_plane(ctx):
    """Blender's startup scene (the cube with its default material, a point light, the camera) with a plane of
    another default material under the cube, 240 x 160."""
    r = ctx.scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 240, 160, 100
    bpy.ops.mesh.primitive_plane_add(size=12.0, location=(0.0, 0.0, -1.0))
    ctx.object.data.materials.append(bpy.data.materials.new("floor"))  # 5.0: a Principled BSDF of the defaults


def test_the_default_material_renders_its_highlight_at_about_a_lambertians_cost(fresh_scene, tmp_path):
    """Blender's default material (Principled BSDF, base 0.8, roughness 0.5, IOR 1.5, Specular IOR Level 0.5)
    rendered as a Lambertian of its base colour while numpy shaded a Principled BSDF (4x a Lambertian's render
    time): its soft highlight, 2% of the light it reflects, was left out, the worst of the sphere's blocks 1.8% of
    the brightest off Cycles' (0.3% with it). It renders through the compiled Principled loop: within 1% of Cycles'
    brightest block, and a cube on a plane of default materials within 2x the time of the same scene of
    Lambertians (measured 1.25-1.3x; numpy's Principled BSDF 2.7-4.1x), the least of three renders each, taken in
    turns in this process (the Lambertian first, its loops compiled)."""
    import time

    from addon.core.render import LambertMaterial, PrincipledMaterial, RenderSettings, render
    from tests.blender.test_render_engine import export

    _sphere_under_sun(fresh_scene, {}, 0.2)
    cycles, ours, warnings = _both(fresh_scene, tmp_path, samples=32, bounces=2)
    assert warnings == []
    _assert_blocks_match(cycles, ours, 0.01)

    bpy.ops.wm.read_homefile(app_template="")
    _cube_on_plane(fresh_scene)
    scene, warnings = export(fresh_scene)
    assert warnings == [] and all(type(m) is PrincipledMaterial for m in scene.materials)
    lambertian = [LambertMaterial(m.color) for m in scene.materials]
    principled = list(scene.materials)
    settings = RenderSettings(samples=16, seed=1, threads=1)
    seconds = {"lambertian": [], "principled": []}
    for materials in (lambertian, principled):  # compile (or load) every loop first
        scene.materials[:] = materials
        render(scene, RenderSettings(samples=1, threads=1))
    for _ in range(3):
        for name, materials in (("lambertian", lambertian), ("principled", principled)):
            scene.materials[:] = materials
            start = time.perf_counter()
            render(scene, settings)
            seconds[name].append(time.perf_counter() - start)
    assert min(seconds["principled"]) < 2.0 * min(seconds["lambertian"]), seconds

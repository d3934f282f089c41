"""Ordinary Blender materials (not made with a layer stack) render as Cycles renders them where the export reads
them (the output Cycles renders, reroutes, muted nodes and links, constant colours, colours above 1), and what the
Lambertian that stands for them leaves out is said, in words the user sees in Blender, in F12 and in the viewport.
The image cases render a small scene with Cycles and with this renderer's export of it and compare them block by
block."""

import math

import numpy as np
import pytest

from tests.blender.helpers import viewport_reports
from tests.blender.test_cycles_settings import (
    _assert_blocks_match,
    _both,
    _camera,
    _empty_scene,
    _textured_plane_in_white_sky,
)

bpy = pytest.importorskip("bpy")


def _bare_material(name: str):
    """A material with a Material Output alone (targeted at All, active)."""
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    for node in [n for n in nodes if n.type != "OUTPUT_MATERIAL"]:
        nodes.remove(node)
    return mat, nodes["Material Output"]


def _principled(mat, colour):
    """A Principled BSDF of base ``colour`` and no specular layer (Specular IOR Level 0): Lambertian in Cycles."""
    node = mat.node_tree.nodes.new("ShaderNodeBsdfPrincipled")
    node.inputs["Base Color"].default_value = (*colour, 1.0)
    node.inputs["Specular IOR Level"].default_value = 0.0
    return node


def _diffuse_node(mat, colour):
    node = mat.node_tree.nodes.new("ShaderNodeBsdfDiffuse")
    node.inputs["Color"].default_value = (*colour, 1.0)
    return node


def _world(ctx, colour):
    """A world of a Background of ``colour`` (strength 1) on its World Output."""
    world = bpy.data.worlds.new("sky")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (*colour, 1.0)
    ctx.scene.world = world
    return world


def _half_plane_in_sky(ctx, mat, sky=(1.0, 1.0, 1.0)):
    """A plane of material ``mat`` on the left half of a 16 x 8 view, the sky (``sky``) on the right half and all
    round it: direct light only, a pixel of the plane is its albedo times the sky (a black surface leaves the sky
    in the image, which the block comparison needs)."""
    _empty_scene(ctx, 16, 8)
    bpy.ops.mesh.primitive_plane_add(size=4.0, location=(-2.0, 0.0, 0.0))
    ctx.object.data.materials.append(mat)
    _camera(ctx, location=(0.0, 0.0, 4.0))
    return _world(ctx, sky)


def _tiles(name="tiles"):
    """A 4 x 4 float image of random texels (none near the colours the cases expect instead)."""
    px = np.ones((4, 4, 4), np.float32)
    px[..., :3] = np.random.default_rng(0).uniform(0.3, 0.95, (4, 4, 3))
    image = bpy.data.images.new(name, 4, 4, float_buffer=True)
    image.pixels.foreach_set(px.ravel())
    return image


def _assert_channels_match(cycles, ours, rel=0.05, n=4):
    for c in range(3):
        _assert_blocks_match(cycles[..., c], ours[..., c], rel, n=n)


# ---------------------------------------------------------------------------------------------- what Cycles renders


def test_the_output_cycles_renders_is_the_one_targeted_at_cycles(fresh_scene, tmp_path):
    """The output node's Target was ignored: the active output rendered, an EEVEE-only one too (a red material on a
    Cycles output rendered the green of an active All output; a grey world the red of an active EEVEE output,
    2.3x Cycles' image). Cycles renders Blender's choice for it: an output targeted at Cycles, else at All."""
    ctx = fresh_scene
    mat, cycles_out = _bare_material("two outputs")
    cycles_out.target = "CYCLES"
    mat.node_tree.links.new(_principled(mat, (0.8, 0.1, 0.1)).outputs[0], cycles_out.inputs["Surface"])
    all_out = mat.node_tree.nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(_diffuse_node(mat, (0.1, 0.8, 0.1)).outputs[0], all_out.inputs["Surface"])
    all_out.is_active_output = True
    world = _half_plane_in_sky(ctx, mat, sky=(0.5, 0.5, 0.5))
    tree = world.node_tree
    eevee_out = tree.nodes.new("ShaderNodeOutputWorld")
    eevee_out.target = "EEVEE"
    red = tree.nodes.new("ShaderNodeBackground")
    red.inputs["Color"].default_value = (1.0, 0.0, 0.0, 1.0)
    tree.links.new(red.outputs[0], eevee_out.inputs["Surface"])
    eevee_out.is_active_output = True
    assert all_out.is_active_output and eevee_out.is_active_output
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert warnings == []
    _assert_channels_match(cycles, ours)
    assert cycles[:, :8, 0].mean() > 3.0 * cycles[:, :8, 1].mean()  # the red material, under the grey sky


def test_a_reroute_between_an_image_and_the_base_colour_is_followed(fresh_scene, tmp_path):
    """A Reroute node between an Image Texture and the colour: the texture was not read (the viewport colour
    rendered, 2.6x Cycles' object pixels, with a warning naming a REROUTE node)."""
    ctx = fresh_scene
    _, mat, tex = _textured_plane_in_white_sky(ctx)
    tree = mat.node_tree
    colour = tree.nodes["Diffuse BSDF"].inputs["Color"]
    tree.links.remove(colour.links[0])
    first, second = tree.nodes.new("NodeReroute"), tree.nodes.new("NodeReroute")
    tree.links.new(tex.outputs["Color"], first.inputs[0])
    tree.links.new(first.outputs[0], second.inputs[0])
    tree.links.new(second.outputs[0], colour)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert warnings == []
    _assert_channels_match(cycles, ours, 0.06, n=8)


def _muted_principled(mat, out):
    principled = _principled(mat, (0.8, 0.1, 0.1))
    mat.node_tree.links.new(principled.outputs[0], out.inputs["Surface"])
    principled.mute = True  # a BSDF passes nothing through: the surface is black


def _muted_surface_link(mat, out):
    principled = _principled(mat, (0.8, 0.1, 0.1))
    mat.node_tree.links.new(principled.outputs[0], out.inputs["Surface"]).is_muted = True


def _image_on_base_colour(mat, out):
    principled = _principled(mat, (0.8, 0.1, 0.1))
    mat.node_tree.links.new(principled.outputs[0], out.inputs["Surface"])
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = _tiles()
    return tex, mat.node_tree.links.new(tex.outputs["Color"], principled.inputs["Base Color"])


def _muted_image(mat, out):
    tex, _ = _image_on_base_colour(mat, out)
    tex.mute = True  # no texture: the Base Color's own red


def _muted_image_link(mat, out):
    _, link = _image_on_base_colour(mat, out)
    link.is_muted = True


def _muted_mix_shader(mat, out):
    mix = mat.node_tree.nodes.new("ShaderNodeMixShader")
    mat.node_tree.links.new(_diffuse_node(mat, (0.1, 0.8, 0.1)).outputs[0], mix.inputs[1])
    mat.node_tree.links.new(_principled(mat, (0.8, 0.1, 0.1)).outputs[0], mix.inputs[2])
    mat.node_tree.links.new(mix.outputs[0], out.inputs["Surface"])
    mix.mute = True  # passes its first shader on: the green Diffuse BSDF


def _rgb_node(mat, out):
    principled = _principled(mat, (0.8, 0.8, 0.8))
    mat.node_tree.links.new(principled.outputs[0], out.inputs["Surface"])
    rgb = mat.node_tree.nodes.new("ShaderNodeRGB")
    rgb.outputs[0].default_value = (0.1, 0.7, 0.2, 1.0)
    mat.node_tree.links.new(rgb.outputs[0], principled.inputs["Base Color"])


def _value_node_through_a_reroute(mat, out):
    diffuse = _diffuse_node(mat, (0.8, 0.8, 0.8))
    mat.node_tree.links.new(diffuse.outputs[0], out.inputs["Surface"])
    value, reroute = mat.node_tree.nodes.new("ShaderNodeValue"), mat.node_tree.nodes.new("NodeReroute")
    value.outputs[0].default_value = 0.3
    mat.node_tree.links.new(value.outputs[0], reroute.inputs[0])
    mat.node_tree.links.new(reroute.outputs[0], diffuse.inputs["Color"])


@pytest.mark.parametrize(
    "build",
    [_muted_principled, _muted_surface_link, _muted_image, _muted_image_link, _muted_mix_shader, _rgb_node,
     _value_node_through_a_reroute],
    ids=["muted-principled", "muted-surface-link", "muted-image-node", "muted-image-link", "muted-mix-shader",
         "color-node", "value-node"],
)  # fmt: skip
def test_node_chains_render_as_in_cycles(fresh_scene, tmp_path, build):
    """Muted nodes and links rendered as live ones: a muted Principled BSDF rendered its red where Cycles renders
    black (357x Cycles' object pixels), a muted Image Texture its image where Cycles renders the Base Color, a muted
    Mix Shader the viewport colour. Cycles takes a muted link as absent and a muted node as passing on the input
    its internal link names (a BSDF or an Image Texture names none). A Color (RGB) or Value node on the base colour
    rendered the viewport colour (a green RGB node rendered grey, 2.7x Cycles' object pixels), with a warning: its
    value renders, as in Cycles (a value as grey)."""
    ctx = fresh_scene
    mat, out = _bare_material("chain")
    build(mat, out)
    _half_plane_in_sky(ctx, mat)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert warnings == []
    _assert_channels_match(cycles, ours)


@pytest.mark.parametrize("kind", ["diffuse", "principled"])
def test_a_colour_above_1_renders_as_in_cycles(fresh_scene, tmp_path, kind):
    """Cycles does not clip a surface's colour to 1: a Diffuse BSDF of colour 1.5 rendered 0.667 of Cycles' image,
    a Principled base colour of 2 half of it, clipped without a word."""
    ctx = fresh_scene
    mat, out = _bare_material("bright")
    node = _diffuse_node(mat, (1.5, 1.2, 0.6)) if kind == "diffuse" else _principled(mat, (2.0, 1.3, 0.4))
    mat.node_tree.links.new(node.outputs[0], out.inputs["Surface"])
    _half_plane_in_sky(ctx, mat)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert warnings == []
    assert cycles[:, :8, 0].mean() > 1.3  # brighter than the white sky beside it
    _assert_channels_match(cycles, ours)


@pytest.mark.parametrize("missing", ["no-image", "missing-file"])
def test_a_missing_image_renders_magenta_as_in_cycles(fresh_scene, tmp_path, missing):
    """An Image Texture node without an image, or whose image's file is missing, rendered the socket's own colour
    (grey) where Cycles renders magenta, its sign of a missing image; it renders magenta, with a warning."""
    ctx = fresh_scene
    mat, out = _bare_material("missing")
    node = _diffuse_node(mat, (0.5, 0.5, 0.5))
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    if missing == "missing-file":
        tex.image = bpy.data.images.load(str(_write_png(tmp_path / "gone.png")))
        (tmp_path / "gone.png").unlink()
        tex.image.reload()
    mat.node_tree.links.new(tex.outputs["Color"], node.inputs["Color"])
    mat.node_tree.links.new(node.outputs[0], out.inputs["Surface"])
    _half_plane_in_sky(ctx, mat)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert len(warnings) == 1 and "rendered magenta" in warnings[0]
    assert cycles[:, :8, 0].mean() > 0.9 and cycles[:, :8, 1].mean() < 0.05  # magenta in Cycles
    _assert_channels_match(cycles, ours)


def test_a_world_environment_without_an_image_renders_magenta_as_in_cycles(fresh_scene, tmp_path):
    """An Environment Texture node without an image lit the scene with the Background's own colour where Cycles
    lights it magenta."""
    ctx = fresh_scene
    mat, out = _bare_material("grey")
    mat.node_tree.links.new(_diffuse_node(mat, (0.5, 0.5, 0.5)).outputs[0], out.inputs["Surface"])
    world = _half_plane_in_sky(ctx, mat)
    env = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    world.node_tree.links.new(env.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert len(warnings) == 1 and "rendered magenta" in warnings[0]
    assert cycles[:, 8:, 0].mean() > 0.9 and cycles[:, 8:, 1].mean() < 0.05  # the sky beside the plane
    assert ours[..., 1].max() < 1e-6  # no green anywhere: the plane is lit by magenta alone
    for c in (0, 2):
        _assert_blocks_match(cycles[..., c], ours[..., c], 0.05, n=4)


def _write_png(path):
    image = bpy.data.images.new("written", 2, 2)
    image.pixels.foreach_set(np.full(16, 0.25, np.float32))
    image.filepath_raw = str(path)
    image.file_format = "PNG"
    image.save()
    bpy.data.images.remove(image)
    return path


def test_a_lambertian_colour_keeps_what_is_above_1_and_zeroes_what_is_not_a_reflectance():
    from addon.core.render import LambertMaterial

    assert np.array_equal(LambertMaterial((1.5, 0.25, 3.0)).color, (1.5, 0.25, 3.0))
    assert np.array_equal(LambertMaterial((-0.5, math.nan, math.inf)).color, (0.0, 0.0, 0.0))
    assert np.array_equal(LambertMaterial((-math.inf, 0.5, 1.0)).color, (0.0, 0.5, 1.0))
    # a texture's texels too (an HDR image on the base colour): kept above 1, a negative one (a filter's ring) 0
    from addon.core import kernels

    texels = np.array([[1.5, -0.2, 0.5]], np.float32)
    np.testing.assert_array_equal(kernels.tinted_albedo(texels, np.array([2.0, 2.0, 1.0])), [[3.0, 0.0, 0.5]])


# ---------------------------------------------------------------------------------------------- what is said


def _warnings_of(mat) -> list[str]:
    from addon.blender import scene_export

    warnings: list[str] = []
    scene_export.unmanaged_material(mat, warnings)
    return warnings


def _default_principled(name="m"):
    mat = bpy.data.materials.new(name)  # 5.0: a new material has its node tree, Principled on the output
    return mat, mat.node_tree.nodes["Principled BSDF"]


def test_a_specular_layer_that_changes_the_image_noticeably_is_named(fresh_scene):
    """The Principled BSDF's specular layer was left out without a word: a black plastic (base 0, roughness 0.2)
    rendered 0.03 of Cycles' object pixels, a dark blue one 0.52. It is rendered where its Metallic, Roughness, IOR
    and Specular IOR Level are constants (``PrincipledMaterial``: test_principled_render.py); where one is linked
    the surface is a Lambertian, and the layer is named where it reflects more than 5% of the light the surface
    reflects in Cycles, or where its own inputs are linked; a pale base colour (the default 0.8, 1.5% off Cycles'
    image) stays quiet. The default material itself, its inputs constant, renders its layer."""
    from addon.blender import scene_export
    from addon.core.render import LambertMaterial, PrincipledMaterial

    mat, principled = _default_principled("default")
    assert _warnings_of(mat) == []
    # the default material's layer (2% of its light) is rendered too: it was a Lambertian while numpy shaded it
    assert isinstance(scene_export.unmanaged_material(mat, []), PrincipledMaterial)
    principled.inputs["Base Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    principled.inputs["Roughness"].default_value = 0.2
    assert _warnings_of(mat) == []  # rendered
    assert isinstance(scene_export.unmanaged_material(mat, []), PrincipledMaterial)
    value = mat.node_tree.nodes.new("ShaderNodeValue")
    value.outputs[0].default_value = 0.0
    mat.node_tree.links.new(value.outputs[0], principled.inputs["Metallic"])  # a linked Metallic: a Lambertian
    assert isinstance(scene_export.unmanaged_material(mat, []), LambertMaterial)
    (warning,) = _warnings_of(mat)
    assert "its specular reflection is left out (IOR 1.5," in warning
    assert "about 100% of the light" in warning
    principled.inputs["Base Color"].default_value = (0.02, 0.04, 0.3, 1.0)  # dark blue
    (warning,) = _warnings_of(mat)
    assert "specular reflection is left out" in warning
    principled.inputs["Specular IOR Level"].default_value = 0.0  # no specular layer: a Lambertian in Cycles too
    assert "specular reflection" not in _warnings_of(mat)[0]
    mat, principled = _default_principled("rough map")
    noise = mat.node_tree.nodes.new("ShaderNodeTexNoise")
    mat.node_tree.links.new(noise.outputs[0], principled.inputs["Roughness"])
    assert _warnings_of(mat) == ["material 'rough map': its specular reflection is left out (its Roughness is linked)"]
    # the estimate: a smooth dielectric's Fresnel average (0.092 at n = 1.5, Specular IOR Level 0.5) over the base
    albedo = scene_export.specular_albedo(1.5, 0.5, (1.0, 1.0, 1.0))
    assert albedo == pytest.approx(0.0918, abs=5e-4)
    assert scene_export.specular_share(albedo, 0.8) == pytest.approx(0.0224, abs=5e-4)
    assert scene_export.specular_albedo(1.5, 0.0, (1.0, 1.0, 1.0)) == 0.0
    assert scene_export.specular_albedo(1.5, 1.0, (1.0, 1.0, 1.0)) > albedo  # F0 doubled
    assert scene_export.specular_albedo(1.5, 0.5, (1.0, 0.0, 0.0)) < albedo  # a tint darkens F0


def test_principled_diffuse_roughness_anisotropic_and_thin_film_are_named(fresh_scene):
    """A Diffuse BSDF's Roughness was named, a Principled BSDF's Diffuse Roughness (3.6% off Cycles at 1),
    Anisotropic (2.7% at 0.5) and Thin Film (3.5%) were not."""
    mat, principled = _default_principled("rough")
    principled.inputs["Diffuse Roughness"].default_value = 1.0
    assert _warnings_of(mat) == ["material 'rough': its Principled BSDF's Diffuse Roughness is left out"]
    principled.inputs["Diffuse Roughness"].default_value = 0.0
    principled.inputs["Anisotropic"].default_value = 0.5
    principled.inputs["Thin Film Thickness"].default_value = 300.0
    assert _warnings_of(mat) == ["material 'rough': its Principled BSDF's Anisotropic and Thin Film are left out"]


def test_warnings_name_nodes_as_blender_shows_them(fresh_scene):
    """The warnings named nodes by their internal identifiers (BSDF_GLOSSY, MIX_SHADER, VALTORGB, TEX_COORD
    Generated, GROUP) in broken English ("a EMISSION node", "the Principled BSDF's Metallic are left out"). They
    name them as their headers do, with "a" or "an" as said and verbs that agree."""
    from addon.blender import scene_export

    def surface(kind, name):
        mat, out = _bare_material(name)
        node = mat.node_tree.nodes.new(kind)
        mat.node_tree.links.new(node.outputs[0], out.inputs["Surface"])
        return mat, node

    said = []
    mat, _ = surface("ShaderNodeBsdfGlossy", "glossy")
    said += _warnings_of(mat)
    assert said[-1].startswith("material 'glossy': its surface is a Glossy BSDF node, which this renderer does not")
    mat, _ = surface("ShaderNodeEmission", "emit")
    said += _warnings_of(mat)
    assert "its surface is an Emission node" in said[-1] and "emits no light" in said[-1]
    mat, _ = surface("ShaderNodeMixShader", "mix")
    said += _warnings_of(mat)
    assert "its surface is a Mix Shader node" in said[-1] and "the viewport colour" in said[-1]
    mat, out = _bare_material("grouped")
    group = mat.node_tree.nodes.new("ShaderNodeGroup")
    group.node_tree = bpy.data.node_groups.new("Wood", "ShaderNodeTree")
    group.node_tree.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    mat.node_tree.links.new(group.outputs[0], out.inputs["Surface"])
    said += _warnings_of(mat)
    assert "its surface is a Group node 'Wood'" in said[-1]

    mat, principled = _default_principled("shiny")
    value = mat.node_tree.nodes.new("ShaderNodeValue")
    value.outputs[0].default_value = 1.0
    mat.node_tree.links.new(value.outputs[0], principled.inputs["Metallic"])  # constant Metallic is rendered
    said += _warnings_of(mat)
    assert said[-1] == "material 'shiny': its Principled BSDF's Metallic is left out (a Lambertian of its base colour)"
    principled.inputs["Coat Weight"].default_value = 1.0
    principled.inputs["Alpha"].default_value = 0.5
    said += _warnings_of(mat)
    assert "its Principled BSDF's Metallic, Coat and Alpha are left out" in said[-1]

    mat, principled = _default_principled("ramp")
    ramp = mat.node_tree.nodes.new("ShaderNodeValToRGB")
    ramp.label = "Rust"
    mat.node_tree.links.new(ramp.outputs["Color"], principled.inputs["Base Color"])
    said += _warnings_of(mat)
    assert "its Base Color comes from a Color Ramp node 'Rust', which this renderer does not evaluate" in said[-1]

    mat, principled = _default_principled("generated")
    tex, coords = mat.node_tree.nodes.new("ShaderNodeTexImage"), mat.node_tree.nodes.new("ShaderNodeTexCoord")
    tex.image = bpy.data.images.new("img", 2, 2)
    mat.node_tree.links.new(coords.outputs["Generated"], tex.inputs["Vector"])
    mat.node_tree.links.new(tex.outputs["Color"], principled.inputs["Base Color"])
    said += _warnings_of(mat)
    assert "its Vector is a Texture Coordinate node's Generated output (looked up with the UV map)" in said[-1]

    world = bpy.data.worlds.new("sky")
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    world.node_tree.links.new(sky.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    scene_export._world(world, said)
    assert "the Background colour comes from a Sky Texture node" in said[-1]
    for identifier in ("BSDF_", "MIX_SHADER", "VALTORGB", "TEX_", "GROUP", "EMISSION", " a E", " a A"):
        assert not any(identifier in line for line in said), (identifier, said)


# ---------------------------------------------------------------------------------------------- the viewport


def test_the_viewport_reports_what_f12_warns_of_once_per_line():
    """The viewport's Rendered mode threw every export warning away (a Glossy BSDF rendered as a flat Lambertian
    without a word there). It reports them as F12 does, each distinct line once, not at every edit."""
    from addon.blender import engine

    said: set[str] = set()
    assert engine.viewport_reports(["stale"], ["a", "b", "a"], said) == [
        ("INFO", "stale"),
        ("WARNING", "a"),
        ("WARNING", "b"),
    ]
    assert engine.viewport_reports(["stale"], ["b", "c"], said) == [("WARNING", "c")]
    # a slider dragged: the same warning with another share, said once
    assert engine.viewport_reports([], ["m: about 54% of it"], said) == [("WARNING", "m: about 54% of it")]
    assert engine.viewport_reports([], ["m: about 53% of it", "m: IOR 1.45"], said) == [("WARNING", "m: IOR 1.45")]
    # two materials whose names differ in a number alone are two lines
    two = ["material 'Mat.001': a Glossy BSDF", "material 'Mat.002': a Glossy BSDF"]
    assert engine.viewport_reports([], two, said) == [("WARNING", two[0]), ("WARNING", two[1])]


def test_the_viewport_shows_the_exports_warnings(fresh_scene, monkeypatch):
    mat, out = _bare_material("glossy")
    glossy = mat.node_tree.nodes.new("ShaderNodeBsdfGlossy")
    mat.node_tree.links.new(glossy.outputs[0], out.inputs["Surface"])
    fresh_scene.scene.objects["Cube"].material_slots[0].material = mat
    reports = viewport_reports(monkeypatch, fresh_scene)
    glossy_lines = [(kind, text) for kind, text in reports if "Glossy BSDF" in text]
    assert glossy_lines == [({"WARNING"}, glossy_lines[0][1])], reports
    assert glossy_lines[0][1].startswith("material 'glossy': its surface is a Glossy BSDF node")

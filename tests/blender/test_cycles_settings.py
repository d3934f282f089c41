"""The light, camera and world settings a Blender user sets render as Cycles renders them: each case renders a
small scene with Cycles and with this renderer's export of it, and compares their images block by block."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from tests.blender.helpers import DrawnProps
from tests.blender.test_render_engine import export, read_image

bpy = pytest.importorskip("bpy")


def _empty_scene(ctx, w: int, h: int):
    for ob in list(ctx.scene.objects):
        bpy.data.objects.remove(ob)
    ctx.scene.world = None
    r = ctx.scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
    return ctx.scene


def _diffuse(color):
    """A Diffuse BSDF material: Lambertian in both renderers."""
    mat = bpy.data.materials.new("diffuse")
    if mat.node_tree is None:
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    for n in list(nodes):
        nodes.remove(n)
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (*color, 1.0)
    out = nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(diffuse.outputs[0], out.inputs["Surface"])
    return mat


def _floor(ctx, size=100.0, z=0.0, color=(0.5, 0.5, 0.5)):
    bpy.ops.mesh.primitive_plane_add(size=size, location=(0.0, 0.0, z))
    ctx.object.data.materials.append(_diffuse(color))
    return ctx.object


def _checker_floor(ctx, size: float, cuts: int, tiles_per_metre: float):
    """A floor of ``size`` metres in checkers of a light and a dark Lambertian, ``tiles_per_metre`` a side: a
    misframed image moves their edges from block to block."""
    floor = _floor(ctx, size=size)
    floor.data.materials.append(_diffuse((0.05, 0.05, 0.05)))
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.subdivide(number_cuts=cuts)
    bpy.ops.object.mode_set(mode="OBJECT")
    for poly in floor.data.polygons:
        x, y = (math.floor(tiles_per_metre * c) for c in poly.center[:2])
        poly.material_index = int(x + y) % 2
    return floor


def _camera(ctx, location=(0.0, 0.0, 4.0), rotation=(0.0, 0.0, 0.0), **settings):
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.location, cam.rotation_euler = location, rotation
    cam.data.lens = 30.0
    for k, v in settings.items():
        setattr(cam.data, k, v)
    ctx.scene.collection.objects.link(cam)
    ctx.scene.camera = cam
    return cam


def _light(ctx, kind, location=(0.3, 0.2, 1.5), rotation=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0), **settings):
    light = bpy.data.lights.new("L", kind)
    if kind in ("POINT", "SPOT"):
        light.shadow_soft_size = 0.0
    for k, v in settings.items():
        setattr(light, k, v)
    ob = bpy.data.objects.new("L", light)
    ob.location, ob.rotation_euler, ob.scale = location, rotation, scale
    ctx.scene.collection.objects.link(ob)
    return ob


def _both(ctx, tmp_path, samples=64, bounces=0, channels=3):
    """(Cycles' image, ours) of the scene as it is, (H, W, ``channels``) float64 (4: with alpha), with the export's
    warnings."""
    from addon.core.render import RenderSettings, render

    scene, warnings = export(ctx)
    transparent = ctx.scene.render.film_transparent
    settings = RenderSettings(samples=samples, max_bounces=bounces, seed=3, transparent=transparent)
    ours = render(scene, settings)[0].rgba()[..., :channels]
    s = ctx.scene
    s.render.engine = "CYCLES"
    s.cycles.device = "CPU"
    s.cycles.samples, s.cycles.max_bounces, s.cycles.use_denoising = samples, bounces, False
    s.cycles.use_adaptive_sampling = False
    s.cycles.pixel_filter_type = "BOX"
    s.cycles.light_sampling_threshold = 0.0
    s.view_settings.view_transform = "Standard"
    s.render.image_settings.file_format = "OPEN_EXR"
    s.render.image_settings.color_depth = "32"
    s.render.image_settings.color_mode = "RGBA"
    s.render.filepath = str(tmp_path / "cycles.exr")
    bpy.ops.render.render(write_still=True)
    cycles = read_image(tmp_path / "cycles.exr")[..., :channels].astype(np.float64)
    return cycles, ours.astype(np.float64), warnings


def _blocks(img, n=4):
    h, w = img.shape[:2]
    return np.array(
        [[img[i * h // n : (i + 1) * h // n, j * w // n : (j + 1) * w // n].mean() for j in range(n)] for i in range(n)]
    )


def _assert_blocks_match(cycles, ours, rel, n=4):
    """Every block of the two images within ``rel`` of Cycles' (relative to the image's brightest block, so that
    a block at a cone's dark edge is held to the image's scale)."""
    bc, bo = _blocks(cycles, n), _blocks(ours, n)
    assert bc.max() > 1e-3, "Cycles rendered black"
    assert np.abs(bo - bc).max() <= rel * bc.max(), f"blocks, Cycles:\n{bc}\nours:\n{bo}"


@pytest.mark.parametrize(
    "kind, settings",
    [
        ("POINT", {"energy": 100.0, "exposure": 1.5}),
        ("SUN", {"energy": 2.0, "exposure": -1.0, "angle": 0.0}),
        ("AREA", {"energy": 100.0, "shape": "SQUARE", "size": 0.5, "normalize": False}),
        ("POINT", {"energy": 100.0, "use_temperature": True, "temperature": 3000.0}),
        ("AREA", {"energy": 100.0, "shape": "DISK", "size": 0.6, "spread": math.radians(60.0)}),
    ],
    ids=["exposure", "sun-exposure", "area-not-normalized", "temperature", "area-spread"],
)
def test_light_settings_render_as_in_cycles(fresh_scene, tmp_path, kind, settings):
    """Exposure, Normalize, Temperature and Spread: each was left out of the export (ratios 0.50, 4.0 and white
    light for 3000 K; blocks 0.25 to 13 of Cycles' under a 30-degree spread)."""
    ctx = fresh_scene
    _empty_scene(ctx, 24, 16)
    _floor(ctx)
    _camera(ctx)
    _light(ctx, kind, rotation=(0.2, -0.15, 0.0), **settings)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=256 if "spread" in settings else 64)
    assert warnings == []
    for c in range(3):  # per channel: a temperature tints
        _assert_blocks_match(cycles[..., c], ours[..., c], 0.05 if "spread" in settings else 0.02)


@pytest.mark.parametrize("scale", [(1.0, 1.0, 0.5), (1.0, 0.4, 1.0)])
def test_a_scaled_spot_lights_the_cone_cycles_does(fresh_scene, tmp_path, scale):
    """Blender tests the cone in the light's own scaled frame: flattened along z, a wider cone; squeezed in y, an
    ellipse (ours was the unscaled circle: means 0.45 and 2.3 of Cycles')."""
    ctx = fresh_scene
    _empty_scene(ctx, 24, 24)
    _floor(ctx)
    _camera(ctx)
    _light(ctx, "SPOT", location=(0.0, 0.0, 2.0), scale=scale, energy=300.0, spot_size=math.radians(60), spot_blend=0.0)
    cycles, ours, _ = _both(ctx, tmp_path)
    _assert_blocks_match(cycles, ours, 0.03, n=6)


def test_an_area_light_hidden_from_the_camera_is_not_seen(fresh_scene, tmp_path):
    """Blender's new lights are hidden from camera rays (Object > Visibility > Camera); ours drew them (a mean of
    3.7 where Cycles' image was black)."""
    ctx = fresh_scene
    _empty_scene(ctx, 16, 12)
    light = _light(ctx, "AREA", location=(0.0, 0.0, 2.0), energy=50.0, size=1.0)  # shining down
    _camera(ctx, location=(0.0, 0.0, 0.0), rotation=(math.pi, 0.0, 0.0), lens=20.0)  # looking up into it
    light.visible_camera = False
    cycles, ours, _ = _both(ctx, tmp_path, samples=16)
    assert cycles.max() < 1e-6 and ours.max() < 1e-6
    light.visible_camera = True
    cycles, ours, _ = _both(ctx, tmp_path, samples=64)
    assert ours.max() > 1.0
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.02)  # the light's edges cut pixels: their means


@pytest.mark.parametrize(
    "size, settings, aspect",
    [
        ((32, 20), {"shift_x": 0.2, "shift_y": -0.1, "sensor_fit": "VERTICAL"}, (1.0, 1.0)),
        ((20, 32), {"shift_x": 0.2, "shift_y": -0.1, "sensor_fit": "HORIZONTAL"}, (1.0, 1.0)),
        ((32, 20), {"shift_x": -0.15}, (2.0, 1.0)),
        ((32, 20), {"sensor_fit": "VERTICAL"}, (1.0, 1.5)),
    ],
    ids=["shift-vertical-fit", "shift-horizontal-fit", "pixel-aspect", "pixel-aspect-vertical-fit"],
)
def test_the_camera_frames_what_cycles_frames(fresh_scene, tmp_path, size, settings, aspect):
    """The lens shift counts in the fitted side and the pixel aspect widens the view (ours were off by about 5
    pixels of 32, and the same image whatever the aspect). A floor of checkers under a sun: a misframed image
    moves its edges from block to block."""
    ctx = fresh_scene
    _empty_scene(ctx, *size)
    ctx.scene.render.pixel_aspect_x, ctx.scene.render.pixel_aspect_y = aspect
    _checker_floor(ctx, 6.0, cuts=5, tiles_per_metre=1.0)
    _camera(ctx, location=(0.3, -0.2, 5.0), **settings)
    _light(ctx, "SUN", energy=3.0, angle=0.0)
    cycles, ours, _ = _both(ctx, tmp_path, samples=32)
    _assert_blocks_match(cycles, ours, 0.04, n=4)


@pytest.mark.parametrize("clip", [(7.0, 100.0), (0.1, 3.5)], ids=["start-beyond-floor", "end-before-floor"])
def test_the_camera_clips_as_cycles_does_and_the_world_shows_beyond(fresh_scene, tmp_path, clip):
    """Clip Start and End (ours rendered everything): a floor 4 m from the camera is cut by either, and the
    world is seen where it was."""
    ctx = fresh_scene
    _empty_scene(ctx, 16, 12)
    _floor(ctx)
    _camera(ctx, clip_start=clip[0], clip_end=clip[1])
    world = bpy.data.worlds.new("sky")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.2, 0.3, 0.4, 1.0)
    ctx.scene.world = world
    _light(ctx, "SUN", energy=3.0, angle=0.0)
    cycles, ours, _ = _both(ctx, tmp_path, samples=8)
    assert np.allclose(cycles, (0.2, 0.3, 0.4), atol=1e-3)
    assert np.allclose(ours, (0.2, 0.3, 0.4), atol=1e-6)


def _sky(ctx, tmp_path, rotation_z=None, vector_type="POINT"):
    """A world of an equirectangular image whose pixels tell directions apart, turned by a Mapping node."""
    w, h = 64, 32
    u, v = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    px = np.ones((h, w, 4), np.float32)
    px[..., 0], px[..., 1], px[..., 2] = 2.0 * u, 2.0 * v, ((np.floor(u * 8) + np.floor(v * 4)) % 2) * 0.5 + 0.1
    image = bpy.data.images.new("sky", w, h, float_buffer=True)
    image.pixels = px.ravel()
    image.filepath_raw = str(tmp_path / "sky.exr")
    image.file_format = "OPEN_EXR"
    image.save()
    world = bpy.data.worlds.new("W")
    tree = world.node_tree
    if tree is None:
        world.use_nodes = True
        tree = world.node_tree
    env = tree.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(str(tmp_path / "sky.exr"), check_existing=False)
    env.interpolation = "Closest"  # ours looks a pixel up as it is
    tree.links.new(env.outputs["Color"], tree.nodes["Background"].inputs["Color"])
    if rotation_z is not None:
        coords, mapping = tree.nodes.new("ShaderNodeTexCoord"), tree.nodes.new("ShaderNodeMapping")
        mapping.vector_type = vector_type
        mapping.inputs["Rotation"].default_value = (0.0, 0.0, rotation_z)
        tree.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
        tree.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    ctx.scene.world = world


@pytest.mark.parametrize(
    "rotation, vector_type", [(0.0, "POINT"), (math.radians(90.0), "POINT"), (math.radians(37.0), "TEXTURE")]
)
def test_a_mapping_nodes_z_rotation_turns_the_sky_as_in_cycles(fresh_scene, tmp_path, rotation, vector_type):
    """The usual HDRI rotation (ours ignored it: blocks 0.46 to 1.37 of Cycles' at 90 degrees). Seen directly, so
    every block is a part of the sky; a fraction of a column is interpolated, hence the looser bound at 37."""
    ctx = fresh_scene
    _empty_scene(ctx, 32, 16)
    _camera(ctx, location=(0.0, 0.0, 0.0), rotation=(math.radians(80), 0.0, math.radians(30)), lens=12.0)
    _sky(ctx, tmp_path, rotation, vector_type)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=16)
    assert warnings == []
    for c in range(3):
        _assert_blocks_match(cycles[..., c], ours[..., c], 0.02 if rotation in (0.0, math.radians(90.0)) else 0.06)


def test_sky_mappings_left_out_are_named(fresh_scene, tmp_path):
    from addon.blender import scene_export

    ctx = fresh_scene
    _sky(ctx, tmp_path, math.radians(20.0))
    tree = ctx.scene.world.node_tree
    mapping = next(n for n in tree.nodes if n.type == "MAPPING")
    mapping.inputs["Rotation"].default_value = (0.3, 0.0, 0.2)
    next(n for n in tree.nodes if n.type == "TEX_ENVIRONMENT").projection = "MIRROR_BALL"
    warnings = []
    scene_export._world(ctx.scene.world, warnings)
    assert any("MIRROR_BALL" in w for w in warnings)
    assert any("only the Z rotation" in w for w in warnings)


def test_turned_image_moves_whole_and_fractional_columns():
    from addon.blender.scene_export import turned_image

    img = np.arange(8, dtype=np.float32).reshape(1, 8, 1)
    assert np.array_equal(turned_image(img, 2 * math.pi * 2 / 8)[0, :, 0], np.roll(np.arange(8), 2))
    half = turned_image(img, 2 * math.pi * 0.5 / 8)[0, :, 0]
    assert half[3] == pytest.approx(2.5) and half.dtype == np.float32
    assert np.array_equal(turned_image(img, 0.0), img)


def test_the_light_panel_draws_the_settings_this_engine_renders(bpy_addon):
    """Blender 5's own light panel draws only the type for an engine other than its own: the add-on's panel
    draws the power, colour and each kind's settings."""
    from addon.blender import render_ui

    class Context:
        engine = "NEURAL_LAYERED"

    for kind, expected in (
        ("POINT", {"energy", "color", "exposure", "use_temperature", "use_shadow"}),
        ("SPOT", {"energy", "spot_size", "spot_blend"}),
        ("SUN", {"energy", "color"}),
        ("AREA", {"energy", "shape", "size", "normalize", "spread", "visible_camera"}),
    ):
        light = bpy.data.lights.new(kind, kind)
        ob = bpy.data.objects.new(kind, light)
        ctx = Context()
        ctx.light, ctx.object = light, ob
        assert render_ui.NLM_PT_light.poll(ctx)
        layout = DrawnProps()
        render_ui.NLM_PT_light.draw(SimpleNamespace(layout=layout), ctx)
        assert expected <= set(layout.drawn), (kind, layout.drawn)


def test_an_area_light_beyond_clip_end_is_not_seen(fresh_scene, tmp_path):
    """A camera ray clipped at Clip End meets nothing: an area light beyond it was drawn (mean 0.67 where Cycles'
    image was black)."""
    ctx = fresh_scene
    _empty_scene(ctx, 16, 12)
    light = _light(ctx, "AREA", location=(0.0, 0.0, 10.0), energy=500.0, size=4.0)  # shining down
    light.visible_camera = True
    _camera(ctx, location=(0.0, 0.0, 0.0), rotation=(math.pi, 0.0, 0.0), lens=20.0, clip_end=5.0)  # looking up
    cycles, ours, _ = _both(ctx, tmp_path, samples=8)
    assert cycles.max() < 1e-6 and ours.max() < 1e-6


@pytest.mark.parametrize("kind", ["SPOT", "POINT", "EMPTY"])
def test_a_light_or_an_empty_as_the_scene_camera_frames_what_cycles_frames(fresh_scene, tmp_path, kind):
    """Cycles frames a light set as the camera by its spot size (45 degrees stored for a point light), an empty by
    a 50 mm lens: ours took 50 mm for both (a 90-degree spot saw a third of the width Cycles sees)."""
    ctx = fresh_scene
    _empty_scene(ctx, 32, 32)
    _checker_floor(ctx, 6.0, cuts=11, tiles_per_metre=2.0)
    if kind == "EMPTY":
        viewer = bpy.data.objects.new("viewer", None)
        viewer.location = (0.0, 0.0, 4.0)
        ctx.scene.collection.objects.link(viewer)
    else:
        settings = {"spot_size": math.radians(90.0)} if kind == "SPOT" else {}
        viewer = _light(ctx, kind, location=(0.0, 0.0, 4.0), energy=0.0, **settings)
    ctx.scene.camera = viewer
    _light(ctx, "SUN", energy=3.0, angle=0.0)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=16)
    assert any("not a camera" in w for w in warnings)
    _assert_blocks_match(cycles, ours, 0.05, n=4)


def _textured_plane_in_white_sky(ctx):
    """A 2 m plane filling a 32 x 32 view under a white sky, its Diffuse BSDF's colour from an Image Texture node of
    a 4 x 4 float image of random texels: direct light only, a pixel is the texture's albedo there. Returns the
    plane, its material and the node."""
    _empty_scene(ctx, 32, 32)
    world = bpy.data.worlds.new("white")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    ctx.scene.world = world
    _camera(ctx, location=(0.0, 0.0, 2.0), lens=36.0)
    bpy.ops.mesh.primitive_plane_add(size=2.0)
    plane = ctx.object
    mat = _diffuse((1.0, 1.0, 1.0))
    px = np.ones((4, 4, 4), np.float32)
    px[..., :3] = np.random.default_rng(0).uniform(0.05, 0.95, (4, 4, 3))
    image = bpy.data.images.new("tiles", 4, 4, float_buffer=True)
    image.pixels.foreach_set(px.ravel())
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = image  # Linear interpolation (the default) on both sides: magnified, no mip level in play
    mat.node_tree.links.new(tex.outputs["Color"], mat.node_tree.nodes["Diffuse BSDF"].inputs["Color"])
    plane.data.materials.append(mat)
    return plane, mat, tex


@pytest.mark.parametrize(
    "vector_type, location, rotation, scale",
    [
        ("POINT", (0.0, 0.0, 0.0), 0.0, (2.0, 2.0, 1.0)),
        ("POINT", (0.3, -0.1, 0.0), math.radians(30.0), (1.5, 0.75, 1.0)),
        ("TEXTURE", (0.2, 0.4, 0.0), math.radians(-50.0), (0.8, 1.7, 1.0)),
        ("VECTOR", (0.5, 0.5, 0.0), math.radians(90.0), (3.0, 3.0, 1.0)),
    ],
    ids=["scale", "point", "texture", "vector"],
)
def test_a_mapping_node_places_an_image_texture_as_in_cycles(
    fresh_scene, tmp_path, vector_type, location, rotation, scale
):
    """A Mapping node between the UV coordinates and an Image Texture (the usual way to tile or turn a texture):
    ignored, a texture scaled 2x rendered blocks 0.61 of the image's brightest off Cycles'. A plane in a white sky,
    direct light only: a pixel is the texture's albedo there."""
    ctx = fresh_scene
    _, mat, tex = _textured_plane_in_white_sky(ctx)
    tree = mat.node_tree
    mapping, coords = tree.nodes.new("ShaderNodeMapping"), tree.nodes.new("ShaderNodeTexCoord")
    mapping.vector_type = vector_type
    if vector_type != "VECTOR":  # a Vector mapping has no Location
        mapping.inputs["Location"].default_value = location
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, rotation)
    mapping.inputs["Scale"].default_value = scale
    tree.links.new(coords.outputs["UV"], mapping.inputs["Vector"])
    tree.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert warnings == []
    for c in range(3):
        _assert_blocks_match(cycles[..., c], ours[..., c], 0.06, n=8)


def test_a_transparent_film_renders_as_cycles_renders_it(fresh_scene, tmp_path):
    """Film > Transparent: the sky the camera sees is left out and alpha is the coverage, the sky still lighting
    the floor (ours drew the sky, alpha 1: Cycles' alpha mean 0.52 against 1.0)."""
    ctx = fresh_scene
    _empty_scene(ctx, 24, 16)
    bpy.ops.mesh.primitive_plane_add(size=4.0, location=(-2.0, 0.0, 0.0))  # the image's left half
    ctx.object.data.materials.append(_diffuse((0.5, 0.5, 0.5)))
    _camera(ctx, location=(0.0, 0.0, 4.0))
    world = bpy.data.worlds.new("sky")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.4, 0.5, 0.6, 1.0)
    ctx.scene.world = world
    ctx.scene.render.film_transparent = True
    cycles, ours, warnings = _both(ctx, tmp_path, samples=64, channels=4)
    assert warnings == []
    assert ours[..., 3].mean() == pytest.approx(cycles[..., 3].mean(), abs=0.01)
    for c in range(4):
        _assert_blocks_match(cycles[..., c], ours[..., c], 0.03)


def _image(tmp_path, name, rgba, kind):
    """A 4 x 4 image of one texel value ``rgba``: "png" (8-bit sRGB), "data" (the same, Non-Color), "png-premul" (the
    same, its alpha mode Premultiplied), "png16" (16-bit sRGB), "exr" (a float OpenEXR file holding ``rgba`` as it
    is: linear, its colour premultiplied, as EXR files are)."""
    if kind == "exr":
        bpy.utils.expose_bundled_modules()
        import OpenImageIO as oiio  # noqa: N813

        path = str(tmp_path / (name + ".exr"))
        out = oiio.ImageOutput.create(path)
        out.open(path, oiio.ImageSpec(4, 4, 4, "float"))
        out.write_image(np.tile(np.asarray(rgba, np.float32), (4, 4, 1)))
        out.close()
        del out
        return bpy.data.images.load(path)
    if kind == "png16":  # 16 bits a channel, straight alpha as PNG stores it
        bpy.utils.expose_bundled_modules()
        import OpenImageIO as oiio  # noqa: N813

        path = str(tmp_path / (name + ".png"))
        spec = oiio.ImageSpec(4, 4, 4, oiio.UINT16)
        spec.attribute("oiio:UnassociatedAlpha", 1)
        out = oiio.ImageOutput.create(path)
        out.open(path, spec)
        out.write_image(np.tile(np.asarray(rgba, np.float32), (4, 4, 1)))
        out.close()
        del out
        return bpy.data.images.load(path)
    img = bpy.data.images.new(name, 4, 4, alpha=True)
    img.pixels.foreach_set(np.tile(np.asarray(rgba, np.float32), 16))
    path = tmp_path / (name + ".png")
    img.filepath_raw, img.file_format = str(path), "PNG"
    img.save()
    bpy.data.images.remove(img)
    loaded = bpy.data.images.load(str(path))
    if kind == "data":
        loaded.colorspace_settings.name = "Non-Color"
    if kind == "png-premul":
        loaded.alpha_mode = "PREMUL"
    return loaded


@pytest.mark.parametrize(
    "kind, rgba, working_space",
    [
        ("png", (1.0, 0.5, 0.25, 0.25), "Linear Rec.709"),
        ("png", (1.0, 0.5, 0.25, 1.0), "Linear Rec.709"),
        ("data", (1.0, 0.5, 0.25, 0.25), "Linear Rec.709"),
        ("exr", (0.25, 0.125, 0.0625, 0.25), "Linear Rec.709"),
        ("png16", (1.0, 0.5, 0.25, 0.5), "Linear Rec.709"),
        ("png-premul", (1.0, 0.5, 0.25, 0.5), "Linear Rec.709"),
        ("png", (1.0, 0.5, 0.0, 1.0), "ACEScg"),
        ("png", (1.0, 0.5, 0.0, 1.0), "Linear Rec.2020"),
        ("exr", (0.25, 0.125, 0.0, 1.0), "ACEScg"),
    ],
    ids=[
        "srgb-alpha",
        "srgb-opaque",
        "non-color-alpha",
        "float-alpha",
        "srgb16-alpha",
        "srgb-premultiplied",
        "srgb-acescg",
        "srgb-rec2020",
        "float-acescg",
    ],  # fmt: skip
)
def test_an_image_textures_colour_is_the_one_cycles_node_gives(fresh_scene, tmp_path, kind, rgba, working_space):
    """Where the node's Alpha output is unused, Cycles multiplies a byte image's colour by its alpha before it
    decodes it, and leaves float (stored premultiplied) and Non-Color images as they are: multiplied after the
    decoding, or always, a texel of alpha 0.25 read 2.5-4.9 times too bright or 0.25 times as bright. Byte images
    are decoded into the file's Working Color Space (Blender 5), as Cycles decodes them: into Rec.709 whatever it
    was, an orange texel read 1.56x Cycles' red and 0.83x its green in ACEScg."""
    from addon.blender import scene_export

    ctx = fresh_scene
    if working_space != bpy.data.colorspace.working_space:
        bpy.ops.wm.set_working_color_space(working_space=working_space)
        assert bpy.data.colorspace.working_space == working_space
    _empty_scene(ctx, 4, 4)
    image = _image(tmp_path, "texel", rgba, kind)
    emit = bpy.data.materials.new("emit")
    tree = emit.node_tree
    for node in [n for n in tree.nodes if n.type != "OUTPUT_MATERIAL"]:
        tree.nodes.remove(node)
    tex, emission = tree.nodes.new("ShaderNodeTexImage"), tree.nodes.new("ShaderNodeEmission")
    tex.image = image
    tree.links.new(tex.outputs["Color"], emission.inputs["Color"])
    tree.links.new(emission.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    bpy.ops.mesh.primitive_plane_add(size=2.0)
    ctx.object.data.materials.append(emit)
    _camera(ctx, location=(0.0, 0.0, 1.0), lens=50.0)  # the plane fills the view
    cycles, _, _ = _both(ctx, tmp_path, samples=1)
    plain, principled = bpy.data.materials.new("plain"), None
    principled = plain.node_tree.nodes["Principled BSDF"]
    tex2 = plain.node_tree.nodes.new("ShaderNodeTexImage")
    tex2.image = image
    plain.node_tree.links.new(tex2.outputs["Color"], principled.inputs["Base Color"])
    ours = scene_export.unmanaged_material(plain, []).texture.levels[0]
    np.testing.assert_allclose(ours.reshape(-1, 3).mean(axis=0), cycles.reshape(-1, 3).mean(axis=0), rtol=0.02)


@pytest.mark.parametrize("extension", ["REPEAT", "EXTEND", "CLIP", "MIRROR"])
def test_an_image_textures_extension_is_rendered_as_in_cycles(fresh_scene, tmp_path, extension):
    """The Image Texture node's Extension beyond the uv square (the plane's uv span -0.5 to 1.5): every mode was
    looked up as Repeat (Clip 5.4 times Cycles' image mean). A plane in a white sky: a pixel is the albedo."""
    ctx = fresh_scene
    plane, _, tex = _textured_plane_in_white_sky(ctx)
    for loop in plane.data.uv_layers.active.data:
        loop.uv = (2.0 * loop.uv[0] - 0.5, 2.0 * loop.uv[1] - 0.5)
    tex.extension = extension
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert warnings == []
    for c in range(3):
        _assert_blocks_match(cycles[..., c], ours[..., c], 0.08, n=8)


def _depth_pass(ctx, tmp_path, engine: str, samples: int):
    """The Depth pass F12 writes with ``engine``, (H, W) float32, from its multilayer EXR."""
    s = ctx.scene
    s.render.engine = engine
    s.neural_render.samples, s.neural_render.max_bounces = samples, 0
    s.cycles.device, s.cycles.samples, s.cycles.use_denoising = "CPU", samples, False
    ctx.view_layer.use_pass_z = True
    s.render.image_settings.media_type = "MULTI_LAYER_IMAGE"  # Blender 5's multilayer OpenEXR
    s.render.filepath = str(tmp_path / f"{engine}.exr")
    bpy.ops.render.render(write_still=True)
    bpy.utils.expose_bundled_modules()
    import OpenImageIO as oiio  # noqa: N813

    inp = oiio.ImageInput.open(s.render.filepath)
    try:
        part = 0
        while inp.seek_subimage(part, 0):  # the passes may lie in several parts of the file
            names = list(inp.spec().channelnames)
            if f"{ctx.view_layer.name}.Depth.Z" in names:
                z = names.index(f"{ctx.view_layer.name}.Depth.Z")
                return inp.read_image(part, 0, z, z + 1, oiio.FLOAT)[..., 0]
            part += 1
    finally:
        inp.close()
    raise AssertionError(f"{engine} wrote no Depth pass")


def test_the_depth_pass_is_cycles_z(fresh_scene, tmp_path):
    """The Depth pass was the distance along each camera ray, averaged over the pixel's samples with 0 for those that
    escaped: a floor 4 m under the camera read 4.54 m near the frame's edge, 0 where the sky was (Cycles: 1e10), and
    2.4 m on the floor's edge, where nothing is. Cycles writes the depth along the camera's axis."""
    ctx = fresh_scene
    _empty_scene(ctx, 24, 16)
    _floor(ctx, size=4.0)
    _camera(ctx)  # 4 m above, looking down: the floor's edges inside the frame, the sky beyond
    _light(ctx, "SUN", energy=2.0)
    ours, cycles = _depth_pass(ctx, tmp_path, "NEURAL_LAYERED", 16), _depth_pass(ctx, tmp_path, "CYCLES", 16)
    floor, sky = cycles < 100.0, cycles > 1e9
    assert floor.sum() > 100 and sky.sum() > 50
    np.testing.assert_allclose(ours[floor], cycles[floor], rtol=1e-4)
    assert np.all(ours[sky] == cycles[sky])
    assert np.all((np.abs(ours - 4.0) < 1e-3) | (ours == cycles.max()))  # each pixel a surface's depth, or none


def test_an_animation_renders_each_frames_world(fresh_scene, tmp_path):
    """The world was read from the scene's original data, which an animation render does not evaluate: a Background
    Strength keyed from 1 to 5 rendered 1 in every frame of Render Animation (Cycles: 1, 3, 5)."""
    ctx = fresh_scene
    s = _empty_scene(ctx, 8, 6)
    _camera(ctx)
    s.world = bpy.data.worlds.new("sky")
    if s.world.node_tree is None:
        s.world.use_nodes = True
    strength = s.world.node_tree.nodes["Background"].inputs["Strength"]
    for frame, value in ((1, 1.0), (3, 5.0)):
        strength.default_value = value
        strength.keyframe_insert("default_value", frame=frame)  # Bezier: 3 halfway
    s.render.engine = "NEURAL_LAYERED"
    s.neural_render.samples = 1
    s.frame_start, s.frame_end = 1, 3
    s.frame_set(1)
    s.render.image_settings.file_format = "OPEN_EXR"
    s.render.filepath = str(tmp_path / "frame_")
    bpy.ops.render.render(animation=True)
    sky = [read_image(tmp_path / f"frame_{f:04d}.exr")[..., :3].mean() for f in (1, 2, 3)]
    np.testing.assert_allclose(np.array(sky) / sky[0], [1.0, 3.0, 5.0], rtol=1e-3)


def _sequence(tmp_path, colours):
    """An image sequence "tex_0001.png", ... of 8-bit sRGB frames, one colour each, loaded as Blender loads one."""
    for i, colour in enumerate(colours, start=1):
        img = bpy.data.images.new(f"frame{i}", 4, 4, alpha=True)
        img.pixels.foreach_set(np.tile(np.asarray((*colour, 1.0), np.float32), 16))
        img.filepath_raw, img.file_format = str(tmp_path / f"tex_{i:04d}.png"), "PNG"
        img.save()
        bpy.data.images.remove(img)
    image = bpy.data.images.load(str(tmp_path / "tex_0001.png"))
    image.source = "SEQUENCE"
    return image


def test_an_image_sequence_renders_the_frame_its_node_shows(fresh_scene, tmp_path):
    """An Image Texture of an image sequence rendered the frame Blender last showed, or none at all with a warning of
    a missing file that was there (a headless animation render): every frame grey where Cycles renders red, green,
    blue. Each export now reads the frame its node's Image User shows at the scene's frame: Start Frame, Offset,
    Frames and Cyclic as Blender counts them."""
    from addon.blender import scene_export

    ctx = fresh_scene
    colours = [(1.0, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 1.0)]
    image = _sequence(tmp_path, colours)
    mat, principled = bpy.data.materials.new("seq"), None
    principled = mat.node_tree.nodes["Principled BSDF"]
    principled.inputs["Specular IOR Level"].default_value = 0.0  # a Lambertian: no warning of its specular layer
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    tex.image_user.frame_duration, tex.image_user.frame_start = 3, 1
    mat.node_tree.links.new(tex.outputs["Color"], principled.inputs["Base Color"])
    ctx.scene.objects["Cube"].data.materials[0] = mat
    decoded = [np.array(c) for c in ((1.0, 0.0, 0.0), (0.0, 0.2158605, 0.0), (0.0, 0.0, 1.0))]  # sRGB 0.5: 0.216

    def shown(frame):
        ctx.scene.frame_set(frame)
        core, warnings = export(ctx)
        assert warnings == []
        return core.materials[core.material_names.index("seq")].texture.levels[0].reshape(-1, 3).mean(axis=0)

    for frame, want in ((1, 0), (2, 1), (3, 2), (5, 2)):  # past its last frame: the last
        np.testing.assert_allclose(shown(frame), decoded[want], atol=2e-3)
    tex.image_user.use_cyclic = True
    np.testing.assert_allclose(shown(4), decoded[0], atol=2e-3)
    tex.image_user.use_cyclic, tex.image_user.frame_offset = False, 1
    np.testing.assert_allclose(shown(1), decoded[1], atol=2e-3)
    tex.image_user.frame_offset = 5  # a frame with no file: said, and the colour used
    ctx.scene.frame_set(1)
    _, warnings = export(ctx)
    assert len(warnings) == 1 and "tex_0006.png" in warnings[0] and "cannot be read" in warnings[0]
    assert scene_export.images.frame_path(image, 12345) == str(tmp_path / "tex_12345.png")


def _both_views(s, tmp_path, views_format: str, samples: int):
    """(ours, Cycles'): each the left and right views (H, W, 3) F12 writes as individual files of ``s`` with
    Stereoscopy's ``views_format``, direct light only."""
    s.render.use_multiview, s.render.views_format = True, views_format
    s.render.image_settings.file_format, s.render.image_settings.views_format = "OPEN_EXR", "INDIVIDUAL"
    views = []
    for engine in ("NEURAL_LAYERED", "CYCLES"):
        s.render.engine = engine
        s.neural_render.samples, s.neural_render.max_bounces = samples, 0
        s.cycles.device, s.cycles.samples, s.cycles.max_bounces, s.cycles.use_denoising = "CPU", samples, 0, False
        s.cycles.pixel_filter_type, s.view_settings.view_transform = "BOX", "Standard"
        s.render.filepath = str(tmp_path / engine)
        bpy.ops.render.render(write_still=True)
        views.append([read_image(tmp_path / f"{engine}_{e}.exr")[..., :3].astype(np.float64) for e in "LR"])
    return views


@pytest.mark.parametrize("mode", ["OFFAXIS", "TOE"])
def test_each_eye_of_a_stereo_pair_renders_what_cycles_renders(fresh_scene, tmp_path, mode):
    """Stereoscopy (Stereo 3D, individual views): the left eye was rendered from the camera itself and the right eye
    left black, without a word, and the panel was hidden. Each eye is now rendered from its own camera, as Blender
    places it (its interocular distance, convergence mode and shift)."""
    ctx = fresh_scene
    s = _empty_scene(ctx, 32, 24)
    _checker_floor(ctx, 6.0, cuts=11, tiles_per_metre=2.0)
    cam = _camera(ctx, location=(0.3, -0.2, 5.0))
    cam.data.stereo.convergence_mode, cam.data.stereo.interocular_distance = mode, 0.4
    _light(ctx, "SUN", energy=3.0, angle=0.0)
    (ours_l, ours_r), (cycles_l, cycles_r) = _both_views(s, tmp_path, "STEREO_3D", samples=32)
    assert np.abs(cycles_l - cycles_r).max() > 0.1  # the eyes see the checkers' edges apart
    _assert_blocks_match(cycles_l, ours_l, 0.04, n=4)
    _assert_blocks_match(cycles_r, ours_r, 0.04, n=4)


@pytest.mark.parametrize("kind", ["POINT", "SUN", "AREA", "AREA-large"])
def test_a_light_that_casts_no_shadow_renders_as_in_cycles(fresh_scene, tmp_path, kind):
    """A light's Cast Shadow off (a fill light's usual setting): Cycles lights what lies behind a blocker; its
    shadow was rendered, without a word. Under a large area light close by, what the blocker leaves is the light
    sampling's share of multiple importance sampling, whose weights follow the light's sampling density: sampled
    by area, the shadow read 1.5 times as deep as Cycles' (which samples a rectangle by solid angle)."""
    ctx = fresh_scene
    _empty_scene(ctx, 24, 16)
    _floor(ctx)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 0.6))
    ctx.object.data.materials.append(_diffuse((0.5, 0.5, 0.5)))
    _camera(ctx, location=(0.0, 0.0, 6.0))
    settings = {
        "POINT": {"energy": 300.0}, "SUN": {"energy": 2.0, "angle": 0.0}, "AREA": {"energy": 300.0},
        "AREA-large": {"energy": 600.0, "shape": "RECTANGLE", "size": 3.0, "size_y": 2.0},
    }[kind]  # fmt: skip
    kind = kind.removesuffix("-large")
    light = _light(ctx, kind, location=(0.4, 0.3, 2.5), rotation=(0.3, 0.2, 0.0), **settings)
    light.data.use_shadow = False
    if kind == "AREA" and settings.get("size") == 3.0:  # the blocks at the cube's edges, where the shadow was
        ctx.scene.render.resolution_x, ctx.scene.render.resolution_y = 48, 32
        cycles, ours, _ = _both(ctx, tmp_path, samples=256)
        _assert_blocks_match(cycles, ours, 0.008, n=8)  # 0.012 sampled by area, 0.005 by solid angle
        return
    cycles, ours, _ = _both(ctx, tmp_path, samples=64)
    _assert_blocks_match(cycles, ours, 0.04, n=4)


@pytest.mark.parametrize("depth", ["8", "16"])
def test_a_sequence_frame_reads_as_the_same_file_loaded_as_a_still(fresh_scene, tmp_path, depth):
    """A frame with straight alpha read 4-10 times too dark (OpenImageIO multiplied it by its alpha as it read, and
    the colour was multiplied again); a ".jp2" sequence's extension was taken for its frame number; a frame cut
    short rendered what was left in memory, without a word. An 8-bit frame reads as Blender's still of it; a 16-bit
    one as Cycles reads it (premultiplied, then decoded: decoded first, 1.4-2.1x Cycles' at alpha 0.5)."""
    from addon.blender import images

    bpy.utils.expose_bundled_modules()
    import OpenImageIO as oiio  # noqa: N813

    path = str(tmp_path / "alpha_0001.png")
    spec = oiio.ImageSpec(4, 4, 4, oiio.UINT8 if depth == "8" else oiio.UINT16)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(np.tile(np.array([1.0, 0.5, 0.25, 0.5], np.float32), (4, 4, 1)))  # straight, as PNG stores it
    out.close()
    del out
    for associate in (False, True):
        still = images.linear_pixels(bpy.data.images.load(path, check_existing=False), associate)
        sequence = bpy.data.images.load(path, check_existing=False)
        sequence.source = "SEQUENCE"
        node = bpy.data.materials.new("m").node_tree.nodes.new("ShaderNodeTexImage")
        node.image, node.image_user.frame_duration = sequence, 1
        px, read = images.sequence_pixels(sequence, node.image_user, 1, associate)
        assert read == path
        if depth == "16":  # a float image, premultiplied as stored and then decoded, as Cycles reads it
            straight = np.full((4, 4, 3), 0.5, np.float32) * np.array([1.0, 0.5, 0.25], np.float32)
            still = np.concatenate([images._to_working_space(sequence, straight),
                                    np.full((4, 4, 1), 0.5)], axis=2)  # fmt: skip
        np.testing.assert_allclose(px, still, atol=1e-4)
    sequence.filepath = str(tmp_path / "shot_0001.jp2")
    assert images.frame_path(sequence, 7) == str(tmp_path / "shot_0007.jp2")
    assert images.frame_path(sequence, -2) == str(tmp_path / "shot_0000.jp2")  # as Blender names it
    noise = str(tmp_path / "noise.png")  # a frame whose header reads and whose pixels stop half-way
    out = oiio.ImageOutput.create(noise)
    out.open(noise, oiio.ImageSpec(64, 64, 3, oiio.UINT8))
    out.write_image(np.random.default_rng(1).random((64, 64, 3)).astype(np.float32))
    out.close()
    del out
    whole = open(noise, "rb").read()
    (tmp_path / "alpha_0002.png").write_bytes(whole[: len(whole) // 2])
    sequence.filepath = path
    node.image_user.frame_duration = 2
    assert images.sequence_pixels(sequence, node.image_user, 2)[0] is None


def test_multi_view_renders_each_view_from_its_own_camera(fresh_scene, tmp_path, capfd):
    """Multi-View finds each view's camera by the scene camera's name with the view's suffix ("cam_L", "cam_R"):
    every view rendered from the scene camera, pixel for pixel the same. The camera's Stereoscopy panel and the
    output's Views panel are drawn for this engine. What the export says is said once, not once a view."""
    from addon.blender import engine

    ctx = fresh_scene
    s = _empty_scene(ctx, 32, 24)
    _floor(ctx, size=1.0)  # a bright square on nothing
    for suffix, x, lens in (("_L", -0.3, 60.0), ("_R", 0.3, 30.0)):
        cam = bpy.data.objects.new("cam" + suffix, bpy.data.cameras.new("cam" + suffix))
        cam.location, cam.data.lens = (x, 0.0, 5.0), lens
        s.collection.objects.link(cam)
    s.camera = s.objects["cam_L"]
    _light(ctx, "SUN", energy=3.0, angle=0.0)
    s.collection.objects.link(bpy.data.objects.new("hair", bpy.data.hair_curves.new("hair")))  # said, not rendered
    capfd.readouterr()
    our_views, cycles_views = _both_views(s, tmp_path, "MULTIVIEW", samples=16)
    for ours, cycles in zip(our_views, cycles_views, strict=True):
        _assert_blocks_match(cycles, ours, 0.04, n=4)
    printed = capfd.readouterr()  # Blender prints a render's reports headless
    assert (printed.out + printed.err).count("hair curves are not rendered") == 1, printed.out[-2000:]
    shown = {p.__name__ for p in engine._panels}
    assert {"RENDER_PT_stereoscopy", "RENDER_PT_output_views", "DATA_PT_camera_stereoscopy"} <= shown


def _cube(ctx, size=0.6, location=(0.0, 0.0, 0.3)):
    bpy.ops.mesh.primitive_cube_add(size=size, location=location)
    ctx.object.data.materials.append(_diffuse((0.6, 0.6, 0.6)))
    return ctx.object


@pytest.mark.parametrize(
    "kind, settings, location",
    [
        ("POINT", {"energy": 150.0, "shadow_soft_size": 1.0}, (0.4, 0.3, 1.3)),
        ("POINT", {"energy": 150.0, "shadow_soft_size": 0.8, "use_soft_falloff": False}, (0.4, 0.3, 1.3)),
        ("SPOT", {"energy": 400.0, "shadow_soft_size": 0.6, "spot_size": 0.9, "spot_blend": 0.2}, (0.0, 0.0, 2.0)),
        ("SUN", {"energy": 3.0, "angle": math.radians(60.0)}, (0.0, 0.0, 3.0)),
        ("POINT", {"energy": 150.0, "shadow_soft_size": 0.1, "normalize": False}, (0.4, 0.3, 1.3)),
    ],
    ids=["point-radius", "point-sphere", "spot-radius", "sun-angle", "point-not-normalized"],
)
def test_a_lights_radius_or_angle_renders_as_in_cycles(fresh_scene, tmp_path, kind, settings, location):
    """A point or spot light's Radius (a disk facing the lit point with Soft Falloff, Blender's default, else a
    sphere) and a sun's Angle, over a cube's soft shadow: ours rendered every one as a point or one direction (a point
    light of radius 1 m 1.2 m off: blocks off by over half the brightest, and hard shadows where Cycles' are soft;
    Normalize off: Cycles' power over pi, 0.13 of the normalised light at a radius of 0.1 m)."""
    ctx = fresh_scene
    _empty_scene(ctx, 32, 24)
    _floor(ctx)
    _cube(ctx)
    _camera(ctx, location=(0.0, 0.0, 4.0))
    _light(ctx, kind, location=location, rotation=(0.35, -0.2, 0.0) if kind == "SUN" else (0.0, 0.0, 0.0), **settings)
    cycles, ours, warnings = _both(ctx, tmp_path, samples=128)
    assert warnings == []
    _assert_blocks_match(cycles, ours, 0.03, n=8)


def test_a_point_light_of_a_radius_is_seen_by_the_camera_as_in_cycles(fresh_scene, tmp_path):
    """Where camera rays meet a point light of a radius that is visible to them (Object > Visibility > Camera), Cycles
    draws the disk facing the camera at the light's radiance (ours drew nothing: a mean of 0.03 against 1.3)."""
    ctx = fresh_scene
    _empty_scene(ctx, 24, 16)
    _floor(ctx)
    _camera(ctx, location=(0.0, -4.0, 1.0), rotation=(math.radians(80.0), 0.0, 0.0))
    light = _light(ctx, "POINT", location=(0.4, 0.0, 1.3), energy=60.0, shadow_soft_size=0.3)
    light.visible_camera = True
    cycles, ours, _ = _both(ctx, tmp_path, samples=128)
    assert ours.max() > 10.0  # the light itself
    _assert_blocks_match(cycles, ours, 0.03, n=4)


def test_a_lights_max_bounces_renders_as_in_cycles(fresh_scene, tmp_path):
    """Cycles' per-light Max Bounces (Light > Settings): at 0 the light lights the first surfaces the camera sees
    only (ours kept its indirect light: a point light's image 1.055 times Cycles', its worst block off by 0.105 of
    the brightest). A cube's sides, which the light does not reach, show the bounce."""
    ctx = fresh_scene
    _empty_scene(ctx, 32, 24)
    _floor(ctx)
    _cube(ctx, size=1.0, location=(0.0, 0.0, 0.5))
    _camera(ctx, location=(0.0, -4.5, 2.5), rotation=(math.radians(60.0), 0.0, 0.0))
    light = _light(ctx, "POINT", location=(1.2, 1.0, 2.0), energy=300.0)
    light.data.cycles.max_bounces = 0
    cycles, ours, warnings = _both(ctx, tmp_path, samples=128, bounces=2)
    assert warnings == []
    _assert_blocks_match(cycles, ours, 0.02, n=8)


def test_a_portal_light_emits_nothing_as_in_cycles(fresh_scene, tmp_path):
    """An area light marked a Portal only guides Cycles' sampling of the world through it: ours lit the scene with
    its power (a 500 W portal made the image 3 times Cycles'). It is left out, with a line that says so (not a
    warning: the image is Cycles')."""
    from addon.blender import scene_export

    ctx = fresh_scene
    _empty_scene(ctx, 24, 16)
    _floor(ctx)
    _camera(ctx)
    world = bpy.data.worlds.new("sky")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    ctx.scene.world = world
    portal = _light(ctx, "AREA", location=(0.0, 0.0, 2.0), energy=500.0, size=2.0)
    portal.data.cycles.is_portal = True
    info = []
    scene, warnings = scene_export.export_scene(ctx.evaluated_depsgraph_get(), info=info)
    assert scene.lights == [] and warnings == []
    assert any("portal" in line and "'L'" in line for line in info)
    cycles, ours, _ = _both(ctx, tmp_path, samples=128, bounces=1)
    _assert_blocks_match(cycles, ours, 0.03, n=4)


def test_a_uv_map_node_naming_the_render_uv_map_renders_as_in_cycles_without_a_warning(fresh_scene, tmp_path):
    """A UV Map node that names the mesh's render UV map (the camera icon) looks up what Cycles looks up: it was
    warned of as another source of coordinates. One naming another map is still warned of."""
    ctx = fresh_scene
    plane, mat, tex = _textured_plane_in_white_sky(ctx)
    node = mat.node_tree.nodes.new("ShaderNodeUVMap")
    node.uv_map = plane.data.uv_layers[0].name
    mat.node_tree.links.new(node.outputs["UV"], tex.inputs["Vector"])
    cycles, ours, warnings = _both(ctx, tmp_path, samples=32)
    assert warnings == []
    for c in range(3):
        _assert_blocks_match(cycles[..., c], ours[..., c], 0.06, n=8)
    plane.data.uv_layers.new(name="other")
    node.uv_map = "other"
    _, warnings = export(ctx)
    assert any("UV Map node" in w for w in warnings), warnings


def test_the_light_panel_draws_a_lights_radius_angle_normalize_and_max_bounces(bpy_addon):
    """The settings ours now renders are drawn where it said the light renders as a point or one direction."""
    from addon.blender import render_ui

    class Context:
        engine = "NEURAL_LAYERED"

    for kind, expected in (
        ("POINT", {"shadow_soft_size", "use_soft_falloff", "normalize", "max_bounces"}),
        ("SPOT", {"shadow_soft_size", "use_soft_falloff", "normalize"}),
        ("SUN", {"angle", "normalize", "max_bounces"}),
        ("AREA", {"max_bounces"}),
    ):
        light = bpy.data.lights.new(kind, kind)
        ctx = Context()
        ctx.light, ctx.object = light, bpy.data.objects.new(kind, light)
        layout = DrawnProps()
        render_ui.NLM_PT_light.draw(SimpleNamespace(layout=layout), ctx)
        assert expected <= set(layout.drawn), (kind, layout.drawn)

"""Scene export, the render engine (F12, EXR/PNG output) and the Render Preview operator."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from tests.blender.helpers import DrawnProps, run_operator, viewport_reports

bpy = pytest.importorskip("bpy")


def export(ctx, **kw):
    from addon.blender import scene_export

    return scene_export.export_scene(ctx.evaluated_depsgraph_get(), **kw)


def small(scene, w=32, h=24, samples=2):
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = w, h, 100
    scene.neural_render.samples = samples
    scene.neural_render.preview_samples = samples
    scene.neural_render.max_bounces = 3


def read_image(path):
    bpy.utils.expose_bundled_modules()
    import OpenImageIO as oiio  # noqa: N813

    buf = oiio.ImageBuf(str(path))
    assert not buf.has_error, buf.geterror()
    return buf.get_pixels(oiio.FLOAT)


def test_startup_scene_exports_world_space_triangles_light_camera(fresh_scene):
    ctx = fresh_scene
    cube = ctx.scene.objects["Cube"]
    cube.location = (1.0, 2.0, 3.0)
    cube.scale = (2.0, 1.0, 1.0)
    small(ctx.scene, 64, 32)
    scene, warnings = export(ctx)
    assert warnings == []
    assert scene.mesh.triangle_count == 12
    lo, hi = scene.mesh.positions.reshape(-1, 3).min(0), scene.mesh.positions.reshape(-1, 3).max(0)
    assert np.allclose(lo, [-1, 1, 2], atol=1e-5) and np.allclose(hi, [3, 3, 4], atol=1e-5)
    # Flat cube: every corner normal is its face normal, unit length, in world space.
    assert np.allclose(scene.mesh.normals, scene.mesh.face_normals[:, None, :], atol=1e-5)
    assert scene.mesh.uvs is not None
    (light,) = scene.lights
    assert type(light).__name__ == "PointLight" and light.power == 1000.0
    assert np.allclose(light.position, ctx.scene.objects["Light"].matrix_world.translation)
    # 50 mm lens on a 36 mm sensor across the wider side.
    assert scene.camera.tan_half_fov == pytest.approx((0.36, 0.18))
    assert scene.camera.width == 64 and scene.camera.height == 32


def test_export_applies_modifiers_expands_instances_and_skips_what_does_not_render(fresh_scene):
    ctx = fresh_scene
    cube = ctx.scene.objects["Cube"]
    mod = cube.modifiers.new("Array", "ARRAY")
    mod.count = 3
    assert export(ctx)[0].mesh.triangle_count == 36
    # A collection instance of the cube adds its triangles again.
    coll = bpy.data.collections.new("Inst")
    coll.objects.link(cube)
    empty = bpy.data.objects.new("Empty", None)
    empty.instance_type = "COLLECTION"
    empty.instance_collection = coll
    empty.location = (10, 0, 0)
    ctx.scene.collection.objects.link(empty)
    mesh = export(ctx)[0].mesh
    assert mesh.triangle_count == 72
    assert mesh.positions[..., 0].max() > 9
    # Objects disabled in renders are left out.
    bpy.ops.mesh.primitive_cube_add(location=(0, 0, 10))
    assert export(ctx)[0].mesh.triangle_count == 84
    ctx.object.hide_render = True
    ctx.view_layer.update()
    assert export(ctx)[0].mesh.triangle_count == 72


def test_smooth_shading_exports_interpolated_normals(fresh_scene):
    ctx = fresh_scene
    bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, location=(0, 0, 5))
    sphere = ctx.object
    bpy.ops.object.shade_smooth()
    mesh = export(ctx)[0].mesh
    sel = mesh.positions[:, :, 2].mean(axis=1) > 3
    n = mesh.normals[sel]
    p = mesh.positions[sel] - np.array([0, 0, 5], np.float32)
    # Smooth sphere normals point along the radius, not along the faces.
    radial = p / np.linalg.norm(p, axis=2, keepdims=True)
    assert (np.einsum("tci,tci->tc", n, radial) > 0.99).all()
    assert not np.allclose(n, mesh.face_normals[sel][:, None, :], atol=1e-2)
    del sphere


@pytest.mark.parametrize("scale", [(1, 1, 1), (-1, 1, 1), (-1, -1, -1)])
def test_a_mirrored_object_keeps_its_outward_faces_and_smooth_normals(fresh_scene, scale):
    ctx = fresh_scene
    bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, location=(0, 0, 5))
    bpy.ops.object.shade_smooth()
    ctx.object.scale = scale
    mesh = export(ctx)[0].mesh
    sel = mesh.positions[:, :, 2].mean(axis=1) > 3
    p = mesh.positions[sel] - np.array([0, 0, 5], np.float32)
    radial = p / np.linalg.norm(p, axis=2, keepdims=True)
    # The faces (their corners' order) still face out, and so every corner normal agrees with its face: none is
    # dropped for the flat normal when the renderer checks them.
    assert (np.einsum("ti,ti->t", mesh.face_normals[sel], radial.mean(axis=1)) > 0).all()
    assert (np.einsum("tci,ti->tc", mesh.normals[sel], mesh.face_normals[sel]) > 0).all()
    assert (np.einsum("tci,tci->tc", mesh.normals[sel], radial) > 0.99).all()


def test_lights_world_and_layered_materials_export(fresh_scene):
    ctx = fresh_scene
    from addon.blender import stack_io
    from addon.core.render import LayeredSpec
    from addon.core.stack import PRESETS

    for kind, energy in (("SUN", 4.0), ("SPOT", 300.0), ("AREA", 50.0)):
        data = bpy.data.lights.new(kind, kind)
        data.energy = energy
        if kind == "AREA":
            data.shape, data.size, data.size_y = "RECTANGLE", 2.0, 0.5
        ob = bpy.data.objects.new(kind, data)
        ob.rotation_euler = (math.radians(90), 0, 0)  # local -z now points along +y
        ctx.scene.collection.objects.link(ob)
    img = bpy.data.images.new("sky", 16, 8, float_buffer=True)
    img.pixels.foreach_set(np.full(16 * 8 * 4, 0.5, np.float32))
    world = ctx.scene.world
    tex = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    tex.image = img
    world.node_tree.links.new(tex.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 2.0
    stack_io.stack_to_material(PRESETS["coated_gold"], ctx.scene.objects["Cube"].active_material)
    scene, warnings = export(ctx)
    kinds = {type(li).__name__: li for li in scene.lights}
    assert set(kinds) == {"PointLight", "SunLight", "SpotLight", "AreaLight"}
    assert np.allclose(kinds["SunLight"].direction, [0, 1, 0], atol=1e-6)
    assert np.allclose(kinds["SpotLight"].direction, [0, 1, 0], atol=1e-6)
    assert kinds["AreaLight"].area == pytest.approx(1.0)
    assert np.allclose(kinds["AreaLight"].normal, [0, 1, 0], atol=1e-6)
    assert scene.environment.image.shape == (8, 16, 3) and np.allclose(scene.environment.image, 1.0)
    (spec,) = scene.materials
    assert isinstance(spec, LayeredSpec)
    assert spec.stack.base.roughness == pytest.approx(PRESETS["coated_gold"].base.roughness)
    assert len(spec.stack.coatings) == 1


def test_f12_render_writes_png_and_exr(fresh_scene, tmp_path):
    ctx = fresh_scene
    scene = ctx.scene
    small(scene)
    scene.render.engine = "NEURAL_LAYERED"
    for fmt, ext in (("PNG", "png"), ("OPEN_EXR", "exr")):
        scene.render.image_settings.file_format = fmt
        scene.render.filepath = str(tmp_path / f"frame.{ext}")
        bpy.ops.render.render(write_still=True)
        px = read_image(tmp_path / f"frame.{ext}")
        assert px.shape[:2] == (24, 32)
        assert np.isfinite(px).all() and px[..., :3].max() > 0
    # The EXR holds the linear render: the lit cube is brighter than the dim grey world.
    px = read_image(tmp_path / "frame.exr")
    assert px[..., :3].max() > 4 * np.median(px[..., :3])


def test_f12_renders_the_render_region_into_its_place_in_the_frame_or_cropped(fresh_scene, tmp_path):
    from addon.blender.engine import render_region

    scene = fresh_scene.scene
    small(scene, 40, 30, samples=16)
    scene.render.engine = "NEURAL_LAYERED"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"

    def frame(name, border, crop=False):
        scene.render.use_border, scene.render.use_crop_to_border = border, crop
        scene.render.filepath = str(tmp_path / f"{name}.exr")
        bpy.ops.render.render(write_still=True)
        return read_image(tmp_path / f"{name}.exr")

    whole = frame("whole", False)
    scene.render.border_min_x, scene.render.border_max_x = 0.1, 0.6
    scene.render.border_min_y, scene.render.border_max_y = 0.2, 0.9
    scene.render.use_border = True
    x0, y0, x1, y1 = render_region(scene, 40, 30)
    # the fractions times the size in float32, truncated, as Blender cuts it: 0.9 x 30 is 27 there, 26.99999 in
    # doubles
    assert (x0, y0, x1, y1) == (4, 6, 24, 27)
    scene.render.border_min_x, scene.render.border_max_x = 0.27, 0.71  # 10.8 and 28.4 columns: truncated
    assert render_region(scene, 40, 30)[::2] == (10, 28)
    scene.render.border_min_x, scene.render.border_max_x = 0.1, 0.6
    rows, cols = slice(30 - y1, 30 - y0), slice(x0, x1)  # the file's rows run from the top
    placed = frame("placed", True)
    assert placed.shape[:2] == (30, 40)
    inside = np.zeros((30, 40), bool)
    inside[rows, cols] = True
    assert (placed[..., 3] > 0).tolist() == inside.tolist()  # the region's pixels, and only those
    cropped = frame("cropped", True, crop=True)
    assert cropped.shape[:2] == (y1 - y0, x1 - x0)  # Blender's own cut of the region is the same
    # Each holds the region's image: the whole frame's pixels there (other random numbers: the same scene
    # within the noise of 16 samples).
    for part in (placed[rows, cols, :3], cropped[..., :3]):
        ref = whole[rows, cols, :3]
        assert np.corrcoef(part.ravel(), ref.ravel())[0, 1] > 0.9
        assert part.mean() == pytest.approx(ref.mean(), rel=0.1)


def test_each_view_layer_renders_into_its_own_layer(fresh_scene, tmp_path):
    from addon.blender import engine

    scene = fresh_scene.scene
    small(scene, 24, 18, samples=2)
    scene.render.engine = "NEURAL_LAYERED"
    scene.render.use_compositing = False
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(tmp_path / "alone.exr")
    bpy.ops.render.render(write_still=True)
    alone = read_image(tmp_path / "alone.exr")
    # A second view layer without the cube: rendered after the first, it must not land in the first's layer.
    cube = scene.objects["Cube"]
    group = bpy.data.collections.new("Cube only")
    scene.collection.children.link(group)
    for c in list(cube.users_collection):
        c.objects.unlink(cube)
    group.objects.link(cube)
    first = scene.view_layers[0]
    second = scene.view_layers.new("Without the cube")
    second.layer_collection.children["Cube only"].exclude = True
    layers = []
    render = engine.NeuralLayeredRenderEngine._render

    def spy(self, depsgraph, scene, props, result, region, thumbnail=False, view=""):
        layers.append((depsgraph.view_layer.name, [layer.name for layer in result.layers]))
        return render(self, depsgraph, scene, props, result, region, thumbnail, view)

    engine.NeuralLayeredRenderEngine._render = spy
    try:
        scene.render.filepath = str(tmp_path / "layers.exr")
        bpy.ops.render.render(write_still=True)
    finally:
        engine.NeuralLayeredRenderEngine._render = render
    assert layers == [(first.name, [first.name]), (second.name, [second.name])]
    assert np.array_equal(read_image(tmp_path / "layers.exr"), alone)  # the first layer's image, the cube in it


def test_render_preview_operator_fills_an_image(fresh_scene, tmp_path):
    ctx = fresh_scene
    small(ctx.scene)
    out = tmp_path / "preview.png"
    report = run_operator(bpy.ops.neural_layers.render_preview, width=20, height=10, samples=2, filepath=str(out))
    assert report.finished, report.error
    image = bpy.data.images["Neural Layered Render"]
    assert tuple(image.size) == (20, 10)
    px = np.empty(20 * 10 * 4, np.float32)
    image.pixels.foreach_get(px)
    assert np.isfinite(px).all() and px.max() > 0
    assert out.exists()
    bad = run_operator(bpy.ops.neural_layers.render_preview, width=8, height=8, filepath=str(tmp_path / "x.jpg"))
    assert bad.error and ".exr or .png" in bad.error
    # A "//" path in a file never saved would land in the process's working folder: refused, as the bake does.
    assert not bpy.data.filepath
    bad = run_operator(bpy.ops.neural_layers.render_preview, width=8, height=8, filepath="//preview.png")
    assert bad.error and "not saved" in bad.error
    # A folder that is not there yet is made, as F12 makes its output's (it failed with an empty reason).
    deeper = tmp_path / "renders" / "today" / "view.png"
    report = run_operator(bpy.ops.neural_layers.render_preview, width=8, height=8, samples=1, filepath=str(deeper))
    assert report.finished, report.error
    assert deeper.exists()


def test_render_preview_in_an_orthographic_view_renders_that_view(fresh_scene):
    """Numpad 1, 3 and 7 give orthographic views: Render Preview rendered the scene camera instead without a word
    (and failed in a scene without one), where the viewport's Rendered mode renders the view."""
    from types import SimpleNamespace

    from mathutils import Matrix

    from addon.blender import render_operators

    ctx = fresh_scene
    region = SimpleNamespace(
        view_perspective="ORTHO", is_perspective=False, view_matrix=Matrix.Translation((0.0, 0.0, -10.0))
    )
    space = SimpleNamespace(type="VIEW_3D", lens=50.0)
    context = SimpleNamespace(region_data=region, space_data=space, scene=ctx.scene)
    warnings = []
    camera = render_operators._view_camera(context, 16, 8, warnings)
    assert camera is not None and np.allclose(camera.matrix[:3, 3], (0.0, 0.0, 10.0))
    assert any("orthographic" in w for w in warnings)


def test_render_preview_chooses_decoders_for_the_samples_it_renders(fresh_scene, monkeypatch, tmp_path):
    """Auto's time budget is for the frame rendered: Render Preview's samples (16 by default), not F12's Samples
    (64), which left out sizes whose cost fits the preview."""
    from addon.core import quality

    ctx = fresh_scene
    small(ctx.scene)
    asked = []
    real = quality.assign_decoders

    def spy(scene, *args, **kwargs):
        asked.append(kwargs["evaluations"])
        return real(scene, *args, **kwargs)

    monkeypatch.setattr(quality, "assign_decoders", spy)
    props = ctx.scene.neural_render
    props.decoder_quality = "AUTO"
    props.samples = props.preview_samples + 5
    for samples, expected in ((0, props.preview_samples), (3, 3)):
        asked.clear()
        out = str(tmp_path / "preview.png")
        report = run_operator(bpy.ops.neural_layers.render_preview, width=20, height=10, samples=samples, filepath=out)
        assert report.finished, report.error
        hits = asked[0] / quality.frame_decoder_queries(20 * 10, expected, props.max_bounces, 1.0)
        assert asked == [quality.frame_decoder_queries(20 * 10, expected, props.max_bounces, hits)]
        assert 0.0 <= hits < props.max_bounces + 1  # the pilot's hits on layered materials, not the bound


def test_awkward_blender_scenes_render_without_errors(fresh_scene, tmp_path):
    ctx = fresh_scene
    small(ctx.scene, 16, 12)
    # A mesh without UVs, a material whose image file is missing, a zero-strength light.
    bpy.ops.mesh.primitive_cube_add(size=1, location=(0, 0, 2), calc_uvs=False)
    ob = ctx.object
    assert len(ob.data.uv_layers) == 0
    mat = bpy.data.materials.new("Missing")
    if mat.node_tree is None:
        mat.use_nodes = True
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    missing = bpy.data.images.new("gone", 4, 4)
    missing.source = "FILE"
    missing.filepath = str(tmp_path / "does_not_exist.png")
    tex.image = missing
    mat.node_tree.links.new(tex.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    ob.data.materials.append(mat)
    ctx.scene.objects["Light"].data.energy = 0.0
    scene, warnings = export(ctx)
    assert any("does_not_exist" in w for w in warnings)
    from addon.core.render import RenderSettings, render

    film, stats = render(scene, RenderSettings(samples=2))
    assert stats.nonfinite == 0 and np.isfinite(film.mean()).all()
    # An empty scene (only the camera) renders the world; no camera is a clear error.
    for o in [o for o in ctx.scene.objects if o.type != "CAMERA"]:
        bpy.data.objects.remove(o)
    scene, _ = export(ctx)
    assert scene.mesh.triangle_count == 0
    film, _ = render(scene, RenderSettings(samples=1))
    assert np.allclose(film.mean(), scene.environment.constant, atol=1e-6)
    ctx.scene.camera = None
    with pytest.raises(ValueError, match="no active camera"):
        export(ctx)


def test_the_demo_scene_keeps_its_sky_and_floor_texture_through_a_saved_blend(fresh_scene, tmp_path):
    """Blender saves no pixels written into a generated image: a saved demo scene reopened with its sky and floor
    texture black (the sky's maximum 22.46 before, 0 after). Its images are packed as OpenEXR."""
    from addon.blender import render_demo
    from addon.core.render.demo_scene import demo_scene

    core = demo_scene(40, 24, ("coated_gold",))
    render_demo.build_scene(core, fresh_scene)
    before, _ = export(fresh_scene)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "demo.blend"))
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "demo.blend"))
    after, _ = export(bpy.context)
    assert before.environment.image.max() > 20.0
    np.testing.assert_allclose(after.environment.image, before.environment.image, rtol=1e-6)
    floor = next(m for m in after.materials if getattr(m, "texture", None) is not None)
    assert np.asarray(floor.texture.levels[0]).max() > 0.1


def test_core_scene_round_trips_through_blender(fresh_scene):
    """demo scene -> Blender data (render_demo) -> scene export: the same triangles, normals,
    uvs, materials, light, sky and camera."""
    from addon.blender import render_demo
    from addon.core.render import LambertMaterial, LayeredSpec
    from addon.core.render.demo_scene import demo_scene

    ctx = fresh_scene
    core = demo_scene(40, 24, ("coated_gold", "lacquered_plastic"))
    render_demo.build_scene(core, ctx)
    back, warnings = export(ctx)
    assert warnings == []
    m0, m1 = core.mesh, back.mesh
    assert m1.triangle_count == m0.triangle_count
    assert np.allclose(m1.positions, m0.positions, atol=1e-5)
    assert np.allclose(m1.normals, m0.normals, atol=2e-3)
    assert np.allclose(m1.uvs, m0.uvs, atol=1e-6)
    names = [back.material_names[i] for i in m1.material_index[:5]]
    assert names == [core.material_names[i] for i in m0.material_index[:5]]
    kinds = [type(m) for m in back.materials]
    assert kinds == [LambertMaterial, LayeredSpec, LayeredSpec]
    assert back.materials[1].stack.base.roughness == pytest.approx(core.materials[1].stack.base.roughness, rel=1e-5)
    assert back.materials[0].texture is not None
    assert np.allclose(back.materials[0].texture.levels[0], core.materials[0].texture.levels[0], atol=1e-6)
    (l0,), (l1,) = core.lights, back.lights
    assert l1.power == pytest.approx(l0.power) and l1.area == pytest.approx(l0.area)
    assert np.allclose(l1.normal, l0.normal, atol=1e-6) and np.allclose(l1.center, l0.center, atol=1e-6)
    assert np.allclose(back.environment.image, core.environment.image, rtol=1e-6)
    assert np.allclose(back.camera.matrix, core.camera.matrix, atol=1e-6)
    assert back.camera.tan_half_fov == pytest.approx(core.camera.tan_half_fov, rel=1e-5)


@pytest.mark.parametrize("kind", ["POINT", "SPOT", "SUN", "AREA"])
def test_lights_match_cycles_on_a_lambertian_floor(fresh_scene, tmp_path, kind):
    """Blender's light units and orientations: our render of an exported scene against Cycles."""
    ctx = fresh_scene
    for ob in list(ctx.scene.objects):
        bpy.data.objects.remove(ob)
    bpy.ops.mesh.primitive_plane_add(size=100)
    mat = bpy.data.materials.new("floor")
    if mat.node_tree is None:
        mat.use_nodes = True
    p = mat.node_tree.nodes["Principled BSDF"]
    p.inputs["Base Color"].default_value = (0.5, 0.4, 0.3, 1)
    p.inputs["Roughness"].default_value = 1.0
    p.inputs["Specular IOR Level"].default_value = 0.0
    ctx.object.data.materials.append(mat)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.data.lens = 200
    cam.location = (0.0, -1.0, 1.5)
    cam.rotation_euler = (0.6, 0.0, 0.0)
    ctx.scene.collection.objects.link(cam)
    ctx.scene.camera = cam
    light = bpy.data.lights.new("L", kind)
    light.energy = 3.0 if kind == "SUN" else 200.0
    if kind == "SUN":
        light.angle = 0.0
    elif kind == "AREA":
        light.size = 0.5
    else:
        light.shadow_soft_size = 0.0
    if kind == "SPOT":
        light.spot_size, light.spot_blend = 0.8, 0.2
    lo = bpy.data.objects.new("L", light)
    lo.location = (0.3, 0.2, 2.0)
    lo.rotation_euler = (0.2, -0.15, 0.0)  # tilted: orientation matters for spot, sun and area
    ctx.scene.collection.objects.link(lo)
    ctx.scene.world = None
    small(ctx.scene, 8, 8)
    scene, _ = export(ctx)
    from addon.core.render import RenderSettings, render

    ours = render(scene, RenderSettings(samples=64, max_bounces=1))[0].mean().astype(np.float64)
    s = ctx.scene
    s.render.engine = "CYCLES"
    s.cycles.samples, s.cycles.max_bounces, s.cycles.use_denoising = 64, 1, False
    s.cycles.use_adaptive_sampling = False
    s.cycles.pixel_filter_type = "BOX"
    s.view_settings.view_transform = "Standard"
    s.render.image_settings.file_format = "OPEN_EXR"
    s.render.image_settings.color_depth = "32"
    s.render.filepath = str(tmp_path / "cycles.exr")
    bpy.ops.render.render(write_still=True)
    cycles = read_image(tmp_path / "cycles.exr")[..., :3].astype(np.float64)
    assert cycles.mean() > 1e-3
    # Image means within 3% (Principled diffuse at roughness 1 is not exactly Lambertian).
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.03)


@pytest.mark.parametrize("mode", ["reference", "neural"])
def test_f12_renders_layered_materials(fresh_scene, tmp_path, mode):
    from addon.blender import stack_io
    from addon.core.stack import PRESETS

    ctx = fresh_scene
    small(ctx.scene, 16, 12, samples=1)
    stack_io.stack_to_material(PRESETS["red_car_paint"], ctx.scene.objects["Cube"].active_material)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.neural_render.mode = mode
    ctx.scene.neural_render.reference_walks = 1
    ctx.scene.render.image_settings.file_format = "OPEN_EXR"
    ctx.scene.render.filepath = str(tmp_path / "layered.exr")
    bpy.ops.render.render(write_still=True)
    px = read_image(tmp_path / "layered.exr")[..., :3]
    assert np.isfinite(px).all() and px.max() > 0


def test_f12_reports_every_failure_and_falls_back_to_the_reference(fresh_scene, tmp_path, monkeypatch):
    from addon.blender import engine, stack_io
    from addon.core.stack import PRESETS

    ctx = fresh_scene
    small(ctx.scene, 12, 8, samples=1)
    stack_io.stack_to_material(PRESETS["red_car_paint"], ctx.scene.objects["Cube"].active_material)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.neural_render.reference_walks = 1
    real = engine.render
    modes = []

    def neural_breaks(scene, settings, **kw):
        modes.append(settings.mode)
        if settings.mode == "neural":
            raise RuntimeError("ONNX Runtime: model file damaged")
        return real(scene, settings, **kw)

    monkeypatch.setattr(engine, "render", neural_breaks)
    ctx.scene.render.filepath = str(tmp_path / "fallback.exr")
    ctx.scene.render.image_settings.file_format = "OPEN_EXR"
    bpy.ops.render.render(write_still=True)
    assert modes == ["neural", "reference"]
    assert np.isfinite(read_image(tmp_path / "fallback.exr")).all()

    def always_breaks(scene, settings, **kw):
        raise MemoryError("out of memory while tracing")

    monkeypatch.setattr(engine, "render", always_breaks)
    with pytest.raises(RuntimeError, match="MemoryError: out of memory while tracing"):
        bpy.ops.render.render(write_still=True)


def test_esc_stops_an_f12_render_between_passes_and_keeps_what_was_rendered(fresh_scene, tmp_path, monkeypatch):
    from addon.blender import engine
    from addon.core.render import Cancelled

    ctx = fresh_scene
    small(ctx.scene, 64, 48, samples=64)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.render.image_settings.file_format = "OPEN_EXR"
    ctx.scene.render.filepath = str(tmp_path / "stopped.exr")
    real, given, stopped, shown = engine.render, [], [], []

    def esc_after_the_first_pass(scene, settings, **kw):
        """The engine's render with Esc pressed once the first pass is shown (Blender's test_break cannot be made
        to say so headless): the engine gives its own test_break as ``stop``; the render polls the stand-in
        before it takes each chunk, and so stops before the second pass's, where only ``progress`` (which asks the
        real test_break: no Esc) would have let it run on."""
        given.append((repr(kw["stop"]), kw["stop"]()))

        def progress(*args):
            shown.append(args[1])
            return kw["progress"](*args)

        try:
            return real(scene, settings, **{**kw, "progress": progress, "stop": lambda: bool(shown)})
        except Cancelled as c:
            stopped.append(c.film.passes)
            raise

    monkeypatch.setattr(engine, "render", esc_after_the_first_pass)
    bpy.ops.render.render(write_still=True)  # a stopped render is no failure
    assert len(given) == 1 and "test_break" in given[0][0] and given[0][1] is False
    assert shown == [1] and stopped == [1]  # the first pass, then Esc before the second pass's chunk
    px = read_image(tmp_path / "stopped.exr")[..., :3]
    assert np.isfinite(px).all() and px.max() > 0  # the pass rendered before Esc is the result

    def neural_fails(scene, settings, **kw):  # Esc during the reference fallback keeps its result too
        if settings.mode == "neural":
            raise RuntimeError("ONNX Runtime: model file damaged")
        return real(scene, settings, **{**kw, "stop": lambda: True})

    monkeypatch.setattr(engine, "render", neural_fails)
    bpy.ops.render.render(write_still=True)


def test_the_progress_bar_and_the_remaining_time_move_with_each_chunk_of_a_pass(fresh_scene, tmp_path, monkeypatch):
    from dataclasses import replace

    from addon.blender import engine

    ctx = fresh_scene
    small(ctx.scene, 64, 48, samples=3)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.render.filepath = str(tmp_path / "chunks.exr")
    ctx.scene.render.image_settings.file_format = "OPEN_EXR"
    real, real_line, bar, lines, passes = engine.render, engine.status_line, [], [], []

    def in_chunks(scene, settings, **kw):
        """The engine's render in chunks of 1,024 pixels (3 a pass)."""

        def chunk_progress(fraction):
            bar.append(fraction)
            kw["chunk_progress"](fraction)  # the engine's: Blender's progress bar and status line

        def progress(film, done, total):
            passes.append((done, len(bar)))
            return kw["progress"](film, done, total)

        calls = {**kw, "progress": progress, "chunk_progress": chunk_progress}
        return real(scene, replace(settings, chunk_paths=1024), **calls)

    monkeypatch.setattr(engine, "render", in_chunks)
    monkeypatch.setattr(engine, "status_line", lambda *a: lines.append(real_line(*a)) or lines[-1])
    bpy.ops.render.render(write_still=True)
    assert bar == pytest.approx([k / 9 for k in range(1, 10)])  # every chunk
    assert passes == [(1, 3), (2, 6), (3, 9)]  # the image and the sample count with each pass
    # a line with every chunk (before its pass's) and every pass; the time left from the first pass's end on
    assert [line.split(" | ")[0] for line in lines] == ["Sample 0/3"] * 3 + ["Sample 1/3"] * 4 + ["Sample 2/3"] * 4 + [
        "Sample 3/3"
    ]
    assert all("Remaining" not in line for line in lines[:3]) and all(" | Remaining:" in line for line in lines[3:])
    assert lines[-1].startswith("Sample 3/3 | Remaining:00:00.00 | ")
    assert real_line(2, 16, 3725.5, 11042) == "Sample 2/16 | Remaining:01:02:05.50 | 11042 triangles"
    assert real_line(0, 16, None, 12) == "Sample 0/16 | 12 triangles"
    assert np.isfinite(read_image(tmp_path / "chunks.exr")).all()


def test_render_threads_follow_the_scene_setting(fresh_scene):
    import os

    scene = fresh_scene.scene
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 3
    assert scene.neural_render.to_core(scene=scene).thread_count == 3
    scene.render.threads_mode = "AUTO"
    assert scene.neural_render.to_core(scene=scene).thread_count == (os.cpu_count() or 1)


def test_denoise_option_brings_a_4_spp_render_closer_to_256_spp(fresh_scene, tmp_path):
    ctx = fresh_scene
    scene = ctx.scene
    small(scene, 48, 36)
    scene.render.engine = "NEURAL_LAYERED"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"

    def frame(samples, denoise, name):
        scene.neural_render.samples = samples
        scene.neural_render.denoise = denoise
        scene.render.filepath = str(tmp_path / f"{name}.exr")
        bpy.ops.render.render(write_still=True)
        return read_image(tmp_path / f"{name}.exr")[..., :3].astype(np.float64)

    truth = frame(256, False, "truth")
    noisy = frame(4, False, "noisy")
    assert scene.compositing_node_group is None
    denoised = frame(4, True, "denoised")
    group = scene.compositing_node_group
    assert group is not None and any(n.bl_idname == "CompositorNodeDenoise" for n in group.nodes)
    denoise = next(n for n in group.nodes if n.bl_idname == "CompositorNodeDenoise")
    assert denoise.inputs["Normal"].is_linked and denoise.inputs["Albedo"].is_linked
    err = {k: float(((v - truth) ** 2).mean()) for k, v in (("noisy", noisy), ("denoised", denoised))}
    assert err["denoised"] < 0.7 * err["noisy"], err
    scene.neural_render.denoise = False
    assert scene.compositing_node_group is None


def test_denoise_gives_each_scene_its_own_compositor_and_says_when_a_scene_has_another(
    fresh_scene, tmp_path, monkeypatch
):
    from addon.blender import engine
    from addon.blender.render_properties import denoise_note

    first = fresh_scene.scene
    second = bpy.data.scenes.new("Shot B")
    first.neural_render.denoise = True
    second.neural_render.denoise = True
    groups = [s.compositing_node_group for s in (first, second)]
    assert groups[0] is not None and groups[1] is not None and groups[0] != groups[1]
    for scene, group in zip((first, second), groups, strict=True):
        (layers,) = [n for n in group.nodes if n.bl_idname == "CompositorNodeRLayers"]
        assert layers.scene == scene  # the other scene's Denoise took the first's compositor over, before
    second.neural_render.denoise = False
    assert second.compositing_node_group is None and first.compositing_node_group == groups[0]
    # A scene with a compositor of its own keeps it, and F12 says that Denoise does nothing there.
    small(first, 16, 12, samples=1)
    first.neural_render.denoise = False
    first.compositing_node_group = bpy.data.node_groups.new("My Comp", "CompositorNodeTree")
    first.neural_render.denoise = True
    assert first.compositing_node_group.name == "My Comp" and "My Comp" in denoise_note(first)
    first.render.engine = "NEURAL_LAYERED"
    first.render.use_compositing = False
    first.render.filepath = str(tmp_path / "frame.png")
    notes = []  # the engine's reports cannot be watched from Python (RNA functions): its call of denoise_note can

    def watched(scene):
        notes.append(denoise_note(scene))
        return notes[-1]

    monkeypatch.setattr(engine.render_properties, "denoise_note", watched)
    bpy.ops.render.render(write_still=True)
    assert len(notes) == 1 and "My Comp" in notes[0]


def test_denoising_passes_reach_the_compositor(fresh_scene, tmp_path):
    ctx = fresh_scene
    scene = ctx.scene
    small(scene, 16, 12)
    scene.render.engine = "NEURAL_LAYERED"
    scene.neural_render.denoise = True
    group = scene.compositing_node_group
    layers = next(n for n in group.nodes if n.bl_idname == "CompositorNodeRLayers")
    assert {"Denoising Normal", "Denoising Albedo"} <= {o.name for o in layers.outputs if o.enabled}
    out = group.nodes.new("CompositorNodeOutputFile")
    out.directory = str(tmp_path) + "/"
    out.file_name = "albedo"
    out.format.file_format = "OPEN_EXR_MULTILAYER"
    out.file_output_items.new("RGBA", "albedo")
    group.links.new(layers.outputs["Denoising Albedo"], out.inputs[0])
    scene.render.filepath = str(tmp_path / "frame.exr")
    bpy.ops.render.render(write_still=True)
    albedo = read_image(tmp_path / "albedo.exr")[..., :3].reshape(-1, 3)
    # The startup cube's directional albedo where the camera rays hit it, the sky's grey where they escape, as
    # Cycles writes it (edge pixels: the mean of both over the samples): its grey base 0.8 under the specular layer,
    # 0.8 (1 - E) + E for the layer's albedo E (0.012 at the median pixel, 0.14 at the most grazing), grey, never
    # above 1.
    sky = np.array(scene.world.node_tree.nodes["Background"].inputs["Color"].default_value[:3])
    seen = np.abs(albedo - sky).max(axis=1) > 1e-4
    assert 0 < seen.sum() < len(seen)
    median = np.median(albedo[seen], axis=0)
    assert np.all((median > 0.8) & (median < 0.81)) and np.ptp(median) < 1e-6 and albedo.max() <= 1.0


def render_as_material_preview(scene, path, monkeypatch) -> None:
    """F12 of ``scene`` into ``path`` (OpenEXR) through the engine's material-preview branch: headless Blender
    renders no material previews, and ``is_preview`` is Blender's read-only flag, so this stands in for it one step
    below (``_render``'s ``thumbnail``)."""
    from addon.blender import engine

    cls = engine.NeuralLayeredRenderEngine
    real_step = cls._render
    monkeypatch.setattr(cls, "_render", lambda self, *a, thumbnail=False, **k: real_step(self, *a, thumbnail=True, **k))
    scene.render.filepath = str(path)
    scene.render.image_settings.file_format = "OPEN_EXR"
    bpy.ops.render.render(write_still=True)


def test_material_thumbnails_render_through_the_engine_with_thumbnail_settings(
    fresh_scene, tmp_path, monkeypatch, capfd
):
    """Headless Blender renders no material previews, so this renders F12 through the engine's own
    code path, its thumbnail branch taken as Blender's read-only ``is_preview`` would take it."""
    from addon.blender import engine, stack_io
    from addon.core.render.thumbnail import THUMBNAIL_DECODER, thumbnail_settings
    from addon.core.stack import PRESETS

    assert engine.NeuralLayeredRenderEngine.bl_use_preview
    ctx = fresh_scene
    small(ctx.scene, 24, 24, samples=64)
    stack_io.stack_to_material(PRESETS["red_car_paint"], ctx.scene.objects["Cube"].active_material)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.neural_render.mode = "reference"  # a thumbnail is neural whatever the scene says
    ctx.scene.neural_render.decoder_quality = "AUTO"
    ctx.scene.neural_render.denoise = True
    real = engine.render
    seen = []

    def recording(scene, settings, **kw):
        seen.append((settings, [getattr(m, "size", None) for m in scene.materials]))
        return real(scene, settings, **kw)

    monkeypatch.setattr(engine, "render", recording)
    # Blender's preview scene holds materials the user never made ("FloorHidden", its Alpha left out): a
    # thumbnail reports nothing of them, where every thumbnail printed their warnings
    bpy.ops.mesh.primitive_plane_add(size=0.5, location=(0.0, 0.0, -2.0))
    hidden = bpy.data.materials.new("FloorHidden")
    hidden.node_tree.nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.5
    ctx.object.data.materials.append(hidden)
    assert export(ctx)[1] == ["material 'FloorHidden': its Principled BSDF's Alpha is left out"]  # what F12 says
    capfd.readouterr()
    render_as_material_preview(ctx.scene, tmp_path / "thumb.exr", monkeypatch)
    assert "FloorHidden" not in capfd.readouterr().out
    ((settings, sizes),) = seen
    expected = thumbnail_settings(24, 24, threads=settings.threads)
    assert settings == expected and settings.samples < 64 and settings.mode == "neural"
    assert THUMBNAIL_DECODER in sizes
    px = read_image(tmp_path / "thumb.exr")
    assert np.isfinite(px).all() and px[..., :3].max() > 0


def test_the_viewport_asks_for_a_redraw_for_every_new_image_of_a_generation(bpy_addon):
    """A generation's reduced images and its first full-resolution pass all have one sample: each new image is
    drawn when it comes, not only when the sample count grows."""
    from types import SimpleNamespace

    from addon.blender import engine
    from addon.core.render.progressive import ViewImage

    def image(h, w, samples, reduced):
        return ViewImage(np.zeros((h, w, 4), np.float32), samples, reduced, generation=3)

    shown = [image(45, 80, 1, True), image(90, 160, 1, True), image(180, 320, 1, False), image(180, 320, 2, False)]
    latest = []
    redraws = []
    viewport = engine._Viewport.__new__(engine._Viewport)  # no timer: _poll is called by hand
    viewport.session = SimpleNamespace(
        latest=lambda: latest[-1] if latest else None, error=None, calibration_failure=None
    )
    viewport.engine_ref = SimpleNamespace(tag_redraw=lambda: redraws.append(latest[-1]), is_preview=False)
    viewport._drawn = None
    viewport._reported_error = viewport._reported_calibration = None
    assert viewport._poll() == 0.05 and redraws == []  # nothing yet
    for im in shown:
        latest.append(im)
        viewport._poll()
        viewport._drawn = im  # what draw does once it has uploaded the image
        viewport._poll()  # on screen already: no second redraw
    assert redraws == shown


def test_a_viewport_failure_is_drawn_once_even_without_a_new_image(bpy_addon):
    """A failed pass publishes no image: the timer asks for a redraw anyway, so its error is shown (the viewport
    kept the old image, silent); a render error and a calibration failure are each reported once, where each one's
    report reset the other's and both came again at every redraw."""
    from types import SimpleNamespace

    from addon.blender import engine

    redraws, reports = [], []
    viewport = engine._Viewport.__new__(engine._Viewport)  # no timer: _poll and draw are called by hand
    viewport.session = SimpleNamespace(latest=lambda: None, error=None, calibration_failure=None)
    viewport.engine_ref = SimpleNamespace(tag_redraw=lambda: redraws.append(1), is_preview=False)
    viewport._drawn, viewport._texture = None, None
    viewport._reported_error = viewport._reported_calibration = None
    fake_engine = SimpleNamespace(report=lambda kind, text: reports.append((kind, text)))
    assert viewport._poll() == 0.05 and redraws == []
    viewport.session.calibration_failure = ValueError("walks failed")
    viewport.session.error = RuntimeError("texture file vanished")
    viewport._poll()
    assert redraws == [1]
    for _ in range(3):
        viewport.draw(fake_engine, None)  # no image: reports only
        viewport._poll()
    assert redraws == [1] and [kind for kind, _ in reports] == [{"ERROR"}, {"WARNING"}]


def test_a_viewport_session_closes_when_its_engine_goes_and_when_the_add_on_does(bpy_addon, fresh_scene):
    """Leaving Rendered mode frees the engine: its session (thread, scene, buffers) closes at the timer's next tick,
    whether or not a new image came (a converged session used to live on, its timer running, one more each time
    the viewport went to Rendered and back); and unregistering the add-on closes the sessions still open."""
    from addon.blender import engine, scene_export

    scene = fresh_scene.scene
    scene.neural_render.samples = 2
    core_scene, _ = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get(), 24, 18)
    settings = scene.neural_render.to_core(scene=scene, viewport=True)

    class Engine:  # as Blender's: once freed, reading it raises ReferenceError
        freed = False

        def tag_redraw(self):
            self.is_preview  # noqa: B018

        @property
        def is_preview(self):
            if self.freed:
                raise ReferenceError("StructRNA of type NeuralLayeredRenderEngine has been removed")
            return False

    views = []
    for _ in range(2):
        view = engine._Viewport(Engine(), settings)
        view.restart(core_scene, settings, ("key",))
        assert view.session.wait(timeout=120) is not None  # converged
        view._drawn = view.session.latest()  # on screen: no new image will come
        assert view._poll() == 0.05
        views.append(view)
    views[0].engine_ref.freed = True
    assert views[0]._poll() is None and views[0].session is None  # closed, its timer ends
    assert views[1] in engine._OPEN_VIEWPORTS and views[0] not in engine._OPEN_VIEWPORTS
    engine.close_viewports()
    assert views[1].session is None and not engine._OPEN_VIEWPORTS
    assert not bpy.app.timers.is_registered(views[1].timer)  # (a new bound method never was registered)


def test_viewport_navigation_moves_the_camera_and_an_edit_or_a_resize_exports_again(bpy_addon, monkeypatch):
    """view_draw with a moved view: the session renders its last scene from the new camera (no export);
    the same with another region size, or with no session yet, goes through view_update (an export)."""
    from types import SimpleNamespace

    from addon.blender import engine, scene_export

    monkeypatch.setattr(scene_export, "view_camera", lambda r3d, lens, w, h, clip: ("camera", r3d.view_matrix, w, h))
    monkeypatch.setattr(scene_export, "view_clip", lambda r3d, space, scene: (0.0, math.inf))
    calls = []

    class Viewport:
        key = None
        session = "rendering"
        settings_key = None

        def move_camera(self, camera, key):
            calls.append(("move", camera))
            self.key = key

        def draw(self, engine, scene):
            pass

    def context(matrix, width=40):
        return SimpleNamespace(
            region_data=SimpleNamespace(view_matrix=matrix, window_matrix=((1, 0), (0, 1)), is_perspective=True),
            space_data=SimpleNamespace(lens=50.0),
            region=SimpleNamespace(width=width, height=30),
            scene=None,
        )

    fake = SimpleNamespace(_viewport=None, report=lambda kind, text: calls.append(("report", text)))
    fake.view_update = lambda ctx, dg: calls.append(("update", ctx.region.width))
    view_draw = engine.NeuralLayeredRenderEngine.view_draw
    graph = SimpleNamespace(scene=None)
    view_draw(fake, context(((1, 0), (0, 1))), graph)
    assert calls == [("update", 40)]  # no session yet: an export
    fake._viewport = Viewport()
    fake._viewport.key = engine._view_key(context(((1, 0), (0, 1))))
    view_draw(fake, context(((1, 0), (0, 1))), graph)
    assert calls == [("update", 40)]  # nothing moved: only drawn
    view_draw(fake, context(((0, 1), (1, 0))), graph)
    assert calls[-1] == ("move", ("camera", ((0, 1), (1, 0)), 40, 30))
    view_draw(fake, context(((0, 1), (1, 0)), width=80), graph)
    assert calls[-1] == ("update", 80)  # another size: Auto's decoder choice may change, so export again
    fake._viewport.session = None  # closed as a file's load began, the load then failed: started again
    view_draw(fake, context(((0, 1), (1, 0)), width=80), graph)
    assert calls[-1] == ("update", 80)


def _frustum(left, right, bottom, top, near=0.1, far=100.0):
    """An OpenGL perspective projection (rows as mathutils gives them), as Blender makes a viewport's."""
    return np.array(
        [
            [2 * near / (right - left), 0, (right + left) / (right - left), 0],
            [0, 2 * near / (top - bottom), (top + bottom) / (top - bottom), 0],
            [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
            [0, 0, -1, 0],
        ]
    )


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.03, -0.02)])
def test_the_viewport_camera_is_the_viewports_projection_in_camera_view_too(bpy_addon, offset):
    """The viewport's camera puts each pixel's centre where the viewport's own projection (its window matrix:
    the lens, or in camera view the scene camera framed with its zoom and offset) puts it; it used to take the
    viewport's lens alone, so camera view showed another field of view than its frame."""
    from types import SimpleNamespace

    from mathutils import Euler, Matrix

    from addon.blender import scene_export

    width, height = 40, 30
    view = Matrix.LocRotScale((0.3, -4.0, 1.2), Euler((1.2, 0.1, 0.3)), None).inverted()
    half_w = 0.06  # at the near distance 0.1: a 62-degree horizontal field of view
    half_h = half_w * height / width
    dx, dy = offset
    window = _frustum(dx - half_w, dx + half_w, dy - half_h, dy + half_h)
    r3d = SimpleNamespace(view_matrix=view, window_matrix=Matrix(window.tolist()), is_perspective=True)
    cam = scene_export.view_camera(r3d, 50.0, width, height)
    px, py = np.meshgrid(np.arange(width), np.arange(height))
    o, d = cam.generate_rays(px.ravel(), py.ravel(), np.full((width * height, 2), 0.5))
    world = np.concatenate([o + d, np.ones((len(o), 1))], axis=1)
    clip = world @ (window @ np.array(view)).T
    ndc = clip[:, :2] / clip[:, 3:]
    want = np.stack([(px.ravel() + 0.5) * 2 / width - 1, 1 - (py.ravel() + 0.5) * 2 / height], axis=1)
    np.testing.assert_allclose(ndc, want, atol=2e-6)  # mathutils holds float32


def test_the_viewports_auto_choice_reads_measured_errors_and_never_stops_to_measure(fresh_scene, monkeypatch):
    """Each edit in the Rendered viewport chose its decoders on Blender's main thread, measuring every new stack
    (reference walks and decodes: 1-2 s at every tick of a slider). The viewport now reads what renders measured:
    the default decoder, said so, until an F12 has measured the stack."""
    from addon.blender import scene_export, stack_io
    from addon.core import quality
    from addon.core.stack import PRESETS

    scene = fresh_scene.scene
    stack_io.stack_to_material(PRESETS["red_car_paint"], scene.objects["Cube"].active_material)
    scene.neural_render.decoder_quality = "AUTO"
    monkeypatch.setattr(quality, "_DEFAULT_CACHE", quality.ErrorCache())
    monkeypatch.setattr(quality, "reference_lobes", lambda *a, **k: pytest.fail("the viewport measured"))
    core_scene, _ = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get(), 32, 24)
    info = []
    scene.neural_render.assign_decoders(core_scene, info=info, viewport=True)
    assert any("not measured yet" in line for line in info), info
    # The viewport says so, once: its edits (a slider dragged) do not repeat the line.
    reports = viewport_reports(monkeypatch, fresh_scene, size=(32, 24))
    assert [kind for kind, text in reports if "not measured yet" in text] == [{"INFO"}], reports


def test_esc_while_f12_chooses_decoders_cancels_the_render_without_a_failure(fresh_scene, tmp_path, monkeypatch):
    """Auto measures each new stack before the first pass (a second or two a size): F12 gives its test_break to
    the choice, which stops at the next measurement; the render then ends cancelled, not failed, and no pass is
    traced (Esc was not heard until the choice had measured everything)."""
    from addon.blender import engine, render_properties, stack_io
    from addon.core.stack import PRESETS

    scene = fresh_scene.scene
    small(scene, 16, 12, samples=2)
    stack_io.stack_to_material(PRESETS["red_car_paint"], scene.objects["Cube"].active_material)
    scene.render.engine = "NEURAL_LAYERED"
    scene.neural_render.decoder_quality = "AUTO"
    real = render_properties.NLM_RenderSettings.assign_decoders
    stops, traced = [], []

    def esc_pressed(self, core_scene, **kw):
        stops.append(repr(kw["stop"]))
        return real(self, core_scene, **{**kw, "stop": lambda: True})

    monkeypatch.setattr(render_properties.NLM_RenderSettings, "assign_decoders", esc_pressed)
    monkeypatch.setattr(engine, "render", lambda *a, **k: traced.append(1))
    scene.render.filepath = str(tmp_path / "frame.png")
    bpy.ops.render.render(write_still=True)  # an ERROR report would raise here
    assert len(stops) == 1 and "test_break" in stops[0] and traced == []


@pytest.mark.parametrize("tau", [0.5, 1.0])
def test_the_cycles_baseline_tints_an_absorbing_coat_for_its_way_in_and_out(fresh_scene, tmp_path, tau):
    """``principled_inputs``' Coat Tint is Cycles' transmittance of the whole trip through the coat at normal
    incidence: exp(-2 tau (1 - albedo)). Applied once, an absorbing coat over a mirror rendered 0.62 in Cycles where
    the stack reflects 0.38 (tau 0.5): the Cycles baseline of the benchmarks was too bright and washed out."""
    from addon.core import reference
    from addon.core.render.principled import principled_inputs
    from addon.core.stack import Coating, Conductor, Stack

    stack = Stack(Conductor(0.0, (1.0, 1.0, 1.0), (20.0, 20.0, 20.0)), (Coating(0.0, 1.5, (0.0, 0.0, 0.0), tau),))
    truth, _ = reference.albedo(stack, np.array([[0.0, 0.0, 1.0]]), samples=4096, seed=1)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    s = bpy.context.scene
    s.render.engine, s.cycles.device, s.cycles.samples, s.cycles.use_denoising = "CYCLES", "CPU", 4, False
    s.render.resolution_x = s.render.resolution_y = 4
    s.view_settings.view_transform = "Standard"
    s.world = bpy.data.worlds.new("white")
    s.world.use_nodes = True
    s.world.node_tree.nodes["Background"].inputs[0].default_value = (1.0, 1.0, 1.0, 1.0)
    bpy.ops.mesh.primitive_plane_add(size=100)
    material = bpy.data.materials.new("coat")
    material.use_nodes = True
    node = material.node_tree.nodes["Principled BSDF"]
    for key, value in principled_inputs(stack).items():
        node.inputs[key].default_value = value
    bpy.context.object.data.materials.append(material)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.data.type, camera.data.ortho_scale, camera.location = "ORTHO", 1.0, (0.0, 0.0, 5.0)
    s.collection.objects.link(camera)
    s.camera = camera
    s.render.image_settings.file_format, s.render.filepath = "OPEN_EXR", str(tmp_path / "tint.exr")
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(str(tmp_path / "tint.exr"))
    cycles = np.array(image.pixels[:]).reshape(-1, 4)[:, :3].mean()
    assert cycles == pytest.approx(float(truth[0].mean()), rel=0.06), (cycles, truth[0])


def test_the_viewport_exports_the_world_again_only_when_it_changed(fresh_scene, monkeypatch):
    """Each edit in the Rendered viewport exported the scene again, its world too: an 8K sky image read and
    tabulated at every tick of a slider (seconds each). The world is now kept while the depsgraph reports no update
    of a world, an image or the scene."""
    from types import SimpleNamespace

    from addon.blender import engine, scene_export

    monkeypatch.setattr(engine, "_view_camera", lambda context: None)  # the scene camera
    worlds = []
    real_world = scene_export._world
    monkeypatch.setattr(scene_export, "_world", lambda *a: worlds.append(1) or real_world(*a))
    graph = fresh_scene.evaluated_depsgraph_get()

    def updates(*ids):  # what the depsgraph reports to view_update after an edit of these
        return [SimpleNamespace(id=i) for i in ids]

    fake = SimpleNamespace(
        _view_info=set(), _view_geometry=scene_export.GeometryCache(), report=lambda kind, text: None
    )
    context = SimpleNamespace(region=SimpleNamespace(width=16, height=12))
    view_scene = engine.NeuralLayeredRenderEngine._view_scene
    first, _ = view_scene(fake, context, graph, updates())
    material = bpy.data.materials["Material"]
    second, _ = view_scene(fake, context, graph, updates(material))  # a material's edit: the world as it was
    assert len(worlds) == 1 and second.environment is first.environment
    view_scene(fake, context, graph, updates(fresh_scene.scene.world))  # the world's edit: exported again
    assert len(worlds) == 2


def test_a_material_preview_larger_than_a_thumbnail_renders_smaller_and_fills_its_size(
    fresh_scene, tmp_path, monkeypatch
):
    """The Properties editor's Preview panel asks for its own size, over 512 pixels on a wide or 2x-DPI editor: the
    thumbnail settings refused it with an error. It renders at most THUMBNAIL_MAX_SIDE a side, shown at the size
    asked (each pixel the nearest rendered one)."""
    from addon.blender import engine
    from addon.core.render.thumbnail import THUMBNAIL_MAX_SIDE

    ctx = fresh_scene
    small(ctx.scene, 600, 300, samples=1)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    seen = []
    real = engine.render
    monkeypatch.setattr(
        engine, "render", lambda scene, s, **kw: seen.append(scene.camera.width) or real(scene, s, **kw)
    )
    render_as_material_preview(ctx.scene, tmp_path / "preview.exr", monkeypatch)
    assert seen == [THUMBNAIL_MAX_SIDE] and engine.thumbnail_size(600, 300) == (512, 256)
    px = read_image(tmp_path / "preview.exr")
    assert px.shape[:2] == (300, 600) and np.isfinite(px).all() and px[..., :3].max() > 0


def test_denoise_turned_on_before_the_engine_says_its_guides_are_missing_and_off_and_on_links_them(fresh_scene):
    """Denoise set by a script before the engine was this one built its Denoise node without the albedo and normal
    guides (the Render Layers node had no such outputs then), silently. F12 now says so; turning Denoise off and on
    again with this engine links them."""
    from addon.blender import render_properties

    scene = fresh_scene.scene
    scene.render.engine = (
        "BLENDER_EEVEE_NEXT"
        if "BLENDER_EEVEE_NEXT"
        in {e.identifier for e in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items}
        else "CYCLES"
    )
    scene.neural_render.denoise = True
    scene.render.engine = "NEURAL_LAYERED"
    note = render_properties.denoise_note(scene)
    assert note is not None and "guides" in note
    scene.neural_render.denoise = False
    scene.neural_render.denoise = True
    assert render_properties.denoise_note(scene) is None


def test_denoise_says_when_the_scene_cannot_composite(fresh_scene):
    """Denoise ticked did nothing, silently, in a scene copied with Copy Settings (the setting copied, not the
    compositor), with its node group removed, or with Post Processing's Compositing off."""
    from addon.blender import render_properties

    scene = fresh_scene.scene
    scene.render.engine = "NEURAL_LAYERED"
    scene.neural_render.denoise = True
    assert render_properties.denoise_note(scene) is None
    scene.render.use_compositing = False
    assert "Compositing is off" in render_properties.denoise_note(scene)
    scene.render.use_compositing = True
    bpy.ops.scene.new(type="EMPTY")  # Copy Settings
    copy = bpy.context.scene
    assert copy.neural_render.denoise and copy.compositing_node_group is None
    assert "no compositor" in render_properties.denoise_note(copy)


def test_f12_with_a_transparent_film_writes_the_coverage_as_alpha(fresh_scene, tmp_path):
    ctx = fresh_scene
    small(ctx.scene, 24, 16, samples=4)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.render.film_transparent = True
    ctx.scene.render.image_settings.file_format = "OPEN_EXR"
    ctx.scene.render.image_settings.color_mode = "RGBA"
    ctx.scene.render.filepath = str(tmp_path / "transparent.exr")
    bpy.ops.render.render(write_still=True)
    px = read_image(tmp_path / "transparent.exr")
    alpha = px[..., 3]
    assert alpha.max() == 1.0 and alpha.min() == 0.0  # the cube, and the world around it
    np.testing.assert_array_equal(px[alpha == 0.0][:, :3], 0.0)


def test_the_viewport_renders_again_when_the_engines_settings_change(fresh_scene):
    """Samples, Max Bounces, Seed, the mode and the decoder name no depsgraph update: the viewport went on
    rendering with the old ones until some other edit. They are read at each draw."""
    from types import SimpleNamespace

    from addon.blender import engine

    scene = fresh_scene.scene
    calls = []
    context = SimpleNamespace(
        region_data=SimpleNamespace(view_matrix=((1, 0), (0, 1)), window_matrix=((1, 0), (0, 1))),
        space_data=SimpleNamespace(lens=50.0),
        region=SimpleNamespace(width=40, height=30),
    )
    view = SimpleNamespace(
        key=engine._view_key(context),
        session="rendering",
        settings_key=engine.settings_key(scene),
        draw=lambda e, s: None,
    )
    fake = SimpleNamespace(_viewport=view, view_update=lambda ctx, dg: calls.append("update"))
    graph = SimpleNamespace(scene=scene)
    engine.NeuralLayeredRenderEngine.view_draw(fake, context, graph)
    assert calls == []  # nothing changed: only drawn
    for name, value in (("max_bounces", 2), ("mode", "reference"), ("decoder_quality", "TINY")):
        setattr(scene.neural_render, name, value)
        engine.NeuralLayeredRenderEngine.view_draw(fake, context, graph)
        assert calls[-1] == "update", name
        view.settings_key = engine.settings_key(scene)  # as view_update sets it


def test_opening_a_file_closes_the_viewports_of_the_last_one(bpy_addon, fresh_scene):
    """The viewport's timer, the one thing that closes its session once Blender frees the engine, was dropped when
    a file was opened: the old file's session went on rendering, one more thread and 133 MB of buffers (at 1280 x
    720) for each file opened."""
    from types import SimpleNamespace

    from addon.blender import engine, scene_export

    scene = fresh_scene.scene
    scene.neural_render.samples = 2
    core_scene, _ = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get(), 24, 18)
    settings = scene.neural_render.to_core(scene=scene, viewport=True)
    view = engine._Viewport(SimpleNamespace(tag_redraw=lambda: None, is_preview=False), settings)
    view.restart(core_scene, settings, ("key",))
    assert view in engine._OPEN_VIEWPORTS
    bpy_addon.ops.wm.read_homefile(app_template="")
    assert view.session is None and view not in engine._OPEN_VIEWPORTS
    assert not bpy_addon.app.timers.is_registered(view.timer)


def test_the_viewport_exports_a_sky_of_an_image_sequence_again_at_each_frame(fresh_scene, tmp_path, monkeypatch):
    """A sky of an image sequence changes with the frame, which names no update: the viewport kept its first frame's
    sky (red at frames 1, 2 and 3, where F12 renders red, green, blue)."""
    from types import SimpleNamespace

    from addon.blender import engine, scene_export
    from tests.blender.test_cycles_settings import _sequence

    monkeypatch.setattr(engine, "_view_camera", lambda context: None)  # the scene camera
    scene = fresh_scene.scene
    world = scene.world
    if world.node_tree is None:
        world.use_nodes = True
    sky = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    sky.image = _sequence(tmp_path, [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)])
    sky.image_user.frame_duration = 3
    world.node_tree.links.new(sky.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    fake = SimpleNamespace(
        _view_info=set(), _view_geometry=scene_export.GeometryCache(), report=lambda kind, text: None
    )
    context = SimpleNamespace(region=SimpleNamespace(width=16, height=12))
    colours = []
    for frame in (1, 2, 3, 3):
        scene.frame_set(frame)
        core, _ = engine.NeuralLayeredRenderEngine._view_scene(fake, context, fresh_scene.evaluated_depsgraph_get(), [])
        colours.append(int(np.argmax(core.environment.image.reshape(-1, 3).mean(axis=0))))
    assert colours == [0, 1, 2, 2]


def test_a_selection_leaves_the_viewport_rendering(fresh_scene):
    """A selection or a new active object names the scene alone: each click threw the viewport's samples away and
    exported the scene again (1.0-1.4 s with a 500,000-triangle mesh under a 4K sky). An update naming the scene
    alone that changes what renders (a transparent film, an object hidden in the viewport) still restarts it."""
    from types import SimpleNamespace

    from addon.blender import engine

    scene = fresh_scene.scene
    context = SimpleNamespace(
        region_data=SimpleNamespace(view_matrix=((1, 0), (0, 1)), window_matrix=((1, 0), (0, 1))),
        space_data=SimpleNamespace(lens=50.0),
        region=SimpleNamespace(width=40, height=30),
    )
    exports = []

    def view_scene(ctx, graph):
        exports.append(1)
        raise ValueError("stop here")  # the export itself is not what is tested

    view = SimpleNamespace(key=engine._view_key(context), session=object(), settings_key=engine.settings_key(scene))
    fake = SimpleNamespace(_viewport=view, _view_scene=view_scene, report=lambda kind, text: None)

    def update(*edits):
        for edit in edits:
            edit()
        real = fresh_scene.evaluated_depsgraph_get()
        scene_alone = SimpleNamespace(
            id=scene, is_updated_transform=False, is_updated_geometry=False, is_updated_shading=False
        )
        graph = SimpleNamespace(updates=[scene_alone], scene=scene, objects=real.objects)
        engine.NeuralLayeredRenderEngine.view_update(fake, context, graph)

    update()  # the first: the state seen
    assert exports == [1]
    update(lambda: scene.objects["Light"].select_set(True))
    update(lambda: setattr(fresh_scene.view_layer.objects, "active", scene.objects["Light"]))
    assert exports == [1]  # nothing exported, the session left rendering
    update(lambda: setattr(scene.render, "film_transparent", True))
    assert exports == [1, 1]
    update(lambda: scene.objects["Cube"].hide_set(True))
    assert exports == [1, 1, 1]
    update(lambda: setattr(scene.render, "threads_mode", "FIXED"))  # the session's threads
    assert exports == [1, 1, 1, 1]


def test_esc_while_a_fixed_decoder_size_calibrates_cancels_the_render_without_a_failure(
    fresh_scene, tmp_path, monkeypatch
):
    """A fixed Decoder size (Calibrate Albedo on) calibrates each new stack before the first pass, a second or two
    each: the calibrations heard no stop, and F12 returned 14.8 s (tiny) and 22.4 s (paper) after Esc, against
    1.5 s for Auto. They now hear F12's test_break between their parts: cancelled, not failed, nothing traced and
    nothing half made kept."""
    from addon.blender import engine, render_properties, stack_io
    from addon.core.neural import calibrate as cal
    from addon.core.neural import encode_stack, load_models
    from addon.core.stack import Coating, Diffuse, Stack

    scene = fresh_scene.scene
    small(scene, 16, 12, samples=2)
    # a stack no other test calibrates (the calibrations are kept on disk for the session)
    new = Stack(Diffuse((0.31, 0.42, 0.53)), (Coating(roughness=0.37, ior=1.47, thickness=0.3),))
    stack_io.stack_to_material(new, scene.objects["Cube"].active_material)
    scene.render.engine = "NEURAL_LAYERED"
    scene.neural_render.decoder_quality = "TINY"
    scene.neural_render.calibrate = True
    real = render_properties.NLM_RenderSettings.assign_decoders
    checks, traced = [], []

    def esc_during_the_calibration(self, core_scene, **kw):
        assert "test_break" in repr(kw["stop"])

        def stop():  # the check before the material, then Esc inside its calibration
            checks.append(1)
            return len(checks) > 1

        return real(self, core_scene, **{**kw, "stop": stop})

    monkeypatch.setattr(render_properties.NLM_RenderSettings, "assign_decoders", esc_during_the_calibration)
    monkeypatch.setattr(engine, "render", lambda *a, **k: traced.append(1))
    scene.render.filepath = str(tmp_path / "frame.png")
    bpy.ops.render.render(write_still=True)  # an ERROR report would raise here
    assert len(checks) == 2 and traced == []
    models = load_models("tiny")
    assert cal.cached(new, models, encode_stack(new, models)) is None


def test_the_reference_fallback_after_a_neural_failure_renders_the_stacks_in_reference_mode(
    fresh_scene, tmp_path, monkeypatch, capfd
):
    """The neural runtime failing in a render (an ONNX Runtime error in a batch) made F12 say "rendering in
    reference mode" and render the decoder choice's neural materials again, which failed the same way: the fallback
    now renders the exported stacks. Nothing of the render is stubbed: the sessions fail from its first batch."""
    from addon.blender import engine, stack_io
    from addon.core.neural import session
    from addon.core.render.neural_material import NeuralMaterial
    from addon.core.stack import PRESETS

    ctx = fresh_scene
    small(ctx.scene, 12, 8, samples=1)
    stack_io.stack_to_material(PRESETS["red_car_paint"], ctx.scene.objects["Cube"].active_material)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.neural_render.decoder_quality = "TINY"
    ctx.scene.neural_render.calibrate = False
    ctx.scene.neural_render.reference_walks = 1
    broken, renders = [], []
    real_run, real_render = session.ChunkedSession.run_once, engine.render

    def run_once(self, *args, **kwargs):
        if broken:
            raise RuntimeError("ONNX Runtime: [ONNXRuntimeError] : 6 : RUNTIME_EXCEPTION : simulated failure")
        return real_run(self, *args, **kwargs)

    def rendered(scene, settings, **kw):
        broken.append(1)  # after the decoder choice, which encoded the stack: the render's batches fail
        renders.append((settings.mode, [type(m) for m in scene.materials]))
        return real_render(scene, settings, **kw)

    monkeypatch.setattr(session.ChunkedSession, "run_once", run_once)
    monkeypatch.setattr(engine, "render", rendered)
    ctx.scene.render.filepath = str(tmp_path / "fallback.exr")
    ctx.scene.render.image_settings.file_format = "OPEN_EXR"
    capfd.readouterr()
    bpy.ops.render.render(write_still=True)  # the failure of the fallback was an ERROR, which raises here
    assert [mode for mode, _ in renders] == ["neural", "reference"]
    assert NeuralMaterial in renders[0][1] and NeuralMaterial not in renders[1][1]
    assert "rendering in reference mode" in capfd.readouterr().out
    px = read_image(tmp_path / "fallback.exr")[..., :3]
    assert np.isfinite(px).all() and px.max() > 0


def test_the_render_summary_counts_the_decoder_choice_before_the_render(fresh_scene, tmp_path, monkeypatch):
    """The summary's setup said "0.00 s: materials, calibrations, scene" where the decoder choice and the
    calibrations had taken 10-69 s before the render began: F12's last line now counts them."""
    import time

    from addon.blender import engine, render_properties

    scene = fresh_scene.scene
    small(scene, 8, 6, samples=1)
    scene.render.engine = "NEURAL_LAYERED"
    real_assign, real_summary = render_properties.NLM_RenderSettings.assign_decoders, engine.render_summary
    lines = []

    def slow_choice(self, core_scene, **kw):  # as a first render's measurements and calibrations are
        time.sleep(0.3)
        return real_assign(self, core_scene, **kw)

    def summary(stats, decoder_seconds=None):
        lines.append((decoder_seconds, real_summary(stats, decoder_seconds)))
        return lines[-1][1]

    monkeypatch.setattr(render_properties.NLM_RenderSettings, "assign_decoders", slow_choice)
    monkeypatch.setattr(engine, "render_summary", summary)
    scene.render.filepath = str(tmp_path / "frame.png")
    bpy.ops.render.render(write_still=True)
    ((seconds, line),) = lines
    assert seconds >= 0.3 and line.startswith(f"decoders {seconds:.2f} s") and "paths in" in line, line


def test_the_settings_this_engine_renders_are_drawn_for_it(bpy_addon):
    """Film > Transparent, Threads, the Z pass and the Material Override render here, and Blender draws them only in
    other engines' panels: the add-on's panels draw them for this one."""
    from addon.blender import render_ui

    layout = DrawnProps()
    ctx = SimpleNamespace(
        engine="NEURAL_LAYERED", scene=bpy_addon.context.scene, view_layer=bpy_addon.context.view_layer
    )
    for panel in (render_ui.NLM_PT_film, render_ui.NLM_PT_performance, render_ui.NLM_PT_view_layer):
        assert panel.poll(ctx) and panel.is_registered
        panel.draw(SimpleNamespace(layout=layout), ctx)
    assert {"film_transparent", "threads_mode", "threads", "use_pass_z", "material_override"} <= set(layout.drawn)
    assert not render_ui.NLM_PT_film.poll(SimpleNamespace(engine="CYCLES"))


def test_a_view_turned_orthographic_in_rendered_mode_is_said_to_render_in_perspective(bpy_addon, monkeypatch):
    """Numpad 5 in Rendered mode turns the view orthographic without an edit: ``view_draw`` moves the camera, and
    the warning that an orthographic view renders in perspective, said when Rendered mode began in one, went unsaid.
    Said once, however often the view moves."""
    from addon.blender import engine, scene_export

    monkeypatch.setattr(scene_export, "view_camera", lambda r3d, lens, w, h, clip: "camera")
    monkeypatch.setattr(scene_export, "view_clip", lambda r3d, space, scene: (0.0, math.inf))
    reports = []

    def context(window, perspective):
        return SimpleNamespace(
            region_data=SimpleNamespace(view_matrix=((1, 0), (0, 1)), window_matrix=window, is_perspective=perspective),
            space_data=SimpleNamespace(lens=50.0),
            region=SimpleNamespace(width=40, height=30),
            scene=None,
        )

    view = SimpleNamespace(session="rendering", settings_key=None, draw=lambda engine, scene: None)
    view.move_camera = lambda camera, key: setattr(view, "key", key)
    view.key = engine._view_key(context(((2, 0), (0, 2)), True))
    fake = SimpleNamespace(_viewport=view, _view_info=set(), report=lambda kind, text: reports.append((kind, text)))
    graph = SimpleNamespace(scene=None)
    engine.NeuralLayeredRenderEngine.view_draw(fake, context(((2, 0), (0, 2)), True), graph)
    assert reports == []  # perspective: nothing to say
    for zoom in (0.2, 0.1):  # orthographic, then zoomed in it
        engine.NeuralLayeredRenderEngine.view_draw(fake, context(((zoom, 0), (0, zoom)), False), graph)
    assert reports == [({"WARNING"}, "an orthographic view renders in perspective: this engine's camera is a pinhole")]


def test_the_viewport_accumulates_viewport_samples_and_renders_accumulate_render_samples(fresh_scene, monkeypatch):
    """The viewport accumulated F12's Samples, while Preview Samples, drawn beside them, drove the Render Preview
    operator alone: a Cycles user reads it as the viewport's count. The viewport has a sample count of its own, as
    Cycles' has (Viewport > Max Samples), drawn with the two others, each saying what it drives."""
    from addon.blender import engine, render_ui, scene_export

    scene = fresh_scene.scene
    props = scene.neural_render
    assert props.viewport_samples == props.samples == 64  # the viewport's count as it was by default
    props.samples, props.viewport_samples, props.preview_samples = 5, 7, 3
    monkeypatch.setattr(engine, "_view_camera", lambda context: None)  # the scene camera
    fake = SimpleNamespace(
        _view_info=set(), _view_geometry=scene_export.GeometryCache(), report=lambda kind, text: None
    )
    region = SimpleNamespace(region=SimpleNamespace(width=16, height=12))
    graph = fresh_scene.evaluated_depsgraph_get()
    _, settings = engine.NeuralLayeredRenderEngine._view_scene(fake, region, graph, [])
    assert settings.samples == 7 and props.to_core(scene=scene).samples == 5
    before = engine.settings_key(scene)
    props.viewport_samples = 9
    assert engine.settings_key(scene) != before  # the viewport renders again with the new count
    layout = DrawnProps()
    render_ui.NLM_PT_render.draw(SimpleNamespace(layout=layout), SimpleNamespace(scene=scene))
    drawn = layout.drawn
    assert drawn[:3] == ["samples", "viewport_samples", "preview_samples"]
    rna = props.bl_rna.properties
    assert [rna[n].name for n in drawn[:3]] == ["Render Samples", "Viewport Samples", "Render Preview Samples"]
    assert "Viewport Samples" in rna["samples"].description and "Viewport Samples" in rna["preview_samples"].description

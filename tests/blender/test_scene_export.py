"""What the scene export cannot evaluate is said, not silently replaced by a flat colour."""

from __future__ import annotations

import numpy as np
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
    assert any("Sky Texture" in w and "does not evaluate" in w and "flat" in w for w in warnings), warnings


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
    assert any("Noise Texture" in w and "does not evaluate" in w for w in warnings), warnings


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


def test_a_linked_object_and_material_beside_local_ones_of_the_same_names_export_as_their_own(
    bpy_addon, fresh_scene, tmp_path
):
    from addon.blender import scene_export, stack_io
    from addon.core.stack import PRESETS

    bpy = bpy_addon
    # The library: its "Cube" is a sphere's mesh (also named "Cube") with a layered "Material".
    cube = bpy.data.objects["Cube"]
    bpy.ops.mesh.primitive_uv_sphere_add()
    sphere = bpy.context.active_object
    old = cube.data
    cube.data = sphere.data
    bpy.data.objects.remove(sphere)
    bpy.data.meshes.remove(old)
    cube.data.name = "Cube"
    cube.data.materials.append(bpy.data.materials["Material"])
    stack_io.stack_to_material(PRESETS["red_car_paint"], cube.active_material)
    triangles = sum(len(p.vertices) - 2 for p in cube.data.polygons)
    library = tmp_path / "lib.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(library))
    # The shot: the factory cube and material, and the library's, linked, of the same names.
    bpy.ops.wm.read_homefile(app_template="")
    with bpy.data.libraries.load(str(library), link=True) as (_, linked):
        linked.objects = ["Cube"]
    bpy.context.scene.collection.objects.link(linked.objects[0])
    scene, _ = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), 32, 24)
    assert scene.mesh.triangle_count == 12 + triangles
    assert sorted(scene.material_names) == ["Material", "Material [lib.blend]"]
    kinds = dict(zip(scene.material_names, (type(m).__name__ for m in scene.materials), strict=True))
    assert kinds["Material"] == "PrincipledMaterial" and kinds["Material [lib.blend]"] == "LayeredSpec"


def test_each_geometry_that_geometry_nodes_instance_exports_as_itself(bpy_addon, fresh_scene):
    from addon.blender import scene_export

    bpy = bpy_addon
    # The cube's points, each instancing a cone (32 triangles) or an icosphere (20), in turn.
    tree = bpy.data.node_groups.new("instances", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = tree.nodes, tree.links
    given, result = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    points, on_points = nodes.new("GeometryNodeMeshToPoints"), nodes.new("GeometryNodeInstanceOnPoints")
    cone, ico = nodes.new("GeometryNodeMeshCone"), nodes.new("GeometryNodeMeshIcoSphere")
    pick, index = nodes.new("GeometryNodeGeometryToInstance"), nodes.new("GeometryNodeInputIndex")
    links.new(given.outputs[0], points.inputs["Mesh"])
    links.new(points.outputs[0], on_points.inputs["Points"])
    links.new(cone.outputs["Mesh"], pick.inputs[0])
    links.new(ico.outputs["Mesh"], pick.inputs[0])
    links.new(pick.outputs[0], on_points.inputs["Instance"])
    on_points.inputs["Pick Instance"].default_value = True
    links.new(index.outputs[0], on_points.inputs["Instance Index"])
    links.new(on_points.outputs[0], result.inputs[0])
    bpy.data.objects["Cube"].modifiers.new("instances", "NODES").node_group = tree
    depsgraph = bpy.context.evaluated_depsgraph_get()
    sizes = [
        sum(len(p.vertices) - 2 for p in i.object.data.polygons)
        for i in depsgraph.object_instances
        if i.is_instance and i.object.type == "MESH"
    ]
    assert len(sizes) == 8 and len(set(sizes)) == 2  # the cube's 8 corners, two geometries
    scene, _ = scene_export.export_scene(depsgraph, 32, 24)
    assert scene.mesh.triangle_count == sum(sizes)


def test_a_bake_on_another_drive_than_the_blend_file_keeps_its_absolute_path(
    bpy_addon, fresh_scene, tmp_path, monkeypatch
):
    """On Windows a Bake Folder on another drive has no path relative to the .blend file (os.path.relpath raises):
    the bake keeps the absolute path, where that error used to lose the finished bake."""
    from addon.blender import bake_ops

    bpy = bpy_addon
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    inside = str(tmp_path / "textures" / "Material.exr")
    assert bake_ops._blend_relative(inside) == "//textures/Material.exr"

    def across_drives(path, start=None):
        raise ValueError("path is on mount 'D:', start on mount 'C:'")

    monkeypatch.setattr(bpy.path, "relpath", across_drives)
    assert bake_ops._blend_relative("D:\\bakes\\Material.exr") == "D:\\bakes\\Material.exr"


def test_an_object_without_uvs_under_a_textured_material_is_named_whatever_the_others_have(bpy_addon, fresh_scene):
    """The warning names each object without a UV map whose material reads a texture, even when other objects have
    UV maps (the scene-wide check said nothing then); an object without UVs under a plain colour is no concern."""
    from addon.blender import scene_export

    bpy = bpy_addon
    bpy.ops.mesh.primitive_ico_sphere_add(calc_uvs=False, location=(3, 0, 0))
    sphere = bpy.context.object
    textured = bpy.data.materials.new("Checker")
    tree = textured.node_tree
    image = tree.nodes.new("ShaderNodeTexImage")
    image.image = bpy.data.images.new("checker", 8, 8)
    tree.links.new(image.outputs["Color"], tree.nodes["Principled BSDF"].inputs["Base Color"])
    sphere.data.materials.append(bpy.data.materials.new("Plain"))
    _, warnings = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), 32, 24)
    assert not any("UV map" in w for w in warnings)
    sphere.data.materials[0] = textured
    _, warnings = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), 32, 24)  # the cube has UVs
    (warning,) = [w for w in warnings if "UV map" in w]
    assert "'Icosphere'" in warning and "'Checker'" in warning and "Cube" not in warning


def test_a_udim_image_of_several_tiles_is_said_not_read_as_its_first_tile(bpy_addon, material):
    """Blender gives a UDIM image's first tile alone: a base colour from one renders its colour with a warning
    naming the image, where the first tile covered the whole uv square."""
    from addon.blender import scene_export

    bpy = bpy_addon
    udim = bpy.data.images.new("udim", 8, 8, tiled=True)
    udim.tiles.new(tile_number=1002)
    tree = material.node_tree
    node = tree.nodes.new("ShaderNodeTexImage")
    node.image = udim
    tree.links.new(node.outputs["Color"], tree.nodes["Principled BSDF"].inputs["Base Color"])
    warnings = []
    exported = scene_export.export_material(material, warnings)
    assert exported.texture is None
    assert any("'udim'" in w and "UDIM" in w and "2 tiles" in w for w in warnings), warnings


def test_light_values_blender_allows_render_as_cycles_does_not_fail_the_render(bpy_addon, fresh_scene):
    """Blender's largest spot (180 degrees, a float32 just above pi), a light scaled to nothing, an area light of
    size 0, a negative power and a negative world Strength each failed F12 ("SpotLight.spot_size must be in
    (0, pi]", "direction must be a non-zero finite vector", ...). The spot renders; the others shed no light here,
    the negative ones with a warning."""
    bpy = bpy_addon
    from addon.blender import scene_export
    from addon.core.render import AreaLight, SpotLight

    scene = fresh_scene.scene
    for ob in [o for o in scene.objects if o.type == "LIGHT"]:
        bpy.data.objects.remove(ob)

    def add(name, kind, energy=100.0, scale=(1.0, 1.0, 1.0), **settings):
        light = bpy.data.lights.new(name, kind)
        light.energy = energy
        for key, value in settings.items():
            setattr(light, key, value)
        ob = bpy.data.objects.new(name, light)
        ob.location, ob.scale = (0.0, 0.0, 3.0), scale
        scene.collection.objects.link(ob)

    add("wide spot", "SPOT", spot_size=bpy.types.SpotLight.bl_rna.properties["spot_size"].hard_max)
    add("hidden spot", "SPOT", scale=(0.0, 0.0, 0.0))
    add("hidden sun", "SUN", scale=(0.0, 0.0, 0.0))
    add("flat area", "AREA", size=0.0)
    add("hidden area", "AREA", scale=(0.0, 0.0, 0.0))
    add("negative", "POINT", energy=-50.0)
    scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = -1.0
    core, warnings = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get(), 16, 12)
    (spot,) = core.lights
    assert isinstance(spot, SpotLight) and spot.spot_size == pytest.approx(3.141592653589793)
    assert not any(isinstance(li, AreaLight) for li in core.lights) and core.environment is None
    assert any("'negative'" in w and "negative power" in w for w in warnings), warnings
    assert any("negative Strength" in w for w in warnings), warnings
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 16, 12, 100
    scene.neural_render.samples = 1
    assert bpy.ops.render.render() == {"FINISHED"}


@pytest.mark.parametrize("size, percentage", [((1280, 720), 70), ((100, 100), 29), ((100, 100), 57)])
def test_the_render_size_is_blenders_at_every_percentage(bpy_addon, fresh_scene, size, percentage):
    """Blender computes the size in integers: in floating point 720 at 70% was 503, one row short of Blender's
    frame, whose top row came out transparent black."""
    from addon.blender import scene_export

    r = fresh_scene.scene.render
    (r.resolution_x, r.resolution_y), r.resolution_percentage = size, percentage
    assert scene_export.render_size(fresh_scene.scene) == (size[0] * percentage // 100, size[1] * percentage // 100)


def _triangles(depsgraph):
    from addon.blender import scene_export

    return scene_export.export_scene(depsgraph)[0].mesh.triangle_count


def _collection_instance_of(bpy, scene, ob):
    """An empty in ``scene`` instancing a new collection that holds ``ob`` alone (taken out of its collections)."""
    source = bpy.data.collections.new("Source")
    for c in list(ob.users_collection):
        c.objects.unlink(ob)
    source.objects.link(ob)
    instancer = bpy.data.objects.new("Instancer", None)
    instancer.instance_type, instancer.instance_collection = "COLLECTION", source
    scene.collection.objects.link(instancer)
    return instancer


def test_what_renders_is_the_same_in_a_viewports_depsgraph_as_in_f12s(bpy_addon, fresh_scene):
    """Render Preview and the viewport export a viewport's depsgraph, which holds what the viewport shows: a
    collection disabled for renders and the instances of an instancer disabled for them rendered there (1,940
    triangles where F12 rendered 12)."""
    bpy = bpy_addon
    scene = fresh_scene.scene
    hidden = bpy.data.collections.new("NotForRender")
    scene.collection.children.link(hidden)
    hidden.hide_render = True
    bpy.ops.mesh.primitive_monkey_add()
    monkey = fresh_scene.object
    for c in list(monkey.users_collection):
        c.objects.unlink(monkey)
    hidden.objects.link(monkey)
    bpy.ops.mesh.primitive_uv_sphere_add()
    instancer = _collection_instance_of(bpy, scene, fresh_scene.object)
    instancer.hide_render = True
    assert _triangles(fresh_scene.evaluated_depsgraph_get()) == 12  # the cube alone, as F12
    excluded = fresh_scene.view_layer.layer_collection.children["NotForRender"]
    hidden.hide_render, excluded.exclude = False, True  # excluded from the view layer: in neither
    assert _triangles(fresh_scene.evaluated_depsgraph_get()) == 12


def _cube_emitting_icospheres(bpy, ctx):
    """The startup cube emitting 10 particles rendered as a small icosphere of 20 triangles (at frame 2): the cube,
    the icosphere and the particle settings."""
    scene = ctx.scene
    cube = scene.objects["Cube"]
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=1, radius=0.05, location=(5, 5, 5))
    ico = ctx.object
    cube.modifiers.new("particles", "PARTICLE_SYSTEM")
    settings = cube.particle_systems[0].settings
    settings.count, settings.frame_start, settings.frame_end = 10, 1, 1
    settings.render_type, settings.instance_object = "OBJECT", ico
    scene.frame_set(2)
    return cube, ico, settings


def test_an_emitter_shown_without_itself_is_not_rendered(bpy_addon, fresh_scene):
    """A particle emitter with Show Emitter off for renders: its particles render, not its own faces (the export
    read every row of the depsgraph, the emitter's own too)."""
    cube, ico, settings = _cube_emitting_icospheres(bpy_addon, fresh_scene)
    # the render's setting decides, in a viewport's depsgraph too (whose rows follow the viewport's setting)
    for for_render, for_viewport in ((False, True), (False, False), (True, False)):
        cube.show_instancer_for_render, cube.show_instancer_for_viewport = for_render, for_viewport
        expected = 10 * 20 + 20 + (12 if for_render else 0)  # the particles, the ico itself, and the emitter
        assert _triangles(fresh_scene.evaluated_depsgraph_get()) == expected, (for_render, for_viewport)


@pytest.mark.parametrize("kind", ["EMPTY", "LIGHT"])
def test_a_scene_camera_that_is_not_a_camera_renders_its_view_with_blenders_lens(bpy_addon, fresh_scene, kind):
    """Blender lets an empty or a light be the scene camera, and renders its view (an empty's with a 50 mm lens, a
    light's with its spot size's); F12 failed with an AttributeError."""
    import math

    from addon.blender import scene_export

    bpy = bpy_addon
    scene = fresh_scene.scene
    data = bpy.data.lights.new("L", "POINT") if kind == "LIGHT" else None
    ob = bpy.data.objects.new("viewer", data)
    ob.location = (0.0, -8.0, 0.0)
    ob.rotation_euler = (math.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(ob)
    scene.camera = ob
    core, warnings = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())
    assert any("not a camera" in w for w in warnings)
    w, h = scene_export.render_size(scene)
    # an empty: Blender's 50 mm; a light: the lens of its spot size, 45 degrees stored for a point light
    lens = 50.0 if kind == "EMPTY" else 16.0 / math.tan(math.radians(45.0) / 2.0)
    assert core.camera.tan_half_fov[0] == pytest.approx(18.0 / lens)
    assert core.camera.tan_half_fov[1] == pytest.approx(18.0 / lens * h / w)


def test_the_render_uv_map_places_textures_as_cycles_does(bpy_addon, fresh_scene):
    """Cycles textures with the UV map marked for renders (the camera icon), not the active one being edited."""
    import numpy as np

    from addon.blender import scene_export

    uv_layers = fresh_scene.scene.objects["Cube"].data.uv_layers
    name = uv_layers.active.name
    edit_map = uv_layers.new(name="edit")  # the collection's items move: read again by name below
    for loop in edit_map.data:
        loop.uv = (loop.uv[0] * 0.5, loop.uv[1] * 0.5)
    uv_layers.active = uv_layers["edit"]
    uv_layers[name].active_render = True
    core, _ = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())
    render_uv = np.array([d.uv[:] for d in uv_layers[name].data])
    assert np.isclose(core.mesh.uvs.max(), render_uv.max(), atol=1e-6)  # the edit map's is half of it


def _principled(bpy, name="m"):
    mat = bpy.data.materials.new(name)  # 5.0: a new material has its node tree, Principled on the output
    return mat, mat.node_tree.nodes["Principled BSDF"]


def test_what_a_lambertian_leaves_out_of_a_material_is_said(bpy_addon, fresh_scene):
    """A Lambertian of the base colour stands for every unmanaged material: Metallic, Transmission, Emission or
    Alpha set on a Principled BSDF, another surface node (Emission rendered as an orange reflector, Glass as white),
    or an Image Texture's own settings (Clip, a Mapping node) changed Cycles' image a lot, without a word."""
    from addon.blender import scene_export

    bpy = bpy_addon
    mat, principled = _principled(bpy)
    value = mat.node_tree.nodes.new("ShaderNodeValue")  # a Metallic a node computes: the Lambertian of its colour
    mat.node_tree.links.new(value.outputs[0], principled.inputs["Metallic"])
    principled.inputs["Transmission Weight"].default_value = 1.0
    warnings = []
    scene_export.unmanaged_material(mat, warnings)
    assert len(warnings) == 1 and "Metallic and Transmission" in warnings[0]
    mat, principled = _principled(bpy, "plain")
    warnings = []
    scene_export.unmanaged_material(mat, warnings)
    assert warnings == []  # the defaults: nothing left out that matters
    emission = mat.node_tree.nodes.new("ShaderNodeEmission")
    out = mat.node_tree.nodes["Material Output"]
    mat.node_tree.links.new(emission.outputs[0], out.inputs["Surface"])
    scene_export.unmanaged_material(mat, warnings)
    assert len(warnings) == 1 and "an Emission node" in warnings[0] and "emits no light" in warnings[0]
    mat.node_tree.links.remove(out.inputs["Surface"].links[0])  # nothing on the output: Cycles renders black
    assert np.array_equal(scene_export.unmanaged_material(mat, []).color, (0.0, 0.0, 0.0))
    mat, principled = _principled(bpy, "tex")
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.new("img", 2, 2)
    tex.extension = "CLIP"
    mapping = mat.node_tree.nodes.new("ShaderNodeMapping")
    mat.node_tree.links.new(mapping.outputs[0], tex.inputs["Vector"])
    mat.node_tree.links.new(tex.outputs["Color"], principled.inputs["Base Color"])
    warnings = []
    scene_export.unmanaged_material(mat, warnings)
    assert len(warnings) == 1 and "Mapping node maps no coordinates" in warnings[0]  # Clip is rendered
    # a bump on the Normal and a Displacement (Blender's default, a bump): Cycles' image shows the relief
    mat, principled = _principled(bpy, "bumpy")
    noise, bump = mat.node_tree.nodes.new("ShaderNodeTexNoise"), mat.node_tree.nodes.new("ShaderNodeBump")
    mat.node_tree.links.new(noise.outputs["Fac"], bump.inputs["Height"])
    mat.node_tree.links.new(bump.outputs["Normal"], principled.inputs["Normal"])
    mat.node_tree.links.new(noise.outputs["Fac"], mat.node_tree.nodes["Material Output"].inputs["Displacement"])
    warnings = []
    scene_export.unmanaged_material(mat, warnings)
    assert len(warnings) == 1 and "Normal input (a Bump" in warnings[0] and "Displacement" in warnings[0]


def test_settings_cycles_renders_and_this_renderer_does_not_are_said(bpy_addon, fresh_scene):
    """Holdouts, an object hidden from camera rays and a point cloud rendered as if unset, silently. The view
    layer's Material Override is rendered, and so is a transparent film (``test_cycles_settings``)."""
    from addon.blender import scene_export

    bpy = bpy_addon
    scene = fresh_scene.scene
    cube = scene.objects["Cube"]
    cube.is_holdout = True
    cube.is_shadow_catcher = True
    cube.visible_camera = False
    points = bpy.data.objects.new("points", bpy.data.pointclouds.new("points"))
    scene.collection.objects.link(points)
    hair = bpy.data.objects.new("hair", bpy.data.hair_curves.new("hair"))
    scene.collection.objects.link(hair)
    receivers = bpy.data.collections.new("receivers")
    scene.objects["Light"].light_linking.receiver_collection = receivers  # lights only what it holds
    scene.objects["Light"].visible_glossy = False
    _, warnings = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())
    text = "\n".join(warnings)
    assert "Holdout, Shadow Catcher, Camera ray visibility off" in text and "point cloud" in text
    assert "'Light': its Light Linking is not rendered" in text
    assert "'Light': its ray visibility (Glossy off) is not rendered" in text
    assert "'hair': hair curves are not rendered" in text and not any("\n" in w for w in warnings)
    override, principled = _principled(bpy, "override")
    principled.inputs["Base Color"].default_value = (0.1, 0.2, 0.9, 1.0)
    fresh_scene.view_layer.material_override = override
    core, _ = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())
    assert core.material_names == ["override"]
    np.testing.assert_allclose(core.materials[0].color, (0.1, 0.2, 0.9), rtol=1e-6)


def test_particle_hair_depth_of_field_and_motion_blur_that_cycles_renders_are_said(bpy_addon, fresh_scene):
    """A mesh's particle hair (rendered as strands, Path), a camera's depth of field and the render's Motion Blur
    rendered as if unset, silently (hair curves objects were already said): each is said. Hair that renders
    nothing in Cycles either (Render As None) says nothing, nor does Motion Blur where the view layer renders none
    (its Use > Motion Blur off), or in a viewport's export (its own camera)."""
    from addon.blender import scene_export

    scene = fresh_scene.scene
    cube = scene.objects["Cube"]
    cube.modifiers.new("fur", "PARTICLE_SYSTEM")
    settings = cube.particle_systems[0].settings
    settings.type, settings.count, settings.hair_length = "HAIR", 50, 0.5
    assert settings.render_type == "PATH"
    graph = fresh_scene.evaluated_depsgraph_get()
    _, warnings = scene_export.export_scene(graph)
    assert [w for w in warnings if "hair" in w] == [
        "object 'Cube': particle hair 'fur' is not rendered here (Cycles renders its strands); the object renders "
        "without it"
    ]
    settings.render_type = "NONE"  # hair that renders nothing in Cycles either
    assert scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())[1] == []
    cube.modifiers.clear()
    scene.camera.data.dof.use_dof = True
    scene.render.use_motion_blur = True
    graph = fresh_scene.evaluated_depsgraph_get()
    _, warnings = scene_export.export_scene(graph)
    assert len(warnings) == 2, warnings
    assert "camera 'Camera': Depth of Field is not rendered here" in warnings[0] and "Motion Blur" in warnings[1]
    core, _ = scene_export.export_scene(graph)
    _, viewport = scene_export.export_scene(graph, camera=core.camera)
    assert not any("Motion Blur" in w for w in viewport)
    fresh_scene.view_layer.use_motion_blur = False  # the view layer's own Use > Motion Blur: none in Cycles either
    assert not any("Motion Blur" in w for w in scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())[1])


def _f12_triangles(bpy, scene, monkeypatch) -> int:
    """The triangles F12's own depsgraph exports (one small render of this engine)."""
    from addon.blender import scene_export

    exported = []

    def spy(depsgraph, *a, **k):
        exported.append(export(depsgraph, *a, **k))
        return exported[-1]

    export = scene_export.export_scene
    monkeypatch.setattr(scene_export, "export_scene", spy)
    scene.render.engine = "NEURAL_LAYERED"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 8, 6, 100
    scene.neural_render.samples = 1
    assert bpy.ops.render.render() == {"FINISHED"}
    return exported[0][0].mesh.triangle_count


def test_particles_of_an_object_hidden_for_renders_render(bpy_addon, fresh_scene, monkeypatch):
    """The usual scatter: the source object hidden for renders, its particles shown. Cycles renders the particles;
    they were dropped with their source, in F12 and in the viewport (12 triangles where there were 212). A collection
    instance's object hidden for renders is left out, as Cycles leaves it out."""
    bpy = bpy_addon
    scene = fresh_scene.scene
    cube, ico, settings = _cube_emitting_icospheres(bpy, fresh_scene)
    ico.hide_render = True
    assert _triangles(fresh_scene.evaluated_depsgraph_get()) == 10 * 20 + 12  # the particles and the emitter
    assert _f12_triangles(bpy, scene, monkeypatch) == 10 * 20 + 12
    # a collection of it, which the particles render as a collection: its hidden member is left out, in both
    members = bpy.data.collections.new("Members")
    members.objects.link(ico)
    settings.render_type, settings.instance_collection = "COLLECTION", members
    assert _triangles(fresh_scene.evaluated_depsgraph_get()) == 12
    assert _f12_triangles(bpy, scene, monkeypatch) == 12
    settings.render_type = "OBJECT"
    # a collection instance of a collection whose object is hidden for renders: nothing of it, in both
    cube.modifiers.clear()
    _collection_instance_of(bpy, scene, ico)
    assert _triangles(fresh_scene.evaluated_depsgraph_get()) == 12
    assert _f12_triangles(bpy, scene, monkeypatch) == 12


def test_the_instances_of_a_geometry_are_placed_at_once_as_each_would_be_alone(bpy_addon):
    """Each instance made and checked a mesh of its own, and the scene checked them again (90,000 instances of a
    scatter: 18.7 s, the same triangles realised 3.6 s): a geometry's instances are now placed together. Each is as it
    was alone: positions by its matrix, normals by its inverse transpose, a mirrored one's corners reversed, a
    matrix scaled to nothing leaving its normals as they are."""
    from addon.blender import scene_export

    rng = np.random.default_rng(4)
    t = 5
    pos, nrm = rng.normal(size=(t, 3, 3)).astype(np.float32), rng.normal(size=(t, 3, 3)).astype(np.float32)
    uvs = rng.random((t, 3, 2)).astype(np.float32)
    arrays = (pos, nrm, uvs, np.array([0, 1, 1, 0, 7]), np.array([3, 5]))
    matrices = np.tile(np.eye(4), (4, 1, 1))
    matrices[0, :3] = rng.normal(size=(3, 4))
    matrices[1, :3, :3] = np.diag([-1.0, 2.0, 1.0])  # mirrored
    matrices[2, :3, :3] = 0.0  # scaled to nothing
    matrices[3, :3] = rng.normal(size=(3, 4))
    p, n, uv, slot = scene_export._placed_arrays(arrays, matrices)
    assert p.shape == (4 * t, 3, 3) and n.shape == (4 * t, 3, 3) and uv.shape == (4 * t, 3, 2)
    for k, m in enumerate(matrices):
        rows = slice(k * t, (k + 1) * t)
        order = [0, 2, 1] if np.linalg.det(m[:3, :3]) < 0 else [0, 1, 2]
        want_n = nrm @ (np.linalg.inv(m[:3, :3]) if abs(np.linalg.det(m[:3, :3])) > 1e-30 else np.eye(3))
        np.testing.assert_allclose(p[rows], (pos @ m[:3, :3].T + m[:3, 3])[:, order], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(n[rows], want_n[:, order], rtol=1e-4, atol=1e-5)
        np.testing.assert_array_equal(uv[rows], uvs[:, order])
        np.testing.assert_array_equal(slot[rows], [3, 5, 5, 3, 5])  # an index past the last slot: the last
    mesh = scene_export._world_mesh(
        {"a": (arrays, list(matrices[[0, 3]])), "b": (arrays[:2] + (None,) + arrays[3:], [np.eye(4)])}
    )
    assert mesh.triangle_count == 3 * t and mesh.uvs is not None and not mesh.uvs[2 * t :].any()


@pytest.mark.parametrize("kind", ["POINT", "SUN", "AREA"])
def test_a_light_or_an_object_placed_at_no_number_is_skipped_and_said(bpy_addon, fresh_scene, kind):
    """A driver or a constraint can place a light or an object at NaN: a point light there failed the whole F12, and
    any other light or the object vanished without a word."""
    from addon.blender import scene_export

    scene = fresh_scene.scene
    light = scene.objects["Light"]
    light.data.type = kind
    light.location, light.rotation_euler = (float("nan"), 0.0, 0.0), (float("nan"), 0.0, 0.0)
    scene.objects["Cube"].scale = (float("nan"), 1.0, 1.0)
    core, warnings = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())
    assert core.lights == [] and core.mesh.triangle_count == 0
    assert any("light 'Light'" in w and "not a number" in w for w in warnings)
    assert any("object 'Cube'" in w and "not a number" in w for w in warnings)
    # a NaN in what the light does not read leaves it shining, as in Cycles: a sun's location, a point light's scale
    if kind != "AREA":
        light.location, light.rotation_euler = (0.0, 0.0, 3.0), (0.0, 0.0, 0.0)
        if kind == "SUN":
            light.location = (float("nan"), 0.0, 0.0)
        else:
            light.scale = (float("nan"), 1.0, 1.0)
        core, warnings = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get())
        assert len(core.lights) == 1 and not any("'Light'" in w for w in warnings)


def test_the_viewports_exports_read_again_only_the_geometry_an_edit_changed(bpy_addon, fresh_scene, monkeypatch):
    """Every viewport edit exported the scene whole on the main thread: a light moved in a scene of 500,000 triangles
    blocked it 0.5-1.3 s. A geometry is read again only when the depsgraph says its geometry changed, and the
    scene's mesh is kept whole when nothing it is made of changed; what is exported is what an export from scratch
    gives."""
    from types import SimpleNamespace

    from addon.blender import scene_export

    bpy = bpy_addon
    reads = []
    real = scene_export._mesh_arrays
    monkeypatch.setattr(scene_export, "_mesh_arrays", lambda ob: reads.append(ob.name) or real(ob))
    scene = fresh_scene.scene
    cube, light = scene.objects["Cube"], scene.objects["Light"]
    kept = scene_export.GeometryCache()

    def export(*updates):
        kept.forget([SimpleNamespace(id=i, is_updated_geometry=g) for i, g in updates])
        graph = fresh_scene.evaluated_depsgraph_get()
        core = scene_export.export_scene(graph, 16, 12, kept=kept)[0]
        fresh = scene_export.export_scene(graph, 16, 12)[0]
        np.testing.assert_array_equal(core.mesh.positions, fresh.mesh.positions)
        return core

    first = export()
    assert reads.count("Cube") == 2  # the kept export's read and the fresh one's
    light.location.x += 1.0
    assert export((light, False)).mesh is first.mesh and reads.count("Cube") == 3  # only the fresh export read it
    cube.location.x += 1.0
    moved = export((cube, False))
    assert moved.mesh is not first.mesh and reads.count("Cube") == 4  # placed again, not read again
    cube.data.vertices[0].co.z += 0.5
    cube.data.update()
    export((cube.data, True))
    assert reads.count("Cube") == 6  # its geometry changed: read again
    tree = bpy.data.node_groups.new("G", "GeometryNodeTree")
    kept.forget([SimpleNamespace(id=tree, is_updated_geometry=True)])  # anything else's geometry: all read again
    assert kept.arrays == {}


def test_a_scatter_groups_collection_member_hidden_for_renders_is_left_out_as_f12_leaves_it(
    bpy_addon, fresh_scene, monkeypatch
):
    """A Geometry Nodes scatter whose Collection Info sits in a node group, the collection set on the group node (a
    scatter asset's usual layout): the viewport rendered the collection's member hidden for renders (80 triangles),
    which F12 leaves out."""
    bpy = bpy_addon
    scene = fresh_scene.scene
    bpy.data.objects.remove(scene.objects["Cube"])
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=1, location=(0, 0, -5))
    ico = fresh_scene.object
    members = bpy.data.collections.new("Members")
    scene.collection.children.link(members)
    for c in list(ico.users_collection):
        c.objects.unlink(ico)
    members.objects.link(ico)
    ico.hide_render = True
    bpy.ops.mesh.primitive_plane_add(size=2)  # 4 points to scatter on
    plane = fresh_scene.object

    def tree(name, inputs):
        t = bpy.data.node_groups.new(name, "GeometryNodeTree")
        for n, kind in inputs:
            t.interface.new_socket(n, in_out="INPUT", socket_type=kind)
        t.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        return t, t.nodes.new("NodeGroupInput"), t.nodes.new("NodeGroupOutput")

    inner, gi, go = tree("Scatter", [("Points", "NodeSocketGeometry"), ("Collection", "NodeSocketCollection")])
    info, scatter = inner.nodes.new("GeometryNodeCollectionInfo"), inner.nodes.new("GeometryNodeInstanceOnPoints")
    inner.links.new(gi.outputs["Collection"], info.inputs["Collection"])
    inner.links.new(gi.outputs["Points"], scatter.inputs["Points"])
    inner.links.new(info.outputs[0], scatter.inputs["Instance"])
    inner.links.new(scatter.outputs[0], go.inputs[0])
    outer, ogi, ogo = tree("Outer", [("Geometry", "NodeSocketGeometry")])
    group = outer.nodes.new("GeometryNodeGroup")
    group.node_tree = inner
    group.inputs["Collection"].default_value = members
    outer.links.new(ogi.outputs[0], group.inputs["Points"])
    outer.links.new(group.outputs[0], ogo.inputs[0])
    plane.modifiers.new("GN", "NODES").node_group = outer
    assert _triangles(fresh_scene.evaluated_depsgraph_get()) == 0  # the plane became its 4 points
    assert _f12_triangles(bpy, scene, monkeypatch) == 0


def test_an_image_file_is_read_once_for_each_version_of_it(bpy_addon, fresh_scene, tmp_path, monkeypatch):
    """Every export read, decoded and filtered each texture again: the viewport exports at every edit, and a 4K
    texture took 1.4-1.8 s of each. A texture whose pixels are its file's is read (and its mip chain made) once for
    each version of the file (and of its colour space), from the file; one painted and not saved, from Blender at
    every export. Blender's own pixels kept under the file's key went on being served after Image > Reload, where
    an export had come between the file's edit and the reload."""
    from addon.blender import images, scene_export

    bpy = bpy_addon
    reads = []
    for name in ("linear_pixels", "file_pixels"):
        real = getattr(images, name)
        monkeypatch.setattr(images, name, lambda image, *a, real=real: reads.append(image.name) or real(image, *a))
    path = tmp_path / "tex.png"

    def write(value):
        img = bpy.data.images.new("w", 4, 4)
        img.pixels.foreach_set(np.full(64, value, np.float32))
        img.filepath_raw, img.file_format = str(path), "PNG"
        img.save()
        bpy.data.images.remove(img)

    write(1.0)
    mat = bpy.data.materials["Material"]
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.load(str(path))
    mat.node_tree.links.new(tex.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])

    def colour():
        core, _ = scene_export.export_scene(fresh_scene.evaluated_depsgraph_get(), 8, 6)
        return float(core.materials[core.material_names.index("Material")].texture.levels[0].mean())

    assert colour() == pytest.approx(1.0, abs=1e-3) and colour() == pytest.approx(1.0, abs=1e-3) and len(reads) == 1
    textures = [
        c.materials[c.material_names.index("Material")].texture
        for c in (scene_export.export_scene(fresh_scene.evaluated_depsgraph_get(), 8, 6)[0] for _ in range(2))
    ]
    assert textures[0] is textures[1]  # its mip chain made once too
    write(0.0)  # the file edited elsewhere: an export before the reload, and one after
    assert colour() == pytest.approx(0.0, abs=1e-3) and len(reads) == 2
    tex.image.reload()
    assert colour() == pytest.approx(0.0, abs=1e-3) and len(reads) == 2
    tex.image.colorspace_settings.name = "Non-Color"
    colour()
    assert len(reads) == 3
    # a multilayer OpenEXR's pass or a multi-view image's view is the node's choice, not the file's first image
    from types import SimpleNamespace

    for kind, views in (("MULTILAYER", False), ("IMAGE", True)):
        other = SimpleNamespace(source="FILE", packed_file=None, is_dirty=False, type=kind, use_multiview=views)
        assert scene_export._image_file_key(other, False) is None
    tex.image.pixels.foreach_set(np.full(64, 0.5, np.float32))  # painted, not saved: its pixels are not its file's
    assert tex.image.is_dirty
    assert colour() == pytest.approx(0.5, abs=3e-3) and colour() == pytest.approx(0.5, abs=3e-3) and len(reads) == 5

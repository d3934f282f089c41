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
    assert kinds["Material"] == "LambertMaterial" and kinds["Material [lib.blend]"] != "LambertMaterial"


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

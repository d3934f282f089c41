"""No more geometry than renders: scene export keeps only what Blender would render."""

from __future__ import annotations

from addon.blender import scene_export


def _export(ctx):
    return scene_export.export_scene(ctx.evaluated_depsgraph_get(), 16, 16)


def test_only_rendered_geometry_and_its_materials_are_exported(fresh_scene):
    import bpy

    ctx = fresh_scene
    scene, _ = _export(ctx)
    base_tris = scene.mesh.triangle_count
    assert base_tris == 12  # the startup cube

    hidden = bpy.data.objects.new("hidden", bpy.data.meshes.new_from_object(ctx.scene.objects["Cube"]))
    ctx.scene.collection.objects.link(hidden)
    hidden.hide_render = True
    hidden_mat = bpy.data.materials.new("only on the hidden object")
    hidden.data.materials.clear()
    hidden.data.materials.append(hidden_mat)

    excluded = bpy.data.collections.new("excluded")
    ctx.scene.collection.children.link(excluded)
    ob = bpy.data.objects.new("in excluded collection", bpy.data.meshes.new_from_object(ctx.scene.objects["Cube"]))
    excluded.objects.link(ob)
    ctx.view_layer.layer_collection.children["excluded"].exclude = True

    bpy.data.materials.new("unused")  # in the file, on no object

    scene, _ = _export(ctx)
    assert scene.mesh.triangle_count == base_tris
    assert "only on the hidden object" not in scene.material_names
    assert "unused" not in scene.material_names

    hidden.hide_render = False  # once it renders, it is exported with its material
    scene, _ = _export(ctx)
    assert scene.mesh.triangle_count == 2 * base_tris
    assert "only on the hidden object" in scene.material_names

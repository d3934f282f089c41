"""A core ``Scene`` as Blender data: the demo scene as a .blend, the Cycles benchmark's scene.

``build_scene(scene)`` replaces the current scene's objects with one mesh (triangles, custom
normals, UVs, material slots), an area light per ``AreaLight``, a world with the environment
image, and the camera. Managed materials get their layer stack (the add-on's properties, when
registered) and a Principled BSDF coat approximation (``addon.core.render.principled``) so that
Cycles and EEVEE show something close.
"""

from __future__ import annotations

import bpy
import mathutils
import numpy as np

from ..core.render import AreaLight, LambertMaterial, LayeredSpec
from ..core.render.principled import principled_inputs


def image_from_array(name: str, rgb: np.ndarray):
    """A float, linear image (rows of ``rgb`` top to bottom), packed into the .blend as OpenEXR: Blender saves no
    pixels written into a generated image, so a saved demo reopened with a black sky and floor."""
    h, w, _ = rgb.shape
    img = bpy.data.images.new(name, w, h, float_buffer=True)
    img.colorspace_settings.name = "Linear Rec.709"  # before the pixels: changing it regenerates them
    rgba = np.concatenate([rgb, np.ones((h, w, 1), np.float32)], axis=2)[::-1]
    img.pixels.foreach_set(np.ascontiguousarray(rgba, dtype=np.float32).ravel())
    img.update()
    img.file_format = "OPEN_EXR"  # float, unclipped (the sky's sun is 22 times white)
    img.pack()
    return img


def _material(name: str, spec):
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    p = mat.node_tree.nodes["Principled BSDF"]
    if isinstance(spec, LambertMaterial):
        p.inputs["Base Color"].default_value = (*spec.color, 1.0)
        p.inputs["Roughness"].default_value = 1.0
        p.inputs["Specular IOR Level"].default_value = 0.0
        if spec.texture is not None:
            tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
            tex.image = image_from_array(f"{name} texture", spec.texture.levels[0])
            mat.node_tree.links.new(tex.outputs["Color"], p.inputs["Base Color"])
    elif isinstance(spec, LayeredSpec):
        for key, value in principled_inputs(spec.stack).items():
            p.inputs[key].default_value = value
        if hasattr(mat, "neural_layers"):
            from . import stack_io

            stack_io.stack_to_material(spec.stack, mat)
    return mat


def build_scene(scene, context=None):
    """Fill the current Blender scene from a core ``Scene``; returns the Blender scene."""
    context = context or bpy.context
    bs = context.scene
    for ob in list(bs.objects):
        bpy.data.objects.remove(ob)
    mesh = scene.mesh
    me = bpy.data.meshes.new("scene mesh")
    verts = mesh.positions.reshape(-1, 3)
    faces = np.arange(len(verts)).reshape(-1, 3)
    me.from_pydata(verts.tolist(), [], faces.tolist())
    me.polygons.foreach_set("material_index", mesh.material_index.astype(np.int32))
    me.polygons.foreach_set("use_smooth", np.ones(len(faces), bool))
    if mesh.uvs is not None:
        uv = me.uv_layers.new(name="UVMap")
        uv.data.foreach_set("uv", mesh.uvs.reshape(-1).astype(np.float32))
    me.normals_split_custom_set(mesh.normals.reshape(-1, 3).tolist())
    me.update()
    names = scene.material_names or [f"material {i}" for i in range(len(scene.materials))]
    for name, spec in zip(names, scene.materials, strict=True):
        me.materials.append(_material(name, spec))
    ob = bpy.data.objects.new("scene mesh", me)
    bs.collection.objects.link(ob)
    for i, light in enumerate(scene.lights):
        if not isinstance(light, AreaLight):
            continue  # the demo and benchmark scenes use area lights only
        ld = bpy.data.lights.new(f"area {i}", "AREA")
        ld.shape = "ELLIPSE" if light.ellipse else "RECTANGLE"
        ld.energy, ld.color = light.power, tuple(light.color)
        ld.size, ld.size_y = 2 * np.linalg.norm(light.axis_u), 2 * np.linalg.norm(light.axis_v)
        lo = bpy.data.objects.new(f"area {i}", ld)
        m = np.eye(4)
        m[:3, 0] = light.axis_u / np.linalg.norm(light.axis_u)
        m[:3, 1] = light.axis_v / np.linalg.norm(light.axis_v)
        m[:3, 2] = -light.normal
        m[:3, 3] = light.center
        lo.matrix_world = mathutils.Matrix(m.tolist())
        bs.collection.objects.link(lo)
    env = scene.environment
    world = bpy.data.worlds.new("environment")
    if world.node_tree is None:
        world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    if env is not None and env.image is not None:
        tex = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
        tex.image = image_from_array("environment", env.image.astype(np.float32))
        tex.interpolation = "Closest"  # the renderer looks up the nearest texel
        world.node_tree.links.new(tex.outputs["Color"], bg.inputs["Color"])
    elif env is not None:
        bg.inputs["Color"].default_value = (*env.constant, 1.0)
    else:
        bg.inputs["Strength"].default_value = 0.0
    bs.world = world
    cam = scene.camera
    cd = bpy.data.cameras.new("camera")
    cd.sensor_fit = "AUTO"
    cd.lens_unit = "FOV"
    cd.angle = 2 * float(np.arctan(max(cam.tan_half_fov)))
    co = bpy.data.objects.new("camera", cd)
    co.matrix_world = mathutils.Matrix(cam.matrix.tolist())
    bs.collection.objects.link(co)
    bs.camera = co
    bs.render.resolution_x, bs.render.resolution_y, bs.render.resolution_percentage = cam.width, cam.height, 100
    return bs

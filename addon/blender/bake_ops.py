"""Latent-texture baking from the sidebar: parameter maps per layer and the bake operator.

The bake itself is ``addon.core.textures.bake.bake_stack`` (the same code as ``bake/bake.py``);
the operator gathers the material's stack and images, runs the bake on a worker thread (or
blocking in background mode), writes the EXR and points the material at it. The renderer uses
the baked texture for that material while its inputs are unchanged.
"""

from __future__ import annotations

import os
import time

import bpy
from bpy.props import EnumProperty, IntProperty

from ..core.neural.models import resolve_size
from ..core.textures.bake import bake_key, bake_stack, neural_encoder

from . import bake_inputs, stack_io
from .operators import UserError, _guarded, _LongOperator, _MaterialOperator
from .properties import MAP_PARAMETERS


DEFAULT_BAKE_FOLDER = "//textures/"


def texture_output_path(mat) -> str:
    """Where the bake of ``mat`` goes: its Bake Folder (relative to the .blend file by default).

    A folder relative to the .blend file ("//...") needs a saved file; without one Blender would
    resolve it against the process's working folder, so the bake refuses instead.
    """
    folder = mat.neural_layers.bake_directory or DEFAULT_BAKE_FOLDER
    if folder.startswith("//") and not bpy.data.filepath:
        raise UserError(
            f"the bake folder {folder!r} is relative to the .blend file, which is not saved: "
            "save the file first or choose an absolute Bake Folder"
        )
    return os.path.join(bpy.path.abspath(folder), f"{bpy.path.clean_name(mat.name)}.exr")


def bake_size(mat) -> str:
    """The decoder size a bake of ``mat`` uses: its model-size setting, "auto" resolved (``neural.resolve_size``)."""
    try:
        return resolve_size(stack_io.model_size(mat))
    except (ValueError, FileNotFoundError) as e:
        raise UserError(str(e)) from None


def baked_texture_state(mat) -> tuple[str | None, str]:
    """(path of a current baked texture or None, a line for the user about its state)."""
    s = mat.neural_layers
    if not s.texture_path:
        return None, "not baked"
    path = bpy.path.abspath(s.texture_path)
    if not os.path.isfile(path):
        return None, f"baked texture missing: {path}"
    try:
        found = bake_inputs.spatial_stack_from_material(mat)
    except ValueError as e:
        return None, str(e)
    if found is None:
        return None, "no layer stack"
    spatial, _ = found
    res = tuple(s.texture_size)
    try:
        size = bake_size(mat)
    except UserError as e:
        return None, str(e)
    if bake_key(spatial, res, size) != s.texture_key:
        return None, "baked texture is out of date: bake again"
    return path, f"baked: {os.path.basename(path)}"


def camera_resolution(context, mat, spatial) -> tuple[int, int]:
    """(height, width) no finer than the material's smallest footprint through the scene camera."""
    from ..core import quality

    from . import scene_export

    scene, _ = scene_export.export_scene(context.evaluated_depsgraph_get())
    footprints = quality.primary_footprints(scene)
    names = list(getattr(scene, "material_names", []))
    footprint = footprints[names.index(mat.name)] if mat.name in names else float("inf")
    return quality.texture_resolution_for_footprint(footprint, spatial.resolution or (1, 1))


class NLM_OT_map_add(_MaterialOperator, bpy.types.Operator):
    """Drive a parameter of the active layer by an image"""

    bl_idname = "neural_layers.map_add"
    bl_label = "Add Parameter Map"
    bl_options = {"REGISTER", "UNDO"}

    parameter: EnumProperty(name="Parameter", items=MAP_PARAMETERS, default="ROUGHNESS")

    def execute(self, context):
        return _guarded(self.bl_label, self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        s = mat.neural_layers
        if not (0 <= s.active_index < len(s.layers)):
            raise UserError(f"material {mat.name!r} has no active layer to add a map to")
        item = s.layers[s.active_index]
        pmap = item.maps.add()
        pmap.parameter = self.parameter
        return {"FINISHED"}


class NLM_OT_map_remove(_MaterialOperator, bpy.types.Operator):
    """Remove a parameter map of the active layer"""

    bl_idname = "neural_layers.map_remove"
    bl_label = "Remove Parameter Map"
    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(name="Index", default=0, min=0)

    def execute(self, context):
        return _guarded(self.bl_label, self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        s = mat.neural_layers
        if not (0 <= s.active_index < len(s.layers)):
            raise UserError(f"material {mat.name!r} has no active layer")
        item = s.layers[s.active_index]
        if not (0 <= self.index < len(item.maps)):
            raise UserError(f"layer {item.name!r} has {len(item.maps)} map(s); there is no map {self.index}")
        item.maps.remove(self.index)
        return {"FINISHED"}


class NLM_OT_bake_texture(_LongOperator, bpy.types.Operator):
    """Bake the material's stack and its parameter maps into a mip-mapped latent texture (EXR)"""

    bl_idname = "neural_layers.bake_texture"
    bl_label = "Bake Latent Texture"
    bl_options = {"REGISTER", "UNDO"}

    def prepare(self, context):
        mat = self.target(context)
        found = bake_inputs.spatial_stack_from_material(mat)
        if found is None:
            raise UserError(f"material {mat.name!r} has an empty layer stack: add a base layer or pick a preset")
        spatial, sources = found
        s = mat.neural_layers
        res = spatial.resolution_for_max_side(s.bake_resolution)
        if s.bake_fit_camera:
            res = min(res, camera_resolution(context, mat, spatial), key=lambda r: r[0] * r[1])
        size = bake_size(mat)
        path = texture_output_path(mat)
        key = bake_key(spatial, res, size)
        name = mat.name

        def work(progress):
            t0 = time.perf_counter()
            encode = neural_encoder(size)
            tex, stats = bake_stack(spatial, encode, resolution=res, progress=progress,
                                    metadata={"material": name, "model": size, "key": key})
            os.makedirs(os.path.dirname(path), exist_ok=True)
            tex.write_exr(path)
            return stats, time.perf_counter() - t0

        def finish(context, result):
            stats, seconds = result
            mat.neural_layers.texture_path = bpy.path.relpath(path) if bpy.data.filepath else path
            mat.neural_layers.texture_key = key
            mat.neural_layers.texture_size = res
            self.report({"INFO"}, f"{name}: baked {res[1]}x{res[0]} ({stats.unique} distinct of {stats.texels} texels, "
                                  f"{stats.texels_per_second:,.0f} texels/s) in {seconds:.1f} s -> {path}")
            return {"FINISHED"}

        return work, finish


class NLM_OT_texture_clear(_MaterialOperator, bpy.types.Operator):
    """Stop using the baked latent texture for this material (the file is kept)"""

    bl_idname = "neural_layers.texture_clear"
    bl_label = "Clear Latent Texture"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return _guarded(self.bl_label, self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        mat.neural_layers.texture_path = ""
        mat.neural_layers.texture_key = ""
        return {"FINISHED"}


_CLASSES = (NLM_OT_map_add, NLM_OT_map_remove, NLM_OT_bake_texture, NLM_OT_texture_clear)


def register() -> None:
    for cls in _CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(_CLASSES):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)

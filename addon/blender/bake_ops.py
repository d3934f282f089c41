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

from ..core.render import RenderSettings
from ..core.textures import files
from ..core.textures.bake import bake_key, bake_stack, check_bake_memory, neural_encoder
from . import bake_inputs, stack_io
from .bake_state import (  # noqa: F401 (baked_texture_state: API; _blend_relative: the tests reach it here)
    _blend_relative,
    attach_texture,
    bake_model_key,
    bake_size,
    bake_target,
    baked_texture_state,
    blend_file_name,
    check_bake_folder,
    inputs_digest,
)
from .operator_base import LongOperator, MaterialOperator, UserError, context_material, guarded
from .properties import MAP_PARAMETERS


def camera_resolution(context, mat, spatial) -> tuple[int, int]:
    """(height, width) no finer than the material's smallest footprint through the scene camera."""
    from ..core import quality
    from . import scene_export

    scene, _ = scene_export.export_scene(context.evaluated_depsgraph_get())
    footprints = quality.primary_footprints(scene)
    names = list(getattr(scene, "material_names", []))
    footprint = footprints[names.index(mat.name_full)] if mat.name_full in names else float("inf")
    return quality.texture_resolution_for_footprint(footprint, spatial.resolution or (1, 1))


_MAP_ITEMS: list = []  # the menu's items, kept alive while Blender shows them (a dynamic enum's rule)


def _map_parameter_items(op, context):
    """The parameters the active layer can have a map of (every one without a layer to ask): a diffuse base's
    albedo, a coating's roughness, ior, medium albedo and thickness... The menu offered every parameter for every
    layer, so an Albedo map added to a coating failed only at the bake."""
    mat = bpy.data.materials.get(op.material) if getattr(op, "material", "") else None
    mat = mat or (context_material(context) if context is not None else None)
    layers = mat.neural_layers.layers if mat is not None else ()
    index = mat.neural_layers.active_index if mat is not None else -1
    allowed = bake_inputs.map_parameters(layers[index].layer_type) if 0 <= index < len(layers) else None
    _MAP_ITEMS[:] = [item for item in MAP_PARAMETERS if allowed is None or item[0] in allowed]
    return _MAP_ITEMS


class NLM_OT_map_add(MaterialOperator, bpy.types.Operator):
    """Drive a parameter of the active layer by an image"""

    poll_needs = "stack"
    bl_idname = "neural_layers.map_add"
    bl_label = "Add Parameter Map"
    bl_options = {"REGISTER", "UNDO"}

    parameter: EnumProperty(
        name="Parameter",
        items=_map_parameter_items,
        description="The parameter of the active layer the new map drives",
    )

    def execute(self, context):
        return guarded(self.bl_label, self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        s = mat.neural_layers
        if not (0 <= s.active_index < len(s.layers)):
            raise UserError(f"material {mat.name!r} has no active layer to add a map to")
        item = s.layers[s.active_index]
        allowed = bake_inputs.map_parameters(item.layer_type)
        if self.parameter not in allowed:  # a script's value: the menu offers only these
            raise UserError(
                f"layer {item.name!r} ({item.layer_type.title()}) has no {self.parameter.lower()} to map; its maps: "
                f"{', '.join(p.lower() for p in allowed)}"
            )
        pmap = item.maps.add()
        pmap.parameter = self.parameter
        # the parameter's trained range, as its slider's: Low 0, High 1 made every texel of a new IOR map an invalid IOR
        pmap.low, pmap.high = bake_inputs.map_range(self.parameter, item.layer_type)
        stack_io.tag_changed(mat)  # the texture baked from the maps is now out of date
        return {"FINISHED"}


class NLM_OT_map_remove(MaterialOperator, bpy.types.Operator):
    """Remove a parameter map of the active layer"""

    poll_needs = "stack"
    bl_idname = "neural_layers.map_remove"
    bl_label = "Remove Parameter Map"
    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(name="Index", default=0, min=0, description="Which of the layer's maps to remove (0 = first)")

    def execute(self, context):
        return guarded(self.bl_label, self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        s = mat.neural_layers
        if not (0 <= s.active_index < len(s.layers)):
            raise UserError(f"material {mat.name!r} has no active layer")
        item = s.layers[s.active_index]
        if not (0 <= self.index < len(item.maps)):
            raise UserError(f"layer {item.name!r} has {len(item.maps)} map(s); there is no map {self.index}")
        n = len(item.maps)
        item.maps.remove(self.index)
        moved = stack_io.follow_maps(mat, s.active_index, [None if j == self.index else j - (j > self.index)
                                                          for j in range(n)])  # fmt: skip
        if moved.removed:
            self.report({"INFO"}, f"removed {sum(moved.removed.values())} animation curve(s) of the map")
        stack_io.tag_changed(mat)  # the texture baked from the maps is now out of date
        return {"FINISHED"}


class NLM_OT_bake_texture(LongOperator, bpy.types.Operator):
    """Bake the material's stack and its parameter maps into a mip-mapped latent texture (EXR)"""

    poll_needs = "stack"
    bl_idname = "neural_layers.bake_texture"
    bl_label = "Bake Latent Texture"
    # undoable, with no Adjust Last Operation panel: its redo calls execute(), the whole job on Blender's thread
    # with no progress and no Esc (seconds to minutes)
    bl_options = {"UNDO"}

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
        try:
            check_bake_memory(*res)
        except ValueError as e:
            raise UserError(f"{e}: lower Bake Resolution or turn on Fit to Camera") from None
        size = bake_size(mat)
        path, kept = bake_target(mat)  # never over a file that holds another file's or material's bake
        check_bake_folder(os.path.dirname(path))  # before the work, not after it
        refine_s = float(f"{s.bake_refine:g}")  # the float32 property's 0.01 is 0.00999999977 in float64
        model = bake_model_key(size, refine_s)
        key = bake_key(spatial, res, model)  # decoder digest and budget, as bake_state checks
        inputs = inputs_digest(mat, res, model)  # what renders the bake while its maps' images cannot be read
        refine_cache = os.path.join(os.path.dirname(path), ".refine")  # as the bake CLI's OUT/.refine
        name, blend = mat.name, blend_file_name()  # whose bake it is, recorded in the texture's header
        render = context.scene.render
        threads = RenderSettings.threads_for(render.threads_mode, render.threads)  # Blender's Threads setting

        def work(progress):
            t0 = time.perf_counter()
            encode = neural_encoder(size, refine_s=refine_s, refine_cache=refine_cache)
            tex, stats = bake_stack(
                spatial,
                encode,
                resolution=res,
                progress=progress,
                metadata={"material": name, "blend": blend, "model": size, "key": key, "inputs": inputs},
                threads=threads,
            )
            if progress is not None:  # an Esc up to here cancels (raises): from here the file is written, and kept
                progress(1.0)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            files.remove_stale_temps(os.path.dirname(path))  # what a killed Blender's writes left there, as the CLI
            tex.write_exr(path)
            refined = (getattr(encode, "metadata", None) or {}).get("refined")
            return stats, time.perf_counter() - t0, refined, (tex.filter_levels, len(tex.levels))

        def finish(context, result):
            stats, seconds, refined, (filtered, levels) = result
            target = self.again(mat, name)  # an undo during the bake replaced the one read above
            attach_texture(target, path, key, res)
            refined = "" if refined is None else f", {refined} refined"
            calibrated = f", calibrated in {stats.clusters} cluster(s)" if stats.clusters else ""
            if kept is not None:
                self.report({"INFO"}, f"{name}: {kept}")
            for note in stats.clamped:  # the networks' trained ranges: what the texture holds is the clamped stack
                self.report({"WARNING"}, f"{name}: {note}; baked clamped")
            self.report(
                {"INFO"},
                f"{name}: baked {res[1]}x{res[0]} ({stats.unique} distinct of {stats.texels} texels"
                f"{refined}, {stats.texels_per_second:,.0f} texels/s{calibrated}, filtered across {filtered} of "
                f"{levels} mip levels) in {seconds:.1f} s -> {path}",
            )
            return {"FINISHED"}

        return work, finish


class NLM_OT_texture_clear(MaterialOperator, bpy.types.Operator):
    """Stop using the baked latent texture for this material (the file is kept)"""

    poll_needs = "texture"
    bl_idname = "neural_layers.texture_clear"
    bl_label = "Clear Latent Texture"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return guarded(self.bl_label, self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        mat.neural_layers.texture_path = ""
        mat.neural_layers.texture_file = ""
        mat.neural_layers.texture_key = ""
        return {"FINISHED"}


_CLASSES = (NLM_OT_map_add, NLM_OT_map_remove, NLM_OT_bake_texture, NLM_OT_texture_clear)

register, unregister = bpy.utils.register_classes_factory(_CLASSES)

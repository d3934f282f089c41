"""The Neural Layered render engine: F12 and ``blender -b file.blend -E NEURAL_LAYERED -f 1``.

``render()`` exports the evaluated depsgraph (``scene_export``), renders it with the core path
tracer one pass of one sample per pixel at a time, shows each pass (progressive), reports
progress and statistics, and stops when the user cancels (Esc). Blender writes the result in the
scene's output format (OpenEXR, PNG, ...).
"""

from __future__ import annotations

import bpy
import numpy as np

from . import render_operators, render_properties, render_ui, scene_export
from ..core.render import Cancelled, render

ENGINE_ID = "NEURAL_LAYERED"


def _compatible_panels():
    """Blender's own panels that make sense for this engine (output, dimensions, film...)."""
    keep = {"RENDER_PT_format", "RENDER_PT_frame_range", "RENDER_PT_output", "RENDER_PT_color_management",
            "RENDER_PT_dimensions", "RENDER_PT_format_presets", "RENDER_PT_encoding", "RENDER_PT_stamp",
            "DATA_PT_context_light", "DATA_PT_light", "DATA_PT_area", "DATA_PT_spot", "DATA_PT_camera",
            "DATA_PT_lens", "DATA_PT_camera_display", "WORLD_PT_context_world", "EEVEE_WORLD_PT_surface",
            "EEVEE_MATERIAL_PT_context_material", "EEVEE_MATERIAL_PT_surface", "MATERIAL_PT_preview"}
    return [p for p in bpy.types.Panel.__subclasses__()
            if getattr(p, "COMPAT_ENGINES", None) is not None and p.__name__ in keep]


class NeuralLayeredRenderEngine(bpy.types.RenderEngine):
    bl_idname = ENGINE_ID
    bl_label = "Neural Layered"
    bl_use_preview = False
    bl_use_shading_nodes_custom = False

    def render(self, depsgraph):
        scene = depsgraph.scene
        props = scene.neural_render
        width, height = scene_export.render_size(scene)
        result = self.begin_result(0, 0, width, height)
        try:
            self.update_stats("", "Exporting scene")
            try:
                core_scene, warnings = scene_export.export_scene(depsgraph, width, height)
            except ValueError as e:
                self.report({"ERROR"}, str(e))
                return
            self.update_stats("", "Choosing decoders")
            for w in warnings + props.assign_decoders(core_scene):
                self.report({"WARNING"}, w)
            settings = props.to_core()
            combined = result.layers[0].passes["Combined"]

            def progress(film, done, total):
                combined.rect.foreach_set(np.ascontiguousarray(film.rgba()[::-1]).ravel())
                self.update_result(result)
                self.update_progress(done / total)
                self.update_stats("", f"Sample {done}/{total} | {core_scene.mesh.triangle_count} triangles")
                return not self.test_break()

            try:
                film, stats = render(core_scene, settings, progress=progress)
                self.update_stats("", stats.summary())
            except Cancelled as c:
                film = c.film
            combined.rect.foreach_set(np.ascontiguousarray(film.rgba()[::-1]).ravel())
        finally:
            self.end_result(result)


_panels: list = []


def register() -> None:
    render_properties.register()
    bpy.utils.register_class(NeuralLayeredRenderEngine)
    for panel in _compatible_panels():
        panel.COMPAT_ENGINES.add(ENGINE_ID)
        _panels.append(panel)
    render_operators.register()
    render_ui.register()


def unregister() -> None:
    render_ui.unregister()
    render_operators.unregister()
    for panel in _panels:
        panel.COMPAT_ENGINES.discard(ENGINE_ID)
    _panels.clear()
    if getattr(NeuralLayeredRenderEngine, "is_registered", False):
        bpy.utils.unregister_class(NeuralLayeredRenderEngine)
    render_properties.unregister()

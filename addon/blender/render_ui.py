"""Render properties panel of the Neural Layered engine, and the Render Preview menu entry."""

from __future__ import annotations

import bpy


class NLM_PT_render(bpy.types.Panel):
    bl_label = "Neural Layered"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {"NEURAL_LAYERED"}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES

    def draw(self, context):
        props = context.scene.neural_render
        layout = self.layout
        layout.use_property_split = True
        col = layout.column()
        col.prop(props, "samples")
        col.prop(props, "preview_samples")
        col.prop(props, "max_bounces")
        col.prop(props, "seed")
        col.prop(props, "denoise")
        col.prop(props, "mode")
        if props.mode == "reference":
            col.prop(props, "reference_walks")
        else:
            col.prop(props, "decoder_quality")
            col.prop(props, "calibrate")
            if props.decoder_quality == "AUTO":
                col.prop(props, "tolerance")
                col.prop(props, "time_budget")
        layout.operator("neural_layers.render_preview", icon="RENDER_STILL")


def _menu(self, context):
    self.layout.operator("neural_layers.render_preview", icon="RENDER_STILL")


def register() -> None:
    bpy.utils.register_class(NLM_PT_render)
    bpy.types.TOPBAR_MT_render.append(_menu)


def unregister() -> None:
    bpy.types.TOPBAR_MT_render.remove(_menu)
    if getattr(NLM_PT_render, "is_registered", False):
        bpy.utils.unregister_class(NLM_PT_render)

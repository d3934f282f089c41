"""Render properties panel of the Neural Layered engine, its light panel, and the Render Preview menu entry."""

from __future__ import annotations

import bpy

from . import render_properties


class _EnginePanel:
    """A Properties editor panel of this engine's (``bl_context`` set by each)."""

    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    COMPAT_ENGINES = {"NEURAL_LAYERED"}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES


class NLM_PT_render(_EnginePanel, bpy.types.Panel):
    bl_label = "Neural Layered"
    bl_context = "render"

    def draw(self, context):
        props = context.scene.neural_render
        layout = self.layout
        layout.use_property_split = True
        col = layout.column()
        # each sample count says what it drives: F12, the viewport's Rendered mode, the Render Preview operator
        col.prop(props, "samples")
        col.prop(props, "viewport_samples")
        col.prop(props, "preview_samples")
        col.prop(props, "max_bounces")
        col.prop(props, "seed")
        col.prop(props, "denoise")
        kept = render_properties.denoise_off_note(context.scene)
        if kept is not None:
            col.label(text=kept, icon="INFO")
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


class NLM_PT_film(_EnginePanel, bpy.types.Panel):
    """Blender's Film > Transparent, which this engine renders (``RenderProperties.settings``). Blender's own Film
    panels are Cycles', EEVEE's and Workbench's, hidden for this engine."""

    bl_label = "Film"
    bl_context = "render"
    bl_parent_id = "NLM_PT_render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(context.scene.render, "film_transparent", text="Transparent")


class NLM_PT_performance(_EnginePanel, bpy.types.Panel):
    """Blender's Threads setting (Auto: every core, or Fixed), which decides this engine's and the bakes' thread
    count (``RenderSettings.threads_for``); Blender draws it only in Cycles' Performance panel."""

    bl_label = "Performance"
    bl_context = "render"
    bl_parent_id = "NLM_PT_render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        rd = context.scene.render
        col = layout.column(align=True)
        col.prop(rd, "threads_mode")
        sub = col.column(align=True)
        sub.enabled = rd.threads_mode == "FIXED"
        sub.prop(rd, "threads")


class NLM_PT_view_layer(_EnginePanel, bpy.types.Panel):
    """The view layer's settings this engine renders: its Z pass (written as Depth, ``update_render_passes``) and
    its Material Override. Blender's panels for them belong to Cycles, EEVEE and Workbench; their World Override
    and Samples are not read here, so this panel leaves them out."""

    bl_label = "Neural Layered"
    bl_context = "view_layer"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        view_layer = context.view_layer
        col = layout.column(heading="Passes")
        col.prop(view_layer, "use_pass_z")
        layout.prop(view_layer, "material_override")


class NLM_PT_light(_EnginePanel, bpy.types.Panel):
    """A light's settings as this engine renders them (``scene_export._light``): Blender's own light panel
    draws only the type for engines other than its own, and EEVEE's holds settings this engine leaves out."""

    bl_label = "Light"
    bl_context = "data"

    @classmethod
    def poll(cls, context):
        return super().poll(context) and getattr(context, "light", None) is not None

    def draw(self, context):
        light = context.light
        layout = self.layout
        layout.row().prop(light, "type", expand=True)
        layout.use_property_split = True
        col = layout.column()
        row = col.row(heading="Temperature")
        row.prop(light, "use_temperature", text="")
        sub = row.row()
        sub.active = light.use_temperature
        sub.prop(light, "temperature", text="")
        col.prop(light, "color", text="Tint" if light.use_temperature else "Color")
        col = layout.column()
        col.prop(light, "energy", text="Strength" if light.type == "SUN" else "Power")
        col.prop(light, "exposure")
        col.prop(light, "use_shadow", text="Cast Shadow")
        col = layout.column()
        if light.type == "SPOT":
            col.prop(light, "spot_size", text="Spot Size")
            col.prop(light, "spot_blend", text="Blend")
            col.prop(light, "show_cone")
        elif light.type == "AREA":
            col.prop(light, "normalize")
            col.prop(light, "shape")
            sub = col.column(align=True)
            if light.shape in {"SQUARE", "DISK"}:
                sub.prop(light, "size")
            else:
                sub.prop(light, "size", text="Size X")
                sub.prop(light, "size_y", text="Y")
            col.prop(light, "spread")
            ob = context.object
            if ob is not None and ob.data == light:
                col.prop(ob, "visible_camera", text="Visible to Camera")
        if light.type in {"POINT", "SPOT"}:
            col.prop(light, "shadow_soft_size", text="Radius")
            col.prop(light, "use_soft_falloff")
        elif light.type == "SUN":
            col.prop(light, "angle")
        if light.type != "AREA":
            col.prop(light, "normalize")
        if getattr(light, "cycles", None) is not None:
            col.prop(light.cycles, "max_bounces")


def _menu(self, context):
    self.layout.operator("neural_layers.render_preview", icon="RENDER_STILL")


_CLASSES = (NLM_PT_render, NLM_PT_film, NLM_PT_performance, NLM_PT_view_layer, NLM_PT_light)


def register() -> None:
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_render.append(_menu)


def unregister() -> None:
    bpy.types.TOPBAR_MT_render.remove(_menu)
    for cls in reversed(_CLASSES):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)

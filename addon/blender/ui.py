"""The "Layers" sidebar tab of the 3D Viewport and the Shader Editor."""

from __future__ import annotations

import os
import time
from collections import OrderedDict

import bpy

from ..core.stack import PRESETS
from . import bake_state, images, layer_types, stack_io
from .operator_base import UserError, context_material
from .operators import PRESET_SUBDIR, PRESETS_MENU_LABEL


class NLM_UL_layers(bpy.types.UIList):
    """The stack, drawn top layer first so the base sits at the bottom."""

    bl_idname = "NLM_UL_layers"

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        kind = layer_types.BY_ID.get(item.layer_type)
        row = layout.row(align=True)
        row.prop(item, "name", text="", emboss=False, icon=kind.icon if kind else "DOT")
        row.label(text=layer_types.label(item.layer_type))

    def filter_items(self, context, data, propname):
        items = getattr(data, propname)
        n = len(items)
        flags = [self.bitflag_filter_item] * n
        if self.filter_name:
            flags = bpy.types.UI_UL_list.filter_items_by_name(self.filter_name, self.bitflag_filter_item, items, "name")
        order = list(range(n - 1, -1, -1))  # display position of item i: top layer first
        return flags, order


class NLM_MT_presets(bpy.types.Menu):
    """The bundled layer stacks, then your own (saved with the + beside this menu)."""

    bl_idname = "NLM_MT_presets"
    bl_label = PRESETS_MENU_LABEL
    preset_subdir = PRESET_SUBDIR
    preset_operator = "neural_layers.preset_file_apply"  # Blender's execute_preset, as one undo step

    def draw(self, context):
        layout = self.layout
        for key in sorted(PRESETS):
            op = layout.operator("neural_layers.preset_apply", text=key.replace("_", " ").title())
            op.preset = key
        if bpy.utils.preset_paths(self.preset_subdir):
            layout.separator()
            bpy.types.Menu.draw_preset(self, context)
            last = removable_preset()
            if last is not None:
                remove = layout.operator("neural_layers.preset_add", text=f"Remove Preset {last!r}", icon="REMOVE")
                remove.remove_active = True


class NLM_MT_stack_specials(bpy.types.Menu):
    """More for the layer stack: copy it to another material (Blender's Copy Material leaves it behind)."""

    bl_idname = "NLM_MT_stack_specials"
    bl_label = "Layer Stack Specials"

    def draw(self, context):
        layout = self.layout
        layout.operator("neural_layers.stack_copy", icon="COPYDOWN")
        layout.operator("neural_layers.stack_paste", icon="PASTEDOWN")


def removable_preset() -> str | None:
    """The preset of yours applied last, which Remove Preset removes: Blender's presets keep its name as the menu's
    label. None when a bundled stack came after it, or it is gone: after a removal Blender sets the label to
    "Presets", which names no file (the menu offered a Remove Preset 'Presets' that did nothing)."""
    last = NLM_MT_presets.bl_label
    found = last != PRESETS_MENU_LABEL and bpy.utils.preset_find(last, PRESET_SUBDIR, display_name=True)
    return last if found else None


def _material(context):
    """The object and the material the panels edit: the Shader Editor's shown material (pinned too), else the
    active object's (``operator_base.context_material``, which the operators act on)."""
    return context.object, context_material(context)


def _draw_stack(layout, context):
    ob, mat = _material(context)
    if ob is None and mat is None:
        layout.label(text="Select an object", icon="INFO")
        return None
    if ob is not None and mat is ob.active_material:
        layout.template_ID(ob, "active_material", new="material.new")
    else:  # a material the Shader Editor pins: the panels edit it, not the active object's
        layout.label(text=f"Pinned: {mat.name}", icon="PINNED")
    if mat is None:
        layout.label(text="The object has no material", icon="INFO")
        return None
    s = mat.neural_layers
    row = layout.row()
    row.template_list("NLM_UL_layers", "", s, "layers", s, "active_index", rows=4)
    col = row.column(align=True)
    col.operator_menu_enum("neural_layers.layer_add", "layer_type", text="", icon="ADD")
    col.operator("neural_layers.layer_remove", text="", icon="REMOVE")
    col.separator()
    col.operator("neural_layers.layer_duplicate", text="", icon="DUPLICATE")
    col.menu("NLM_MT_stack_specials", text="", icon="DOWNARROW_HLT")
    col.separator()
    col.operator("neural_layers.layer_move", text="", icon="TRIA_UP").direction = "UP"
    col.operator("neural_layers.layer_move", text="", icon="TRIA_DOWN").direction = "DOWN"
    col.separator()
    col.menu("NLM_MT_presets", text="", icon="PRESET")
    col.operator("neural_layers.preset_add", text="", icon="FILE_NEW")
    try:
        stack_io.stack_from_material(mat)
    except ValueError as e:
        box = layout.box()
        box.alert = True
        for line in _wrap(str(e), 48):
            box.label(text=line)
    return mat


def _wrap(text, width):
    words, lines, line = text.split(), [], ""
    for w in words:
        if len(line) + len(w) + 1 > width and line:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}".strip()
    return lines + ([line] if line else [])


def _draw_layer(layout, item):
    layout.prop(item, "name")
    layout.prop(item, "layer_type")
    t = item.layer_type
    if t == "DIFFUSE":
        layout.prop(item, "albedo")
        _draw_maps(layout, item)  # an albedo map: a wood grain under its varnish
        return
    layout.prop(item, "roughness", slider=True)
    if t == "CONDUCTOR":
        layout.prop(item, "conductor_mode", expand=True)
        if item.conductor_mode == "F0":
            layout.prop(item, "f0")
        else:
            layout.prop(item, "eta")
            layout.prop(item, "k")
    elif t == "DIELECTRIC":
        layout.prop(item, "ior")
    else:
        layout.prop(item, "ior")
        layout.prop(item, "medium_albedo")
        layout.prop(item, "thickness")
        layout.prop(item, "g")
    _draw_maps(layout, item)


def _draw_maps(layout, item):
    """The layer's parameter maps: image, value range, remove; and the add menu."""
    col = layout.column(align=True)
    for i, pmap in enumerate(item.maps):
        box = col.box()
        row = box.row(align=True)
        row.prop(pmap, "parameter", text="")
        row.operator("neural_layers.map_remove", text="", icon="X").index = i
        box.template_ID(pmap, "image", open="image.open")
        row = box.row(align=True)
        row.prop(pmap, "low")
        row.prop(pmap, "high")
    col.operator_menu_enum("neural_layers.map_add", "parameter", text="Add Parameter Map", icon="IMAGE_DATA")


class _LayersPanel:
    bl_region_type = "UI"
    bl_category = "Layers"

    @classmethod
    def poll(cls, context):
        space = context.space_data
        return space.type == "VIEW_3D" or getattr(space, "tree_type", "") == "ShaderNodeTree"


class _StackPanel(_LayersPanel):
    bl_label = "Layer Stack"

    def draw(self, context):
        layout = self.layout
        mat = _draw_stack(layout, context)
        if mat is None:
            return
        s = mat.neural_layers
        if 0 <= s.active_index < len(s.layers):
            box = layout.box()
            _draw_layer(box, s.layers[s.active_index])
        elif len(s.layers) == 0:
            layout.label(text="Add a base layer or pick a preset", icon="INFO")


class _PreviewPanel(_LayersPanel):
    bl_label = "Latent and Previews"

    def draw(self, context):
        layout = self.layout
        _, mat = _material(context)
        if mat is None:
            layout.label(text="No material")
            return
        s = mat.neural_layers
        row = layout.row(align=True)
        current = stack_io.latent_is_current(mat)
        text = f"Latent: current ({s.latent_size})" if current else "Latent: stale"
        row.label(text=text, icon="CHECKMARK" if current else "ERROR")
        row.operator("neural_layers.evaluate_latent", text="Evaluate")
        row.operator("neural_layers.refine_latent", text="Refine").budget = s.refine_budget
        layout.prop(s, "model_size")
        layout.prop(s, "auto_latent")
        layout.prop(s, "refine_budget")
        col = layout.column()
        col.enabled = len(s.layers) > 0
        col.prop(s, "preview_method")
        col.prop(s, "theta_i")
        col.prop(s, "lobe_resolution")
        col.prop(s, "sphere_resolution")
        col.prop(s, "env_samples")
        col.prop(s, "walks")
        row = col.row(align=True)
        row.operator("neural_layers.preview_lobe", text="Lobe", icon="LIGHT_SPOT")
        row.operator("neural_layers.preview_sphere", text="Sphere", icon="SHADING_RENDERED")
        col.operator("neural_layers.compare_reference", icon="IMAGE_REFERENCE")
        _draw_preview_images(col, mat)


PREVIEW_IMAGES = (("Lobe", "Lobe {}"), ("Sphere", "Sphere {}"), ("Compare: neural | reference | error", "Compare {}"))


def _draw_preview_images(layout, mat) -> None:
    """The material's latest previews, in the panel (they are also in the Image Editor)."""
    for label, pattern in PREVIEW_IMAGES:
        image = bpy.data.images.get(pattern.format(mat.name))
        if image is None or image.preview is None:
            continue
        box = layout.box()
        box.label(text=label, icon="IMAGE_DATA")
        box.template_icon(icon_value=image.preview.icon_id, scale=8.0)


class _BakePanel(_LayersPanel):
    bl_label = "Latent Texture"

    def draw(self, context):
        layout = self.layout
        _, mat = _material(context)
        if mat is None:
            layout.label(text="No material")
            return
        s = mat.neural_layers
        col = layout.column()
        col.enabled = len(s.layers) > 0
        col.prop(s, "bake_resolution")
        col.prop(s, "bake_fit_camera")
        col.prop(s, "bake_refine")
        col.prop(s, "bake_directory")
        col.operator("neural_layers.bake_texture", icon="RENDER_STILL")
        if s.texture_path:
            # the bake's state, not only its file's name: one out of date, missing or another's renders no texture
            path, state = texture_state(mat)
            first, *rest = _wrap(state, 40) or [""]
            row = col.row(align=True)
            row.label(text=first, icon="TEXTURE" if path is not None else "ERROR")
            row.operator("neural_layers.texture_clear", text="", icon="X")
            for line in rest:
                col.label(text=line)


# The Latent Texture panel's state lines (``bake_state.baked_texture_state``), by material, with what they were read
# from (``_state_inputs``): the panel draws at every hover and change, and the state of a material whose maps are
# painted images hashes their pixels (0.1 s for a 2048-pixel map, measured).
_STATES: OrderedDict = OrderedDict()
STATES_KEPT = 32
# How long the state of a material with a map whose pixels are Blender's (painted, generated, packed) is kept: no cheap
# key follows a stroke of paint, so it is read again this often while the panel is drawn
PAINTED_STATE_S = 2.0


def _file_identity(path: str):
    """The modification time and size of the file at ``path``; None where there is none."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_mtime_ns, st.st_size


def _state_inputs(mat) -> tuple:
    """What ``bake_state.baked_texture_state`` of ``mat`` reads, cheaply: the material's stack (as text), its bake
    settings, the texture's file (its path and modification time), and each map's settings and image (its file's
    path and modification time where its pixels are its file's, ``images.pixels_file``; where they are Blender's,
    the time, by steps of :data:`PAINTED_STATE_S`)."""
    s = mat.neural_layers
    try:
        stack = stack_io.stack_text(mat)
    except ValueError as e:
        stack = str(e)
    library = getattr(mat, "original", mat).library
    texture = bpy.path.abspath(s.texture_path, library=library)
    parts = [
        stack,
        bpy.data.filepath,
        images.working_space(),
        s.texture_path,
        s.texture_file,
        s.texture_key,
        tuple(s.texture_size),
        s.bake_refine,
        s.model_size,
        _file_identity(texture),
        _file_identity(s.texture_file) if s.texture_file else None,
    ]
    for item in s.layers:
        for pmap in item.maps:
            image = pmap.image
            if image is None:
                continue
            settings = (item.layer_type, item.conductor_mode, pmap.parameter, pmap.low, pmap.high)
            space = (image.name_full, image.colorspace_settings.name, image.alpha_mode)
            source = images.pixels_file(image)
            if source is not None:
                parts.append((*settings, *space, source, _file_identity(source)))
            else:
                painted = int(time.monotonic() // PAINTED_STATE_S)
                parts.append((*settings, *space, image.filepath, tuple(image.size), painted))
    return tuple(parts)


def texture_state(mat) -> tuple[str | None, str]:
    """``bake_state.baked_texture_state`` of ``mat`` (the path of its current baked texture or None, and a line about
    its state), read again only when what it reads changed (``_state_inputs``)."""
    inputs = _state_inputs(mat)
    key = mat.as_pointer()
    held = _STATES.get(key)
    if held is not None and held[0] == inputs:
        _STATES.move_to_end(key)
        return held[1]
    try:
        state = bake_state.baked_texture_state(mat)
    except (ValueError, UserError) as e:  # a stack that is no stack: the Layer Stack panel says why
        state = None, str(e)
    _STATES[key] = inputs, state
    while len(_STATES) > STATES_KEPT:
        _STATES.popitem(last=False)
    return state


class NLM_PT_view3d_stack(_StackPanel, bpy.types.Panel):
    bl_idname = "NLM_PT_view3d_stack"
    bl_space_type = "VIEW_3D"


class NLM_PT_view3d_preview(_PreviewPanel, bpy.types.Panel):
    bl_idname = "NLM_PT_view3d_preview"
    bl_space_type = "VIEW_3D"
    bl_options = {"DEFAULT_CLOSED"}


class NLM_PT_shader_stack(_StackPanel, bpy.types.Panel):
    bl_idname = "NLM_PT_shader_stack"
    bl_space_type = "NODE_EDITOR"


class NLM_PT_shader_preview(_PreviewPanel, bpy.types.Panel):
    bl_idname = "NLM_PT_shader_preview"
    bl_space_type = "NODE_EDITOR"
    bl_options = {"DEFAULT_CLOSED"}


class NLM_PT_view3d_bake(_BakePanel, bpy.types.Panel):
    bl_idname = "NLM_PT_view3d_bake"
    bl_space_type = "VIEW_3D"
    bl_options = {"DEFAULT_CLOSED"}


class NLM_PT_shader_bake(_BakePanel, bpy.types.Panel):
    bl_idname = "NLM_PT_shader_bake"
    bl_space_type = "NODE_EDITOR"
    bl_options = {"DEFAULT_CLOSED"}


_CLASSES = (
    NLM_UL_layers,
    NLM_MT_presets,
    NLM_MT_stack_specials,
    NLM_PT_view3d_stack,
    NLM_PT_view3d_preview,
    NLM_PT_shader_stack,
    NLM_PT_shader_preview,
    NLM_PT_view3d_bake,
    NLM_PT_shader_bake,
)

register, unregister = bpy.utils.register_classes_factory(_CLASSES)

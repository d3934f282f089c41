"""Operators of the Layers sidebar. Each gathers its inputs from Blender and calls one core function.

Every operator acts on the active object's active material, or on ``material`` (a material name)
when given, so scripts need no selection. Problems are reported with ``self.report`` and the
operator returns ``{'CANCELLED'}``; nothing escapes as a traceback. (When an operator is called
from Python, Blender turns an ERROR report into a ``RuntimeError`` carrying the message.)

Previews and the comparison are long: invoked from the UI they run on a worker thread with
progress in the status bar and can be cancelled with Esc; executed (scripts, background mode)
they run blocking.
"""

from __future__ import annotations

import math
import time

import bpy
from bl_operators.presets import AddPresetBase
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..core import preview
from ..core.stack import PRESETS, Stack
from . import bake_state, layer_types, stack_io
from .layer_types import BASE_LAYER_TYPES
from .operator_base import LongOperator, MaterialOperator, UserError, fail, guarded

# --------------------------------------------------------------------------------------------
# Editing the stack


class NLM_OT_layer_add(MaterialOperator, bpy.types.Operator):
    """Add a layer: a base (when the stack has none) or a coating above the active layer"""

    bl_idname = "neural_layers.layer_add"
    bl_label = "Add Layer"
    bl_options = {"REGISTER", "UNDO"}

    layer_type: EnumProperty(
        name="Type", items=layer_types.enum_items(), default="COATING", description="The type of the new layer"
    )

    def execute(self, context):
        return guarded("adding a layer", self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        with stack_io.bulk_edit(mat) as s:
            layers = s.layers
            has_base = len(layers) > 0 and layers[0].layer_type in BASE_LAYER_TYPES
            if self.layer_type in BASE_LAYER_TYPES:
                if has_base:
                    raise UserError(
                        f"material {mat.name!r} already has a base layer {layers[0].name!r}: "
                        "change its type or remove it first (a stack has one base)"
                    )
                position = 0
            else:
                if not has_base:
                    raise UserError("add a base layer first (Diffuse, Conductor or Dielectric); coatings go above it")
                position = min(max(s.active_index, 0) + 1, len(layers))
            item = layers.add()
            stack_io.write_layer(item, layer_types.BY_ID[self.layer_type].default())
            if self.layer_type == "CONDUCTOR":
                item.conductor_mode = "F0"
            item.name = stack_io.default_layer_name(self.layer_type, {x.name for x in layers})
            layers.move(len(layers) - 1, position)
            s.active_index = position
        return {"FINISHED"}


def _active_item(op, context):
    mat = op.target(context)
    s = mat.neural_layers
    if len(s.layers) == 0:
        raise UserError(f"material {mat.name!r} has no layers")
    if not (0 <= s.active_index < len(s.layers)):
        raise UserError(f"no active layer (index {s.active_index} of {len(s.layers)} layers): click a layer first")
    return mat, s, s.active_index


class NLM_OT_layer_remove(MaterialOperator, bpy.types.Operator):
    """Remove the active layer"""

    poll_needs = "stack"
    bl_idname = "neural_layers.layer_remove"
    bl_label = "Remove Layer"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return guarded("removing a layer", self, lambda: self._run(context))

    def _run(self, context):
        mat, s, i = _active_item(self, context)
        with stack_io.bulk_edit(mat):
            s.layers.remove(i)
            s.active_index = min(i, len(s.layers) - 1) if len(s.layers) else 0
        return {"FINISHED"}


class NLM_OT_layer_move(MaterialOperator, bpy.types.Operator):
    """Move the active coating up (toward the top) or down (toward the base)"""

    poll_needs = "stack"
    bl_idname = "neural_layers.layer_move"
    bl_label = "Move Layer"
    bl_options = {"REGISTER", "UNDO"}

    direction: EnumProperty(
        name="Direction",
        items=[("UP", "Up", "Toward the top of the stack"), ("DOWN", "Down", "Toward the base")],
        default="UP",
        description="Which way the active coating moves",
    )

    def execute(self, context):
        return guarded("moving a layer", self, lambda: self._run(context))

    def _run(self, context):
        mat, s, i = _active_item(self, context)
        j = i + 1 if self.direction == "UP" else i - 1
        if not (0 <= j < len(s.layers)):
            where = "top" if self.direction == "UP" else "bottom"
            raise UserError(f"layer {s.layers[i].name!r} is already at the {where} of the stack")
        lower = s.layers[min(i, j)]
        if min(i, j) == 0 and lower.layer_type in BASE_LAYER_TYPES:
            raise UserError(f"the base layer {lower.name!r} stays at the bottom; only coatings move")
        with stack_io.bulk_edit(mat):
            s.layers.move(i, j)
            s.active_index = j
        return {"FINISHED"}


def _copy_properties(src, dst) -> None:
    """Copy every property of a PropertyGroup, collections (parameter maps) item by item."""
    for key, prop in src.bl_rna.properties.items():
        if key in {"rna_type", "name"}:
            continue
        if prop.type == "COLLECTION":
            target = getattr(dst, key)
            target.clear()
            for element in getattr(src, key):
                _copy_properties(element, target.add())
        else:
            setattr(dst, key, getattr(src, key))


class NLM_OT_layer_duplicate(MaterialOperator, bpy.types.Operator):
    """Duplicate the active coating (placed above it)"""

    poll_needs = "stack"
    bl_idname = "neural_layers.layer_duplicate"
    bl_label = "Duplicate Layer"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return guarded("duplicating a layer", self, lambda: self._run(context))

    def _run(self, context):
        mat, s, i = _active_item(self, context)
        src = s.layers[i]
        if src.layer_type in BASE_LAYER_TYPES:
            raise UserError(f"{src.name!r} is the base and a stack has one base: duplicate a coating instead")
        if src.layer_type not in layer_types.BY_ID:  # a newer version's type: its properties cannot be copied
            raise UserError(f"{src.name!r} has a layer type this version does not know: it cannot be duplicated")
        with stack_io.bulk_edit(mat):
            item = s.layers.add()
            src = s.layers[i]  # found again: adding an item can move the collection's items in memory
            try:
                _copy_properties(src, item)
            except Exception:
                s.layers.remove(len(s.layers) - 1)  # no half-made layer left behind
                raise
            item.name = stack_io.default_layer_name(src.layer_type, {x.name for x in s.layers})
            s.layers.move(len(s.layers) - 1, i + 1)
            s.active_index = i + 1
        return {"FINISHED"}


class NLM_OT_layer_rename(MaterialOperator, bpy.types.Operator):
    """Rename the active layer"""

    poll_needs = "stack"
    bl_idname = "neural_layers.layer_rename"
    bl_label = "Rename Layer"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty(name="Name", default="", options={"SKIP_SAVE"})

    def invoke(self, context, event):
        try:
            _, s, i = _active_item(self, context)
            self.name = s.layers[i].name
        except UserError as e:
            return fail(self, str(e))
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        return guarded("renaming a layer", self, lambda: self._run(context))

    def _run(self, context):
        _, s, i = _active_item(self, context)
        if not self.name.strip():
            raise UserError("a layer name cannot be empty")
        s.layers[i].name = self.name.strip()
        return {"FINISHED"}


class NLM_OT_preset_apply(MaterialOperator, bpy.types.Operator):
    """Replace the stack with one of the bundled presets"""

    bl_idname = "neural_layers.preset_apply"
    bl_label = "Apply Preset"
    bl_options = {"REGISTER", "UNDO"}

    preset: EnumProperty(
        name="Preset",
        items=[(k, k.replace("_", " ").title(), f"Layer stack preset {k!r}") for k in sorted(PRESETS)],
        description="The bundled layer stack that replaces the material's",
    )

    def execute(self, context):
        return guarded("applying a preset", self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        stack_io.stack_to_material(PRESETS[self.preset], mat)
        # A bundled preset is now the last applied: none of the user's is, so "Remove Preset" has none to remove
        # (it would have removed the user's preset applied before this one).
        bpy.types.NLM_MT_presets.bl_label = PRESETS_MENU_LABEL
        return {"FINISHED"}


class NLM_OT_preset_file_apply(bpy.types.Operator):
    """Apply a layer preset of your own (the presets menu's entries)"""

    bl_idname = "neural_layers.preset_file_apply"
    bl_label = "Apply Layer Preset"
    # Blender's own script.execute_preset pushes no undo step, and the operator its file runs is nested in it, whose
    # push Blender skips: Ctrl+Z after a preset undid the edit before it too. This one runs it and is the step.
    bl_options = {"REGISTER", "UNDO", "INTERNAL"}

    filepath: StringProperty(
        name="File Path", description="The preset file to run", subtype="FILE_PATH", options={"SKIP_SAVE"}
    )
    menu_idname: StringProperty(
        name="Menu", description="The presets menu whose label names the preset applied", options={"SKIP_SAVE"}
    )

    def execute(self, context):
        try:
            return bpy.ops.script.execute_preset(filepath=self.filepath, menu_idname=self.menu_idname)
        except RuntimeError as e:  # the preset's own operator reported an error: say it as this one's
            return fail(self, str(e).removeprefix("Error: ").strip())


class NLM_OT_stack_apply(MaterialOperator, bpy.types.Operator):
    """Replace the stack with one given as JSON (what a saved layer preset runs)"""

    bl_idname = "neural_layers.stack_apply"
    bl_label = "Apply Layer Stack"
    bl_options = {"REGISTER", "UNDO"}

    stack: StringProperty(
        name="Stack",
        default="",
        options={"SKIP_SAVE"},
        description="The layer stack as JSON (addon.core.stack.Stack.to_json)",
    )

    def execute(self, context):
        return guarded("applying a layer stack", self, lambda: self._run(context))

    def _run(self, context):
        try:
            stack = Stack.from_json(self.stack)
        except (ValueError, TypeError, KeyError) as e:
            raise UserError(f"not a layer stack ({type(e).__name__}: {e}); a preset holds Stack.to_json()") from None
        stack_io.stack_to_material(stack, self.target(context))
        return {"FINISHED"}


PRESET_SUBDIR = "neural_layered_materials/layer_stacks"
# The presets menu's label while no preset of the user's is the last applied: Blender's preset menus hold the name
# of the last one applied in their label, and that is the preset "Remove Preset" removes.
PRESETS_MENU_LABEL = "Layer Presets"


def preset_file_text(stack: Stack) -> str:
    """A layer preset file: Python that Blender's preset menu runs, applying ``stack`` to the
    active material. Plain JSON inside, so presets can be read, shared and edited by hand."""
    return (
        "import bpy\n\n"
        "# A Neural Layered Materials layer stack (bottom to top); applied to the active material.\n"
        f"bpy.ops.neural_layers.stack_apply(stack={stack.to_json()!r})\n"
    )


class NLM_OT_preset_add(AddPresetBase, MaterialOperator, bpy.types.Operator):
    """Save the material's layer stack as a preset of your own (in your Blender scripts folder,
    presets/neural_layered_materials/layer_stacks), or remove the active one of yours"""

    poll_needs = "material"
    edits = False  # reads the stack, writes a preset file
    bl_idname = "neural_layers.preset_add"
    bl_label = "Add Layer Preset"
    bl_options = {"REGISTER", "INTERNAL"}
    preset_menu = "NLM_MT_presets"
    preset_subdir = PRESET_SUBDIR
    # AddPresetBase's own switches, with tooltips
    remove_name: BoolProperty(
        default=False,
        options={"HIDDEN", "SKIP_SAVE"},
        description="Remove the preset called Name instead of adding one",
    )
    remove_active: BoolProperty(
        default=False,
        options={"HIDDEN", "SKIP_SAVE"},
        description="Remove the preset applied last instead of adding one",
    )

    def add(self, context, filepath):  # AddPresetBase's hook: write our own file
        mat, stack = self.target_stack(context)
        with open(filepath, "w", encoding="utf-8") as f:
            f.write(preset_file_text(stack))

    def execute(self, context):
        return guarded(self.bl_label, self, lambda: AddPresetBase.execute(self, context))


# --------------------------------------------------------------------------------------------
# Latent


class NLM_OT_evaluate_latent(MaterialOperator, bpy.types.Operator):
    """Encode the stack into its latent code with the neural encoder and store it on the material"""

    poll_needs = "stack"
    bl_idname = "neural_layers.evaluate_latent"
    bl_label = "Evaluate Latent"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return guarded("evaluating the latent", self, lambda: self._run(context))

    def _run(self, context):
        mat, _ = self.target_stack(context)
        notes = stack_io.compute_latent(mat)
        self.report_notes(notes)
        self.report({"INFO"}, f"latent of {mat.name!r} updated ({mat.neural_layers.latent_size} decoder)")
        return {"FINISHED"}


# --------------------------------------------------------------------------------------------
# Long operations: previews and comparison


class NLM_OT_preview_lobe(LongOperator, bpy.types.Operator):
    """Show the BRDF lobe (f cos over the projected outgoing hemisphere) for the incident angle in the Image Editor"""

    poll_needs = "stack"
    edits = False  # reads the stack, shows an image
    bl_idname = "neural_layers.preview_lobe"
    bl_label = "Preview Lobe"
    bl_options = {"REGISTER"}

    def prepare(self, context):
        mat, stack = self.target_stack(context)
        stack, latent, texel_notes = bake_state.preview_target(mat, stack)
        s = mat.neural_layers
        theta, res, method, walks = math.degrees(s.theta_i), s.lobe_resolution, s.preview_method, s.walks
        size = stack_io.model_size(mat)
        calibrated = context.scene.neural_render.calibrate  # as F12 renders it

        def work(progress):
            t0 = time.perf_counter()
            choice = preview.choose_brdf(stack, method, latent=latent, size=size, walks=walks, calibrated=calibrated)
            img = preview.lobe_preview(choice.brdf, theta, res, progress, choice.chunk)
            return img, choice, time.perf_counter() - t0

        def finish(context, result):
            img, choice, seconds = result
            img, bad = preview.sanitize(img)
            notes = texel_notes + choice.notes + ([f"{bad} negative or non-finite values set to 0"] if bad else [])
            meta = {"method": choice.method, "theta_i_deg": theta, "seconds": seconds}
            summary = f"{choice.method.lower()} lobe at {theta:.0f} deg, {res}x{res}, {seconds:.2f} s"
            return self.show(context, f"Lobe {mat.name}", img, meta, notes, summary)

        return work, finish


class NLM_OT_preview_sphere(LongOperator, bpy.types.Operator):
    """Show a sphere shaded with the stack under a default sky and sun in the Image Editor"""

    poll_needs = "stack"
    edits = False  # reads the stack, shows an image
    bl_idname = "neural_layers.preview_sphere"
    bl_label = "Preview Sphere"
    bl_options = {"REGISTER"}

    def prepare(self, context):
        mat, stack = self.target_stack(context)
        stack, latent, texel_notes = bake_state.preview_target(mat, stack)
        s = mat.neural_layers
        res, method, walks, k = s.sphere_resolution, s.preview_method, s.walks, s.env_samples
        size = stack_io.model_size(mat)
        calibrated = context.scene.neural_render.calibrate  # as F12 renders it

        def work(progress):
            t0 = time.perf_counter()
            choice = preview.choose_brdf(stack, method, latent=latent, size=size, walks=walks, calibrated=calibrated)
            # an importance sampler (the reference's walks) gets the walk budget per pixel
            samples = k * walks if choice.sampler is not None else k
            img = preview.choice_sphere(choice, res, env_samples=samples, progress=progress)
            return img, choice, time.perf_counter() - t0

        def finish(context, result):
            img, choice, seconds = result
            img, bad = preview.sanitize(img)
            notes = texel_notes + choice.notes + ([f"{bad} negative or non-finite values set to 0"] if bad else [])
            meta = {"method": choice.method, "seconds": seconds}
            summary = f"{choice.method.lower()} sphere, {res}x{res}, {seconds:.2f} s"
            return self.show(context, f"Sphere {mat.name}", img, meta, notes, summary)

        return work, finish


class NLM_OT_compare_reference(LongOperator, bpy.types.Operator):
    """Neural and Monte Carlo reference lobes side by side with their error image and timings"""

    poll_needs = "stack"
    edits = False  # reads the stack, shows an image
    bl_idname = "neural_layers.compare_reference"
    bl_label = "Compare with Reference"
    bl_options = {"REGISTER"}

    def prepare(self, context):
        mat, stack = self.target_stack(context)
        stack, latent, texel_notes = bake_state.preview_target(mat, stack)
        s = mat.neural_layers
        theta, res, walks = math.degrees(s.theta_i), s.lobe_resolution, s.walks
        size = stack_io.model_size(mat)
        calibrated = context.scene.neural_render.calibrate  # as F12 renders it

        def work(progress):
            return preview.compare_with_reference(
                stack, theta, res, walks=walks, latent=latent, size=size, progress=progress, calibrated=calibrated
            )

        def finish(context, cmp):
            meta = {
                "seconds_neural": cmp.seconds_neural,
                "seconds_reference": cmp.seconds_reference,
                "relative_rmse": cmp.relative_rmse,
                "theta_i_deg": theta,
            }
            summary = "neural | reference | error: " + cmp.summary()
            return self.show(context, f"Compare {mat.name}", cmp.side_by_side(), meta, texel_notes + cmp.notes, summary)

        return work, finish


_CLASSES = (
    NLM_OT_layer_add,
    NLM_OT_layer_remove,
    NLM_OT_layer_move,
    NLM_OT_layer_duplicate,
    NLM_OT_layer_rename,
    NLM_OT_preset_apply,
    NLM_OT_preset_file_apply,
    NLM_OT_stack_apply,
    NLM_OT_preset_add,
    NLM_OT_evaluate_latent,
    NLM_OT_preview_lobe,
    NLM_OT_preview_sphere,
    NLM_OT_compare_reference,
)

register, unregister = bpy.utils.register_classes_factory(_CLASSES)

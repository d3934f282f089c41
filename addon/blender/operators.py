"""Operators of the Layers sidebar. Each gathers its inputs from Blender and calls one core function.

Every operator acts on the active object's active material, or on ``material`` (a material name)
when given, so scripts need no selection. Problems are reported with ``self.report`` and the
operator returns ``{'CANCELLED'}``; nothing escapes as a traceback. (When an operator is called
from Python, Blender turns an ERROR report into a ``RuntimeError`` carrying the message.)

Blender keys a layer's keyframes and drivers by its position in the stack; every operator that inserts, removes,
moves or replaces layers moves them with their layers (``stack_io.follow_layers``) and says what it removed.

Previews and the comparison are long: invoked from the UI they run on a worker thread with
progress in the status bar and can be cancelled with Esc; executed (scripts, background mode)
they run blocking.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import bpy
from bl_operators.presets import AddPresetBase
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..core import preview
from ..core.stack import PRESETS
from . import bake_state, layer_types, stack_io
from .layer_types import BASE_LAYER_TYPES
from .operator_base import LongOperator, MaterialOperator, UserError, fail, guarded

# --------------------------------------------------------------------------------------------
# Editing the stack


def _count(n: int, thing: str) -> str:
    return f"{n} {thing}" if n == 1 else f"{n} {thing}s"


def _report_removed_animation(op, done: stack_io.LayerAnimation, name: str) -> None:
    """Say how many keyframe curves and drivers went with the removed layer ``name`` (undo brings them back)."""
    removed = sum(done.removed.values())
    if removed:
        op.report({"INFO"}, f"removed {_count(removed, 'animation curve')} (keyframes, drivers) of layer {name!r}")


def follow_layers(op, mat, new_index_of, copies=None) -> stack_io.LayerAnimation:
    """``stack_io.follow_layers``, saying when ``mat`` got its own copy of an action it shared with another data-block
    (so that the edit leaves the other's keyframes as they were)."""
    done = stack_io.follow_layers(mat, new_index_of, copies)
    for action, copy in done.separated:
        op.report(
            {"INFO"},
            f"material {mat.name!r} shared the action {action!r} with another data-block: it now has its own copy, "
            f"{copy!r}, which follows its layers (the other keeps its keyframes)",
        )
    return done


def replace_stack(op, mat, stack, sidebar=None) -> None:
    """Replace ``mat``'s layers with ``stack`` (a preset, an applied or pasted stack): keyframes and drivers of the old
    layers stay on the positions the new stack has, where they now animate other layers, and the others are removed;
    a warning says so, since nothing ties the old layers to the new ones."""
    old_count = len(mat.neural_layers.layers)
    stack_io.stack_to_material(stack, mat, sidebar)
    new_count = len(stack.layers)
    done = follow_layers(op, mat, [i if i < new_count else None for i in range(old_count)])
    if done.total:
        removed = sum(done.removed.values())
        what = []
        if done.moved:
            what.append(f"{done.moved} kept, now animating the new layers at the same positions")
        if removed:
            what.append(f"{removed} removed with the positions the new stack does not have")
        op.report(
            {"WARNING"},
            f"material {mat.name!r}: its old layers were animated ({_count(done.total, 'curve')} of keyframes or "
            f"drivers): {'; '.join(what)}; check them in the Graph Editor and the Drivers editor (Ctrl+Z undoes)",
        )


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
        old_count = len(s.layers) - 1
        follow_layers(self, mat, [i if i < position else i + 1 for i in range(old_count)])
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
    """Remove the active layer, with its keyframes and drivers"""

    poll_needs = "stack"
    bl_idname = "neural_layers.layer_remove"
    bl_label = "Remove Layer"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return guarded("removing a layer", self, lambda: self._run(context))

    def _run(self, context):
        mat, s, i = _active_item(self, context)
        name, old_count = s.layers[i].name, len(s.layers)
        base_under_coatings = i == 0 and s.layers[0].layer_type in BASE_LAYER_TYPES and old_count > 1
        with stack_io.bulk_edit(mat):
            s.layers.remove(i)
            s.active_index = min(i, len(s.layers) - 1) if len(s.layers) else 0
        done = follow_layers(self, mat, [j if j < i else None if j == i else j - 1 for j in range(old_count)])
        _report_removed_animation(self, done, name)
        if base_under_coatings:  # allowed, as Blender allows an edit that leaves a half-made state, but said
            self.report(
                {"WARNING"},
                f"material {mat.name!r} has no base layer now: its coatings sit on nothing, so it renders as a plain "
                "Lambertian of its base colour (its Principled BSDF's Base Color, else its Viewport Display colour) "
                "and the previews refuse it until you add a base (Add Layer > Diffuse, Conductor or Dielectric)",
            )
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
        swapped = list(range(len(s.layers)))
        swapped[i], swapped[j] = j, i
        follow_layers(self, mat, swapped)
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
    """Duplicate the active coating (placed above it), with its keyframes and drivers"""

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
        # the copy animates as its source does: a duplicate is the same layer twice, through time too
        old_count = len(s.layers) - 1
        done = follow_layers(self, mat, [j if j <= i else j + 1 for j in range(old_count)], copies={i: i + 1})
        if done.copied:
            self.report(
                {"INFO"},
                f"{s.layers[i + 1].name!r} animates as {s.layers[i].name!r} does: "
                f"{_count(done.copied, 'animation curve')} (keyframes, drivers) copied",
            )
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
        replace_stack(self, mat, PRESETS[self.preset])
        # A bundled preset is now the last applied: none of the user's is, so "Remove Preset" has none to remove
        # (it would have removed the user's preset applied before this one).
        bpy.types.NLM_MT_presets.bl_label = PRESETS_MENU_LABEL
        return {"FINISHED"}


class NLM_OT_preset_file_apply(bpy.types.Operator):
    """Apply a layer preset of your own (the presets menu's entries)"""

    bl_idname = "neural_layers.preset_file_apply"
    bl_label = "Apply Layer Preset"
    # Blender's own script.execute_preset pushes no undo step, and the operator its file runs is nested in it, whose
    # push Blender skips: Ctrl+Z after a preset undid the edit before it too. This one runs the file itself (as
    # execute_preset does, so that a broken file's report says what is wrong in words) and is the step.
    bl_options = {"REGISTER", "UNDO", "INTERNAL"}

    filepath: StringProperty(
        name="File Path", description="The preset file to run", subtype="FILE_PATH", options={"SKIP_SAVE"}
    )
    menu_idname: StringProperty(
        name="Menu", description="The presets menu whose label names the preset applied", options={"SKIP_SAVE"}
    )

    def execute(self, context):
        path = Path(self.filepath)
        # As execute_preset: the menu's label names the preset applied last, the one its Remove Preset removes (a
        # broken one too, so that it can be removed).
        menu = getattr(bpy.types, self.menu_idname, None)
        if menu is not None:
            menu.bl_label = bpy.path.display_name(path.name, title_case=False)
        problem = run_preset_file(path)
        if problem is not None:
            return fail(self, f"Preset file {path.name!r} was not applied: {problem}")
        return {"FINISHED"}


def run_preset_file(path: Path) -> str | None:
    """Run a layer preset file (Python, ``preset_file_text``); None when it ran, else what went wrong, in words."""
    if path.suffix.lower() != ".py":
        return "a layer preset is a .py file"
    try:
        source = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return f"there is no such file in {str(path.parent)!r} (moved or removed since the menu was drawn)"
    except (OSError, UnicodeDecodeError) as e:
        return f"it cannot be read ({getattr(e, 'strerror', None) or e})"
    if not source.strip():
        return "the file is empty; save the stack as a preset again (Add Layer Preset, beside the presets menu)"
    try:
        code = compile(source, str(path), "exec")
    except SyntaxError as e:
        return (
            f"line {e.lineno} of the file is not valid Python ({e.msg}); save the stack as a preset again, or mend "
            "the file"
        )
    try:
        exec(code, {"__name__": "__main__", "__file__": str(path)})
    except RuntimeError as e:
        if not str(e).lstrip().startswith("Error:"):  # not an operator's report: the file's own code failed
            return f"running it stopped with an error: {e}"
        # an operator the file runs reported an error: its message ("Error: ...", a line each)
        lines = [line.strip().removeprefix("Error:").strip() for line in str(e).splitlines()]
        return "; ".join(line for line in lines if line)
    except Exception as e:  # its own code failed: the message, without the exception's Python spelling
        return f"running it stopped with an error: {e}" if str(e) else "running it stopped with an error"
    return None


class NLM_OT_stack_apply(MaterialOperator, bpy.types.Operator):
    """Replace the stack with one given as JSON (what a saved layer preset runs)"""

    bl_idname = "neural_layers.stack_apply"
    bl_label = "Apply Layer Stack"
    bl_options = {"REGISTER", "UNDO"}

    stack: StringProperty(
        name="Stack",
        default="",
        options={"SKIP_SAVE"},
        description="The layer stack as JSON with its layers' names (what Add Layer Preset and Copy Layer Stack write)",
    )

    def execute(self, context):
        return guarded("applying a layer stack", self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        try:
            stack, sidebar = stack_io.stack_from_text(self.stack)
        except ValueError as e:
            raise UserError(f"not a layer stack: {e}") from None
        replace_stack(self, mat, stack, sidebar)
        return {"FINISHED"}


# Blender without a window (background mode: scripts, the tests) has no system clipboard, where
# WindowManager.clipboard reads "": the last stack copied in this session is kept too, and pasted when the clipboard
# holds no text.
_copied_stack = ""


class NLM_OT_stack_copy(MaterialOperator, bpy.types.Operator):
    """Copy the material's layer stack (its layers, their names and values, as a layer preset holds them) to the
    clipboard, for Paste Layer Stack on another material: Blender's Copy Material leaves it behind"""

    poll_needs = "stack"
    edits = False  # reads the stack, writes the clipboard
    bl_idname = "neural_layers.stack_copy"
    bl_label = "Copy Layer Stack"
    bl_options = {"REGISTER"}

    def execute(self, context):
        return guarded("copying the layer stack", self, lambda: self._run(context))

    def _run(self, context):
        global _copied_stack
        mat = self.target(context)
        text = stack_io.stack_text(mat)
        _copied_stack = text
        context.window_manager.clipboard = text
        maps = sum(len(item.maps) for item in mat.neural_layers.layers)
        left_out = f"; its {_count(maps, 'parameter map')} (images) stay behind" if maps else ""
        layers = _count(len(mat.neural_layers.layers), "layer")
        self.report({"INFO"}, f"copied the layer stack of {mat.name!r} ({layers}){left_out}")
        return {"FINISHED"}


class NLM_OT_stack_paste(MaterialOperator, bpy.types.Operator):
    """Replace the material's layer stack with the one on the clipboard (Copy Layer Stack, or the JSON of a layer
    preset)"""

    bl_idname = "neural_layers.stack_paste"
    bl_label = "Paste Layer Stack"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return guarded("pasting a layer stack", self, lambda: self._run(context))

    def _run(self, context):
        mat = self.target(context)
        text = context.window_manager.clipboard.strip() or _copied_stack
        if not text:
            raise UserError("the clipboard is empty: copy a layer stack first (Copy Layer Stack, in the stack's menu)")
        try:
            stack, sidebar = stack_io.stack_from_text(text)
        except ValueError as e:
            raise UserError(
                f"the clipboard holds no layer stack: {e}; copy one with Copy Layer Stack (in the stack's menu)"
            ) from None
        replace_stack(self, mat, stack, sidebar)
        return {"FINISHED"}


PRESET_SUBDIR = "neural_layered_materials/layer_stacks"
# The presets menu's label while no preset of the user's is the last applied: Blender's preset menus hold the name
# of the last one applied in their label, and that is the preset "Remove Preset" removes.
PRESETS_MENU_LABEL = "Layer Presets"


def preset_file_text(stack_json: str) -> str:
    """A layer preset file: Python that Blender's preset menu runs, applying a stack (``stack_io.stack_text``) to the
    active material. Plain JSON inside, so presets can be read, shared and edited by hand."""
    return (
        "import bpy\n\n"
        "# A Neural Layered Materials layer stack (bottom to top); applied to the active material.\n"
        f"bpy.ops.neural_layers.stack_apply(stack={stack_json!r})\n"
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
        text = preset_file_text(stack_io.stack_text(self.target(context)))
        with open(filepath, "w", encoding="utf-8") as f:
            f.write(text)

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
    NLM_OT_stack_copy,
    NLM_OT_stack_paste,
    NLM_OT_preset_add,
    NLM_OT_evaluate_latent,
    NLM_OT_preview_lobe,
    NLM_OT_preview_sphere,
    NLM_OT_compare_reference,
)

register, unregister = bpy.utils.register_classes_factory(_CLASSES)

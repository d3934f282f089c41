"""What every operator of the add-on shares: user errors, guarded execution, the target material,
and long operations on a worker thread.

- :class:`UserError`: a problem the user can fix; its message is reported as is.
- :func:`guarded`: runs an operator's body and turns every failure into a report (``{'CANCELLED'}``),
  never a traceback.
- :class:`MaterialOperator`: acts on the active object's active material, or on ``material`` (a
  material name) when given; ``poll`` greys the button out where there is no material to act on
  (scripts that pass ``material`` always run and get a report instead).
- :class:`LongOperator`: ``prepare(context)`` reads Blender and returns ``(work, finish)``;
  ``work(progress)`` is core-only and runs on a worker thread when invoked from the UI (progress in
  the status bar, Esc cancels), blocking when executed (scripts, background mode).
"""

from __future__ import annotations

import traceback

import bpy
from bpy.props import StringProperty

from ..core import preview
from . import images, jobs, stack_io


class UserError(Exception):
    """A problem the user can fix; its message is reported as is."""


def fail(op, message: str) -> set:
    op.report({"ERROR"}, message)
    return {"CANCELLED"}


def guarded(label: str, op, fn) -> set:
    """Run ``fn()``; turn any failure into a report instead of a traceback."""
    try:
        return fn()
    except preview.NeuralUnavailable as e:
        return fail(op, f"neural models not available: {e}")
    except (UserError, ValueError) as e:
        return fail(op, str(e))
    except Exception as e:  # unexpected: a report for the user, the traceback for a bug report
        traceback.print_exc()
        return fail(op, f"{label} failed: {type(e).__name__}: {e}")


def scripted() -> bool:
    """True in background mode: no one presses buttons, scripts call the operators."""
    return bool(bpy.app.background)


def read_only_problem(mat) -> str | None:
    """Why ``mat`` cannot be edited (linked from a library, or a library override of one, whose layer stack Blender
    does not override: an edit would be lost when the file is saved), or None."""
    override = getattr(mat, "override_library", None)
    if override is not None:
        source = getattr(override.reference, "library", None)
        where = f" of a material from {source.filepath!r}" if source is not None else ""
        return (
            f"Material {mat.name_full!r} is a library override{where}, whose layer stack cannot be overridden: an "
            "edit would be lost when the file is saved; make it local (Outliner: Library Override > Clear, then "
            "Make Local) or edit it in its own file"
        )
    if mat.library is not None or not mat.is_editable:
        where = f" from {mat.library.filepath!r}" if mat.library is not None else ""
        return (
            f"Material {mat.name_full!r} is linked{where} and cannot be edited here: make it local "
            "(Object > Relations > Make Local) or edit it in its own file"
        )
    return None


def context_material(context):
    """The material the context shows: in the Shader Editor, the one it displays (a pinned one too, which need not
    be the active object's); elsewhere the active object's active material. None when there is none."""
    space = getattr(context, "space_data", None)
    if space is not None and getattr(space, "type", "") == "NODE_EDITOR":
        shown = getattr(space, "id", None)
        if isinstance(shown, bpy.types.Material):
            return shown
    ob = getattr(context, "object", None) or getattr(context, "active_object", None)
    return getattr(ob, "active_material", None) if ob is not None else None


def poll_problem(context, needs: str = "material", edits: bool = False) -> str | None:
    """Why an operator that needs ``needs`` ("material", "stack" or "texture") cannot act on the
    context's material (``context_material``; ``edits``: and change it), or None when it can."""
    ob = getattr(context, "object", None)
    mat = context_material(context)
    if mat is None:
        return "Select an object with a material" if ob is None else f"Object {ob.name!r} has no material"
    if edits and (problem := read_only_problem(mat)) is not None:
        return problem
    if needs in ("stack", "texture") and len(mat.neural_layers.layers) == 0:
        return f"The layer stack of {mat.name!r} is empty: add a base layer or pick a preset"
    if needs == "texture" and not mat.neural_layers.texture_path:
        return f"{mat.name!r} has no baked latent texture"
    return None


class MaterialOperator:
    material: StringProperty(
        name="Material",
        description="Name of the material to act on (default: the active object's active material)",
        default="",
        options={"SKIP_SAVE"},
    )

    # What the button needs to be pressable: "material" (an active material), "stack" (one with
    # layers) or "texture" (one with a baked latent texture).
    poll_needs = "material"
    # Whether the operator changes the material (then a linked one, read-only, is refused).
    edits = True

    @classmethod
    def poll(cls, context):
        """Grey the button out (with the reason as its tooltip) where it cannot run. In background
        mode (scripts, which may name any material) it always runs and reports what is missing."""
        problem = poll_problem(context, cls.poll_needs, cls.edits)
        if problem is None or scripted():
            return True
        cls.poll_message_set(problem)
        return False

    def target(self, context):
        if self.material:
            mat = bpy.data.materials.get(self.material)
            if mat is None:
                raise UserError(f"there is no material named {self.material!r}")
            return self._editable(mat)
        mat = context_material(context)
        if mat is None:
            ob = getattr(context, "object", None) or getattr(context, "active_object", None)
            if ob is None:
                raise UserError('no active object: select an object with a material (or pass material="Name")')
            raise UserError(f"object {ob.name!r} has no material: add one (Material Properties > New)")
        return self._editable(mat)

    def _editable(self, mat):
        """``mat``, if the operator may act on it (a read-only operator on any; one that edits on a local one)."""
        if self.edits and (problem := read_only_problem(mat)) is not None:
            raise UserError(problem)
        return mat

    def target_stack(self, context):
        mat = self.target(context)
        stack = stack_io.stack_from_material(mat)
        if stack is None:
            raise UserError(f"material {mat.name!r} has an empty layer stack: add a base layer or pick a preset")
        return mat, stack

    def report_notes(self, notes):
        for note in notes:
            self.report({"WARNING"}, note)


class LongOperator(jobs.ModalJob, MaterialOperator):
    """prepare() reads Blender and returns (work, finish): work(progress) is core-only."""

    _finish = None

    def prepare(self, context):
        raise NotImplementedError

    def execute(self, context):
        def run():
            work, finish = self.prepare(context)
            return finish(context, work(None))

        return guarded(self.bl_label, self, run)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        prepared = []

        def prepare():
            prepared.append(self.prepare(context))
            return {"FINISHED"}

        if guarded(self.bl_label, self, prepare) != {"FINISHED"}:
            return {"CANCELLED"}
        work, self._finish = prepared[0]
        return self.start_job(context, work)

    @staticmethod
    def again(mat, name: str):
        """The material ``mat`` (named ``name`` when ``prepare`` read it) as it is now, for a job's finish: itself
        (renamed meanwhile, too), or after an undo during the job, which replaced every data-block (``mat`` then
        raises ReferenceError), the material of that name."""
        try:
            mat.name  # noqa: B018 (an RNA read: raises once Blender freed the data-block)
            return mat
        except ReferenceError:
            pass
        found = bpy.data.materials.get(name)
        if found is None:
            raise UserError(f"material {name!r} is gone (undone or deleted while the job ran): nothing was changed")
        return found

    def job_done(self, context, job):
        if job.error is not None:
            err = job.error

            def reraise():
                raise err

            return guarded(self.bl_label, self, reraise)
        return guarded(self.bl_label, self, lambda: self._finish(context, job.result))

    def show(self, context, name, rgba, metadata, notes, summary):
        image = images.store_image(name, rgba, metadata)
        images.show_in_image_editor(context, image)
        self.report_notes(notes)
        self.report({"INFO"}, f"{image.name}: {summary}")
        return {"FINISHED"}

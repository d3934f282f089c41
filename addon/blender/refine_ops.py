"""The *Refine* button: fit the material's latent to the reference (``core.neural.refine.refine_latent``).

The refined latent is stored where the encoded one lives (``neural_layers.latent``, with its decoder
size and the stack's hash, so previews use it and any edit of the stack makes it stale), and what the
refinement measured goes into ``neural_refine`` on the material: the refinement's cache key, the
validation error before and after and the seconds it took. A refinement that was not better on its
validation pairs leaves the encoded latent in place and says so. The renderer's background compile (right after
Blender starts) pauses while a refinement runs, and its budget counts from then on.
"""

from __future__ import annotations

import time

import bpy
from bpy.props import FloatProperty, PointerProperty, StringProperty

from ..core import preview
from ..core.render import warm_up
from . import stack_io
from .operator_base import LongOperator, UserError


class NLM_RefineResult(bpy.types.PropertyGroup):
    key: StringProperty(
        name="Key", description="Cache key of the refinement (stack, model files, settings)", default=""
    )
    stack_hash: StringProperty(name="Stack hash", description="Hash of the stack that was refined", default="")
    size: StringProperty(name="Decoder size", description="Decoder size of the refined latent", default="")
    decoder_digest: StringProperty(
        name="Decoder digest",
        description="sha256 of the decoder file the latent was "
        "refined for: F12 renders the refined latent only while that decoder is shipped",
        default="",
    )
    error_before: FloatProperty(
        name="Error before", description="Validation lobe error of the encoded latent", default=0.0
    )
    error_after: FloatProperty(
        name="Error after", description="Validation lobe error of the refined latent", default=0.0
    )
    seconds: FloatProperty(name="Seconds", description="Seconds the refinement took", default=0.0)
    kept: StringProperty(
        name="Kept",
        description="'yes' when the refined latent is the one stored; 'replaced' once the stack was encoded again "
        "over it (an edit, Evaluate, a model size change)",
        default="",
    )


class NLM_OT_refine_latent(LongOperator, bpy.types.Operator):
    """Fit the latent code to the reference BRDF of the stack (a few seconds; cached by stack and model
    files) and store it on the material when it is better on separate validation pairs"""

    poll_needs = "stack"
    bl_idname = "neural_layers.refine_latent"
    bl_label = "Refine Latent"
    # undoable, with no Adjust Last Operation panel: its redo calls execute(), the whole job on Blender's thread
    # with no progress and no Esc (seconds to minutes)
    bl_options = {"UNDO"}

    budget: FloatProperty(
        name="Budget (s)", description="Seconds the refinement may take", default=8.0, min=0.5, max=600.0
    )

    def prepare(self, context):
        """On a worker thread with a progress bar and Esc, as the other long operators (it held Blender's UI for
        its whole budget, up to ten minutes, with no way to stop it)."""
        from ..core.neural.models import load_models
        from ..core.neural.refine import refine_latent
        from ..core.stack import clamp_to_trained
        from . import bake_state

        mat, stack = self.target_stack(context)
        if bake_state.current_texture(mat)[0] is not None:  # F12 renders the bake, not a latent
            raise UserError(
                f"material {mat.name!r}: its maps drive it, through a baked texture, not one latent: Refine fits a "
                "constant stack's latent, which F12 would not render; refine the bake instead "
                "(Latent Texture > Refine (s))"
            )
        name = mat.name
        size = preview.resolve_size(stack_io.model_size(mat))
        _, notes = clamp_to_trained(stack)  # the encoder sees the clamped stack; the reference the real one
        self.report_notes(notes)
        budget = float(self.budget)

        def work(progress):
            # The renderer's loops compile on a background thread after Blender starts (warm_up): beside it a 3 s
            # refinement took 8.7-15.4 s, its steps slowed by the compile. The compile pauses at its next step (the
            # loop being compiled finishes), the budget's clock starts after that (the loops the refinement itself
            # needs still compile within it, once), and the compile goes on once the refinement is done.
            paused = time.perf_counter()
            warm_up.wait_for_background()
            paused = time.perf_counter() - paused
            try:
                return refine_latent(stack, size, budget_s=budget, progress=progress), load_models(size).digest, paused
            finally:
                warm_up.warm_up_in_background()

        def finish(context, result):
            (z, rep), digest, paused = result
            if paused >= 0.1:
                self.report({"INFO"}, f"waited {paused:.1f} s for the renderer's background compile before refining")
            target = self.again(mat, name)  # an undo during the refinement replaced the one read above
            if stack_io.stack_from_material(target) != stack:
                raise UserError(f"the stack of {target.name!r} changed while it was refined: press Refine again")
            self._store(target, stack, size, z, rep, digest)
            return {"FINISHED"}

        return work, finish

    def _store(self, mat, stack, size, z, rep, digest) -> None:
        s = stack_io.settings(mat)
        s.latent = z.tolist()
        s.latent_size = size
        s.latent_hash = preview.stack_hash(stack)
        r = mat.neural_refine
        r.key, r.stack_hash, r.size = rep.key, s.latent_hash, size
        r.decoder_digest = digest
        r.error_before, r.error_after = rep.validation_error_before, rep.validation_error_after
        r.seconds, r.kept = rep.total_s, "yes" if rep.kept else "no"
        stack_io.tag_changed(mat)  # the viewport and the render operators' evaluated copies: another latent now
        how = "cached" if rep.cached else f"{rep.total_s:.1f} s"
        # what decided (the mean squared relative error over the validation groups) first, then the median lobe
        # error, which can move the other way: a latent kept with "0.107 -> 0.122" alone read as a step back
        figures = (
            f"validation loss {rep.validation_loss_before:.4f} -> {rep.validation_loss_after:.4f} (what decides), "
            f"median lobe error {rep.validation_error_before:.3f} -> {rep.validation_error_after:.3f}"
        )
        # a fit its time budget stopped says so, and what to do: it read "did not improve" where it had made no step
        walks = f"its reference walks took {rep.reference_s:.1f} s"
        ran_out = f"its time budget of {rep.budget_s:g} s ran out after {rep.steps} step(s) of the fit ({walks})"
        more = "give Refine more time (Refine Budget)"
        if rep.kept:
            cut = f"; {ran_out}: a larger Refine Budget may refine it further" if rep.stopped == "budget" else ""
            self.report({"INFO"}, f"latent of {mat.name!r} refined ({size}, {how}): {figures}{cut}")
        elif rep.stopped == "budget" and rep.steps == 0:
            self.report(
                {"WARNING"},
                f"refining {mat.name!r} ({size}, {how}): its time budget of {rep.budget_s:g} s ran out before the "
                f"fit made a step ({walks}): the encoded latent is kept; {more}",
            )
        elif rep.stopped == "budget":
            self.report(
                {"WARNING"},
                f"refining {mat.name!r} ({size}, {how}): {ran_out}, not yet better on the validation pairs "
                f"({figures}): the encoded latent is kept; {more}",
            )
        else:
            self.report(
                {"WARNING"},
                f"refining {mat.name!r} ({size}, {how}) did not improve on the validation pairs ({figures}): "
                "the encoded latent is kept",
            )


_CLASSES = (NLM_RefineResult, NLM_OT_refine_latent)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_CLASSES)


def register() -> None:
    _register_classes()
    bpy.types.Material.neural_refine = PointerProperty(type=NLM_RefineResult)


def unregister() -> None:
    if hasattr(bpy.types.Material, "neural_refine"):
        del bpy.types.Material.neural_refine
    _unregister_classes()

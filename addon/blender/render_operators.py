"""Render Preview: render the current view with the core path tracer into an Image Editor image.

From the 3D viewport it renders what the viewport shows (its view, unless it looks through the
scene camera); elsewhere it renders the scene camera. Resolution and samples are operator
options. Invoked from the UI it runs on a worker thread (progress in the status bar, Esc
cancels); from scripts and in background mode it runs blocking. With ``filepath`` it also writes
the image (OpenEXR for ``.exr``, PNG for ``.png``).
"""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import BoolProperty, IntProperty, StringProperty

from ..core.render import Cancelled, render, write_exr, write_png
from . import images, jobs, scene_export

IMAGE_NAME = "Neural Layered Render"


def _view_camera(context, width: int, height: int, warnings: list[str]):
    """The 3D viewport's view as a core camera, or None where the operator runs elsewhere or the view looks
    through the scene camera. An orthographic view renders as a perspective one of the same view (as the
    viewport's Rendered mode does), with a warning."""
    region = getattr(context, "region_data", None)
    space = getattr(context, "space_data", None)
    if region is None or space is None or getattr(space, "type", "") != "VIEW_3D":
        return None
    if region.view_perspective == "CAMERA":
        return None
    if not region.is_perspective:
        warnings.append("the orthographic view is rendered as a perspective view of the same lens")
    clip = scene_export.view_clip(region, space, context.scene)
    return scene_export.view_camera(region, space.lens, width, height, clip)


def render_work(core_scene, settings, assign):
    """The core part: a function of ``progress(fraction)`` that chooses the decoders (``assign``:
    ``NLM_RenderSettings.decoder_assignment``'s, seconds for Auto's measurements and the calibrations) and renders;
    it returns (film, stats, warnings, info lines). Esc stops it in either step."""

    def work(progress):
        info: list[str] = []
        stop = None if progress is None else (lambda: progress(0.0) or False)  # progress raises once cancelled
        notes = assign(core_scene, info, stop)

        def on_pass(film, done, total):
            if progress is not None:
                progress(done / total)  # raises when the user cancels (jobs.Job)
            return True

        film, stats = render(core_scene, settings, progress=on_pass)
        return film, stats, notes, info

    return work


def save_image(path: str, rgba) -> None:
    p = Path(bpy.path.abspath(path))
    if p.suffix.lower() == ".exr":
        write_exr(p, rgba)
    elif p.suffix.lower() == ".png":  # with its alpha where a transparent film left some
        write_png(p, rgba if (rgba[:, :, 3] < 1.0).any() else rgba[:, :, :3])
    else:
        raise ValueError(f"filepath {path!r} must end in .exr or .png")


class NLM_OT_render_preview(jobs.ModalJob, bpy.types.Operator):
    """Render the current view with the Neural Layered path tracer into the Image Editor"""

    bl_idname = "neural_layers.render_preview"
    bl_label = "Render Preview"
    bl_options = {"REGISTER"}

    width: IntProperty(
        name="Width", description="Image width (0: the scene's render resolution)", default=0, min=0, max=16384
    )
    height: IntProperty(
        name="Height", description="Image height (0: the scene's render resolution)", default=0, min=0, max=16384
    )
    samples: IntProperty(
        name="Samples", description="Paths per pixel (0: the scene's preview samples)", default=0, min=0, max=65536
    )
    use_view: BoolProperty(
        name="Current View", description="Render the 3D viewport's view rather than the camera", default=True
    )
    filepath: StringProperty(
        name="File Path",
        description="Also write the image here (.exr or .png)",
        default="",
        subtype="FILE_PATH",
        options={"PATH_SUPPORTS_BLEND_RELATIVE", "SKIP_SAVE"},
    )

    def _prepare(self, context):
        if self.filepath and Path(self.filepath).suffix.lower() not in (".exr", ".png"):
            raise ValueError(f"filepath {self.filepath!r} must end in .exr or .png")
        if self.filepath.startswith("//") and not bpy.data.filepath:  # else it would land in the working folder
            raise ValueError(
                f"filepath {self.filepath!r} is relative to the .blend file, which is not saved: "
                "save the file first or choose an absolute path"
            )
        scene = context.scene
        w, h = scene_export.render_size(scene)
        if self.width and self.height:
            w, h = self.width, self.height
        elif self.width:
            w, h = self.width, max(1, round(self.width * h / w))
        elif self.height:
            w, h = max(1, round(self.height * w / h)), self.height
        view_warnings: list[str] = []
        camera = _view_camera(context, w, h, view_warnings) if self.use_view else None
        depsgraph = context.evaluated_depsgraph_get()
        info: list[str] = []
        core_scene, warnings = scene_export.export_scene(depsgraph, w, h, camera, info=info)
        for msg in info:
            self.report({"INFO"}, msg)
        for msg in view_warnings + warnings:
            self.report({"WARNING"}, msg)
        samples = self.samples or scene.neural_render.preview_samples
        # Auto's time budget for the samples this preview renders, not for the scene's Samples
        assign = scene.neural_render.decoder_assignment(samples)
        settings = scene.neural_render.to_core(samples, scene=scene)
        return render_work(core_scene, settings, assign)

    def _finish(self, context, result):
        film, stats, notes, info = result
        for msg in info:
            self.report({"INFO"}, msg)
        for msg in notes:
            self.report({"WARNING"}, msg)
        rgba = film.rgba()
        old = bpy.data.images.get(IMAGE_NAME)
        if old is not None and tuple(old.size) != (rgba.shape[1], rgba.shape[0]):
            bpy.data.images.remove(old)  # a new size: start a new image rather than rescale
        image = images.store_image(
            IMAGE_NAME, rgba, {"paths_per_second": stats.paths_per_second, "seconds": stats.seconds["total"]}
        )
        images.show_in_image_editor(context, image)
        if self.filepath:
            save_image(self.filepath, rgba)
        self.report({"INFO"}, f"{image.name}: {stats.summary()}")
        return {"FINISHED"}

    def _fail(self, message):
        self.report({"ERROR"}, message)
        return {"CANCELLED"}

    def _failure(self, e: Exception):
        """Every failure as a report: a plain message for bad input, the type too for anything else (a model file
        that cannot be read, an unexpected error), never a traceback alone."""
        if isinstance(e, (ValueError, RuntimeError)):
            return self._fail(str(e))
        return self._fail(f"Render Preview failed: {type(e).__name__}: {e}")

    def execute(self, context):
        try:
            return self._finish(context, self._prepare(context)(None))
        except Cancelled:
            return {"CANCELLED"}
        except Exception as e:
            return self._failure(e)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        try:
            work = self._prepare(context)
        except Exception as e:
            return self._failure(e)
        return self.start_job(context, work, interval=0.2)

    def job_done(self, context, job):
        if job.error is not None:
            return self._fail(f"Render Preview failed: {type(job.error).__name__}: {job.error}")
        try:
            return self._finish(context, job.result)
        except Exception as e:
            return self._failure(e)


_CLASSES = (NLM_OT_render_preview,)

register, unregister = bpy.utils.register_classes_factory(_CLASSES)

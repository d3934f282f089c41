"""The Neural Layered render engine: F12, ``blender -b file.blend -E NEURAL_LAYERED -f 1``, and the
3D viewport's Rendered mode.

``render()`` exports the evaluated depsgraph (``scene_export``), renders it with the core path
tracer one pass of one sample per pixel at a time, shows each pass (progressive), reports
progress and statistics, and stops when the user cancels (Esc). Blender writes the result in the
scene's output format (OpenEXR, PNG, ...). Every failure is reported in the UI (``report`` and
the render's error line); where the neural runtime fails the reference renders instead.

``view_update`` / ``view_draw`` keep a progressive session (``addon.core.render.progressive``)
for the viewport: 1 sample per pixel at reduced resolutions first (at most 64 x 64 pixels, growing to a
quarter of the view on each side), then refinement, restarted on every edit and every view change (the old
render stops within a bounce); ``_Viewport`` draws its newest image.
Material thumbnails (``is_preview``) render with ``core.render.thumbnail``'s settings: a few
samples, few bounces, the fastest decoder, no denoising, no *Auto* measurement.
The render thread setting of the scene (Threads: Auto / Fixed) decides the cores used.
"""

from __future__ import annotations

import re
import time
from dataclasses import replace

import bpy
import numpy as np

from ..core.render import Cancelled, render, warm_up
from ..core.render.progressive import ProgressiveSession
from ..core.render.remaining import RemainingTime, format_duration
from ..core.render.thumbnail import prepare_thumbnail
from . import render_operators, render_properties, render_ui, scene_export

ENGINE_ID = "NEURAL_LAYERED"


def _compatible_panels():
    """Blender's own panels that make sense for this engine (output, dimensions, film...)."""
    keep = {
        "RENDER_PT_format",
        "RENDER_PT_frame_range",
        "RENDER_PT_output",
        "RENDER_PT_color_management",
        "RENDER_PT_format_presets",
        "RENDER_PT_encoding",
        "RENDER_PT_stamp",
        "RENDER_PT_stereoscopy",  # each view rendered from its own camera (``render``)
        "RENDER_PT_output_views",
        "DATA_PT_camera_stereoscopy",
        "DATA_PT_context_light",  # the light's own settings: render_ui.NLM_PT_light
        "DATA_PT_camera",
        "DATA_PT_lens",
        "DATA_PT_camera_display",
        "WORLD_PT_context_world",
        "EEVEE_WORLD_PT_surface",
        "EEVEE_MATERIAL_PT_context_material",
        "EEVEE_MATERIAL_PT_surface",
        "MATERIAL_PT_preview",
    }
    return [
        p
        for p in bpy.types.Panel.__subclasses__()
        if getattr(p, "COMPAT_ENGINES", None) is not None and p.__name__ in keep
    ]


def _failure(e: Exception) -> str:
    """One line for the UI: what failed, named by its type unless it is a plain ValueError."""
    return str(e) if isinstance(e, ValueError) else f"{type(e).__name__}: {e}"


def _view_camera(context):
    """The 3D viewport's view as a core camera (its projection, or the scene camera's as camera view frames it;
    the region's size)."""
    region, r3d, space = context.region, context.region_data, context.space_data
    clip = scene_export.view_clip(r3d, space, context.scene)
    return scene_export.view_camera(r3d, space.lens, region.width, region.height, clip)


def settings_key(scene) -> tuple:
    """The engine's settings of ``scene`` (``scene.neural_render``) as one value: the viewport renders again when
    it changes, since editing them names no depsgraph update (a new sample count or decoder went unseen until some
    other edit)."""
    props = scene.neural_render
    return tuple(
        (p.identifier, tuple(v) if hasattr(v := getattr(props, p.identifier), "__len__") and not isinstance(v, str)
         else v)
        for p in props.bl_rna.properties if p.identifier != "rna_type" and p.type != "POINTER"
    )  # fmt: skip


def _names_the_scene_alone(update) -> bool:
    """Whether a depsgraph update names the scene and nothing of it changed (a selection, the active object, a
    setting of the scene itself: ``_scene_state`` tells those that render)."""
    return (
        isinstance(update.id, bpy.types.Scene)
        and not update.is_updated_transform
        and not update.is_updated_geometry
        and not update.is_updated_shading
    )


def _scene_state(depsgraph) -> tuple:
    """What of the scene itself the viewport renders and an update naming the scene alone may change: the film's
    transparency, the pixel aspect, the render's threads (the session's), the frame (an image sequence's) and the
    objects the viewport shows (an object hidden there)."""
    scene = depsgraph.scene
    r = scene.render
    shown = frozenset(ob.original.session_uid for ob in depsgraph.objects)
    return (
        r.film_transparent,
        r.pixel_aspect_x,
        r.pixel_aspect_y,
        r.threads_mode,
        r.threads,
        scene.frame_current,
        shown,
    )


def _world_reads_a_sequence(world) -> bool:
    """Whether ``world``'s nodes read an image sequence (its sky is another one at each frame)."""
    tree = getattr(world, "node_tree", None)
    return tree is not None and any(getattr(getattr(n, "image", None), "source", "") == "SEQUENCE" for n in tree.nodes)


def _view_key(context) -> tuple:
    """What makes a viewport image stale without an edit: the view and projection matrices (a lens, a zoom or a
    pan in camera view), the lens and the region size."""
    r3d, region = context.region_data, context.region
    projection = (tuple(map(tuple, r3d.window_matrix)), context.space_data.lens)
    return (tuple(map(tuple, r3d.view_matrix)), projection, region.width, region.height)


def viewport_reports(info: list[str], warnings: list[str], said: set[str]) -> list[tuple[str, str]]:
    """What the viewport reports of an export and its decoder choice, as ``(kind, line)``: its INFO lines (a stale
    refined latent, a stack no F12 has measured yet) and its WARNING lines (what the export leaves out of the scene,
    as F12 reports them), each line that ``said`` (the lines the viewport reported so far) does not hold yet, which
    it then holds: once, not at every edit. Lines that differ in their numbers alone, outside quoted names, are one
    line (a slider dragged over a dark material changes the share its specular warning gives at every tick). A long
    session of edits (over 1000 lines) forgets them and reports again. The viewport threw every warning away, so a
    material it rendered as a flat Lambertian looked right there and was named only in F12."""
    reports = []
    for kind, line in [("INFO", line) for line in info] + [("WARNING", line) for line in warnings]:
        parts = line.split("'")  # names in quotes kept whole: 'Material.001' and 'Material.002' are two lines
        key = "'".join(part if i % 2 else re.sub(r"\d+(\.\d+)?", "#", part) for i, part in enumerate(parts))
        if key not in said:
            if len(said) > 1000:
                said.clear()
            said.add(key)
            reports.append((kind, line))
    return reports


class _Viewport:
    """Thin glue between a progressive session and the 3D viewport: a main-thread timer asks
    for a redraw when the session has a new image; ``draw`` uploads it as a texture and draws it
    over the region through Blender's display transform."""

    def __init__(self, engine, settings):
        self.engine_ref = engine
        self.key = None
        self.session = ProgressiveSession(settings, preview_divisor=4)
        self._drawn = None  # the session's image on screen (``ViewImage``: a new object for every image)
        self._texture = None
        self._reported_error = None  # the session's last render error shown
        self._reported_calibration = None  # and its last calibration failure: each shown once, not at every redraw
        _OPEN_VIEWPORTS.add(self)
        self.timer = self._poll  # one bound method: what the timers compare to unregister it
        # persistent: Blender drops other timers when a file is opened, and this one is what closes the session
        # once Blender frees the engine (the session's own reference keeps the engine's Python object alive)
        bpy.app.timers.register(self.timer, first_interval=0.05, persistent=True)
        self.settings_key = None  # the engine's settings it renders with (``settings_key``)

    def restart(self, core_scene, settings, key) -> None:
        self.key = key
        self.session.restart(core_scene, settings)

    def move_camera(self, camera, key) -> None:
        self.key = key
        self.session.move_camera(camera)

    def _poll(self):
        if self.session is None:
            return None  # closed: the timer ends
        try:
            if self._is_new(self.session.latest()) or self._unreported():
                self.engine_ref.tag_redraw()  # a new image, or a failure to show (a failed pass has no image)
            else:
                self.engine_ref.is_preview  # noqa: B018 (an RNA read: raises once Blender freed the engine)
        except ReferenceError:  # the engine is gone (the viewport left Rendered mode): so is its session
            self.close()
            return None
        return 0.05

    def draw(self, engine, scene) -> None:
        import gpu
        from gpu_extras.presets import draw_texture_2d

        image = self.session.latest()
        error = self.session.error
        if error is not None and error is not self._reported_error:  # once per failure, not per redraw
            engine.report({"ERROR"}, _failure(error))
            self._reported_error = error
        failed = self.session.calibration_failure
        if failed is not None and failed is not self._reported_calibration:
            engine.report({"WARNING"}, f"albedo calibration failed ({_failure(failed)}); viewing it uncalibrated")
            self._reported_calibration = failed
        if image is None:
            return
        if self._is_new(image) or self._texture is None:
            h, w, _ = image.rgba.shape
            pixels = np.ascontiguousarray(image.rgba[::-1]).ravel()  # GPU rows run bottom to top
            self._texture = gpu.types.GPUTexture(
                (w, h), format="RGBA16F", data=gpu.types.Buffer("FLOAT", pixels.size, pixels)
            )
            self._drawn = image
        region = bpy.context.region
        gpu.state.blend_set("ALPHA_PREMULT")
        engine.bind_display_space_shader(scene)
        draw_texture_2d(self._texture, (0, 0), region.width, region.height)
        engine.unbind_display_space_shader()
        gpu.state.blend_set("NONE")

    def _unreported(self) -> bool:
        """Whether the session has a failure ``draw`` has not shown yet."""
        error, failed = self.session.error, self.session.calibration_failure
        return (error is not None and error is not self._reported_error) or (
            failed is not None and failed is not self._reported_calibration
        )

    def _is_new(self, image) -> bool:
        """Whether ``image`` is not the one on screen. Told by the object, not by its generation and samples: a
        generation's reduced images and its first full-resolution pass all have one sample (and so does the
        first pass after its calibration), and each must be shown when it comes."""
        return image is not None and image is not self._drawn

    def close(self) -> None:
        _OPEN_VIEWPORTS.discard(self)
        if self.session is not None:
            self.session.close(timeout=5.0)
            self.session = None


# The viewports' sessions not closed yet: ``unregister`` closes them (their threads and buffers), with their timers.
_OPEN_VIEWPORTS: set = set()


def _write_feature_passes(passes, film, region, camera) -> None:
    """Denoising Albedo / Normal and Depth from the film's first-hit features in ``region`` (``render_region``),
    where the result has those passes. The normals in the frame of ``camera`` (the core camera rendered) as Cycles
    writes them (``film.camera_normals``): they were written in world space, which a denoiser trained on Cycles'
    passes does not read."""
    from ..core.render.film import camera_normals

    wanted = {key: i for name, key in _FEATURE_PASSES if (i := passes.find(name)) >= 0}
    for key, features in film.features(tuple(wanted)).items():  # only what the result has passes for
        if key == "normal":
            features = camera_normals(features, camera.matrix)
        passes[wanted[key]].rect.foreach_set(_region_rows(features, region))


_FEATURE_PASSES = (("Denoising Albedo", "albedo"), ("Denoising Normal", "normal"), ("Depth", "depth"))


def render_region(scene, width: int, height: int) -> tuple[int, int, int, int]:
    """The pixels F12 renders of a ``width`` x ``height`` frame, (x0, y0, x1, y1) with rows counted from the bottom
    as Blender counts them: the Render Region (``use_border``) as Blender cuts it (its float32 fractions times the
    size in float32, truncated: 0.9 of 30 rows is 27, where doubles give 26.99999...), else the whole frame.
    Blender's result holds that rectangle only, cropped or not: without *Crop to Render Region* it places it in the
    frame itself."""
    r = scene.render
    if not r.use_border:
        return 0, 0, width, height
    w, h = np.float32(width), np.float32(height)
    x0, x1 = (int(np.float32(f) * w) for f in (r.border_min_x, r.border_max_x))
    y0, y1 = (int(np.float32(f) * h) for f in (r.border_min_y, r.border_max_y))
    return x0, y0, max(x1, x0 + 1), max(y1, y0 + 1)


def region_pixels(region: tuple[int, int, int, int], width: int, height: int) -> np.ndarray | None:
    """Flat indices (row 0 at the top, as the core renderer counts them) of ``region``'s pixels; None for the whole
    frame."""
    x0, y0, x1, y1 = region
    if (x0, y0, x1, y1) == (0, 0, width, height):
        return None
    rows = np.arange(height - y1, height - y0)
    return (rows[:, None] * width + np.arange(x0, x1)[None, :]).ravel()


def thumbnail_size(width: int, height: int) -> tuple[int, int]:
    """The size a material preview asked at ``width`` x ``height`` is rendered at: itself, or the same aspect with
    its longer side THUMBNAIL_MAX_SIDE pixels."""
    from ..core.render.thumbnail import THUMBNAIL_MAX_SIDE

    big = max(width, height)
    if big <= THUMBNAIL_MAX_SIDE:
        return width, height
    return max(1, round(width * THUMBNAIL_MAX_SIDE / big)), max(1, round(height * THUMBNAIL_MAX_SIDE / big))


def _resized(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` (H, W, C) at ``width`` x ``height``, each pixel the nearest of the image's (a preview's
    upscale)."""
    h, w = image.shape[:2]
    rows = np.minimum((np.arange(height) + 0.5) * h / height, h - 1).astype(np.int64)
    cols = np.minimum((np.arange(width) + 0.5) * w / width, w - 1).astype(np.int64)
    return image[rows][:, cols]


def _region_rows(image: np.ndarray, region: tuple[int, int, int, int]) -> np.ndarray:
    """The region's part of a whole frame's ``image`` (H, W, C), row 0 at the top, as Blender's flat pass buffers
    take it: rows from the bottom, C-contiguous and flat."""
    x0, y0, x1, y1 = region
    height = image.shape[0]
    return np.ascontiguousarray(image[height - y1 : height - y0, x0:x1][::-1]).ravel()


def render_summary(stats, decoder_seconds: float | None = None) -> str:
    """F12's last status line: the render's statistics (``RenderStats.summary``) after the seconds the decoder choice
    took before the render began (``decoder_seconds``; None: none was made, a thumbnail's): Auto's measurements, the
    encodings and the calibrations of new stacks, 10-70 s on a first render of three new stacks, which the render's
    own setup (``RenderStats``) does not see and the summary said were 0.00 s."""
    if decoder_seconds is None:
        return stats.summary()
    return f"decoders {decoder_seconds:.2f} s (choice, encodings, calibrations) before the render: {stats.summary()}"


def status_line(passes: int, samples: int, remaining: float | None, triangles: int) -> str:
    """F12's status line: the samples done, the time left once known (Blender's own time format), the triangles."""
    left = "" if remaining is None else f" | Remaining:{format_duration(remaining)}"
    return f"Sample {passes}/{samples}{left} | {triangles} triangles"


def _warn_orthographic(engine, context) -> None:
    """Say, once a viewport session (``engine._view_info``), that an orthographic view renders in perspective
    (``scene_export.view_camera``): whether the view was orthographic when Rendered mode began or turned so after
    (Numpad 5, a view from an axis), which moves the camera without an edit and went unsaid."""
    ortho = "an orthographic view renders in perspective: this engine's camera is a pinhole"
    if not context.region_data.is_perspective and ortho not in engine._view_info:
        engine._view_info.add(ortho)
        engine.report({"WARNING"}, ortho)


class NeuralLayeredRenderEngine(bpy.types.RenderEngine):
    bl_idname = ENGINE_ID
    bl_label = "Neural Layered"
    bl_use_preview = True  # material thumbnails (render() with is_preview)
    bl_use_shading_nodes_custom = False

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._viewport = None  # the 3D viewport's progressive session (view_update / view_draw)
        self._view_info: set[str] = set()  # the viewport's lines reported so far (``viewport_reports``)
        self._view_geometry = scene_export.GeometryCache()  # what the viewport's exports keep of the geometry
        self._view_world = None  # (the viewport's last exported environment,), kept while the world is unchanged

    def __del__(self):
        view = getattr(self, "_viewport", None)
        if view is not None:
            view.close()

    # ------------------------------------------------------------------ F12

    def _fail(self, e: Exception) -> None:
        message = _failure(e)
        self.report({"ERROR"}, message)
        self.error_set(message)

    def update_render_passes(self, scene=None, renderlayer=None):
        """The passes this engine writes, for the compositor's Render Layers node."""
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")
        if scene.neural_render.denoise:
            for name, channels, ids, kind in render_properties.DENOISING_PASSES:
                self.register_pass(scene, renderlayer, name, channels, ids, kind)

    def render(self, depsgraph):
        scene = depsgraph.scene_eval  # the frame rendered: an animation render evaluates keyed settings there only
        props = scene.neural_render
        width, height = scene_export.render_size(scene)
        region = (0, 0, width, height) if self.is_preview else render_region(scene, width, height)
        if props.denoise and not self.is_preview:
            for name, channels, ids, _ in render_properties.DENOISING_PASSES:
                self.add_pass(name, channels, ids, layer=depsgraph.view_layer.name)
        x0, y0, x1, y1 = region
        # The result of the view layer rendered: Blender calls render() once per view layer, each to its own layer,
        # and each of its views (Stereoscopy's eyes) is rendered into its own result, from its own camera.
        views = [""] if self.is_preview else scene_export.render_views(scene.render)
        self._said: set[str] = set()  # what this render's views reported
        for view in views:
            if view:
                self.active_view_set(view)
            result = self.begin_result(0, 0, x1 - x0, y1 - y0, layer=depsgraph.view_layer.name, view=view)
            try:
                if (result.resolution_x, result.resolution_y) != (x1 - x0, y1 - y0):
                    raise RuntimeError(
                        f"Blender's render result is {result.resolution_x}x{result.resolution_y} pixels where the "
                        f"render region was cut to {x1 - x0}x{y1 - y0}: turn Render Region off to render"
                    )
                self._render(depsgraph, scene, props, result, region, thumbnail=self.is_preview, view=view)
            except Cancelled:  # Esc before any pass (the decoder choice): nothing rendered, nothing failed
                self.update_stats("", "Cancelled")
                return
            except Exception as e:  # every failure reaches the UI, not only a console traceback
                self._fail(e)
                return
            finally:
                self.end_result(result)
            if self.test_break():
                return

    def _settings(self, core_scene, scene, props, thumbnail: bool):
        """The core settings and the decoder choice's warnings (INFO lines go to ``info``)."""
        info: list[str] = []
        warnings: list[str] = []
        if thumbnail:  # a material thumbnail: small, fast, nothing measured
            settings, notes = prepare_thumbnail(core_scene, threads=props.to_core(scene=scene).threads)
            return settings, notes, info
        self.update_stats("", "Choosing decoders")
        try:  # Esc heard between the measurements (a second or two a material and size the first time)
            warnings = props.assign_decoders(core_scene, info=info, stop=self.test_break)
        except Cancelled:
            raise
        except Exception as e:  # the stacks stay, on the default decoder or the reference
            warnings.append(f"decoder choice failed ({_failure(e)}); layered materials use the default decoder")
        return props.to_core(scene=scene), warnings, info

    def _render(self, depsgraph, scene, props, result, region, thumbnail: bool = False, view: str = ""):
        self.update_stats("", f"Exporting scene{f' ({view})' if view else ''}")
        info: list[str] = []
        asked = scene_export.render_size(scene)
        # A material preview is rendered at most THUMBNAIL_MAX_SIDE pixels a side and shown at the size Blender asks:
        # the Properties editor's Preview panel asks for its own size (over 512 pixels on a wide or 2x-DPI editor),
        # which failed with an error.
        size = thumbnail_size(*asked) if thumbnail else asked
        camera_warnings: list[str] = []
        camera = scene_export.stereo_view_camera(self, scene, *size, camera_warnings) if view else None
        core_scene, warnings = scene_export.export_scene(depsgraph, *size, camera=camera, info=info)
        warnings = camera_warnings + warnings
        exported = list(core_scene.materials)  # the stacks, before the decoder choice puts them on their decoders
        choosing = time.perf_counter()
        settings, notes, choice_info = self._settings(core_scene, scene, props, thumbnail)
        decoder_seconds = None if thumbnail else time.perf_counter() - choosing
        warnings = warnings + notes
        if props.denoise and not thumbnail and (note := render_properties.denoise_note(scene)) is not None:
            warnings.append(f"Denoise does nothing here: {note}")
        said = self._said if view else set()  # a stereo render's views say the same: once
        # A material thumbnail says nothing: its scene is Blender's preview scene (a warning named its floor's
        # material, which the user never made), and every thumbnail printed the same lines again.
        reported = (
            [] if thumbnail else [("INFO", line) for line in info + choice_info] + [("WARNING", w) for w in warnings]
        )
        for kind, line in reported:
            if line not in said:
                said.add(line)
                self.report({kind}, line)
        layer = result.layers[0]  # the view layer's own: the result was begun for it alone
        combined = layer.passes["Combined"]
        width, height = core_scene.camera.width, core_scene.camera.height
        region = (0, 0, width, height) if thumbnail else region
        pixels = region_pixels(region, width, height)

        def shown(film):  # the pass's pixels as the result takes them
            rgba = film.rgba()
            if thumbnail and (width, height) != tuple(asked):
                return _region_rows(_resized(rgba, *asked), (0, 0, *asked))
            return _region_rows(rgba, region)

        remaining = RemainingTime(settings.samples)

        def status():
            self.update_stats(
                "", status_line(remaining.passes, settings.samples, remaining.seconds(), core_scene.mesh.triangle_count)
            )

        def progress(film, done, total):
            combined.rect.foreach_set(shown(film))
            self.update_result(result)
            remaining.pass_done(done)
            status()
            return not self.test_break()

        def chunk_progress(fraction):
            self.update_progress(fraction)
            status()  # the remaining time counts down between passes

        # Esc ends the render within a bounce (test_break, polled on this thread while chunks are traced), and
        # what it rendered stays in the result, whichever mode it was in. The progress bar and the remaining time
        # move with each chunk (a 4K pass is 64 of them), the image and the sample count with each pass.
        calls = dict(progress=progress, stop=self.test_break, chunk_progress=chunk_progress, pixels=pixels)
        self.update_stats("", "Preparing materials")  # a new stack's calibration: about a second, Esc heard
        try:
            try:
                film, stats = render(core_scene, settings, **calls)
            except (RuntimeError, OSError) as e:
                if settings.mode != "neural":
                    raise
                if self.test_break():  # Esc came too: nothing to fall back for
                    self.update_stats("", "Cancelled")
                    return
                # The neural runtime failed (a broken model file, say): the reference still renders, from the stacks
                # as exported (the decoder choice made neural materials of them, which render neural in any mode)
                self.report({"WARNING"}, f"neural evaluation failed ({_failure(e)}); rendering in reference mode")
                remaining = RemainingTime(settings.samples)  # the fallback's own passes
                core_scene.materials = exported
                film, stats = render(core_scene, replace(settings, mode="reference"), **calls)
        except Cancelled as c:
            film, stats = c.film, c.stats
        self.update_stats("", render_summary(stats, decoder_seconds))
        combined.rect.foreach_set(shown(film))
        if not thumbnail:
            _write_feature_passes(layer.passes, film, region, core_scene.camera)

    # ------------------------------------------------------------------ 3D viewport (Rendered mode)

    def _view_scene(self, context, depsgraph, updates=None):
        """The viewport's core scene and settings. ``updates``: the depsgraph's updates (default
        ``depsgraph.updates``, which Blender fills during ``view_update`` only). The world is exported again only
        when they name a world, an image or the scene: each edit elsewhere re-read and re-tabulated the sky, seconds
        for an 8K image at every tick of a slider."""
        region = context.region
        kept = getattr(self, "_view_world", None)
        updates = depsgraph.updates if updates is None else updates
        # the world exported (its identity; an image sequence's sky changes with the frame, which names no update)
        world = depsgraph.scene.world
        key = (
            getattr(world, "session_uid", None),
            depsgraph.scene.frame_current if _world_reads_a_sequence(world) else None,
        )
        changed = (
            kept is None or kept[1] != key or any(isinstance(u.id, (bpy.types.World, bpy.types.Image)) for u in updates)
        )
        environment = scene_export.EXPORT_WORLD if changed else kept[0]
        self._view_geometry.forget(updates)
        info: list[str] = []
        core_scene, warnings = scene_export.export_scene(
            depsgraph, region.width, region.height, camera=_view_camera(context), info=info, environment=environment,
            kept=self._view_geometry,
        )  # fmt: skip
        self._view_world = (core_scene.environment, key)
        props = depsgraph.scene.neural_render
        try:
            warnings = warnings + props.assign_decoders(core_scene, info=info, viewport=True)
        except Exception as e:  # the default decoder, as for F12
            warnings.append(f"decoder choice failed ({_failure(e)}); layered materials use the default decoder")
        for kind, line in viewport_reports(info, warnings, self._view_info):
            self.report({kind}, line)
        return core_scene, props.to_core(scene=depsgraph.scene, viewport=True)

    def view_update(self, context, depsgraph):
        """An edit (stack, objects, lights, world) or the first draw: restart the progressive session. An update
        that names the scene alone, changing nothing it renders (a selection, another active object), leaves it
        rendering: each click threw the accumulated samples away and exported the scene again (1.0-1.4 s with a
        500,000-triangle mesh under a 4K sky)."""
        state = _scene_state(depsgraph)
        vp = self._viewport
        if (
            vp is not None
            and vp.session is not None
            and vp.key == _view_key(context)
            and vp.settings_key == settings_key(depsgraph.scene)
            and getattr(self, "_view_state", None) == state
            and all(_names_the_scene_alone(u) for u in depsgraph.updates)
        ):
            return
        self._view_state = state
        try:
            core_scene, settings = self._view_scene(context, depsgraph)
        except Exception as e:
            self.report({"ERROR"}, _failure(e))
            return
        _warn_orthographic(self, context)
        if self._viewport is None or self._viewport.session is None:  # none yet, or closed (a file's load began)
            self._viewport = _Viewport(self, settings)
        self._viewport.settings_key = settings_key(depsgraph.scene)
        self._viewport.restart(core_scene, settings, _view_key(context))

    def view_draw(self, context, depsgraph):
        """Draw the newest image; a moved view (navigation does not call view_update) restarts: from the new
        camera alone when the region kept its size (nothing exported again), else as after an edit."""
        key, vp = _view_key(context), self._viewport
        if vp is None or vp.session is None:  # none yet, or closed (a file's load began, and failed)
            self.view_update(context, depsgraph)
        elif vp.settings_key is not None and vp.settings_key != settings_key(depsgraph.scene):
            # the engine's own settings (samples, bounces, decoder...) name no depsgraph update: read at each draw
            self.view_update(context, depsgraph)
        elif vp.key is not None and vp.key != key and vp.key[2:] == key[2:]:
            _warn_orthographic(self, context)  # Numpad 5 in Rendered mode: a moved view, no edit
            try:
                vp.move_camera(_view_camera(context), key)
            except Exception as e:
                self.report({"ERROR"}, _failure(e))
        elif vp.key != key:
            self.view_update(context, depsgraph)
        if self._viewport is not None and self._viewport.session is not None:
            self._viewport.draw(self, depsgraph.scene)


_panels: list = []


def register() -> None:
    # The renderer's compiled loops: compiled (first run after installing, ~10 s) or loaded from
    # their disk cache on a background thread, so that the first render does not wait for them.
    warm_up.warm_up_in_background()
    render_properties.register()
    bpy.utils.register_class(NeuralLayeredRenderEngine)
    for panel in _compatible_panels():
        panel.COMPAT_ENGINES.add(ENGINE_ID)
        _panels.append(panel)
    render_operators.register()
    render_ui.register()
    if _forget_textures not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_forget_textures)
    if _close_viewports_on_load not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_close_viewports_on_load)


@bpy.app.handlers.persistent
def _close_viewports_on_load(*_args) -> None:
    """Another file is opening: the viewports' sessions of this one go, with their threads and buffers (each load
    left one rendering on, and 133 MB of buffers at 1280 x 720)."""
    close_viewports()


@bpy.app.handlers.persistent
def _forget_textures(*_args) -> None:
    """Another file was opened: the latent textures the last one's exports kept go."""
    scene_export.forget_textures()


def close_viewports() -> None:
    """Close every viewport session still open, with its timer (the add-on is going: nothing will draw them)."""
    for view in list(_OPEN_VIEWPORTS):
        view.close()
        if bpy.app.timers.is_registered(view.timer):
            bpy.app.timers.unregister(view.timer)


def unregister() -> None:
    close_viewports()
    if _forget_textures in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_forget_textures)
    if _close_viewports_on_load in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_close_viewports_on_load)
    scene_export.forget_textures()
    warm_up.wait_for_background()
    render_ui.unregister()
    render_operators.unregister()
    for panel in _panels:
        panel.COMPAT_ENGINES.discard(ENGINE_ID)
    _panels.clear()
    if getattr(NeuralLayeredRenderEngine, "is_registered", False):
        bpy.utils.unregister_class(NeuralLayeredRenderEngine)
    render_properties.unregister()

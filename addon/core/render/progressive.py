"""Progressive rendering for an interactive view: a first image fast, then refinement, restarted
on every edit.

A :class:`ProgressiveSession` renders on a background thread: first images of one sample per pixel at
reduced resolutions (:func:`preview_divisors`: the first of at most :data:`PREVIEW_PIXELS` pixels whatever the
viewport's size, each next one twice as large on each side, the last ``preview_divisor`` times smaller than the
view; and one more at half the view's resolution where a full pass is predicted to take longer than
:data:`HALF_IMAGE_SECONDS`), so that the first image of an edit arrives in a fraction of a full pass; then
passes of one sample per pixel at full resolution, accumulated into one film until ``settings.samples`` passes.
``restart(scene)`` (after an edit: stack, camera, objects) drops the old work and starts again; the old render
stops within a bounce (``render``'s ``stop`` event, which each generation has its own of), not at the end of its
pass. The full-resolution accumulation is the offline render of the same settings: the same passes with the
same random numbers (``render(..., film=...)``).

The viewport glue (``addon/blender/engine.py``) calls ``restart`` from ``view_update`` (an edit), ``move_camera``
when only the view moved (navigation: the scene is not exported again), and draws
:meth:`ProgressiveSession.latest` from ``view_draw``.
"""

from __future__ import annotations

import copy
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from ..neural import session
from ..threads import map_on_threads
from .film import Film
from .integrator import Cancelled, RenderSettings, render
from .materials import resolve_all
from .scene import Camera, Scene
from .scratch import ScratchPool


@dataclass
class ViewImage:
    """The newest image of a session: linear RGBA (H, W, 4) float32 (row 0 at the top), the
    samples per pixel in it, whether it is the reduced-resolution first image, and the session's
    generation (one per restart)."""

    rgba: np.ndarray
    samples: int
    reduced: bool
    generation: int


PREVIEW_PIXELS = 64 * 64  # the first image's pixels at most (Cycles' viewport starts at 64 pixels a side too)
# A view whose full-resolution pass is predicted to take longer than this gets one more reduced image, at half its
# resolution on each side, before that pass (as Cycles' viewport halves its pixel size down to 1): a quarter of a
# pass more for a sharp image that much sooner.
HALF_IMAGE_SECONDS = 0.5


def preview_divisors(width: int, height: int, divisor: int, pixels: int = PREVIEW_PIXELS) -> list[int]:
    """How many times smaller on each side than a ``width`` x ``height`` view the reduced images of a generation
    are, first to last: the first ``divisor`` times smaller, or (doubling it) as much more as keeps it within
    ``pixels``; each next one half as much, down to ``divisor``; none for a ``divisor`` of 1. A 320 x 180 view
    gets one image (80 x 45 at the divisor 4), a 1280 x 720 one three (80 x 45, 160 x 90, 320 x 180), where its
    first image at 320 x 180 took 0.08-0.09 s."""
    if divisor <= 1:
        return []
    first = divisor
    while max(1, width // first) * max(1, height // first) > max(1, pixels):  # sides of 1 pixel at least
        first *= 2
    out = []
    while first >= divisor:
        out.append(first)
        first //= 2
    return out


def predicted_pass_seconds(
    pixels: int, pass_seconds_per_pixel: float | None, reduced: list[tuple[int, float]]
) -> float | None:
    """Seconds a full-resolution pass of ``pixels`` pixels is predicted to take: from the seconds a pixel of the
    session's last full pass or, before any, from the seconds per pixel more of the last two ``reduced`` images
    ((pixels, seconds) each: a small image's time is mostly its render's fixed costs, which the difference
    leaves out); None with neither."""
    if pass_seconds_per_pixel is not None:
        return pass_seconds_per_pixel * pixels
    if len(reduced) >= 2:
        (pa, ta), (pb, tb) = reduced[-2:]
        return max(0.0, tb - ta) / max(1, pb - pa) * pixels
    return None


def reduced_camera(camera: Camera, divisor: int) -> Camera:
    """The same view with ``divisor`` times fewer pixels on each side (at least 1 x 1)."""
    return Camera(
        camera.matrix,
        max(1, camera.width // divisor),
        max(1, camera.height // divisor),
        camera.tan_half_fov,
        camera.shift,
        camera.clip,
    )


class ProgressiveSession:
    """Renders the latest scene given to :meth:`restart` on one background thread.

    ``on_image(image)`` (optional) is called from that thread after every new image, e.g. to ask
    the viewport for a redraw. Errors of a render are kept in ``error`` (and passed to
    ``on_error``), never raised on the background thread unseen. A view whose full-resolution pass is predicted to
    take longer than ``half_image_seconds`` gets a reduced image at half its resolution before that pass (0: every
    view, ``inf``: none).
    """

    def __init__(
        self,
        settings: RenderSettings,
        preview_divisor: int = 4,
        on_image=None,
        on_error=None,
        half_image_seconds: float = HALF_IMAGE_SECONDS,
    ):
        if int(preview_divisor) < 1:
            raise ValueError(f"preview_divisor must be >= 1, got {preview_divisor!r}")
        if not half_image_seconds >= 0.0:
            raise ValueError(f"half_image_seconds must be >= 0, got {half_image_seconds!r}")
        self.settings = settings
        self.preview_divisor = int(preview_divisor)
        self.half_image_seconds = float(half_image_seconds)
        # seconds a pixel of the last full-resolution pass took (its render's setup included): what the next
        # generations predict their passes from; None before the first one
        self.pass_seconds_per_pixel: float | None = None
        self.on_image, self.on_error = on_image, on_error
        self.error: Exception | None = None
        # the last calibration that failed (the view renders that material uncalibrated): for a warning
        self.calibration_failure: Exception | None = None
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._scene: Scene | None = None
        self._last: Scene | None = None  # the scene of the last restart (its materials resolved once rendered)
        self._generation = 0
        self._stop = threading.Event()  # set when the generation rendering ends (``render``'s ``stop``)
        self._image: ViewImage | None = None
        self._closed = False
        self._busy = False
        # The arrays the renders' bounces write (``render``'s ``scratches``), kept from one render to the next, so
        # that a view change or an edit does not fault them in again: 104 MB per render thread at 1920x1080 and up
        # (a chunk of 131,072 paths), less for smaller views; freed by ``close``.
        self.scratches = ScratchPool()
        self._thread = threading.Thread(target=self._run, name="progressive-render", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ control (any thread)

    def restart(self, scene: Scene, settings: RenderSettings | None = None) -> int:
        """Render ``scene`` from scratch (the running render stops within a bounce); returns the
        new generation."""
        with self._lock:
            self._last = scene
            return self._start(scene, settings)

    def move_camera(self, camera: Camera) -> int:
        """Render the scene of the last :meth:`restart` again from ``camera``, with the same settings (the
        viewport's navigation: nothing else changed, so nothing is exported or resolved again; its materials
        as the last generation resolved them); returns the new generation."""
        with self._lock:
            if self._last is None:
                raise ValueError("move_camera needs a scene: call restart first")
            return self._start(replace(self._last, camera=camera), None)

    def _start(self, scene: Scene, settings: RenderSettings | None) -> int:
        """A new generation rendering ``scene`` (the lock held)."""
        self._scene = scene
        if settings is not None:
            self.settings = settings
        self._next_generation()
        self.error = None
        return self._generation

    def _next_generation(self) -> None:
        """End the generation rendering (its render stops within a bounce) and start the next (the lock held)."""
        self._stop.set()
        self._stop = threading.Event()
        self._generation += 1
        self._wake.notify_all()

    def cancel(self) -> None:
        """Stop rendering (within a bounce); the newest image stays available."""
        with self._lock:
            self._scene = None
            self._next_generation()

    def close(self, timeout: float | None = 10.0) -> None:
        """Cancel and end the background thread."""
        with self._lock:
            self._closed = True
            self._scene = None
            self._next_generation()
        self._thread.join(timeout)
        self.scratches = ScratchPool()  # the kept arrays go (a render still stopping holds its own until it ends)

    def latest(self) -> ViewImage | None:
        with self._lock:
            return self._image

    def wait(self, samples: int | None = None, timeout: float = 60.0) -> ViewImage | None:
        """Block until the current generation has ``samples`` full-resolution samples per pixel
        (default: all of them) or has stopped; returns the newest image (for tests and scripts)."""
        import time

        end = time.monotonic() + timeout
        with self._lock:
            while time.monotonic() < end:
                img, gen = self._image, self._generation
                want = self.settings.samples if samples is None else samples
                done = img is not None and img.generation == gen and not img.reduced and img.samples >= want
                if done or self.error is not None or (self._scene is None and not self._busy):
                    return img
                self._wake.wait(timeout=max(0.0, min(0.05, end - time.monotonic())))
            return self._image

    @property
    def idle(self) -> bool:
        with self._lock:
            return not self._busy

    # ------------------------------------------------------------------ the background thread

    def _current(self, generation: int) -> bool:
        with self._lock:
            return generation == self._generation and not self._closed

    def _publish(self, film: Film, generation: int, reduced: bool) -> bool:
        image = ViewImage(film.rgba(), film.passes, reduced, generation)
        with self._lock:
            if generation != self._generation:
                return False
            self._image = image
            self._wake.notify_all()
        if self.on_image is not None:
            self.on_image(image)
        return self._current(generation)

    def _run(self) -> None:
        while True:
            with self._lock:
                while self._scene is None and not self._closed:
                    self._busy = False
                    self._wake.notify_all()
                    self._wake.wait()
                if self._closed:
                    self._busy = False
                    self._wake.notify_all()
                    return
                scene, settings, generation, stop = self._scene, self.settings, self._generation, self._stop
                self._busy = True
            try:
                self._render_generation(scene, settings, generation, stop)
            except Exception as e:  # kept and reported, never lost on this thread
                with self._lock:
                    if generation == self._generation:
                        self.error = e
                if self.on_error is not None:
                    self.on_error(e)
            with self._lock:
                if generation == self._generation:
                    self._scene = None  # done: wait for the next restart

    def _calibrate_pending(self, scene: Scene, generation: int, settings: RenderSettings) -> Scene | None:
        """The scene with the calibrations its materials left out (``calibrate="cached"``, the viewport's: no
        reference walks before the first images) made now, after the first full-resolution pass, so that the
        accumulation that follows renders as F12 does (``NeuralMaterial.calibrated``; 0.4 s per changed stack
        with tiny, about 2.5 s with paper, the first time a stack is rendered). A restart that comes meanwhile stops
        the calibration at its next step (``calibrate.STEP_ROWS`` decoded rows, or an event of the reference walks):
        the new scene never waits for the old one's walks. None when a restart came."""
        materials = list(scene.materials)
        pending = [i for i, m in enumerate(materials) if getattr(m, "uncalibrated_stack", None) is not None]

        def step():
            if not self._current(generation):
                raise Cancelled("a restart came during a calibration")

        def calibrated(material):
            step()
            try:
                return material.calibrated(step)
            except (ValueError, ArithmeticError, RuntimeError) as e:  # the view goes on, uncalibrated, says so
                self.calibration_failure = e
                material = copy.copy(material)
                material.uncalibrated_stack = None  # not tried again by camera moves
                return material

        # Side by side on the render's threads (the view waits on them), each stack seeded as alone: with the five
        # stacks of the demo scene to calibrate, the first calibrated pass came 1.70-1.80 s after the edit where it
        # came 2.10-2.17 s after it one stack at a time (320x180).
        try:  # after a restart, no stack not yet started is calibrated; on the generation's threads, its networks too
            with session.threads_in_force(settings.thread_count):
                made = map_on_threads(calibrated, [materials[i] for i in pending], settings.thread_count, "calibrate")
        except Cancelled:
            return None
        for i, material in zip(pending, made, strict=True):
            materials[i] = material
        if not pending:
            return scene
        with self._lock:
            if generation != self._generation:
                return None
            if self._last is not None:  # camera moves keep the calibrated materials
                self._last = replace(self._last, materials=materials)
        return replace(scene, materials=materials)

    def _render_reduced(self, scene: Scene, settings: RenderSettings, generation: int, stop: threading.Event) -> bool:
        """A generation's reduced images (one sample per pixel each): those of :func:`preview_divisors`, then one at
        half the view's resolution where :func:`predicted_pass_seconds` exceeds ``half_image_seconds`` (or that
        is 0). False if stopped."""
        cam = scene.camera
        half = [2] if self.preview_divisor > 2 and min(cam.width, cam.height) >= 2 else []
        timed = []  # (pixels, seconds) of each reduced image
        for divisor in preview_divisors(cam.width, cam.height, self.preview_divisor) + half:
            if half and divisor == 2 and self.half_image_seconds > 0.0:
                predicted = predicted_pass_seconds(cam.width * cam.height, self.pass_seconds_per_pixel, timed)
                if predicted is None or predicted <= self.half_image_seconds:
                    break
            small = replace(scene, camera=reduced_camera(cam, divisor))
            t0 = time.perf_counter()
            try:
                render(
                    small,
                    replace(settings, samples=1),
                    progress=lambda film, done, total: self._publish(film, generation, True),
                    stop=stop,
                    scratches=self.scratches,
                )
            except Cancelled:
                return False
            timed.append((small.camera.width * small.camera.height, time.perf_counter() - t0))
        return True

    def _render_generation(
        self, scene: Scene, settings: RenderSettings, generation: int, stop: threading.Event
    ) -> None:
        def timed_progress():
            """The full-resolution passes' progress, which times the first pass for the next generations."""
            t0, pixels = time.perf_counter(), scene.camera.width * scene.camera.height

            def on_pass(film, done, total):
                if done == 1:
                    self.pass_seconds_per_pixel = (time.perf_counter() - t0) / pixels
                return self._publish(film, generation, False)

            return on_pass

        # Materials resolved (stacks encoded, calibrated as the settings say, as ``render`` would) once for both
        # renders of the generation, and kept for the camera moves that follow.
        materials = resolve_all(
            scene.materials, settings.mode, settings.reference_walks, settings.calibrate, settings.thread_count
        )
        scene = replace(scene, materials=materials)
        with self._lock:
            if generation == self._generation and self._last is not None:
                self._last = replace(self._last, materials=materials)

        if not self._render_reduced(scene, settings, generation, stop):
            return
        if not self._current(generation):
            return
        if any(getattr(m, "uncalibrated_stack", None) is not None for m in scene.materials):
            # One full-resolution pass without the missing calibrations first: while a slider is dragged the next
            # edit comes before it ends, so the viewport never waits for reference walks; once the view rests,
            # the walks run and the accumulation starts again calibrated.
            try:
                render(
                    scene, replace(settings, samples=1), progress=timed_progress(), stop=stop, scratches=self.scratches
                )
            except Cancelled:
                return
            scene = self._calibrate_pending(scene, generation, settings)
            if scene is None:
                return
        try:
            render(scene, settings, progress=timed_progress(), stop=stop, scratches=self.scratches)
        except Cancelled:
            return

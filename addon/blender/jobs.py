"""Long operations: a core computation on a worker thread, driven by a modal operator.

The work function is plain core code (numpy / ONNX Runtime release the GIL) that takes a
``progress(fraction)`` callback; it never touches ``bpy``. The operator reads its inputs from
Blender before starting and writes the result back on the main thread when the job is done.
In background mode (no event loop, timers never fire) operators call the work directly instead.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

from ..core.preview import Cancelled


class Job:
    def __init__(self, work: Callable[[Callable[[float], None]], Any]):
        self._work = work
        self._cancel = threading.Event()
        self.fraction = 0.0
        self.result: Any = None
        self.error: BaseException | None = None
        self.cancelled = False
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "Job":
        self._thread.start()
        return self

    def _progress(self, fraction: float) -> None:
        self.fraction = float(fraction)
        if self._cancel.is_set():
            raise Cancelled()

    def _run(self) -> None:
        try:
            self.result = self._work(self._progress)
        except Cancelled:
            self.cancelled = True
        except BaseException as e:  # reported by the operator on the main thread
            self.error = e

    def cancel(self) -> None:
        self._cancel.set()

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)


class ModalJob:
    """Mixin for operators that run a Job: progress bar, status text, Esc to cancel.

    ``start_job(context, work)`` from ``invoke``; when the job ends, ``modal`` cleans up, reports
    a cancellation itself and hands a finished or failed job to ``job_done(context, job)``.
    """

    _job = None
    _timer = None

    def start_job(self, context, work, interval: float = 0.1) -> set:
        self._job = Job(work).start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(interval, window=context.window)
        wm.progress_begin(0, 100)
        context.workspace.status_text_set(f"{self.bl_label}: Esc to cancel")
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _cleanup(self, context) -> None:
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        context.workspace.status_text_set(None)

    def job_done(self, context, job: Job) -> set:
        raise NotImplementedError(f"{type(self).__name__} must handle the result of its job")

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC":
            job.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        context.window_manager.progress_update(int(100 * job.fraction))
        if not job.done:
            return {"RUNNING_MODAL"}
        self._cleanup(context)
        if job.cancelled:
            self.report({"INFO"}, f"{self.bl_label} cancelled")
            return {"CANCELLED"}
        return self.job_done(context, job)

    def cancel(self, context):
        if self._job is not None:
            self._job.cancel()
        self._cleanup(context)

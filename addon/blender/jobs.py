"""Long operations: a core computation on a worker thread, driven by a modal operator.

The work function is plain core code (numpy / ONNX Runtime release the GIL) that takes a
``progress(fraction)`` callback; it never touches ``bpy``. The operator reads its inputs from
Blender before starting and writes the result back on the main thread when the job is done.
In background mode (no event loop, timers never fire) operators call the work directly instead.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

from addon.core.preview import Cancelled


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

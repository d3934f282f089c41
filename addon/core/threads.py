"""Independent pieces of work side by side on a few threads: a scene's materials, a texture's clusters, the
stacks a viewport calibrates. Each piece is seeded on its own, so what they make does not depend on the thread
count. Their decoder batches release the GIL, their reference walks only in their larger array operations: on two
cores such calibrations took 20-25% less time side by side, where the main job's reference lobes, walks alone,
took longer on threads and run in processes instead (``bake/demo.py``)."""

from __future__ import annotations

import contextvars
import os
from concurrent.futures import FIRST_EXCEPTION, Future, ThreadPoolExecutor, wait
from typing import Callable, Iterable, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def thread_count(threads: int) -> int:
    """The threads a setting means: ``threads``, or one per CPU core for 0 (the renderer's and the bakes' default,
    and Blender's *Auto*)."""
    return int(threads) or (os.cpu_count() or 1)


def submit_in_context(pool: ThreadPoolExecutor, fn: Callable[..., R], *args) -> Future:
    """``pool.submit(fn, *args)``, run in a copy of the calling thread's context: what the caller has in force
    there (``neural.session.threads_in_force``'s thread count) holds for the work too."""
    return pool.submit(contextvars.copy_context().run, fn, *args)


def map_on_threads(
    fn: Callable[[T], R],
    items: Iterable[T],
    threads: int,
    name: str,
    check: Callable[[], object] | None = None,
    check_seconds: float = 0.1,
) -> list[R]:
    """``[fn(x) for x in items]``, in order, on up to ``threads`` threads (named ``name``; inline with one thread or
    one item), each in a copy of the calling context (``submit_in_context``). The first error is raised once the
    pieces running have ended, and the pieces not started are not run (a cancel or a restart raised by one of them
    stops the rest at their next step).

    ``check`` (optional) is called on the calling thread every ``check_seconds`` while it waits for the pieces: what
    only that thread may ask (Blender's ``RenderEngine.test_break``). What it raises is raised here, once the pieces
    running have ended, so it should also make them stop at their next step (an event they read)."""
    items = list(items)
    workers = max(1, min(int(threads), len(items)))
    if workers == 1:
        return [fn(x) for x in items]
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name)
    try:
        futures = [submit_in_context(pool, fn, x) for x in items]
        while check is not None:  # until all are done or one failed (then the rest not started are not run)
            done, pending = wait(futures, timeout=check_seconds, return_when=FIRST_EXCEPTION)
            if not pending or any(f.exception() is not None for f in done):
                break
            check()
        return [f.result() for f in futures]
    finally:
        pool.shutdown(wait=True, cancel_futures=True)

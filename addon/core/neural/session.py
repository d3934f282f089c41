"""ONNX Runtime sessions run over row chunks on a pool of threads.

Our networks are small (the tiny decoder has 32 channels): on a large batch, ONNX Runtime's own
intra-op threads split each operator, and every intermediate tensor (rows x 32 floats) streams
through memory between operators. Cutting the batch into chunks of a few thousand rows keeps the
intermediates in cache, and running the chunks of one batch on ``threads`` Python threads, each
calling a single-threaded session (``InferenceSession.run`` releases the GIL and is safe to call
concurrently), keeps every core busy on whole graphs. On the 2-core development machine this
about doubled the decoders' throughput against one 2-thread call on the whole batch
(``benchmarks/bench_decoders.py`` measures both).
"""

from __future__ import annotations

import contextvars
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np

T = TypeVar("T")
_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()
_CLOCK = threading.local()
# The thread counts in force (``threads_in_force``), innermost last: of the calling context, so that two renders or
# bakes at once each keep their own (one list for the whole process let each take the other's, and a block's end
# remove the other's count). Threads a render or a bake starts run in a copy of its context
# (``threads.submit_in_context``).
_THREADS: contextvars.ContextVar[tuple[int, ...]] = contextvars.ContextVar("threads_in_force", default=())


@contextmanager
def threads_in_force(threads: int):
    """Within the block, every session runs its chunks on ``threads`` threads, whatever count it
    was made with: the bakes put the scene's render thread setting (or every core) in force for their
    work, and the renderer that count or, when every core traces a chunk of paths, 1 (each chunk's batches
    on its own thread), so no constant decides how many cores the networks use."""
    if isinstance(threads, bool) or int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads!r}")
    token = _THREADS.set((*_THREADS.get(), int(threads)))
    try:
        yield
    finally:
        _THREADS.reset(token)


def threads_now() -> int | None:
    """The thread count in force for the calling context (``threads_in_force``), or None."""
    counts = _THREADS.get()
    return counts[-1] if counts else None


def seconds_on_this_thread() -> float:
    """Wall seconds the calling thread has spent waiting on network batches (``ChunkedSession.map``
    and ``run``) so far: the difference around a piece of work is its time in the networks."""
    return getattr(_CLOCK, "seconds", 0.0)


def _pool(threads: int) -> ThreadPoolExecutor:
    with _POOLS_LOCK:  # one pool per count, whichever thread asks first
        if threads not in _POOLS:
            _POOLS[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="onnx")
        return _POOLS[threads]


def shutdown_pools() -> None:
    """End the networks' thread pools (``ChunkedSession``'s: one per thread count, kept for the process). A later
    batch makes a new one; the add-on's unregister ends them, which stayed idle after it, two threads more at each
    disable and enable."""
    with _POOLS_LOCK:
        pools = list(_POOLS.values())
        _POOLS.clear()
    for pool in pools:
        pool.shutdown(wait=False, cancel_futures=True)


def session_options():
    """The options every session is made with: one intra-op and one inter-op thread (the
    parallelism is over chunks, on the pool), every graph optimisation ONNX Runtime has."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return so


class ChunkedSession:
    """One ONNX model as a single-threaded ONNX Runtime session, run over chunks of ``chunk``
    rows on ``threads`` threads (or the count :func:`threads_in_force` puts in force).

    ``run(outputs, rows, shared)``: ``rows`` are inputs whose first axis is the batch (cut into
    chunks), ``shared`` are inputs given whole to every chunk (a material's latent, say). Returns
    the outputs with the chunks joined along the first axis, as ONNX Runtime's ``run`` would.
    """

    def __init__(self, path: Path | str, threads: int = 2, chunk: int = 4096):
        import onnxruntime as ort

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(
                f"neural model file {path} is missing; export it with `python -m onnx_export.export` "
                f"(available here: {sorted(p.name for p in path.parent.glob('*.onnx'))})"
            )
        if int(threads) < 1:
            raise ValueError(f"threads must be >= 1, got {threads!r}")
        if int(chunk) < 1:
            raise ValueError(f"chunk must be >= 1, got {chunk!r}")
        self.path, self.threads, self.chunk = path, int(threads), int(chunk)
        self._session = ort.InferenceSession(
            str(path), sess_options=session_options(), providers=["CPUExecutionProvider"]
        )

    def run_once(self, outputs: list[str], feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """One ONNX Runtime call on the whole of ``feeds`` (on the calling thread)."""
        return self._session.run(outputs, feeds)

    def map(self, fn: Callable[[slice], T], n: int) -> list[T]:
        """``fn(rows)`` for each chunk ``rows`` (a slice) of ``range(n)``, on the pool's threads
        (inline with one thread or one chunk); the results in chunk order."""
        slices = [slice(s, min(n, s + self.chunk)) for s in range(0, n, self.chunk)] or [slice(0, 0)]
        threads = threads_now() or self.threads
        t0 = time.perf_counter()
        try:
            if threads == 1 or len(slices) == 1:
                return [fn(s) for s in slices]
            return list(_pool(threads).map(fn, slices))
        finally:
            _CLOCK.seconds = seconds_on_this_thread() + time.perf_counter() - t0

    def run(
        self, outputs: list[str], rows: dict[str, np.ndarray], shared: dict[str, np.ndarray] | None = None
    ) -> list[np.ndarray]:
        shared = shared or {}
        sizes = {k: v.shape[0] for k, v in rows.items()}
        n = next(iter(sizes.values()), 0)
        if any(s != n for s in sizes.values()):
            raise ValueError(f"row inputs disagree on the batch size: {sizes}")
        parts = self.map(lambda sl: self._session.run(outputs, {**{k: v[sl] for k, v in rows.items()}, **shared}), n)
        if len(parts) == 1:
            return parts[0]
        return [np.concatenate([p[i] for p in parts]) for i in range(len(outputs))]

"""ChunkedSession: chunks on a thread pool, the thread count in force, the network clock."""

import threading

import numpy as np
import pytest

from addon.core.neural import session
from addon.core.neural.models import MODEL_DIR
from addon.core.neural.session import ChunkedSession, seconds_on_this_thread, threads_in_force


def chunk_threads(s: ChunkedSession, n: int) -> set[str]:
    names = []

    def fn(rows):
        names.append(threading.current_thread().name)
        return rows.stop - rows.start

    assert sum(s.map(fn, n)) == n
    return set(names)


def test_threads_in_force_decide_where_chunks_run():
    s = ChunkedSession(MODEL_DIR / "decoder_tiny_rgb.onnx", threads=2, chunk=10)
    with threads_in_force(1):
        assert chunk_threads(s, 100) == {threading.current_thread().name}
    with threads_in_force(3):
        assert all(name.startswith("onnx") for name in chunk_threads(s, 100))
        assert session._THREADS[-1] == 3
    assert not session._THREADS
    with pytest.raises(ValueError, match="threads must be >= 1"):
        with threads_in_force(0):
            pass


def test_network_clock_counts_time_in_batches_on_the_calling_thread():
    s = ChunkedSession(MODEL_DIR / "decoder_tiny_rgb.onnx", threads=1, chunk=4096)
    rng = np.random.default_rng(0)
    w = rng.normal(size=(5000, 3)).astype(np.float32)
    before = seconds_on_this_thread()
    (f,) = s.run(["f"], {"wi": w, "wo": w}, {"zc": np.zeros((1, 96), np.float32)})
    assert f.shape == (5000, 3) and seconds_on_this_thread() > before
    seen = []
    t = threading.Thread(target=lambda: seen.append(seconds_on_this_thread()))
    t.start()
    t.join()
    assert seen == [0.0]  # each thread has its own clock

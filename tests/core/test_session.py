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
        assert session.threads_now() == 3
    assert session.threads_now() is None
    with pytest.raises(ValueError, match="threads must be >= 1"):
        with threads_in_force(0):
            pass


def test_two_renders_at_once_keep_their_own_thread_counts_and_pass_them_to_their_threads():
    """The count in force is the calling context's: a viewport pass and a thumbnail at once each keep theirs (one
    list for the process let each take the other's, and the first to end removed the other's), and the threads a
    render starts (``threads.submit_in_context``) run with the render's."""
    from concurrent.futures import ThreadPoolExecutor

    from addon.core.threads import map_on_threads, submit_in_context

    entered, release = threading.Barrier(2), threading.Event()
    seen = {}

    def render(name, count):
        with threads_in_force(count):
            entered.wait(timeout=10)  # both blocks entered, the second after the first
            seen[name] = session.threads_now()
            if name == "first":
                release.wait(timeout=10)  # the second's block ends before the first reads again
                seen["first, after the second ended"] = session.threads_now()
            else:
                release.set()
            with ThreadPoolExecutor(1) as pool:
                seen[name + " on its pool"] = submit_in_context(pool, session.threads_now).result()
            seen[name + " on map_on_threads"] = set(map_on_threads(lambda _: session.threads_now(), range(3), 3, "t"))

    threads = [threading.Thread(target=render, args=a) for a in (("first", 1), ("second", 4))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert seen == {
        "first": 1,
        "second": 4,
        "first, after the second ended": 1,
        "first on its pool": 1,
        "second on its pool": 4,
        "first on map_on_threads": {1},
        "second on map_on_threads": {4},
    }


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


def test_release_ends_the_networks_threads_and_a_later_batch_makes_them_again():
    """``addon.core.release`` (the add-on's unregister) ends the networks' pools and forgets the loaded models: a
    disabled add-on kept two idle threads more at each disable and enable, and its model sets."""
    import time

    from addon.core import release
    from addon.core.neural import load_models, models

    s = ChunkedSession(MODEL_DIR / "decoder_tiny_rgb.onnx", threads=2, chunk=10)
    with threads_in_force(2):
        assert all(name.startswith("onnx") for name in chunk_threads(s, 100))
    load_models("tiny")
    assert models._CACHE and session._POOLS
    release()
    assert not models._CACHE and not session._POOLS
    end = time.monotonic() + 10
    while any(t.name.startswith("onnx") for t in threading.enumerate()) and time.monotonic() < end:
        time.sleep(0.01)
    assert not any(t.name.startswith("onnx") for t in threading.enumerate())
    with threads_in_force(2):  # a later batch makes its pool again
        assert all(name.startswith("onnx") for name in chunk_threads(s, 100))


def test_a_failed_piece_stops_the_pieces_not_started_while_the_caller_polls():
    """``map_on_threads`` with ``check`` (a render's stop, polled while the materials calibrate) waited for every
    piece before it raised the first error: one material failing calibrated all the others first."""
    import time

    from addon.core.threads import map_on_threads

    ran = []

    def piece(i):
        ran.append(i)
        if i == 0:
            raise ValueError("the first material fails")
        time.sleep(0.1)
        return i

    with pytest.raises(ValueError, match="first material"):
        map_on_threads(piece, range(8), 2, "test", check=lambda: None, check_seconds=0.01)
    assert len(ran) < 8, ran

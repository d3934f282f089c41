"""Arrays a chunk's bounces write into again and again, instead of new ones each bounce.

A bounce of the wavefront renderer writes its rays, hits, light samples, random numbers and paths into arrays with a
row per live path: 797 bytes a path, 104 MB for a chunk of 131,072 paths. Made anew each bounce, they went back to
the allocator after it, which gave memory of that size back to the kernel and faulted it in again on the next
bounce: 190-240 k page faults in each 480x270 x 16 spp render of the demo scene on one thread, in a process whose
first render was a small one (2.85-2.92 s; 2.52-2.56 s with the arrays kept; glibc's thresholds adapt to the sizes
freed first, so how many depends on what the process did before). Under jemalloc, the malloc Blender's Linux builds
link, two-thread renders were 1.52-1.62 s against 1.38-1.40 s kept (docs/render_speed.md, "The allocator"). A chunk
takes one :class:`Scratch` from its render's :class:`ScratchPool` and gives it back when its paths are done, so that
each buffer is faulted in once a render.
"""

from __future__ import annotations

import threading

import numpy as np


class Scratch:
    """Named groups of buffers that only grow: ``arrays(name, n, layout)`` gives views of the first ``n`` rows.

    The views of a name are overwritten by its next ``arrays`` call: a caller keeps a name's arrays only as
    long as it does not ask for that name again (the integrator's paths alternate between two names)."""

    def __init__(self, rows: int = 0):
        self.rows = int(rows)  # the fewest rows a buffer is made with: a chunk's paths, which bound every group
        self._groups: dict[str, tuple[np.ndarray, ...]] = {}
        self._layouts: dict[str, tuple] = {}

    def arrays(self, name: str, n: int, layout) -> tuple[np.ndarray, ...]:
        """``n`` rows of each array of ``layout`` (``kernels.SURFACE_HITS_OUT`` and the like: a (columns,
        dtype) pair per array, 0 columns for a flat one), C-contiguous views of the buffers of ``name``; the
        buffers are made with at least ``rows`` rows, and made again when shorter than ``n`` or of another layout
        (their old contents are not kept)."""
        n = int(n)
        if n < 0:
            raise ValueError(f"a row count is >= 0, got {n}")
        group = self._groups.get(name)
        if group is None or len(group[0]) < n or self._layouts[name] != layout:
            m = max(n, self.rows)
            group = tuple(np.empty((m, c) if c else m, dtype=dt) for c, dt in layout)
            self._groups[name], self._layouts[name] = group, layout
        return tuple(b[:n] for b in group)

    @property
    def nbytes(self) -> int:
        """Bytes its buffers hold."""
        return sum(b.nbytes for group in self._groups.values() for b in group)


class ScratchPool:
    """The :class:`Scratch` objects of a render, or of a viewport's renders: ``take(rows)`` one for a chunk of
    ``rows`` paths (a kept one when there is one, else a new one), ``give(s)`` it back when the chunk is done. As
    many are made as chunks are traced at once; their buffers go when the pool does: a render's own pool at its
    end, a viewport session's when it closes (``progressive.ProgressiveSession.scratches``)."""

    def __init__(self, rows: int = 0):
        self.rows = int(rows)  # each Scratch's (``Scratch.rows``)
        self._free: list[Scratch] = []
        self._lock = threading.Lock()
        self.made = 0

    def take(self, rows: int = 0) -> Scratch:
        """A Scratch whose buffers are made with at least ``rows`` rows (and the pool's ``rows``)."""
        with self._lock:
            scratch = self._free.pop() if self._free else None
            if scratch is None:
                self.made += 1
        scratch = scratch or Scratch(self.rows)
        scratch.rows = max(scratch.rows, int(rows))
        return scratch

    def give(self, scratch: Scratch) -> None:
        with self._lock:
            self._free.append(scratch)

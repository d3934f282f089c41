"""How long a render has left: what F12's status line says beside its sample count."""

from __future__ import annotations

import time
from typing import Callable


class RemainingTime:
    """The seconds a render of ``samples`` passes has left, from the seconds its whole passes took.

    A pass's time is only known at its end: within a pass the chunks done are not a fair share of its work (the
    demo scene's sky rows trace about 20 times faster than its spheres' rows, and come first). So the estimate
    is made at each pass's end and counts down between them: after the first pass, that pass's seconds since the
    render started (the scene's setup and calibrations included: at most an overestimate); after later ones, the
    mean seconds of the passes since the first. None before the first pass ends.
    """

    def __init__(self, samples: int, clock: Callable[[], float] = time.perf_counter):
        if int(samples) < 1:
            raise ValueError(f"samples must be >= 1, got {samples!r}")
        self.samples, self.clock = int(samples), clock
        self.start = clock()
        self._first: float | None = None  # when the first pass ended
        self._last: tuple[int, float] | None = None  # (passes done, when the last of them ended)
        self._per_pass: float | None = None

    def pass_done(self, passes: int) -> None:
        """``passes`` passes are done, now."""
        now = self.clock()
        if self._first is None or passes <= 1:
            self._first = now
            self._per_pass = now - self.start
        else:
            self._per_pass = (now - self._first) / (passes - 1)
        self._last = (passes, now)

    @property
    def passes(self) -> int:
        """The passes done so far."""
        return 0 if self._last is None else self._last[0]

    def seconds(self) -> float | None:
        """Seconds left (0 at the end), None before the first pass ends."""
        if self._last is None:
            return None
        passes, at = self._last
        return max(0.0, self._per_pass * (self.samples - passes) - (self.clock() - at))


def format_duration(seconds: float) -> str:
    """``seconds`` as Blender writes times in its status line: MM:SS.hh, or HH:MM:SS.hh from an hour."""
    hundredths = int(round(max(0.0, seconds) * 100))
    minutes, rest = divmod(hundredths, 6000)
    hours, minutes = divmod(minutes, 60)
    clock = f"{minutes:02d}:{rest // 100:02d}.{rest % 100:02d}"
    return f"{hours:02d}:{clock}" if hours else clock

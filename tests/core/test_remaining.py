"""The time a render has left, as F12's status line says it."""

import pytest

from addon.core.render.remaining import RemainingTime, format_duration


class Clock:
    """A clock the test moves by hand."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_the_time_left_is_known_at_a_pass_end_and_counts_down_between():
    clock = Clock()
    left = RemainingTime(5, clock)
    assert left.seconds() is None and left.passes == 0  # within the first pass: its chunks are no fair share
    clock.now += 3.0  # the first pass, its setup included
    left.pass_done(1)
    assert left.seconds() == pytest.approx(4 * 3.0)
    clock.now += 1.0
    assert left.seconds() == pytest.approx(4 * 3.0 - 1.0)  # counts down between pass ends
    clock.now += 1.0  # the second pass took 2 s: the first one's setup is left out from here on
    left.pass_done(2)
    assert left.seconds() == pytest.approx(3 * 2.0)
    clock.now += 2.5
    left.pass_done(3)  # passes since the first: (2 + 2.5) / 2
    assert left.passes == 3
    assert left.seconds() == pytest.approx(2 * 2.25)
    clock.now += 100.0
    assert left.seconds() == 0.0  # late: never below 0
    left.pass_done(5)
    assert left.seconds() == 0.0
    with pytest.raises(ValueError, match="samples"):
        RemainingTime(0)


def test_times_are_written_as_blender_writes_them():
    assert format_duration(0.0) == "00:00.00"
    assert format_duration(42.333) == "00:42.33"
    assert format_duration(59.999) == "01:00.00"
    assert format_duration(3725.5) == "01:02:05.50"
    assert format_duration(-1.0) == "00:00.00"

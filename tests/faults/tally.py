"""Counts of what the reliability tests tried, for docs/reliability.md: property examples run per
test, and faults injected per kind. The table's command reads them after its pytest run."""

from __future__ import annotations

import os
from collections import Counter

EXAMPLES: Counter[str] = Counter()
FAULTS: Counter[str] = Counter()


def _test() -> str:
    return os.environ.get("PYTEST_CURRENT_TEST", "?").split(" ")[0].split("[")[0]


def example() -> None:
    """Call once per Hypothesis example (first line of the test body)."""
    EXAMPLES[_test()] += 1


def fault(kind: str) -> None:
    """Call once per fault injected (a signal sent, a file damaged)."""
    FAULTS[kind] += 1


def bounded(max_examples: int):
    """Hypothesis settings of the reliability properties: seeded (the same examples every run),
    a fixed number of them, no per-example deadline, no example database."""
    from hypothesis import HealthCheck, settings

    return settings(
        max_examples=max_examples,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    )

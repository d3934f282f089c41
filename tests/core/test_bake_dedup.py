"""The bake's deduplication of parameter rows (hash of the float32 rows, exact fallback)."""

import numpy as np

from addon.core.textures import bake
from addon.core.textures.bake import distinct_rows


def rows_with_repeats(n=5000, distinct=37, cols=23, seed=0):
    rng = np.random.default_rng(seed)
    table = rng.random((distinct, cols))
    return table[rng.integers(0, distinct, n)], table


def test_distinct_rows_finds_every_distinct_row_once():
    m, table = rows_with_repeats()
    first, inverse = distinct_rows(m)
    assert len(first) == len(np.unique(m, axis=0)) == 37
    assert np.array_equal(m[first][inverse], m)
    # Negative zero is the same parameter; rows equal in float32 are one row.
    z = np.array([[0.0, 1.0], [-0.0, 1.0], [0.5, 1.0 + 1e-12]])
    first, inverse = distinct_rows(z)
    assert len(first) == 2 and inverse[0] == inverse[1]


def test_a_hash_collision_falls_back_to_the_exact_row_sort(monkeypatch):
    m, _ = rows_with_repeats(n=800, distinct=9)
    monkeypatch.setattr(bake, "_FNV_PRIME", np.uint64(0))  # every row hashes to 0
    first, inverse = distinct_rows(m)
    assert len(first) == 9 and np.array_equal(m[first][inverse], m)

"""The bake's deduplication of parameter rows (hash of the float32 rows, exact fallback)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from addon.core import rows
from addon.core.rows import distinct_rows


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
    monkeypatch.setattr(rows, "_FNV_PRIME", np.uint64(0))  # every row hashes to 0
    first, inverse = distinct_rows(m)
    assert len(first) == 9 and np.array_equal(m[first][inverse], m)


def test_the_encoder_runs_each_distinct_feature_row_once_with_the_same_latents():
    from addon.core.neural import load_models
    from addon.core.neural.features import base_features

    models = load_models("tiny")
    rng = np.random.default_rng(4)
    n = 300
    kind = rng.integers(0, 3, size=n)
    alpha = rng.choice([0.05, 0.2, 0.6], size=n)  # few distinct layers, repeated
    albedo = rng.choice([0.2, 0.8], size=(n, 1)) * np.ones((1, 3))
    x = base_features(kind, alpha, albedo, (0.2, 0.9, 1.1), (3.9, 2.4, 2.1), 1.5)
    calls = []
    session = models._load("encoder")
    real = session.run
    session.run = lambda outputs, rows, shared=None: calls.append(len(rows["x"])) or real(outputs, rows, shared)
    try:
        z = models.run_encoder(x)
    finally:
        session.run = real
    direct = real(["z"], {"x": x.reshape(-1, x.shape[-1])})[0].reshape(n, 3, -1)
    np.testing.assert_array_equal(z, direct)
    assert calls == [len(distinct_rows(x.reshape(-1, x.shape[-1]))[0])] and calls[0] < 3 * 18


def test_distinct_rows_come_in_order_of_first_occurrence():
    m, _ = rows_with_repeats(n=400, distinct=11, seed=2)
    first, inverse = distinct_rows(m)
    assert np.all(np.diff(first) > 0) and first[0] == 0
    assert np.array_equal(m[first][inverse], m)
    unique = np.random.default_rng(3).random((300, 5))  # all distinct: the identity, nothing to gather
    first, inverse = distinct_rows(unique)
    assert np.array_equal(first, np.arange(300)) and np.array_equal(inverse, np.arange(300))


def test_constant_columns_and_degenerate_shapes():
    m, _ = rows_with_repeats(n=600, distinct=13, cols=3, seed=5)
    wide = np.concatenate([np.full((600, 4), 0.25), m[:, :1], np.full((600, 2), -0.0), m[:, 1:]], axis=1)
    first, inverse = distinct_rows(wide)
    assert len(first) == 13 and np.array_equal(wide[first][inverse], wide)
    same = np.tile([1.0, -0.0, 3.0], (50, 1))
    same[7, 1] = 0.0  # -0.0 and 0.0 in a column that is constant as a parameter
    first, inverse = distinct_rows(same)
    assert np.array_equal(first, [0]) and np.array_equal(inverse, np.zeros(50))
    first, inverse = distinct_rows(np.zeros((0, 4)))
    assert first.shape == (0,) and inverse.shape == (0,)


@given(
    st.integers(1, 60).flatmap(
        lambda n: st.lists(
            st.lists(st.sampled_from([0.0, -0.0, 0.5, 1.0, 2.0]), min_size=n, max_size=n), min_size=1, max_size=5
        )
    )
)
@settings(max_examples=200, deadline=None)
def test_distinct_rows_agrees_with_the_exact_row_sort(columns):
    m = np.array(columns).T  # rows of few values: many repeats, constant columns, signed zeros
    first, inverse = distinct_rows(m)
    exact = np.unique(m + 0.0, axis=0)  # + 0.0 turns -0.0 into 0.0
    assert len(first) == len(exact)
    assert np.all(np.diff(first) > 0) and first[0] == 0
    assert np.array_equal(m[first][inverse] + 0.0, m + 0.0)

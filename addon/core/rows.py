"""Distinct rows of a parameter matrix, by hashing: the deduplication of bakes and encoders."""

from __future__ import annotations

import numpy as np

_FNV_PRIME = np.uint64(1099511628211)
_FNV_OFFSET = np.uint64(14695981039346656037)


def distinct_rows(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Deduplication of parameter rows: ``(first, inverse)`` with ``matrix[first]`` the distinct
    rows (quantised to float32, the precision the encoders compute in) and
    ``matrix[first][inverse]`` equal to every row so quantised.

    ``first`` is ascending (each distinct row's first occurrence), so rows that are all distinct give
    ``first`` and ``inverse`` equal to ``arange(n)`` and a caller can skip both gathers.

    Each row is hashed (FNV-1a over its float32 bit patterns, 64 bits, one vectorised step per
    column) and only the hashes are sorted, instead of sorting whole rows lexicographically
    (``np.unique(axis=0)``, most of a bake's time on large textures). A hash collision is caught by
    comparing every repeated row with its representative; then the exact row sort decides.
    """
    q = np.asarray(matrix, dtype=np.float32)  # a float64 matrix rounds as through float64
    if q.ndim != 2:
        raise ValueError(f"parameter rows must be a 2-D array, got shape {q.shape}")
    if len(q) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    # Only the columns that vary tell rows apart (a texture varies a few of a stack's parameters);
    # a copy, so that -0.0 and 0.0, the same parameter, can be made one
    q = q[:, (q != q[0]).any(axis=0)]
    if q.shape[1] == 0:  # every row is the first
        return np.zeros(1, dtype=np.int64), np.zeros(len(q), dtype=np.int64)
    q[q == 0] = 0.0
    bits = q.view(np.uint32)
    h = np.full(len(q), _FNV_OFFSET, dtype=np.uint64)
    with np.errstate(over="ignore"):
        for j in range(bits.shape[1]):  # a loop over parameter columns, not texels
            h ^= bits[:, j]
            h *= _FNV_PRIME
    first, inverse = _groups(h)
    rep = first[inverse]  # each row's representative
    repeated = np.flatnonzero(rep != np.arange(len(q)))
    if not np.array_equal(bits[rep[repeated]], bits[repeated]):  # a collision: two rows share a hash
        _, first, inverse = np.unique(bits, axis=0, return_index=True, return_inverse=True)
        first, inverse = _ascending(first, inverse.reshape(-1))
    return first, inverse


def _groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(first, inverse)`` of equal ``keys`` (N,): each distinct key's first index, ascending, and each
    row's position in ``first``. One sort of the keys; the rest is linear (the order of first
    occurrence comes from a running count, not from a second sort)."""
    n = len(keys)
    order = np.argsort(keys)
    sk = keys[order]
    starts = np.flatnonzero(np.concatenate(([True], sk[1:] != sk[:-1])))
    first_unsorted = np.minimum.reduceat(order, starts)  # each group's first occurrence (any sort order)
    group_sorted = np.zeros(n, dtype=np.int64)
    group_sorted[starts[1:]] = 1
    np.cumsum(group_sorted, out=group_sorted)  # the group of each sorted position
    is_first = np.zeros(n, dtype=bool)
    is_first[first_unsorted] = True
    rank = np.cumsum(is_first) - 1  # at a first occurrence: its place among the first occurrences
    inverse = np.empty(n, dtype=np.int64)
    inverse[order] = rank[first_unsorted][group_sorted]
    return np.flatnonzero(is_first), inverse


def _ascending(first: np.ndarray, inverse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same deduplication with the distinct rows in order of first occurrence."""
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse]

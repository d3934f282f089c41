"""addon/core/formula.py: one formula, the same numbers from numpy arrays, torch tensors and a compiled loop."""

import math

import numpy as np
import pytest
import torch
from numba import njit

from addon.core import formula as fm
from addon.core.bsdf.dielectric import rough_dielectric_eval_pdf, rough_dielectric_sample
from addon.core.bsdf.frame import basis, refracted
from addon.core.bsdf.ggx import visible_normal
from addon.core.bsdf.lambert import lambert_sample


@fm.formula
def _every_operation(x, y):
    """Each operation of the module once, on two inputs with zeros, negatives and a nan."""
    c = (x > 0.0) & fm.negate(y > 0.5) | (x < -0.5)
    return (
        fm.where(c, x, y),
        fm.sqrt(abs(x)),
        fm.maximum(x, y),
        fm.minimum(x, y),
        fm.clip(x, -0.25, 0.25),
        fm.cos(x),
        fm.sin(y),
        fm.where(fm.isfinite(x / y), 1.0, 0.0),
        fm.copysign(1.0, y),
        fm.where(c, 1.0, 0.0),
        fm.arccos(fm.clip(x, -1.0, 1.0)),
    )


@njit(error_model="numpy")
def _compiled(x, y):
    out = np.empty((11, len(x)))
    for i in range(len(x)):
        r = _every_operation(x[i], y[i])
        for k in range(11):
            out[k, i] = r[k]
    return out


def _inputs():
    rng = np.random.default_rng(3)
    x = np.concatenate([[0.0, -0.0, 1.0, -1.0, np.nan], rng.normal(size=200)])
    y = np.concatenate([[0.0, 2.0, 0.0, -3.0, 0.5], rng.normal(size=200)])
    return x, y


def test_each_operation_gives_the_same_numbers_on_arrays_tensors_and_scalars_in_a_loop():
    x, y = _inputs()
    with np.errstate(all="ignore"):
        want = np.array([np.asarray(v, dtype=float) for v in _every_operation(x, y)])
    got_torch = np.array([np.asarray(v, dtype=float) for v in _every_operation(torch.tensor(x), torch.tensor(y))])
    np.testing.assert_allclose(got_torch, want, rtol=1e-15, equal_nan=True)
    np.testing.assert_allclose(_compiled(x, y), want, rtol=1e-15, equal_nan=True)


@njit(error_model="numpy")
def _compiled_cos_sin(a, u):
    out = np.empty((len(a), 4))
    for i in range(len(a)):
        out[i, 0], out[i, 1] = fm.quarter_cos_sin(a[i])
        out[i, 2], out[i, 3] = fm.turn_cos_sin(u[i])
    return out


def test_the_compiled_cos_and_sin_of_a_quarter_and_of_a_turn_are_within_rounding_of_the_exact_values():
    """Compiled, ``quarter_cos_sin`` and ``turn_cos_sin`` are series, not the C library: within 2.5e-16 of cos and
    sin taken in extended precision (of the exact angle 2 pi u, where the C library's cos of the rounded angle is
    off by up to 7e-16), exact at the quarter turns, and as arrays the C library's."""
    rng = np.random.default_rng(8)
    a = np.concatenate([np.linspace(-np.pi / 4, np.pi / 4, 200_001), [0.0, -0.0, 1e-300], rng.uniform(-0.8, 0.8, 999)])
    u = np.concatenate([np.linspace(0.0, 1.0, 200_001), [-0.25, 1.75, 3.0], rng.uniform(-3, 3, 999)])
    got = _compiled_cos_sin(a, u)
    exact_a = a.astype(np.longdouble)
    exact_phi = 2 * np.longdouble("3.14159265358979323846264338327950288") * u.astype(np.longdouble)
    for k, want in enumerate([np.cos(exact_a), np.sin(exact_a), np.cos(exact_phi), np.sin(exact_phi)]):
        assert float(np.abs(got[:, k] - want).max()) < 2.5e-16, k
    quarters = np.array([0.0, 0.25, 0.5, 0.75, 1.0, -0.25])
    np.testing.assert_array_equal(
        _compiled_cos_sin(np.zeros(6), quarters)[:, 2:], [[1, 0], [0, 1], [-1, 0], [0, -1], [1, 0], [0, -1]]
    )
    assert math.copysign(1.0, _compiled_cos_sin(np.array([-0.0]), np.zeros(1))[0, 1]) == -1.0  # sin(-0) = -0
    assert np.isnan(_compiled_cos_sin(np.array([np.nan]), np.array([np.nan]))).all()
    np.testing.assert_array_equal(fm.turn_cos_sin(u), (np.cos(2 * math.pi * u), np.sin(2 * math.pi * u)))
    np.testing.assert_array_equal(fm.quarter_cos_sin(a), (np.cos(a), np.sin(a)))


def test_negate_is_a_logical_not_for_python_bools_arrays_and_tensors():
    assert fm.negate(True) == False  # noqa: E712 (numpy's bool, not -2)
    assert fm.negate(False) == True  # noqa: E712
    np.testing.assert_array_equal(fm.negate(np.array([True, False])), [False, True])
    assert fm.negate(torch.tensor([True, False])).tolist() == [False, True]


@njit(error_model="numpy")
def _bsdf_rows(wi, wo, alpha, ior, u):
    n = len(wi)
    out = np.empty((n, 22))
    for i in range(n):
        ox, oy, oz = wo[i, 0], wo[i, 1], wo[i, 2]
        a, e, u0, u1, u2 = alpha[i], ior[i], u[i, 0], u[i, 1], u[i, 2]
        out[i, 0], out[i, 1] = rough_dielectric_eval_pdf(wi[i, 0], wi[i, 1], wi[i, 2], ox, oy, oz, a, e, True, False)
        x, y, z, w, p, _delta, reflected, _valid = rough_dielectric_sample(ox, oy, oz, a, e, u0, u1, u2, True, False)
        out[i, 2], out[i, 3], out[i, 4], out[i, 5], out[i, 6], out[i, 7] = x, y, z, w, p, 1.0 if reflected else 0.0
        out[i, 8], out[i, 9], out[i, 10] = visible_normal(ox, oy, oz, a, u1, u2)
        tx, ty, tz, _ok = refracted(ox, oy, oz, 0.0, 0.0, 1.0, e)
        out[i, 11], out[i, 12], out[i, 13] = tx, ty, tz
        sx, sy, sz, _tx, _ty, _tz = basis(ox, oy, oz)
        out[i, 14], out[i, 15], out[i, 16] = sx, sy, sz
        lx, ly, _lz, lp, _lv = lambert_sample(oz, u1, u2)
        out[i, 17], out[i, 18], out[i, 19] = lx, ly, lp
        out[i, 20], out[i, 21] = a, e
    return out


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_the_bsdf_formulas_agree_between_the_arrays_and_a_compiled_loop(backend):
    """The rough dielectric (both lobes, both sides), visible normals, refraction, the shading basis and the
    Lambertian sample: compiled with scalars they give what numpy (or torch) gives on columns."""
    rng = np.random.default_rng(4)
    n = 2000
    wi, wo = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    wi /= np.linalg.norm(wi, axis=1)[:, None]
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    alpha, ior = rng.uniform(0.0005, 0.8, n), rng.uniform(0.7, 2.0, n)
    u = rng.random((n, 3))
    cols = [wi[:, k] for k in range(3)] + [wo[:, k] for k in range(3)]
    args = [alpha, ior, u[:, 0], u[:, 1], u[:, 2]]
    if backend == "torch":
        cols, args = [torch.tensor(c) for c in cols], [torch.tensor(a) for a in args]
    ix, iy, iz, ox, oy, oz = cols
    a, e, u0, u1, u2 = args
    with np.errstate(all="ignore"):
        f, p = rough_dielectric_eval_pdf(ix, iy, iz, ox, oy, oz, a, e, True, False)
        s = rough_dielectric_sample(ox, oy, oz, a, e, u0, u1, u2, True, False)
        m = visible_normal(ox, oy, oz, a, u1, u2)
        t = refracted(ox, oy, oz, 0.0 * ox, 0.0 * ox, 0.0 * ox + 1.0, e)
        b = basis(ox, oy, oz)
        ls = lambert_sample(oz, u1, u2)
    cols = (f, p, *s[:5], s[6], *m, *t[:3], *b[:3], ls[0], ls[1], ls[3], a, e)
    want = np.stack([np.asarray(v, dtype=float) for v in cols], 1)
    got = _bsdf_rows(wi, wo, alpha, ior, u)
    assert (want[:, 0] > 0).mean() > 0.3 and want[:, 10].min() >= 0.0
    # The compiled samples' azimuths are series (``turn_cos_sin``, ``quarter_cos_sin``), the arrays' the C library's:
    # apart by a few 1e-16, which a component that nearly cancels makes larger relative to itself (a visible
    # normal's x of -6.7e-6 at alpha 0.018: 3.2e-12).
    np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-300 if backend == "numpy" else 1e-12)
    assert math.isfinite(got.sum())

"""Property-based tests of the neural runtime: for any shape, dtype and direction the decoder,
the batched encoders and the sampling proxy give finite, non-negative results of the right shape,
or a ValueError that says what was wrong. Seeded and bounded; the shipped ``tiny`` models."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example as also
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from addon.core.neural import encode_arrays, load_models
from addon.core.stack import PRESETS, StackArrays
from tests.faults.tally import bounded, example

DTYPES = [np.float16, np.float32, np.float64, np.int32, np.int64, np.bool_, np.complex64, np.complex128, np.uint8]


@pytest.fixture(scope="module")
def tiny():
    return load_models("tiny").load("layering", "sampling")


def arrays(shape):
    return st.sampled_from(DTYPES).flatmap(
        lambda dt: hnp.arrays(
            dt,
            shape,
            elements=hnp.from_dtype(np.dtype(dt), allow_nan=True, allow_infinity=True)
            if np.dtype(dt).kind == "f"
            else None,
        )
    )


direction_shapes = st.one_of(
    st.tuples(st.integers(0, 40)).map(lambda t: (t[0], 3)),
    st.just((3,)),
    hnp.array_shapes(min_dims=1, max_dims=3, max_side=5),
)


def well_formed(a) -> bool:
    a = np.asarray(a)
    return (
        a.dtype.kind in "fiub"
        and (a.ndim == 2 and a.shape[1] == 3 or a.shape == (3,))
        and bool(np.isfinite(a.astype(np.float64)).all())
    )


@bounded(40)
@given(
    wi=direction_shapes.flatmap(arrays),
    wo_same=st.booleans(),
    z_kind=st.sampled_from(["one", "per-row", "bad"]),
    data=st.data(),
)
@also(wi=np.array([[0.3 + 1j, 0.0, 0.9]]), wo_same=True, z_kind="one", data=None)  # complex: refused, not truncated
@also(wi=np.zeros((0, 3)), wo_same=True, z_kind="per-row", data=None)
def test_decoder_gives_finite_non_negative_values_or_a_clear_error(tiny, wi, wo_same, z_kind, data):
    example()
    models = tiny
    wo = wi if wo_same or data is None else data.draw(direction_shapes.flatmap(arrays), label="wo")
    n = np.atleast_2d(np.asarray(wi)).shape[0] if np.ndim(wi) else 0
    z0 = np.random.default_rng(0).normal(scale=0.5, size=(3, 32)).astype(np.float32)
    z = {"one": z0, "per-row": np.repeat(z0[None], n, axis=0), "bad": np.zeros((n + 1, 3, 31))}[z_kind]
    ok = (
        well_formed(wi) and well_formed(wo) and np.atleast_2d(wi).shape == np.atleast_2d(wo).shape and (z_kind != "bad")
    )
    if not ok:
        with pytest.raises(ValueError, match="wi|wo|z|shape|finite|complex|real|rows"):
            models.eval_brdf(z, wi, wo)
        return
    f = models.eval_brdf(z, wi, wo)
    assert f.shape == (np.atleast_2d(wi).shape[0], 3) and f.dtype == np.float32
    assert np.isfinite(f).all() and (f >= 0).all()


def stack_arrays(n: int, coatings: int, rng) -> StackArrays:
    names = [k for k, s in PRESETS.items() if len(s.coatings) == coatings]
    return (
        StackArrays.from_stacks([PRESETS[names[i % len(names)]] for i in rng.integers(0, 99, n)])
        if n
        else (StackArrays.from_stacks([PRESETS[names[0]]]).take(slice(0, 0)))
    )


@bounded(12)
@given(n=st.integers(0, 20), coatings=st.sampled_from([0, 1, 2]), seed=st.integers(0, 3))
@also(n=0, coatings=1, seed=0)  # N = 0 through the batched encoders: an empty result, not a reshape error
def test_batched_encoders_and_proxy_give_finite_results_for_any_batch(tiny, n, coatings, seed):
    example()
    models = tiny
    if not any(len(s.coatings) == coatings for s in PRESETS.values()):
        return
    arrays = stack_arrays(n, coatings, np.random.default_rng(seed))
    z = encode_arrays(arrays, models)
    assert z.shape == (n, 3, 32) and np.isfinite(z).all()
    proxy = models.proxy_params(z)
    assert proxy.shape == (n, 2) and np.isfinite(proxy).all() and (proxy[:, 0] > 0).all()
    assert ((proxy[:, 1] >= 0) & (proxy[:, 1] <= 1)).all()


@bounded(20)
@given(z=hnp.array_shapes(min_dims=1, max_dims=4, max_side=4).flatmap(arrays))
@also(z=np.full((3, 32), np.nan, np.float32))
def test_proxy_of_any_latent_array_is_finite_or_a_clear_error(tiny, z):
    example()
    za = np.asarray(z)
    good = (
        za.dtype.kind in "fiub"
        and za.shape[-2:] == (3, 32)
        and za.ndim in (2, 3)
        and np.isfinite(za.astype(np.float64)).all()
    )
    if not good:
        with pytest.raises(ValueError, match="z"):
            tiny.proxy_params(z)
        return
    p = tiny.proxy_params(z)
    assert np.isfinite(p).all() and (p[:, 0] > 0).all()

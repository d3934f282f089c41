"""Property-based test of latent-texture reading: any damage to a valid file (flipped bits,
zeroed runs, a cut-off end, bytes spliced in) gives either ``LatentTextureError`` naming the file
or a texture that is whole (a full mip chain of finite texels); never another exception."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from addon.core.textures import LatentTexture, LatentTextureError
from addon.core.textures.latent_texture import oiio_module
from tests.faults.tally import bounded, example, fault


@pytest.fixture(scope="module")
def valid_file(tmp_path_factory):
    oiio_module()
    path = tmp_path_factory.mktemp("exr") / "valid.exr"
    texels = np.random.default_rng(4).normal(size=(21, 34, 100)).astype(np.float32)
    LatentTexture.from_texels(texels, {"key": "0123456789abcdef"}).write_exr(path)
    return path, path.read_bytes()


damage = st.one_of(
    st.tuples(
        st.just("flip"),
        st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 7)), min_size=1, max_size=8),
    ),
    st.tuples(st.just("zero"), st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 256))),
    st.tuples(st.just("cut"), st.floats(0, 1, exclude_max=True)),
    st.tuples(st.just("splice"), st.tuples(st.floats(0, 1, exclude_max=True), st.binary(min_size=1, max_size=64))),
)


def damaged(data: bytes, how) -> bytes:
    kind, arg = how
    b = bytearray(data)
    if kind == "flip":
        for where, bit in arg:
            b[int(where * len(b))] ^= 1 << bit
    elif kind == "zero":
        start = int(arg[0] * len(b))
        b[start : start + arg[1]] = bytes(len(b[start : start + arg[1]]))
    elif kind == "cut":
        del b[int(arg * len(b)) :]
    else:
        start = int(arg[0] * len(b))
        b[start:start] = arg[1]
    return bytes(b)


@bounded(60)
@given(how=damage)
def test_a_damaged_latent_texture_is_a_clear_error_or_whole(valid_file, tmp_path_factory, how):
    example()
    fault(f"EXR damage: {how[0]}")
    path, data = valid_file
    bad = path.with_name("damaged.exr")
    bad.write_bytes(damaged(data, how))
    try:
        tex = LatentTexture.read_exr(bad)
    except LatentTextureError as e:
        assert str(bad) in str(e)
        return
    assert tex.levels[-1].shape[:2] == (1, 1) and all(np.isfinite(level).all() for level in tex.levels)

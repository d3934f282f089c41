"""Latent textures: mip chain = box filter, trilinear lookup, EXR round trip."""

import math

import numpy as np
import pytest

from addon.core.textures import CHANNEL_NAMES, LatentTexture, box_weights, build_mip_chain, trilinear_lookup
from addon.core.textures.mip import MipChain, downsample


@pytest.mark.parametrize("n", [1, 2, 5, 8, 13])
def test_box_weights_rows_sum_to_one_and_preserve_the_mean(n):
    w = box_weights(n)
    assert w.shape == (max(1, n // 2), n)
    assert np.allclose(w.sum(axis=1), 1.0)
    assert np.allclose(w.sum(axis=0).sum(), max(1, n // 2))
    x = np.random.default_rng(n).random(n)
    assert np.isclose((w @ x).mean(), x.mean())


def test_even_levels_are_the_mean_of_two_by_two_blocks():
    base = np.random.default_rng(0).random((8, 16, 3))
    chain = build_mip_chain(base)
    assert [lvl.shape[:2] for lvl in chain] == [(8, 16), (4, 8), (2, 4), (1, 2), (1, 1)]
    blocks = base.reshape(4, 2, 8, 2, 3).mean(axis=(1, 3))
    assert np.allclose(chain[1], blocks, atol=1e-6)
    for fine, coarse in zip(chain, chain[1:], strict=False):
        assert np.allclose(downsample(fine.astype(np.float64)), coarse, atol=1e-6)


def test_odd_sizes_follow_openexr_round_down():
    chain = build_mip_chain(np.ones((7, 5, 2)))
    assert [lvl.shape[:2] for lvl in chain] == [(7, 5), (3, 2), (1, 1)]
    assert all(np.allclose(lvl, 1.0) for lvl in chain)


def test_lookup_at_texel_centres_and_level_selection():
    rng = np.random.default_rng(1)
    base = rng.random((16, 16, 4)).astype(np.float32)
    chain = build_mip_chain(base)
    # texel (row 3, col 5): uv of its centre, v = 0 at the bottom row
    uv = np.array([[(5 + 0.5) / 16, 1 - (3 + 0.5) / 16]])
    assert np.allclose(trilinear_lookup(chain, uv, 1.0 / 16), base[3, 5], atol=1e-6)
    # a footprint covering the whole texture gives the 1x1 level
    assert np.allclose(trilinear_lookup(chain, uv, 1.0), chain[-1][0, 0], atol=1e-6)
    # half-way between levels 0 and 1 in log2 blends them
    fp = np.sqrt(2.0) / 16
    mid = trilinear_lookup(chain, np.array([[0.5, 0.5]]), fp)
    a = trilinear_lookup(chain, np.array([[0.5, 0.5]]), 1 / 16)
    b = trilinear_lookup(chain, np.array([[0.5, 0.5]]), 2 / 16)
    assert np.allclose(mid, 0.5 * (a + b), atol=1e-6)


def _bilinear_oracle(level, uv):
    """Bilinear tap with repeat addressing, float64, written out per corner (v = 0 at the bottom row)."""
    h, w, _ = level.shape
    x = uv[:, 0] * w - 0.5
    y = (1.0 - uv[:, 1]) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(int) % w, y0.astype(int) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    lv = level.astype(np.float64)
    return (1 - fy) * ((1 - fx) * lv[y0, x0] + fx * lv[y0, x1]) + fy * ((1 - fx) * lv[y1, x0] + fx * lv[y1, x1])


@pytest.mark.parametrize("shape", [(16, 16, 3), (13, 7, 5), (1, 9, 2)])
def test_lookup_matches_a_per_corner_oracle_across_levels_and_wrapping(shape):
    """The compiled lookup against the bilinear formula written out in float64: random uv well outside
    [0, 1] (repeat addressing), footprints from below a texel to the whole texture, odd sizes; rows of
    one call fall on different levels."""
    rng = np.random.default_rng(5)
    chain = build_mip_chain(rng.random(shape).astype(np.float32))
    uv = rng.uniform(-2.0, 3.0, (500, 2))
    fp = 2.0 ** rng.uniform(-8.0, 1.0, 500)
    lod = np.clip(np.log2(np.maximum(fp * math.sqrt(shape[0] * shape[1]), 1e-12)), 0.0, len(chain) - 1)
    k = np.floor(lod).astype(int)
    t = (lod - k)[:, None]
    want = np.empty((500, shape[2]))
    for level in np.unique(k):  # the oracle's loop over levels
        sel = k == level
        a = _bilinear_oracle(chain[level], uv[sel])
        b = _bilinear_oracle(chain[min(level + 1, len(chain) - 1)], uv[sel])
        want[sel] = (1 - t[sel]) * a + t[sel] * b
    got = trilinear_lookup(chain, uv, fp)
    assert got.dtype == np.float32 and got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=2e-6)
    # a plain list of levels gives the same as the packed chain
    np.testing.assert_array_equal(trilinear_lookup(list(chain), uv, fp), got)
    # split: the same channels in two contiguous arrays (a latent texture's latents and the rest)
    for split in range(shape[2] + 1):
        first, rest = trilinear_lookup(chain, uv, fp, split=split)
        assert first.flags.c_contiguous and rest.flags.c_contiguous
        np.testing.assert_array_equal(np.concatenate([first, rest], axis=1), got)
    with pytest.raises(ValueError, match="split must be in"):
        trilinear_lookup(chain, uv, fp, split=shape[2] + 1)


@pytest.mark.parametrize("shape", [(16, 16, 3), (13, 7, 5), (1, 9, 100)])
def test_a_half_float_chain_looks_up_what_a_float32_chain_of_its_values_does(shape):
    """A texture read from its file is held in half floats (half the memory); its lookup converts them as it
    reads, exactly: the result is a float32 chain's of the same values, bit for bit (subnormal halves, -0 and
    the largest half included)."""
    rng = np.random.default_rng(6)
    levels = [lv.astype(np.float16) for lv in build_mip_chain((rng.standard_normal(shape) * 4).astype(np.float32))]
    levels[0][0, :4, 0] = [3e-7, -2e-6, -0.0, 65504.0]  # subnormal halves, -0, the largest half
    half = MipChain(levels, dtype=np.float16)
    wide = MipChain(levels)
    assert half.dtype == np.float16 and wide.dtype == np.float32 and 2 * half.flat.nbytes == wide.flat.nbytes
    uv = rng.uniform(-2.0, 3.0, (500, 2))
    uv[:8] = np.stack([(np.arange(8) % 4 + 0.5) / shape[1], np.full(8, 1.0 - 0.5 / shape[0])], axis=1)  # near them
    fp = np.concatenate([np.full(8, 1e-6), 2.0 ** rng.uniform(-8.0, 1.0, 492)])
    got = trilinear_lookup(half, uv, fp)
    np.testing.assert_array_equal(got.view(np.uint32), trilinear_lookup(wide, uv, fp).view(np.uint32))


def test_a_mip_chain_holds_float32_or_half_floats():
    with pytest.raises(ValueError, match="float32 or float16"):
        MipChain.empty(4, 4, 2, dtype=np.float64)


@pytest.mark.parametrize("shape", [(16, 24, 3), (13, 7, 5), (9, 1, 2), (1, 9, 4)])
def test_fill_in_bands_gives_the_whole_levels_box_filter(shape, monkeypatch):
    """``fill`` reduces a level a band of rows at a time: with bands of one or two rows, a float32 chain's levels
    are, bit for bit, those of ``downsample`` over each whole level (odd sizes' fractional taps included); a
    half-float chain's are the same float32 sums of its own level above, rounded to half once."""
    from addon.core.textures import mip

    base = (np.random.default_rng(7).standard_normal(shape) * 3).astype(np.float32)
    whole = [base]
    while whole[-1].shape[0] > 1 or whole[-1].shape[1] > 1:
        whole.append(downsample(whole[-1]))
    monkeypatch.setattr(mip, "BAND_BYTES", 1)  # one output row a band
    chain = build_mip_chain(base)
    assert [lv.shape for lv in chain] == [lv.shape for lv in whole]
    for got, want in zip(chain, whole, strict=True):
        np.testing.assert_array_equal(got, want.astype(np.float32))
    half = build_mip_chain(base, dtype=np.float16)
    assert half.dtype == np.float16
    for fine, coarse in zip(half, half[1:], strict=False):
        np.testing.assert_array_equal(coarse, downsample(fine.astype(np.float32)).astype(np.float16))
    for a, b in zip(half, chain, strict=True):  # within a half's rounding per level of the float32 chain
        np.testing.assert_allclose(a.astype(np.float32), b, rtol=4e-3, atol=4e-3)


def test_a_half_float_chain_refuses_texels_a_half_cannot_hold_and_writes_none_of_them():
    chain = MipChain.empty(2, 3, 2, dtype=np.float16)
    chain.write_texels(0, np.arange(12, dtype=np.float32).reshape(6, 2))
    before = chain.flat.copy()
    for bad in (7e4, -1e5, np.inf, np.nan):
        values = np.ones((2, 2), np.float32)
        values[1, 0] = bad
        with pytest.raises(ValueError, match="half-float range"):
            chain.write_texels(2, values)
        np.testing.assert_array_equal(chain.flat, before)
    chain.write_texels(4, np.full((2, 2), 65504.0))  # the largest half fits
    assert chain[0][1, 2, 1] == 65504.0 and chain[0][0, 2, 0] == 4.0
    with pytest.raises(ValueError, match="half-float range"):
        LatentTexture.from_texels(np.full((2, 2, len(CHANNEL_NAMES)), 1e5, np.float32))
    held = chain.flat.copy()
    for start, values, message in (
        (5, np.ones((2, 2)), "outside the base level"),  # past its 6 texels, into the next level
        (-1, np.ones((1, 2)), "outside the base level"),
        (0, np.ones((2, 1)), r"\(N, 2\) rows"),  # would broadcast to every channel
        (0, np.ones(2), r"\(N, 2\) rows"),
    ):
        with pytest.raises(ValueError, match=message):
            chain.write_texels(start, values)
    np.testing.assert_array_equal(chain.flat, held)  # the next level's texels too


@pytest.mark.parametrize("compiled", [True, False])
def test_texels_stored_as_halves_are_numpys_halves_with_or_without_the_compiled_loop(compiled, monkeypatch):
    """``store_texels`` and ``float32_texels``, with the compiled conversions and with numpy's (a CPU without half
    conversions): the same halves as numpy's rounding, into a strided output too; a value beyond the limit
    refused with nothing written; and halves back to the float32 numpy gives."""
    from addon.core import kernels
    from addon.core.textures.mip import HALF_ROUNDS_FINITE, float32_texels, store_texels

    if not compiled:
        monkeypatch.setattr(kernels, "NATIVE_HALF", False)
    rng = np.random.default_rng(3)
    values = (rng.standard_normal((500, 7)) * np.logspace(-9, 4, 7)).astype(np.float32)
    wide = np.zeros((500, 9), np.float16)
    store_texels(values, wide[:, 1:8], "texels")
    np.testing.assert_array_equal(wide[:, 1:8].view(np.uint16), values.astype(np.float16).view(np.uint16))
    assert not wide[:, [0, 8]].any()
    np.testing.assert_array_equal(float32_texels(wide[:, 1:8]), values.astype(np.float16).astype(np.float32))
    assert float32_texels(values) is values
    values[12, 4] = 65510.0  # rounds to the largest half: refused as a texel, held as a mean of halves
    before = wide.copy()
    with pytest.raises(ValueError, match=r"texels must be finite and within the half-float range.*got 65510"):
        store_texels(values, wide[:, 1:8], "texels")
    np.testing.assert_array_equal(wide.view(np.uint16), before.view(np.uint16))
    store_texels(values, wide[:, 1:8], "texels", HALF_ROUNDS_FINITE)
    assert wide[12, 5] == 65504.0


def test_the_range_check_finds_the_first_row_a_half_float_cannot_hold_in_every_type():
    """``first_row_beyond_half``: the first row (first axis) holding a value that is not finite or beyond the
    limit, for half floats (any inf or nan, whatever its sign and payload; the largest half and subnormals pass),
    float32 (the compiled loop) and float64 (numpy), at any rank; and ``check_half_range`` names the first such
    value in the array's order."""
    from addon.core.textures.mip import HALF_ROUNDS_FINITE, check_half_range, first_row_beyond_half

    rng = np.random.default_rng(4)
    for dtype in (np.float16, np.float32, np.float64):
        values = (rng.standard_normal((40, 3, 5)) * 100).astype(dtype)
        values[0, 0, :3] = [65504.0, -65504.0, 6e-8]
        assert first_row_beyond_half(values) == -1
        assert first_row_beyond_half(values[:0]) == -1
        for bad in (np.inf, -np.inf, np.nan):
            spoilt = values.copy()
            spoilt[31, 2, 4], spoilt[17, 1, 0] = bad, bad
            assert first_row_beyond_half(spoilt) == 17
            assert first_row_beyond_half(spoilt[18:]) == 13
            assert first_row_beyond_half(spoilt[:, 2, 4]) == 31  # one value a row
        if dtype != np.float16:
            spoilt = values.copy()
            spoilt[25, 0, 2], spoilt[25, 1, 1] = 65510.0, -7e4
            assert first_row_beyond_half(spoilt) == 25
            assert first_row_beyond_half(spoilt[:, 0], HALF_ROUNDS_FINITE) == -1
            with pytest.raises(ValueError, match="got 65510$"):
                check_half_range(spoilt, "texels")
    payload = np.full((3, 4), 0x7E01, np.uint16)  # a nan with a payload, either sign
    payload[0], payload[1, :3] = 0, 0x3C00
    assert first_row_beyond_half(payload.view(np.float16)) == 1
    assert first_row_beyond_half((payload | 0x8000).view(np.float16)[2:]) == 0
    assert first_row_beyond_half(np.float32(np.nan)) == 0 and first_row_beyond_half(np.float16(1.0)) == -1


def test_lookup_rejects_bad_input():
    chain = build_mip_chain(np.zeros((4, 4, 1)))
    with pytest.raises(ValueError, match="uv"):
        trilinear_lookup(chain, np.zeros((3, 3)), 0.1)
    with pytest.raises(ValueError, match="finite"):
        trilinear_lookup(chain, np.array([[np.nan, 0.0]]), 0.1)


@pytest.fixture(scope="module")
def oiio():
    from addon.core.textures.latent_texture import oiio_module

    try:
        return oiio_module()
    except RuntimeError as e:
        pytest.skip(str(e))


def test_exr_round_trip_gives_back_the_half_float_chain_bit_for_bit(tmp_path, oiio):
    rng = np.random.default_rng(2)
    texels = rng.normal(size=(37, 70, len(CHANNEL_NAMES))).astype(np.float32)
    tex = LatentTexture.from_texels(texels, metadata={"stack": "demo"})
    path = tmp_path / "wood.exr"
    tex.write_exr(path)
    assert not list(tmp_path.glob("*.partial*"))
    back = LatentTexture.read_exr(path)
    assert len(back.levels) == len(tex.levels) == 7  # 70 -> 35 -> 17 -> 8 -> 4 -> 2 -> 1
    assert tex.levels.dtype == back.levels.dtype == np.float16  # built, written and read as the file stores it
    np.testing.assert_array_equal(back.levels.flat.view(np.uint16), tex.levels.flat.view(np.uint16))
    assert back.metadata.get("stack") == "demo"
    spec = oiio.ImageInput.open(str(path)).spec()
    assert sorted(spec.channelnames) == sorted(CHANNEL_NAMES)
    assert spec.tile_width == 64 and spec.format == oiio.HALF


def test_reading_a_non_latent_exr_is_a_clear_error(tmp_path, oiio):
    p = tmp_path / "rgb.exr"
    out = oiio.ImageOutput.create(str(p))
    out.open(str(p), oiio.ImageSpec(4, 4, 3, "half"))
    out.write_image(np.zeros((4, 4, 3), np.float32))
    out.close()
    with pytest.raises(ValueError, match="not a latent texture"):
        LatentTexture.read_exr(p)
    with pytest.raises(FileNotFoundError):
        LatentTexture.read_exr(tmp_path / "missing.exr")
    with pytest.raises(ValueError, match="shape"):
        LatentTexture.from_texels(np.zeros((4, 4, 3)))


def test_even_levels_take_the_2x2_mean_bit_for_bit_as_the_general_box_filter():
    from addon.core.textures import mip

    rng = np.random.default_rng(1)
    for shape in ((64, 32, 100), (2, 2, 3), (16, 4, 1)):
        x = rng.normal(size=shape).astype(np.float32)
        np.testing.assert_array_equal(mip.downsample(x), mip.resample_area(x, shape[0] // 2, shape[1] // 2))


@pytest.mark.parametrize("width, height", [(512, 256), (256, 512), (1024, 128), (64, 64)])
def test_a_non_square_texture_picks_the_level_of_its_footprint_in_texels(width, height):
    """One texel a pixel is level 0 and four texels a pixel level 2 whatever the texture's aspect: the longer side
    alone put a 2 : 1 texture at 0.5 and 2.5, an 8 : 1 one at 1.5 and 3.5. The footprint's uv scale is a geometric
    mean (``integrator.uv_scale``), so is a texel's side: sqrt(1 / (W H)) in uv."""
    from addon.core.textures.mip import mip_level_for_footprint

    texel = 1.0 / math.sqrt(width * height)
    levels = mip_level_for_footprint(np.array([texel, 4 * texel]), width, height, 12)
    np.testing.assert_allclose(levels, [0.0, 2.0], atol=1e-12)

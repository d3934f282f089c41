"""Spatially varying stacks and the bake pipeline (with a stand-in encoder: a fixed random
linear map of each texel's parameters, so every parameter change shows in the latents)."""

import numpy as np
import pytest

from addon.core.stack import Coating, Diffuse, Stack, StackArrays, preset
from addon.core.textures.bake import BakeCancelled, bake_stack, bake_texels
from addon.core.textures.spatial import SpatialStack


def linear_encoder():
    rng = np.random.default_rng(7)
    proj = {}

    def encode(arrays: StackArrays):
        m = arrays.to_matrix()
        if m.shape[1] not in proj:
            proj[m.shape[1]] = rng.normal(size=(m.shape[1], 98))
        v = m @ proj[m.shape[1]]
        return v[:, :96].reshape(-1, 3, 32), v[:, 96:]

    return encode


def wood():
    return Stack(Diffuse((0.45, 0.22, 0.08)), (Coating(roughness=0.1, ior=1.5, albedo=(0.9, 0.7, 0.3), thickness=0.6),))


def test_texels_take_the_image_values_rows_top_to_bottom():
    rough = np.linspace(0.01, 0.5, 12).reshape(3, 4)
    colour = np.random.default_rng(0).random((3, 4, 3))
    s = SpatialStack(wood(), {"coatings[0].roughness": rough, "base.albedo": colour})
    arrays, res = s.texels()
    assert res == (3, 4)
    assert np.allclose(arrays.coat_roughness[:, 0], rough.reshape(-1))
    assert np.allclose(arrays.base_albedo, colour.reshape(-1, 3))
    assert np.allclose(arrays.coat_thickness, 0.6)
    assert arrays.stack(5).coatings[0].roughness == pytest.approx(rough.reshape(-1)[5])


def test_lower_resolution_box_filters_the_parameters_and_higher_is_refused():
    rough = np.random.default_rng(1).uniform(0.05, 0.9, (8, 8))
    s = SpatialStack(wood(), {"coatings[0].roughness": rough})
    arrays, res = s.texels((4, 4))
    assert res == (4, 4)
    assert np.allclose(arrays.coat_roughness[:, 0], rough.reshape(4, 2, 4, 2).mean(axis=(1, 3)).reshape(-1))
    with pytest.raises(ValueError, match="between 1x1 and"):
        s.texels((16, 16))
    const, res = SpatialStack(wood()).texels()
    assert res == (1, 1) and len(const) == 1


@pytest.mark.parametrize(
    "maps, message",
    [
        ({"coatings[1].roughness": np.zeros((2, 2))}, "has 1 coating"),
        ({"base.roughness": np.zeros((2, 2))}, "Diffuse base has no parameter"),
        ({"top.roughness": np.zeros((2, 2))}, "must look like"),
        ({"base.albedo": np.zeros((2, 2, 2))}, "2 channel"),
        ({"coatings[0].roughness": np.zeros((2, 2, 2))}, "2 channel"),
        ({"coatings[0].roughness": np.full((2, 2), "rough.png")}, "real numbers"),
        ({"coatings[0].thickness": np.ones((2, 2), dtype=bool)}, "real numbers"),
        ({"coatings[0].roughness": np.full((2, 2), 0.1 + 0.2j)}, "real numbers"),
        ({"coatings[0].roughness": np.full((2, 2), 1.5)}, "outside the valid range"),
        ({"coatings[0].thickness": np.full((2, 2), np.nan)}, "outside the valid range"),
        ({"coatings[0].roughness": np.zeros((2, 2)), "base.albedo": np.zeros((3, 2, 3))}, "share a resolution"),
    ],
)
def test_bad_driving_images_are_clear_errors(maps, message):
    with pytest.raises(ValueError, match=message):
        SpatialStack(wood(), maps)


def test_a_colour_image_drives_a_number_by_its_luminance():
    """A grey map saved as RGB or RGBA (every JPEG) is its grey, a coloured one its luminance, as Blender turns a
    colour into a number: the bake command refused them, and the add-on took the red channel."""
    grey = np.linspace(0.05, 0.6, 8).reshape(2, 4)
    for image in (
        np.repeat(grey[..., None], 3, axis=2),
        np.concatenate([np.repeat(grey[..., None], 3, 2)] * 2, 2)[..., :4],
    ):
        got = SpatialStack(wood(), {"coatings[0].roughness": image}).maps["coatings[0].roughness"]
        np.testing.assert_allclose(got[..., 0], grey)
    colour = np.zeros((1, 1, 3))
    colour[..., 1] = 0.5
    got = SpatialStack(wood(), {"coatings[0].roughness": colour}).maps["coatings[0].roughness"]
    assert got[0, 0, 0] == pytest.approx(0.7152 * 0.5)


def test_deduplication_gives_the_same_texels_with_fewer_encodes():
    mask = np.zeros((16, 16))
    mask[4:12, 4:12] = 0.4
    s = SpatialStack(wood(), {"coatings[0].roughness": 0.05 + mask})
    arrays, _ = s.texels()
    enc = linear_encoder()
    a, sa = bake_texels(arrays, enc, dedup=True)
    b, sb = bake_texels(arrays, enc, dedup=False)
    assert sa.unique == 2 and sb.unique == 256
    assert np.allclose(a, b, atol=1e-5)


def test_constant_images_bake_to_the_constant_stack_latent():
    enc = linear_encoder()
    s = SpatialStack(
        wood(), {"coatings[0].roughness": np.full((5, 7), 0.1), "base.albedo": np.tile((0.45, 0.22, 0.08), (5, 7, 1))}
    )
    tex, stats = bake_stack(s, enc)
    z, proxy = enc(StackArrays.from_stacks([wood()]))
    assert stats.unique == 1
    half = np.float16
    for level in tex.levels:  # every level the stack's latent as the file stores it (half floats), exactly
        assert (level[..., :96] == z.reshape(96).astype(half)).all()
        assert (level[..., 96:98] == proxy.reshape(2).astype(half)).all()
        # the top coating's roughness (set by its map) and index, for a remainder decoder's exact top lobe
        assert (level[..., 98:] == np.array((0.1, wood().coatings[-1].ior), np.float32).astype(half)).all()


def test_progress_and_cancel():
    arrays = StackArrays.repeat(preset("three_layer"), 10)
    arrays.coat_thickness[:, 0] = np.linspace(0, 1, 10)
    seen = []
    bake_texels(arrays, linear_encoder(), batch=3, progress=seen.append)
    assert seen[-1] == 1.0 and len(seen) == 4
    with pytest.raises(BakeCancelled):
        bake_texels(arrays, linear_encoder(), batch=3, cancel=lambda: True)


@pytest.mark.parametrize("when", ["the mip chain", "the filtering measurement"])
def test_a_cancel_after_the_encoding_stops_the_bake_before_its_texture_is_made(when):
    """A bake's last parts (its mip chain, the measurement of its filterable levels: seconds a level at large
    sizes) hear a cancel too, where the bar stood full and an Esc there was ignored."""
    from addon.core.textures.bake import neural_encoder

    spatial = SpatialStack(preset("three_layer"), {"coatings[0].thickness": np.linspace(0, 1, 64).reshape(8, 8, 1)})
    seen = []

    def cancel():  # once the encoding is done: at the chain, or at the filtering's first level
        return bool(seen) and seen[-1] >= 1.0 and (when == "the mip chain" or seen.count(1.0) >= 2)

    with pytest.raises(BakeCancelled, match=f"during {when}"):
        bake_stack(spatial, neural_encoder("tiny", threads=1), calibrate=False, progress=seen.append, cancel=cancel)


def test_a_concurrent_encoder_encodes_batches_side_by_side_with_the_same_texels():
    """``encode.concurrent``: ``threads`` batches are in flight at once (one's numpy work overlaps
    another's networks), never more; the texels, the progress and a cancellation are as with one."""
    import threading
    import time

    arrays = StackArrays.repeat(preset("three_layer"), 40)
    arrays.coat_thickness[:, 0] = np.linspace(0, 1, 40)
    inner = linear_encoder()
    lock, state = threading.Lock(), {"now": 0, "most": 0, "calls": 0}

    def encode(a):
        with lock:
            state["now"] += 1
            state["most"] = max(state["most"], state["now"])
            state["calls"] += 1
        time.sleep(0.02)
        with lock:
            out = inner(a)  # the stand-in draws its projection lazily: not thread-safe by itself
            state["now"] -= 1
        return out

    one, _ = bake_texels(arrays, encode, batch=4, threads=3)  # not marked concurrent: one batch at a time
    assert state["most"] == 1
    encode.concurrent = True
    seen = []
    state.update(most=0, calls=0)
    three, stats = bake_texels(arrays, encode, batch=4, threads=3, progress=seen.append)
    assert state["most"] == 3 and state["calls"] == 10 and stats.unique == 40
    np.testing.assert_array_equal(three, one)
    assert seen == sorted(seen) and seen[-1] == 1.0 and len(seen) == 10
    calls = []

    def stop_after_two():
        calls.append(1)
        return len(calls) > 2

    state.update(calls=0)
    with pytest.raises(BakeCancelled, match="of 40 distinct texels"):
        bake_texels(arrays, encode, batch=4, threads=3, cancel=stop_after_two)
    assert state["calls"] == 2 and state["now"] == 0  # nothing started after the cancel, nothing left running


def test_an_encoder_returning_the_wrong_shape_is_reported():
    arrays = StackArrays.repeat(wood(), 2)
    with pytest.raises(ValueError, match="expected"):
        bake_texels(arrays, lambda a: (np.zeros((len(a), 3, 16)), np.zeros((len(a), 2))))


def _within_half_rounding(texels, want) -> bool:
    """``texels`` (half floats) are ``want`` rounded to half: within half a unit of a half's last place."""
    return np.allclose(texels.astype(np.float64), want, rtol=2.0**-11, atol=2.0**-25)


def test_mix_blends_latents_through_the_mask():
    from addon.core.textures.bake import bake_mix

    enc = linear_encoder()
    a = SpatialStack(wood())
    b = SpatialStack(preset("coated_gold"))
    mask = np.tile(np.linspace(0.0, 1.0, 5), (3, 1))
    tex, stats = bake_mix(a, b, mask, enc)
    za, pa = enc(StackArrays.from_stacks([wood()]))
    zb, pb = enc(StackArrays.from_stacks([preset("coated_gold")]))
    from addon.core.neural import top_coat

    ends = tuple(
        np.concatenate([z.reshape(-1), p.reshape(-1), top_coat(st)])
        for z, p, st in ((za, pa, wood()), (zb, pb, preset("coated_gold")))
    )
    base = tex.levels[0]  # half floats, as the file stores them
    assert _within_half_rounding(base[:, 0], ends[0]) and _within_half_rounding(base[:, -1], ends[1])
    halves = [e.astype(np.float16).astype(np.float64) for e in ends]  # each stack's texels as the bake holds them
    assert _within_half_rounding(base[1, 2], 0.5 * (halves[0] + halves[1]))
    with pytest.raises(ValueError, match="share a resolution"):
        bake_mix(SpatialStack(wood(), {"coatings[0].roughness": np.full((4, 4), 0.1)}), b, mask, enc)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        bake_mix(a, b, mask * 2, enc)


def test_the_default_auto_bake_uses_the_default_size_and_records_it():
    """ "auto" (the add-on's default model size) is resolved once, by the neural runtime: the bake
    encodes with the default size's models and the texture says which."""
    from addon.core.neural import DEFAULT_SIZE, encode_stack, load_models
    from addon.core.textures.bake import neural_encoder

    encode = neural_encoder("auto")
    assert encode.metadata == {"model": DEFAULT_SIZE, "model_digest": load_models(DEFAULT_SIZE).digest}
    maps = {"coatings[0].roughness": np.full((2, 3), 0.1)}
    tex, stats = bake_stack(SpatialStack(wood(), maps), encode, metadata={"model": "auto"})
    assert tex.metadata["model"] == DEFAULT_SIZE and stats.unique == 1
    z = encode_stack(wood(), DEFAULT_SIZE)
    assert _within_half_rounding(tex.levels[0][..., :96], z.reshape(96))


def test_the_bake_uses_the_threads_it_is_given_and_their_count_changes_nothing(monkeypatch):
    from addon.core.neural import session
    from addon.core.textures.bake import neural_encoder

    seen = []
    real = session.ChunkedSession.map

    def spy(self, fn, n):
        seen.append(session.threads_now())
        return real(self, fn, n)

    monkeypatch.setattr(session.ChunkedSession, "map", spy)
    stack = preset("varnished_wood")
    rough = np.linspace(0.02, 0.4, 64 * 64).reshape(64, 64)
    spatial = SpatialStack(stack, {"coatings[0].roughness": rough})
    encode = neural_encoder("tiny")
    one, _ = bake_stack(spatial, encode, threads=1)
    assert set(seen) == {1}
    seen.clear()
    two, _ = bake_stack(spatial, encode, threads=2)
    assert set(seen) == {2}
    np.testing.assert_array_equal(one.levels[0], two.levels[0])


def test_a_bake_too_large_for_this_computer_is_refused_before_any_work(monkeypatch):
    """Baking takes about BAKE_FIXED_BYTES and BAKE_BYTES_PER_TEXEL a texel at its peak; where that is over three
    quarters of the computer's memory the bake says so, with the side that fits, instead of ending in the system's
    out-of-memory."""
    from addon.core.textures import bake

    gib = 2**30
    bake.check_bake_memory(4096, 4096, physical=12 * gib)  # 8.3 GB of 12: fine (5.5 GB measured, docs/bake.md)
    with pytest.raises(ValueError, match=r"8192 x 8192 texels takes about 31\.8 GB .* 16\.0 GB: bake at most 4096"):
        bake.check_bake_memory(8192, 8192, physical=16 * gib)
    assert bake.physical_memory_bytes() > gib  # readable here (Linux)
    monkeypatch.setattr(bake, "physical_memory_bytes", lambda: None)
    bake.check_bake_memory(65536, 65536)  # memory unknown: nothing checked

    calls = []
    monkeypatch.setattr(bake, "physical_memory_bytes", lambda: 64 * 2**10)  # 64 kB
    spatial = SpatialStack(wood(), {"coatings[0].roughness": np.full((8, 8), 0.2)})
    with pytest.raises(ValueError, match="8 x 8 texels takes about"):
        bake_stack(spatial, lambda arrays: calls.append(arrays))
    assert calls == []  # nothing encoded


def test_bake_stack_gathers_its_texels_into_the_chain_as_the_texels_and_their_mips():
    """bake_stack writes each texel straight into the base of a half-float mip chain (no texture-sized copy
    between): the chain is the box-filtered chain of bake_texels' texels, with repeated texels and with every one
    distinct."""
    from addon.core.textures import build_mip_chain

    rng = np.random.default_rng(3)
    for rough in (np.round(rng.random((12, 10)) * 3) / 10 + 0.1, 0.05 + 0.3 * rng.random((12, 10))):
        spatial = SpatialStack(wood(), {"coatings[0].roughness": rough})
        tex, stats = bake_stack(spatial, linear_encoder(), calibrate=False, check_filtering=False)
        texels, _ = bake_texels(spatial.texels()[0], linear_encoder())
        want = build_mip_chain(texels.reshape(12, 10, -1), dtype=np.float16)
        assert tex.levels.dtype == np.float16  # as its file stores it
        assert len(tex.levels) == len(want) and all(np.array_equal(a, b) for a, b in zip(tex.levels, want, strict=True))
    assert stats.unique == 120


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1e5])
def test_an_encoder_returning_latents_a_texture_cannot_hold_is_a_clear_error(bad):
    """The texture stores half floats: a latent that is not finite or beyond 65504 stops the bake with a clear
    error (bake_stack holds its distinct texels in halves, where such a value would become inf unnoticed), and so
    does one in bake_texels' float32 texels where it is not finite."""
    encode = linear_encoder()

    def spoiled(arrays):
        z, proxy = encode(arrays)
        z = z.copy()
        z[0, 1, 2] = bad
        return z, proxy

    spatial = SpatialStack(wood(), {"coatings[0].roughness": np.full((3, 4), 0.2)})
    with pytest.raises(ValueError, match="non-finite" if not np.isfinite(bad) else "half-float range"):
        bake_stack(spatial, spoiled, calibrate=False, check_filtering=False)
    if not np.isfinite(bad):
        with pytest.raises(ValueError, match="non-finite"):
            bake_texels(spatial.texels()[0], spoiled)
    else:
        assert bake_texels(spatial.texels()[0], spoiled)[0].max() == np.float32(1e5)  # float32 holds it


def test_a_mix_of_the_largest_halves_is_held_not_refused():
    """Blending two texels at the half range's edge stays there (float32's rounding of the blend could step past
    65504: the mix clips it back rather than refuse the texture)."""
    from addon.core.textures.bake import bake_mix

    def at_the_edge(arrays):
        n = len(arrays)
        return np.full((n, 3, 32), 65504.0, np.float32), np.full((n, 2), -65504.0, np.float32)

    mask = np.tile(np.linspace(0.0, 1.0, 1001), (2, 1))
    tex, _ = bake_mix(SpatialStack(wood()), SpatialStack(preset("coated_gold")), mask, at_the_edge)
    for level in tex.levels:
        assert (level[..., :96] == 65504.0).all() and (level[..., 96:98] == -65504.0).all()


def test_a_bake_says_what_the_networks_saw_clamped():
    """A smooth top coat (roughness 0, below the trained 0.01) is baked as the clamped stack: the bake's statistics
    say so (the add-on reports it, as the command prints it), where it went only to the console once a session."""
    smooth = Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.0, 1.5),))
    stacks = StackArrays.from_stacks([smooth] * 4 + [Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.1, 1.5),))] * 4)
    _, stats = bake_texels(stacks, linear_encoder())
    assert len(stats.clamped) == 1 and "roughness" in stats.clamped[0], stats.clamped
    _, plain = bake_texels(
        StackArrays.from_stacks([Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.1, 1.5),))]), linear_encoder()
    )
    assert plain.clamped == ()

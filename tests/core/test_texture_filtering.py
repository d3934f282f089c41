"""How far a latent texture may be filtered in latent space (addon.core.textures.filtering), and the lookup
that stops there."""

import numpy as np
import pytest

from addon.core.stack import preset
from addon.core.textures import LatentTexture
from addon.core.textures import filtering as F
from addon.core.textures.bake import bake_stack, neural_encoder
from addon.core.textures.latent_texture import LatentTextureError
from addon.core.textures.spatial import SpatialStack


@pytest.fixture(scope="module")
def encode():
    return neural_encoder("tiny", threads=2)


def _bake(encode, rough, **kw):
    return bake_stack(SpatialStack(preset("coated_gold"), {"coatings[0].roughness": rough}), encode, threads=2, **kw)[0]


def test_alike_texels_filter_to_the_last_level_and_unlike_ones_not_at_all(encode):
    flat = np.full((16, 16), 0.3, np.float32)
    tex = _bake(encode, flat)
    assert tex.metadata["filter_levels"] == len(tex.levels) == 5
    # a glossy and a rough coat in stripes two texels wide: the next level's blocks hold one coat each,
    # but a bilinear tap between two of them blends the stripes, which decodes to neither average
    stripes = np.where((np.arange(16) // 2) % 2 == 0, 0.02, 0.6).astype(np.float32)[None, :].repeat(16, 0)
    n, errors = F.filterable_levels(encode.models, _bake(encode, stripes, check_filtering=False).levels)
    assert n == 1 and errors[0] > 10 * F.TOLERANCE
    assert F.level_error(encode.models, tex.levels[0]) < 1e-4  # one latent: its average is itself
    # stripes as wide as the texture's blocks at every level below the last few: those levels filter
    wide = np.where((np.arange(16) // 8) % 2 == 0, 0.2, 0.22).astype(np.float32)[None, :].repeat(16, 0)
    assert F.filterable_levels(encode.models, _bake(encode, wide, check_filtering=False).levels)[0] >= 3


def test_the_lookup_stops_at_the_filterable_levels_and_the_count_survives_the_file(encode, tmp_path):
    stripes = np.where(np.arange(16) % 2 == 0, 0.02, 0.6).astype(np.float32)[None, :].repeat(16, 0)
    tex = _bake(encode, stripes)
    assert tex.metadata["filter_levels"] == 1 and tex.filter_levels == 1
    uv = np.array([[0.5 / 16, 0.5], [1.5 / 16, 0.5]])  # texel centres of a glossy and a rough column
    far = np.full(2, 4.0)  # a footprint wider than the texture: the coarsest level, were it allowed
    z, _, top = tex.lookup(uv, far)
    np.testing.assert_allclose(top[:, 0], tex.levels[0][8, [0, 1], 98], rtol=1e-3)  # level 0's texels
    everything = LatentTexture(tex.levels, {})  # a texture without the measurement: every level
    assert everything.filter_levels == len(tex.levels)
    np.testing.assert_allclose(everything.lookup(uv, far)[2][:, 0], tex.levels[-1][0, 0, 98], rtol=1e-3)
    tex.write_exr(tmp_path / "t.exr")
    back = LatentTexture.read_exr(tmp_path / "t.exr")
    assert back.filter_levels == 1
    for bad in ("0", "x", "-2"):
        LatentTexture(tex.levels, {**tex.metadata, "filter_levels": bad}).write_exr(tmp_path / "bad.exr")
        with pytest.raises(LatentTextureError, match="filter_levels must be a positive count"):
            LatentTexture.read_exr(tmp_path / "bad.exr")


def test_the_pairs_cover_normal_to_grazing_views_with_unit_directions():
    wi, wo = F.PAIRS
    np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1.0)
    np.testing.assert_allclose(np.linalg.norm(wo, axis=1), 1.0)
    assert (wi[:, 2] > 0).all() and (wo[:, 2] > 0).all()
    assert np.degrees(np.arccos(wo[:, 2].min())) == pytest.approx(86.0)


def test_a_mix_of_two_stacks_records_its_filterable_levels_too(encode):
    from addon.core.textures.bake import bake_mix

    mask = np.zeros((16, 16))
    mask[:, 8:] = 1.0  # gold on the left, copper on the right: their averaged latent decodes to neither
    tex, _ = bake_mix(SpatialStack(preset("coated_gold")), SpatialStack(preset("frosted_copper")), mask, encode)
    assert tex.filter_levels == 1 and "calibration" not in tex.metadata
    tex, _ = bake_mix(
        SpatialStack(preset("coated_gold")), SpatialStack(preset("frosted_copper")), mask, encode, check_filtering=False
    )
    assert "filter_levels" not in tex.metadata and tex.filter_levels == len(tex.levels)


def test_a_level_that_steps_within_the_tolerance_but_drifts_from_its_texels_ends_the_chain(encode):
    """Multi-scale roughness noise (one octave a level) on varnished wood: each level decodes within 2% of the
    level below it, yet the coarse levels were 2.1-4.6% off the average of their base texels, and the bake filtered
    across all of them. Each level is now compared with its base texels too: the chain ends where that drifts past
    the tolerance, and every level it keeps is within it."""
    from addon.core.textures.mip import downsample, float32_texels

    rng = np.random.default_rng(0)
    n = 128
    rough = np.full((n, n), 0.5)
    for octave in range(6):
        b = 2**octave
        rough += np.kron(rng.uniform(-0.04, 0.04, (n // b, n // b)), np.ones((b, b)))
    spatial = SpatialStack(preset("varnished_wood"), {"coatings[0].roughness": np.clip(rough, 0.01, 1.0)})
    tex = bake_stack(spatial, encode, calibrate=False, check_filtering=False, threads=2)[0]
    kept, errors = F.filterable_levels(encode.models, tex.levels)
    assert kept < len(tex.levels) and errors[-1] > F.TOLERANCE
    # against the average of the base texels, decoded, over the whole texture: the kept levels are within it
    want = F.decoded(encode.models, float32_texels(tex.levels[0]).reshape(-1, 100)).reshape(n, n, -1)
    for k in range(1, kept):
        want = downsample(want)
        got = F.decoded(encode.models, float32_texels(tex.levels[k]).reshape(-1, 100)).reshape(want.shape)
        assert F.relative_error(got, want) <= 1.5 * F.TOLERANCE


def test_the_worst_pair_of_directions_decides_not_the_grazing_mirror_pairs(encode):
    """A base colour of per-texel noise under a clear coat: its next level decodes 8-9% darker than its texels at
    most pairs of directions, which the pooled measure (1.6-2.0%: the grazing mirror pairs' exact top lobe, the same
    for every texel, held most of the values) passed for 3 levels; the level renders 8% dark seen from afar."""
    from addon.core.stack import Coating, Diffuse, Stack
    from addon.core.textures.mip import downsample, float32_texels

    rng = np.random.default_rng(5)
    stack = Stack(Diffuse((0.7, 0.3, 0.1)), (Coating(roughness=0.3, ior=1.5, albedo=(0.9, 0.8, 0.6), thickness=0.5),))
    spatial = SpatialStack(stack, {"base.albedo": rng.uniform(0.0, 1.0, (32, 32, 3))})
    tex = bake_stack(spatial, encode, calibrate=False, threads=2)[0]
    assert tex.filter_levels == 1
    each = F.decoded(encode.models, float32_texels(tex.levels[0]).reshape(-1, 100)).reshape(32, 32, -1)
    want, got = downsample(each), F.decoded(encode.models, float32_texels(tex.levels[1]).reshape(-1, 100))
    pooled = np.abs(got.reshape(want.shape) - want).mean() / np.abs(want).mean()
    assert pooled < F.TOLERANCE < F.relative_error(got.reshape(want.shape), want)


def test_the_levels_are_measured_where_the_texture_varies_most(encode):
    """A patch of one-texel checkers in a corner of an otherwise even texture: a seeded crop elsewhere passed 4 of
    the levels of a 1,024-texel texture, and the patch rendered 12-32% dark seen from afar."""
    rough = np.full((64, 64), 0.3)
    rough[40:56, 8:24] = np.where((np.add.outer(np.arange(16), np.arange(16)) % 2) == 0, 0.02, 0.6)
    assert F.most_varied_corner(rough[..., None], 16, 16, 2) == (40, 8)
    # a texture larger than the crops, checkers of 8 texels in its first 256 x 256 (which the seeded crops missed:
    # 4 of its 11 levels passed)
    big = np.full((1024, 1024), 0.3)
    big[:256, :256] = np.where((np.add.outer(np.arange(256) // 8, np.arange(256) // 8) % 2) == 0, 0.02, 0.6)
    tex = _bake(encode, big.astype(np.float32), calibrate=False)
    assert tex.filter_levels == 1


def test_a_strip_of_a_texture_is_measured_without_failing(encode):
    """A level one texel high (a 4 x 1,024 texture's third) has no 2 x 2 blocks to choose a crop by: the bake's
    measurement failed with a reshape error."""
    assert F.most_varied_corner(np.zeros((1, 300, 3)), 1, 128, 2) == (0, 0)
    assert F.most_varied_corner(np.zeros((300, 1, 3)), 128, 1, 2) == (0, 0)
    tex = _bake(encode, np.full((4, 64), 0.3, np.float32))
    assert tex.filter_levels == len(tex.levels)

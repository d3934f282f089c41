"""The albedo calibration of latent textures (addon.core.textures.calibration): clusters of texels, a table
per cluster, stored in the texture and applied per hit by the renderer."""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from addon.core.neural import calibrate as cal
from addon.core.render import neural_material
from addon.core.stack import StackArrays, preset
from addon.core.textures import LatentTexture
from addon.core.textures import calibration as tc
from addon.core.textures.bake import BakeCancelled, bake_stack, model_key, neural_encoder
from addon.core.textures.spatial import SpatialStack

K = len(cal.COSINES)


def test_clusters_of_latents_are_found_and_weighted_by_their_texels():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(3, 96)) * 5.0
    truth = np.repeat(np.arange(3), [50, 30, 20])
    z = centres[truth] + rng.normal(size=(100, 96)) * 0.1
    weights = rng.uniform(1.0, 5.0, size=100)
    found, labels = tc.cluster_latents(z, weights, k=3)
    # the same partition (up to the clusters' order), each centroid the weighted mean of its members
    assert len(found) == 3
    for j in range(3):
        members = labels == j
        assert len(np.unique(truth[members])) == 1
        np.testing.assert_allclose(found[j], np.average(z[members], axis=0, weights=weights[members]), atol=1e-6)
    # more clusters asked than distinct latents: one per distinct latent
    found, labels = tc.cluster_latents(centres[truth], np.ones(100), k=8)
    assert len(found) == 3 and len(np.unique(labels)) == 3
    with pytest.raises(ValueError, match="cluster_latents needs rows"):
        tc.cluster_latents(z, np.zeros(100))
    with pytest.raises(ValueError, match="cluster_latents needs rows"):
        tc.cluster_latents(z, np.ones(99))


def _calibration(n_tables, rng):
    tables = rng.uniform(0.3, 3.0, size=(n_tables, K, K, 3))
    tables = (tables + tables.transpose(0, 2, 1, 3)) / 2
    return tc.TextureCalibration(
        np.asarray(cal.COSINES), rng.normal(size=(n_tables, 96)), tables.astype(np.float32), cal.settings_key()
    )


def test_each_row_is_scaled_by_its_own_table_as_one_materials_calibration_would():
    @settings(max_examples=30, deadline=None)
    @given(st.integers(1, 5), st.integers(0, 40), st.integers(0, 2**31))
    def check(n_tables, n, seed):
        rng = np.random.default_rng(seed)
        tex = _calibration(n_tables, rng)
        which = rng.integers(0, n_tables, size=n)
        rows = cal.RowCalibration(tex.cosines, tex.tables, which)
        f = rng.uniform(0.0, 2.0, size=(n, 3))
        wi, wo = (np.c_[rng.normal(size=(n, 2)), rng.uniform(0.0, 1.0, size=n)] for _ in range(2))
        wi, wo = (v / np.linalg.norm(v, axis=1, keepdims=True) for v in (wi, wo))
        got = rows.apply(f, wi, wo)
        for t in range(n_tables):  # one material's calibration with table t, on its rows
            one = cal.AlbedoCalibration(tex.cosines, np.ones((K, 3)), tex.tables[t], *(np.ones((K, 3)),) * 4)
            r = which == t
            np.testing.assert_allclose(got[r], one.apply(f[r], wi[r], wo[r]), rtol=1e-12)
        index = rng.permutation(n)[: n // 2]
        np.testing.assert_allclose(rows.take(index).apply(f[index], wi[index], wo[index]), got[index], rtol=1e-12)

    check()


def test_a_row_choice_of_another_length_than_f_is_a_clear_error():
    from addon.core.neural import load_models

    rng = np.random.default_rng(2)
    tex = _calibration(2, rng)
    rows = cal.RowCalibration(tex.cosines, tex.tables, np.array([0, 1, 0]))
    wi = wo = np.tile([0.0, 0.0, 1.0], (5, 1))
    with pytest.raises(ValueError, match="the calibration has 3 rows, f has 5"):
        rows.apply(np.ones((5, 3)), wi, wo)
    z = np.zeros((3, 32), np.float32)
    with pytest.raises(ValueError, match="the calibration has 3 rows, f has 5"):
        load_models("tiny").eval_brdf(z, wi, wo, calibration=rows)
    rows.check_rows(3)
    cal.RowCalibration(tex.cosines, tex.tables, np.zeros(0, dtype=np.int64)).check_rows(5)  # one table for all


def test_the_calibrations_text_round_trips_and_damage_is_a_clear_error():
    tex = _calibration(3, np.random.default_rng(1))
    back = tc.TextureCalibration.from_text(tex.to_text())
    np.testing.assert_array_equal(back.tables, tex.tables)
    np.testing.assert_allclose(back.centroids, tex.centroids, rtol=1e-6)
    np.testing.assert_array_equal(back.cosines, tex.cosines)
    assert back.is_current() and back.settings == cal.settings_key()
    text = tex.to_text()
    for damaged in (text[:-20], "{}", "not json", text.replace('"shape":[3,', '"shape":[4,')):
        with pytest.raises(ValueError, match="not a latent texture's calibration"):
            tc.TextureCalibration.from_text(damaged)
    negative = tc.TextureCalibration(tex.cosines, tex.centroids, -tex.tables, tex.settings)
    with pytest.raises(ValueError, match="negative"):
        tc.TextureCalibration.from_text(negative.to_text())


def test_the_reference_parts_of_several_stacks_are_their_mean():
    a, b = preset("coated_gold"), preset("frosted_copper")
    walks = (2048,) * K
    both = cal.reference_parts(StackArrays.from_stacks([a, b]), walks=walks, seed=1)
    pa, pb = cal.reference_parts(a, walks=walks, seed=2), cal.reference_parts(b, walks=walks, seed=3)
    for name in ("albedo", "below_top", "below_top_by_exit"):
        mean = (getattr(pa, name) + getattr(pb, name)) / 2
        se = np.sqrt(
            getattr(both, f"{name}_stderr") ** 2
            + (getattr(pa, f"{name}_stderr") ** 2 + getattr(pb, f"{name}_stderr") ** 2) / 4
        )
        assert (np.abs(getattr(both, name) - mean) <= 5 * se + 1e-4).all(), name
    # each of the two rows was walked with half the walks: the mean is about as noisy as one stack's parts
    assert np.median(both.albedo_stderr / pa.albedo_stderr) < 1.2


# coated gold whose clear coat is glossy on the left half and rough on the right: two clusters of texels
def _two_halves():
    rough = np.full((8, 16), 0.02, np.float32)
    rough[:, 8:] = 0.3
    return SpatialStack(preset("coated_gold"), {"coatings[0].roughness": rough})


@pytest.fixture(scope="module")
def baked():
    encode = neural_encoder("tiny", threads=2)
    tex, stats = bake_stack(_two_halves(), encode, threads=2)
    return tex, stats, encode.models


def test_a_bake_stores_one_table_per_cluster_of_its_texels(baked, tmp_path):
    tex, stats, _ = baked
    calibration = tc.TextureCalibration.from_text(tex.metadata["calibration"])
    assert stats.clusters == len(calibration.tables) == 2 and stats.calibration_seconds > 0
    assert calibration.is_current()
    # the two halves' texels choose different tables
    z = tex.levels[0].reshape(-1, 100)[:, :96].reshape(-1, 3, 32)
    which = calibration.at(z).which.reshape(8, 16)
    assert len(np.unique(which[:, :8])) == len(np.unique(which[:, 8:])) == 1 and which[0, 0] != which[0, 15]
    assert not np.allclose(calibration.tables[0], calibration.tables[1], rtol=0.02)
    # written and read back (half-float texels): the same calibration, each texel still its own table
    tex.write_exr(tmp_path / "t.exr")
    back = LatentTexture.read_exr(tmp_path / "t.exr")
    assert back.metadata["calibration"] == tex.metadata["calibration"]
    z_back = back.levels[0].reshape(-1, 100)[:, :96].reshape(-1, 3, 32)
    np.testing.assert_array_equal(calibration.at(z_back).which, calibration.at(z).which)


def test_each_clusters_table_brings_its_texels_albedo_towards_an_independent_reference(baked):
    """The whole directional albedo (exact top lobe + calibrated remainder) of each half's texel, at the
    grid's angles, against reference walks with other seeds than the calibration's."""
    tex, _, models = baked
    calibration = tc.TextureCalibration.from_text(tex.metadata["calibration"])
    arrays, _ = _two_halves().texels()
    errors = {"decoder": [], "texture": []}
    for i in (0, 15):  # a texel of each half
        t = tex.levels[0].reshape(-1, 100)[i]
        z, proxy, top = t[:96].reshape(3, 32), t[96:98], t[98:]
        ref = cal.reference_parts(arrays.stack(i), seed=11)
        moments = cal.decoded_moments(models, z, *proxy, seed=11, top=top)
        table = calibration.tables[calibration.at(z[None]).which[0]]
        above = ref.albedo - ref.below_top  # the top lobe's light, the same in both
        for name, energy in (
            ("decoder", moments.m.sum(axis=1)),
            ("texture", cal.table_energy(moments, table).sum(axis=1)),
        ):
            errors[name].append(np.abs((energy + above) / ref.albedo - 1.0).mean())
    decoder, texture = np.mean(errors["decoder"]), np.mean(errors["texture"])
    assert texture < 0.6 * decoder, (texture, decoder)
    assert max(errors["texture"]) < max(errors["decoder"])


def test_the_renderer_gives_each_hit_the_table_of_its_texels_cluster(baked):
    tex, _, models = baked
    stack = preset("coated_gold")
    material = neural_material.make(stack, tex, calibrate=True)
    assert isinstance(material.calibration, tc.TextureCalibration)
    assert neural_material.make(stack, tex, calibrate="cached").calibration is not None  # read, not made
    assert neural_material.make(stack, tex, calibrate=False).calibration is None
    uv = np.array([[0.1, 0.5], [0.9, 0.5], [0.2, 0.3]])
    bound = material.bind(SimpleNamespace(uv=uv, footprint=np.zeros(3)))
    z, _, top = tex.lookup(uv, np.zeros(3))
    np.testing.assert_array_equal(bound.calibration.which, material.calibration.at(z).which)
    assert bound.calibration.which[0] == bound.calibration.which[2] != bound.calibration.which[1]
    # evaluated per hit: each row the decoder with its cluster's table
    wi = np.array([[0.3, 0.0, 0.95], [0.0, 0.8, 0.6], [0.9, 0.1, 0.1]])
    wo = np.array([[0.0, 0.1, 0.99], [0.5, 0.0, 0.86], [0.0, 0.2, 0.98]])
    wi, wo = (v / np.linalg.norm(v, axis=1, keepdims=True) for v in (wi, wo))
    got = bound.eval(wi, wo)
    for r in range(3):
        one = cal.AlbedoCalibration(
            material.calibration.cosines,
            np.ones((K, 3)),
            material.calibration.tables[bound.calibration.which[r]],
            *(np.ones((K, 3)),) * 4,
        )
        want = models.eval_brdf(z[r], wi[r : r + 1], wo[r : r + 1], top[r], one)
        # the renderer reads the texture's latents through the decoder's first layer, stored in half floats as
        # the texture is (``LatentTexture.projected``): one more rounding of 2^-11 relative
        np.testing.assert_allclose(got[r], want[0], rtol=1e-3)
    # a subset of the rows (the integrator's light rows) keeps each row's table
    np.testing.assert_allclose(bound.eval(wi[[2, 0]], wo[[2, 0]], index=np.array([2, 0])), got[[2, 0]], rtol=1e-6)


@pytest.mark.parametrize("view", [20.0, 80.0])
def test_detail_one_texel_wide_renders_as_the_reference_of_its_texels(view):
    """A checker of a glossy and a rough coat, one texel a square: the renderer blended the latents of the texels
    a hit falls between, which the decoder does not turn into the blend of their BRDFs (0.89 / 0.78 / 0.69 of the
    reference at 80 degrees, magnified or minified). Each hit now decodes one texel, picked by its weight, and the
    pixel's samples average them: the plane in a white sky renders the mean of its two stacks' albedos."""
    import math

    from addon.core import reference
    from addon.core.render import Camera, Environment, RenderSettings, Scene, render, shapes
    from addon.core.render.materials import LayeredSpec
    from addon.core.stack import Coating, Diffuse, Stack

    stack = Stack(Diffuse((0.7, 0.3, 0.1)), (Coating(roughness=0.3, ior=1.5, albedo=(0.9, 0.8, 0.6), thickness=0.5),))
    n = 16
    checker = np.where(np.add.outer(np.arange(n), np.arange(n)) % 2 == 0, 0.02, 0.6)
    spatial = SpatialStack(stack, {"coatings[0].roughness": checker})
    tex, _ = bake_stack(spatial, neural_encoder("tiny", threads=2), threads=2)
    t = math.radians(view)
    wo = np.array([[0.0, -math.sin(t), math.cos(t)]])
    arrays, _ = spatial.texels()
    truth = np.mean([reference.albedo(arrays.take([i]), wo, samples=4000, seed=i)[0][0] for i in (0, 1)], axis=0)
    cam = Camera.look_at((0.0, -20.0 * math.sin(t), 20.0 * math.cos(t)), (0, 0, 0), fov_deg=1.0, width=8, height=8)
    quad = shapes.quad((0, 0, 0), (20, 0, 0), (0, 20, 0))
    quad.uvs = quad.uvs * 40.0  # a texel to about a pixel
    scene = Scene(cam, quad, [LayeredSpec(stack, tex, spatial=spatial)], [], Environment((1.0,) * 3))
    film, _ = render(scene, RenderSettings(samples=64, max_bounces=0, seed=1))
    got = film.mean().reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(got / truth, 1.0, atol=0.05)


def test_a_stale_or_damaged_calibration_renders_uncalibrated_with_a_warning(baked):
    tex, _, _ = baked
    stack = preset("coated_gold")
    stored = tc.TextureCalibration.from_text(tex.metadata["calibration"])
    stale = tc.TextureCalibration(stored.cosines, stored.centroids, stored.tables, "other settings")
    for text, why in ((stale.to_text(), "other calibration settings"), ("{damaged", "cannot be read")):
        other = LatentTexture(tex.levels, {**tex.metadata, "calibration": text})
        with pytest.warns(neural_material.StaleCalibrationWarning, match=why):
            assert neural_material.make(stack, other, calibrate=True).calibration is None
    # a texture baked before calibrations existed: uncalibrated, silently
    old = LatentTexture(tex.levels, {k: v for k, v in tex.metadata.items() if k != "calibration"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert neural_material.make(stack, old, calibrate=True).calibration is None


def test_bakes_without_calibration_and_a_cancel_during_it(baked):
    encode = neural_encoder("tiny", threads=2)
    tex, stats = bake_stack(_two_halves(), encode, calibrate=False)
    assert "calibration" not in tex.metadata and stats.clusters == 0

    def stand_in(arrays):  # an encoder without models: nothing to calibrate against
        return np.zeros((len(arrays), 3, 32)), np.full((len(arrays), 2), 0.5)

    tex, stats = bake_stack(_two_halves(), stand_in)
    assert "calibration" not in tex.metadata
    calls = []

    def cancel():
        calls.append(1)
        return len(calls) > 1  # not during the encoding's one batch, then during the calibration

    fractions = []
    with pytest.raises(BakeCancelled, match="calibration"):
        bake_stack(_two_halves(), encode, cancel=cancel, progress=fractions.append)
    assert fractions and max(fractions) <= 0.3 + 1e-9  # the encoding's share of the bar, nothing after
    # a calibrated bake is keyed apart from an uncalibrated one (and from other calibration settings)
    assert model_key("tiny", "d", calibrated=True) != model_key("tiny", "d")


def test_a_texture_of_more_distinct_texels_than_the_clustering_takes_is_sampled_by_texel_count(monkeypatch, baked):
    """Above ``MAX_ROWS`` distinct texels the clusters come from a sample weighted by texel count: the
    clusters of the two halves are found all the same, each texel still choosing its own half's table."""
    _, _, models = baked
    monkeypatch.setattr(tc, "MAX_ROWS", 20)
    rough = np.linspace(0.02, 0.05, 16 * 8, dtype=np.float32).reshape(8, 16)  # 128 distinct texels
    rough[:, 8:] += 0.4
    spatial = SpatialStack(preset("coated_gold"), {"coatings[0].roughness": rough})
    encode = neural_encoder("tiny", threads=2)
    tex, stats = bake_stack(spatial, encode, threads=2, check_filtering=False)
    calibration = tc.TextureCalibration.from_text(tex.metadata["calibration"])
    assert stats.unique == 128 and 2 <= len(calibration.tables) <= tc.MAX_CLUSTERS
    which = calibration.at(tex.levels[0].reshape(-1, 100)[:, :96].reshape(-1, 3, 32)).which.reshape(8, 16)
    assert not set(which[:, :8].ravel()) & set(which[:, 8:].ravel())  # no table serves both halves


def test_a_cancel_stops_a_bake_inside_a_clusters_calibration(monkeypatch, baked):
    """Esc during a bake's calibration stops it inside the cluster being calibrated (the calibration's ``step``:
    between decoder calls and walk events), not after that cluster's walks."""
    from addon.core.neural import calibrate as cal

    encode = neural_encoder("tiny", threads=2)
    solved = []
    real_solve = cal._solve
    monkeypatch.setattr(cal, "_solve", lambda *a, **k: solved.append(1) or real_solve(*a, **k))
    calls = []

    def cancel():
        calls.append(1)
        return len(calls) > 4  # the encoding's batch, the calibration's start, then two of its steps

    with pytest.raises(BakeCancelled, match="calibration"):
        bake_stack(_two_halves(), encode, cancel=cancel, threads=1)  # one cluster after another
    assert len(calls) == 5 and not solved  # stopped before the first cluster was solved
    # With the clusters calibrated side by side, each stops at its next step: none is solved.
    calls.clear()
    with pytest.raises(BakeCancelled, match="calibration"):
        bake_stack(_two_halves(), encode, cancel=cancel, threads=2)
    assert 5 <= len(calls) <= 6 and not solved


def test_a_textures_clusters_calibrated_side_by_side_are_the_ones_a_lone_thread_makes(baked):
    encode = neural_encoder("tiny", threads=2)
    texts = [bake_stack(_two_halves(), encode, threads=n)[0].metadata["calibration"] for n in (1, 2)]
    assert len(tc.TextureCalibration.from_text(texts[0]).tables) == 2 and texts[0] == texts[1]


def test_a_texture_calibration_of_clamped_top_coatings_records_its_rule_and_older_ones_are_not_current():
    """A remainder decoder's calibration now targets the light below the clamped top coating the renderer adds
    (``calibrate._as_rendered``). A texture calibrated before that rule, some of whose texels' top coatings sit at a
    bound of the trained ranges, is not current (it was rendered with its old factors, silently); one with the rule
    recorded is, and so is an old one whose tops are all inside the ranges (its factors are the same)."""
    from addon.core.neural import calibrate as cal
    from addon.core.textures.calibration import TextureCalibration, top_at_trained_bounds

    tables = np.ones((1, len(cal.COSINES), len(cal.COSINES), 3))
    old = TextureCalibration(np.asarray(cal.COSINES), np.zeros((1, 96)), tables, cal.settings_key())
    new = TextureCalibration(np.asarray(cal.COSINES), np.zeros((1, 96)), tables, cal.settings_key() + cal.TOP_RULE)
    assert new.is_current(True) and new.is_current(False)
    assert old.is_current(False) and not old.is_current(True)
    inside = np.zeros((2, 2, 100), np.float16)
    inside[..., 98], inside[..., 99] = 0.1, 1.5
    assert not top_at_trained_bounds([inside])
    for channel, value in ((98, 0.01), (99, 1.05), (99, 2.0)):  # the clamps' bounds, in half floats
        at = inside.copy()
        at[0, 1, channel] = value
        assert top_at_trained_bounds([at])


def test_a_bake_whose_top_coating_sits_at_a_trained_bound_renders_calibrated():
    """Red car paint's top coat has alpha 0.01, the trained least: its texels sit at a bound, where the renderer asks
    for the rule for clamped tops. The bake recorded the rule only for clamped tops, so every such texture rendered
    uncalibrated with a warning to rebake it, which gave the same texture."""
    texture, _ = bake_stack(SpatialStack(preset("red_car_paint"), {}), neural_encoder())
    assert tc.top_at_trained_bounds(texture.levels)
    with warnings.catch_warnings():
        warnings.simplefilter("error", neural_material.StaleCalibrationWarning)
        assert neural_material._texture_calibration(texture) is not None


def test_a_calibrated_bake_of_a_clamped_top_has_another_key():
    """The bake key of a calibrated texture whose top coatings leave the trained ranges holds the rule, so the
    command's kept bakes and the add-on's texture made before it are baked again; other bakes keep their keys."""
    from addon.core.stack import Coating, Diffuse, Stack
    from addon.core.textures.bake import bake_key
    from addon.core.textures.spatial import SpatialStack

    rough = np.full((4, 4), 0.2)
    clear = SpatialStack(Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.1, 1.5),)), {})
    mapped = SpatialStack(Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.1, 1.5),)), {"coatings[0].roughness": rough})
    smooth = rough.copy()
    smooth[0, 0] = 0.0  # one texel's coat below the trained 0.01
    clamped = SpatialStack(Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.1, 1.5),)), {"coatings[0].roughness": smooth})
    for spatial, changes in ((clear, False), (mapped, False), (clamped, True)):
        calibrated = bake_key(spatial, (4, 4), "tiny+calibrated-abcd1234:digest")
        with pytest.MonkeyPatch.context() as mp:
            from addon.core.textures import bake as bake_module

            mp.setattr(bake_module, "_clamps_top", lambda s: False)
            before = bake_key(spatial, (4, 4), "tiny+calibrated-abcd1234:digest")
        assert (calibrated != before) == changes


def test_a_bake_of_a_top_coating_outside_the_trained_ior_has_another_key(monkeypatch):
    """Texels of a top coating outside the trained ior range hold their own ior since the renderer's top lobe takes
    it: the command's kept bakes and the add-on's textures made before (which hold 1.05 or 2) are baked again;
    others keep their keys."""
    from addon.core.stack import Coating, Diffuse, Stack
    from addon.core.textures import bake as bake_module
    from addon.core.textures.bake import bake_key

    low = SpatialStack(Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.1, 1.0),)), {})
    inside = SpatialStack(Stack(Diffuse((0.5, 0.5, 0.5)), (Coating(0.1, 1.5),)), {})
    keys = [bake_key(s, (4, 4), "tiny") for s in (low, inside)]
    monkeypatch.setattr(bake_module, "_top_ior_outside_trained", lambda s: False)
    assert bake_key(low, (4, 4), "tiny") != keys[0]
    assert bake_key(inside, (4, 4), "tiny") == keys[1]
    texture, _ = bake_stack(low, neural_encoder(), calibrate=False)
    assert float(texture.levels[0][..., -1].max()) == 1.0  # the own ior, as a half float

"""The exact top lobe of the remainder design (addon/core/neural/top_lobe.py) and its consumers:
the decoder's evaluation, the renderer's mixture sampler, the latent texture's top-coat channels."""

import numpy as np
import pytest

from addon.core.bsdf import RoughDielectric
from addon.core.neural import NO_TOP, SIZES, load_models, read_card, top_coat, top_coats
from addon.core.neural import top_lobe as tl
from addon.core.render.neural_material import _BoundNeural
from addon.core.stack import PRESETS, Coating, Conductor, Diffuse, Stack, StackArrays


def hemisphere(rng, n):
    u = rng.random((n, 2))
    z = u[:, 0]
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(2 * np.pi * u[:, 1]), r * np.sin(2 * np.pi * u[:, 1]), z], axis=1)


def test_top_coat_is_the_top_coating_in_the_trained_range_and_none_without_coatings():
    gold = PRESETS["coated_gold"]
    assert np.allclose(top_coat(gold), (gold.coatings[-1].roughness, gold.coatings[-1].ior))
    bare = Stack(Diffuse((0.5, 0.5, 0.5)))
    assert np.array_equal(top_coat(bare), NO_TOP)
    two = Stack(
        Conductor(roughness=0.2, eta=(0.2, 0.9, 1.1), k=(3.9, 2.4, 2.2)),
        [Coating(roughness=0.3, ior=1.4, thickness=0.5), Coating(roughness=0.05, ior=1.6, thickness=0.2)],
    )
    assert np.allclose(top_coat(two), (0.05, 1.6))  # the last coating is the top one
    rows = top_coats(StackArrays.from_stacks([two, two]))
    assert rows.shape == (2, 2) and np.allclose(rows, (0.05, 1.6))
    assert np.array_equal(top_coats(StackArrays.from_stacks([bare])), [NO_TOP])


def test_the_top_lobe_is_the_rough_dielectric_reflection_at_any_direction_length():
    rng = np.random.default_rng(0)
    wi, wo = hemisphere(rng, 500), hemisphere(rng, 500)
    top = np.column_stack([rng.uniform(0.02, 0.6, 500), rng.uniform(1.2, 2.0, 500)])
    f = tl.eval_top(top, wi * 3.0, wo * 0.01)
    want = RoughDielectric(top[:, 0], top[:, 1], reflection_only=True).eval(wi, wo)[:, 0]
    assert np.allclose(f, want, rtol=1e-12)
    assert (f > 0).mean() > 0.9
    below = wi * np.array([1, 1, -1])
    assert not tl.eval_top(top, below, wo).any() and not tl.eval_top(NO_TOP, wi, wo).any()
    with pytest.raises(ValueError, match="alpha >= 0 and ior > 0"):
        tl.eval_top((0.1, -1.5), wi[:1], wo[:1])
    with pytest.raises(ValueError, match="shape"):
        tl.eval_top(np.ones((3, 2)), wi, wo)


def test_eval_pdf_is_eval_and_pdf_from_one_half_vector():
    """``RoughDielectric.eval_pdf`` (and the top lobe's ``eval_pdf_top``) give what ``eval`` and ``pdf`` give
    apart, for reflection, transmission and both sides of the interface."""
    rng = np.random.default_rng(4)
    n = 400
    wi = hemisphere(rng, n)
    wi[:, 2] *= np.where(rng.random(n) < 0.5, 1.0, -1.0)  # reflection and transmission pairs
    wo = hemisphere(rng, n)
    alpha, ior = rng.uniform(0.02, 0.6, n), rng.uniform(0.7, 2.0, n)
    for only in (False, True):
        for mode in ("radiance", "importance"):
            b = RoughDielectric(alpha, ior, reflection_only=only)
            f, p = b.eval_pdf(wi, wo, mode)
            np.testing.assert_allclose(f, b.eval(wi, wo, mode)[:, 0], rtol=1e-12, atol=0)
            np.testing.assert_allclose(p, b.pdf(wi, wo, mode), rtol=1e-12, atol=0)
            assert (f > 0).any() and (p > 0).any()
    top = np.column_stack([alpha, np.maximum(ior, 1.1)])
    f, p = tl.eval_pdf_top(top, wi, wo)
    np.testing.assert_allclose(f, tl.eval_top(top, wi, wo), rtol=1e-12)
    np.testing.assert_allclose(p, tl.pdf_top(top, wi, wo), rtol=1e-12)


@pytest.mark.parametrize("per_hit", [False, True])
def test_the_one_pass_shade_is_eval_pdf_and_sample_direction_together(per_hit):
    """``_BoundNeural.shade`` of a remainder material (one decoder batch and one top-lobe evaluation for the
    proposals and the next-event directions) returns what ``eval``, ``pdf`` and ``sample_direction`` give."""
    m = load_models("tiny", threads=1)
    assert m.remainder
    rng = np.random.default_rng(5)
    n = 2000
    wo = hemisphere(rng, n)
    z = rng.normal(scale=0.5, size=(n, 3, 32)).astype(np.float32) if per_hit else rng.normal(scale=0.5, size=(3, 32))
    top = np.tile([0.1, 1.5], (n, 1)) if per_hit else np.array([0.1, 1.5])
    sig, w = (np.full(n, 0.2), np.full(n, 0.5)) if per_hit else (np.float64(0.2), np.float64(0.5))
    bound = _BoundNeural(m, np.asarray(z, np.float32), sig, w, top=top)
    rows = np.flatnonzero(rng.random(n) < 0.6)
    light_wi = hemisphere(rng, len(rows))
    u_lobe, u = rng.random(n), rng.random((n, 2))
    sh = bound.shade(wo, light_wi, rows, u_lobe, u, need_pdf=True)
    np.testing.assert_allclose(sh.f_light, bound.eval(light_wi, wo[rows], rows), rtol=1e-6)
    np.testing.assert_allclose(sh.pdf_light, bound.pdf(light_wi, wo[rows], rows), rtol=1e-9)
    wi, pdf = bound.sample_direction(wo, u_lobe, u)
    ok = sh.sample.valid
    assert ok.mean() > 0.8
    np.testing.assert_allclose(sh.sample.wi[ok], wi[ok], rtol=1e-12)
    np.testing.assert_allclose(sh.sample.pdf[ok], pdf[ok], rtol=1e-9)
    assert bound.shade(wo, light_wi, rows, u_lobe, u, need_pdf=False).pdf_light is None
    # a bounce with no hit of the material: empty answers
    empty = bound if not per_hit else _BoundNeural(m, z[:0], sig[:0], w[:0], top=top[:0])
    none = empty.shade(wo[:0], light_wi[:0], rows[:0], u_lobe[:0], u[:0], need_pdf=True)
    assert none.f_light.shape == (0, 3) and none.sample.wi.shape == (0, 3) and none.pdf_light is None


@pytest.mark.parametrize("alpha", [0.05, 0.3])
def test_top_samples_carry_their_density_and_estimate_the_lobe_albedo(alpha):
    rng = np.random.default_rng(1)
    n = 200_000
    wo = np.tile([[np.sin(1.0), 0.0, np.cos(1.0)]], (n, 1))
    top = (alpha, 1.5)
    wi, pdf = tl.sample_top(top, wo, rng.random((n, 2)))
    ok = pdf > 0
    assert ok.mean() > 0.9
    assert np.allclose(pdf[ok], tl.pdf_top(top, wi[ok], wo[ok]), rtol=1e-9)
    # E[f cos / pdf] over the samples is the albedo; uniform hemisphere samples give it independently
    est = np.where(ok, tl.eval_top(top, wi, wo) * wi[:, 2] / np.where(ok, pdf, 1.0), 0.0).mean()
    wu = hemisphere(rng, n)
    uniform = (tl.eval_top(top, wu, wo) * wu[:, 2]).mean() * 2 * np.pi
    assert est == pytest.approx(uniform, rel=0.05 if alpha < 0.1 else 0.02)
    assert tl.top_albedo(top, [np.cos(1.0)], samples=n, seed=3)[0] == pytest.approx(est, rel=0.02)
    # the density integrates to the share of samples above the horizon
    assert (tl.pdf_top(top, wu, wo)).mean() * 2 * np.pi == pytest.approx(ok.mean(), rel=0.05)


@pytest.mark.parametrize("alpha", [0.01, 0.1, 0.4])
def test_the_transmission_is_what_the_walks_interface_lets_in(alpha):
    """The table against the interface's own sampler: in importance mode the weight of a transmitted
    sample is f |cos| / pdf, so its mean over samples (reflected ones counting 0) is the share let in."""
    from addon.core.bsdf.base import IMPORTANCE

    rng = np.random.default_rng(8)
    n = 200_000
    cosines = np.array([1.0, 0.6, 0.25, 0.1, 0.03])
    for ior in (1.3, 1.5, 1.9):
        for c in cosines:
            wo = np.tile([np.sqrt(1 - c * c), 0.0, c], (n, 1))
            s = RoughDielectric(alpha, ior).sample(wo, rng.random(n), rng.random((n, 2)), mode=IMPORTANCE)
            mc = np.where(s.transmission, s.weight[:, 0], 0.0).mean()
            got = tl.transmission(np.array([[alpha, ior]]), np.array([c]))[0]
            assert got == pytest.approx(mc, abs=0.01), (alpha, ior, c, got, mc)


def test_the_remainder_scale_is_reciprocal_one_without_a_coat_and_zero_at_the_horizon():
    from addon.core.bsdf.fresnel import fresnel_dielectric

    rng = np.random.default_rng(7)
    wi, wo = hemisphere(rng, 400), hemisphere(rng, 400)
    top = np.column_stack([rng.uniform(0.02, 0.6, 400), rng.uniform(1.2, 2.0, 400)])
    s = tl.remainder_scale(top, wi * 2.0, wo)
    assert np.allclose(s, tl.transmission(top, wi[:, 2]) * tl.transmission(top, wo[:, 2]), rtol=1e-12)
    assert np.allclose(s, tl.remainder_scale(top, wo, wi), rtol=1e-12)
    assert np.all((s > 0) & (s < 1))
    horizon = np.tile([[1.0, 0.0, 0.0]], (400, 1))
    assert np.allclose(tl.remainder_scale(top, horizon, wo), 0.0, atol=1e-12)
    assert np.array_equal(tl.remainder_scale(NO_TOP, wi, wo), np.ones(400))  # uncoated: no factor
    # a nearly smooth coat lets in 1 - F away from grazing
    c = np.array([1.0, 0.7, 0.4])
    smooth = tl.transmission(np.tile([0.01, 1.5], (3, 1)), c)
    assert np.allclose(smooth, 1 - fresnel_dielectric(c, 1.5), atol=0.01)


def test_the_top_share_follows_fresnel_and_is_zero_without_a_top_lobe():
    wo = np.array([[0.0, 0.0, 1.0], [np.sin(1.4), 0.0, np.cos(1.4)], [np.sin(1.55), 0.0, np.cos(1.55)]])
    s = tl.top_share((0.1, 1.5), wo)
    assert np.all(np.diff(s) > 0) and s[0] == pytest.approx(0.04 / (0.04 + 0.25 * 0.96), rel=1e-2)
    assert s.max() <= tl.TOP_SHARE_RANGE[1]
    assert not tl.top_share(NO_TOP, wo).any() and not tl.top_share((0.0, 1.5), wo).any()


class _SamplerOnly:
    """What the mixture sampler reads of a model set (its pdf needs no network)."""

    remainder = True


@pytest.mark.parametrize("per_hit", [False, True])
def test_the_renderers_mixture_sampler_is_consistent_with_its_pdf(per_hit):
    """Exact top-lobe samples mixed with the proxy: every sample's density is the mixture's pdf there,
    and that pdf integrates to the share of samples that land above the horizon."""
    rng = np.random.default_rng(2)
    n = 100_000
    wo = np.tile([[np.sin(0.9), 0.0, np.cos(0.9)]], (n, 1))
    top = np.tile([0.08, 1.5], (n, 1)) if per_hit else np.array([0.08, 1.5])
    sig, w = (np.full(n, 0.3), np.full(n, 0.4)) if per_hit else (np.float64(0.3), np.float64(0.4))
    bound = _BoundNeural(_SamplerOnly(), np.zeros((3, 32), np.float32), sig, w, top=top)
    wi, pdf = bound.sample_direction(wo, rng.random(n), rng.random((n, 2)))
    ok = (pdf > 0) & (wi[:, 2] > 0)
    assert np.allclose(pdf[ok], bound.pdf(wi[ok], wo[ok], np.flatnonzero(ok)), rtol=1e-9)
    share = tl.top_share(np.array([[0.08, 1.5]]), wo[:1])[0]
    assert 0.05 < share < 0.9
    # the samples near the top lobe's mirror direction come from both strategies
    wu = hemisphere(rng, n)
    total = bound.pdf(wu, wo, np.arange(n)).mean() * 2 * np.pi
    assert total == pytest.approx(ok.mean(), rel=0.03)


def test_without_a_remainder_decoder_the_sampler_is_the_proxy():
    class Whole:
        remainder = False

    bound = _BoundNeural(Whole(), np.zeros((3, 32), np.float32), np.float64(0.3), np.float64(0.4), top=(0.1, 1.5))
    assert bound.top is None


@pytest.mark.parametrize("size", SIZES)
def test_a_remainder_decoder_adds_the_exact_top_lobe_and_a_whole_one_does_not(size):
    models = load_models(size, threads=1)
    assert models.remainder is (read_card("decoder", size).get("remainder", False) is True)
    gold = PRESETS["coated_gold"]
    from addon.core.neural import encode_stack

    z = encode_stack(gold, models)
    rng = np.random.default_rng(4)
    wi, wo = hemisphere(rng, 256), hemisphere(rng, 256)
    decoded = models.eval_brdf(z, wi, wo)  # the decoder alone (no top coating given)
    top = top_coat(gold)
    want = decoded
    if models.top_transmission:
        want = want * tl.remainder_scale(top, wi, wo)[:, None]
    if models.remainder:
        want = want + tl.eval_top(top, wi, wo)[:, None]
    assert np.allclose(models.eval_brdf(z, wi, wo, top), want, rtol=1e-5, atol=1e-6)
    assert models.top_transmission <= models.remainder
    if models.remainder:  # the remainder alone, what the sampling network is fitted to
        assert np.allclose(
            models.eval_brdf(z, wi, wo, top, with_top_lobe=False),
            want - tl.eval_top(top, wi, wo)[:, None],
            rtol=1e-4,
            atol=1e-6,
        )


def test_the_default_size_is_a_remainder_decoder():
    """The default size ships the exact top coat + neural remainder design (docs/layering_training.md)."""
    from addon.core.neural import DEFAULT_SIZE

    assert load_models(DEFAULT_SIZE, threads=1).remainder


def test_top_coat_channels_survive_the_exr_and_old_files_read_uncoated(tmp_path):
    pytest.importorskip("bpy")
    from addon.core.textures import CHANNEL_NAMES, LatentTexture
    from addon.core.textures.latent_texture import oiio_module

    rng = np.random.default_rng(5)
    texels = rng.normal(size=(8, 8, len(CHANNEL_NAMES))).astype(np.float32)
    texels[..., -2:] = (0.125, 1.5)
    path = tmp_path / "t.exr"
    LatentTexture.from_texels(texels).write_exr(path)
    back = LatentTexture.read_exr(path)
    assert np.allclose(back.levels[0][..., -2:], (0.125, 1.5))
    _z, _proxy, top = back.lookup(rng.random((10, 2)), np.full(10, 0.01))
    assert np.allclose(top, (0.125, 1.5))
    # a file written before the top-coat channels (98 channels)
    from tests.core.test_texture_files import raw_latent_exr

    levels = LatentTexture.from_texels(texels).levels
    old = raw_latent_exr(oiio_module(), tmp_path / "old.exr", [lv[..., :98] for lv in levels])
    legacy = LatentTexture.read_exr(old)
    assert np.allclose(legacy.levels[0][..., :98], levels[0][..., :98], atol=1e-2)
    assert np.array_equal(legacy.levels[-1][..., 98:], np.broadcast_to(np.float32(NO_TOP), (1, 1, 2)))


@pytest.mark.parametrize("per_hit", [False, True])
def test_the_compiled_proposal_is_the_top_lobe_sampler_where_it_picks_it_and_the_proxy_elsewhere(per_hit):
    """``kernels.propose_with_top`` (one pass over the rows) against the array functions it fuses: the top
    lobe's ``sample_top_directions`` on the rows whose u_lobe falls under ``top_share``, the proxy with u_lobe
    rescaled past the share on the others."""
    from addon.core import kernels
    from addon.core.neural import proxy

    rng = np.random.default_rng(11)
    n = 5000
    wo = hemisphere(rng, n)
    top = np.column_stack([rng.uniform(0.0005, 0.5, n), rng.uniform(0.9, 2.0, n)]) if per_hit else np.array([0.1, 1.5])
    sigma, w = rng.uniform(0.05, 0.5, n), rng.uniform(0.0, 1.0, n)
    u_lobe, u = rng.random(n), rng.random((n, 2))
    wi, share, missed = kernels.propose_with_top(wo, u_lobe, u, sigma, w, np.reshape(top, (-1, 2)))
    np.testing.assert_allclose(share, tl.top_share(top, wo), rtol=1e-12, atol=0)
    pick = u_lobe < share
    assert 0.05 < pick.mean() < 0.9
    t_rows = top[pick] if per_hit else top
    want, ok = tl.sample_top_directions(t_rows, wo[pick], u[pick])
    np.testing.assert_allclose(wi[pick], want, rtol=1e-12, atol=1e-15)
    assert np.array_equal(missed[pick], ~ok) and not missed[~pick].any()
    v = np.clip((u_lobe - share) / (1 - share), 0.0, 1.0 - 1e-12)
    want = proxy.sample_directions(wo[~pick], sigma[~pick], w[~pick], np.column_stack([v, u])[~pick])
    np.testing.assert_allclose(wi[~pick], want, rtol=1e-12, atol=1e-15)


def test_the_transmittance_table_is_made_once_when_two_threads_need_it(monkeypatch):
    """The add-on's warm-up makes the top coat's transmittance table on a thread of its own; a render that needs it
    meanwhile waits for it, where both had made it at once (2-4 s right after Blender starts, against 1.2 s)."""
    import threading
    import time

    from addon.core.neural import top_lobe

    made = []

    def slow_table():
        made.append(threading.get_ident())
        time.sleep(0.2)
        return np.zeros(
            (len(top_lobe.TRANSMITTANCE_COS), len(top_lobe.TRANSMITTANCE_ALPHA), len(top_lobe.TRANSMITTANCE_IOR))
        )

    monkeypatch.setattr(top_lobe, "transmittance_table", slow_table)
    top_lobe._transmittance_grids.cache_clear()
    try:
        threads = [threading.Thread(target=top_lobe.transmittance_grids) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(made) == 1
    finally:
        top_lobe._transmittance_grids.cache_clear()  # the real table for the tests after this one

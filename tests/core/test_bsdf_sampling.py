"""Every sampler against its own density: chi-square over a binned sphere (as Mitsuba 3's
chi2 tests), and the sample weight against f |cos| / pdf."""

import numpy as np
import pytest

from addon.core.bsdf import (
    IMPORTANCE,
    RADIANCE,
    HenyeyGreenstein,
    Lambertian,
    RoughConductor,
    RoughDielectric,
    ggx,
)
from tests.stats import chi2_direction_test, chi2_sphere

N_SAMPLES = 100_000
# equal-area bins in (cos theta, phi), each integrated with SUB midpoints: fine, because rough
# transmission has a steep edge (the pdf grows toward the boundary of the reachable cone)
BINS = dict(theta_bins=40, phi_bins=80, sub=(24, 12))
SIGNIFICANCE = 1e-3  # per test, on a seeded (deterministic) run


def chi2(wi, valid, pdf_fn, pole="z"):
    return chi2_sphere(wi, valid, pdf_fn, pole=pole, **BINS)


def _dir(theta_deg, phi_deg=30.0, below=False):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    w = np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])
    if below:
        w[2] = -w[2]
    return w


def _check_bsdf(bsdf, wo, seed, mode=RADIANCE):
    rng = np.random.default_rng(seed)
    n = N_SAMPLES
    wos = np.tile(wo, (n, 1))
    s = bsdf.sample(wos, rng.random(n), rng.random((n, 2)), mode=mode)
    v = s.valid
    assert v.sum() > 0.5 * n
    # invalid rows are zeroed
    assert np.all(s.weight[~v] == 0.0) and np.all(s.pdf[~v] == 0.0)
    assert np.all(np.isfinite(s.weight)) and np.all(s.weight >= 0.0)
    # the recorded pdf is the pdf() of the sampled direction, and weight = f |cos| / pdf
    p = bsdf.pdf(s.wi[v], wos[v], mode=mode)
    f = bsdf.eval(s.wi[v], wos[v], mode=mode)
    np.testing.assert_allclose(p, s.pdf[v], rtol=1e-6)
    np.testing.assert_allclose(f * np.abs(s.wi[v, 2:3]) / p[:, None], s.weight[v], rtol=1e-6, atol=1e-12)
    # transmission flag = opposite side
    np.testing.assert_array_equal(s.transmission[v], s.wi[v, 2] * wo[2] < 0.0)
    # sample distribution matches pdf()
    res = chi2(s.wi, v, lambda g: bsdf.pdf(g, np.tile(wo, (g.shape[0], 1)), mode=mode))
    total = res.pdf_integral
    assert res.pvalue > SIGNIFICANCE, f"chi-square p = {res.pvalue:.2e} (pdf integrates to {total:.4f})"
    # the fraction of valid samples is the integral of the pdf
    assert abs(v.mean() - total) < 5.0 * np.sqrt(max(total * (1 - total), 0.0) / n) + 2e-3


@pytest.mark.parametrize("below", [False, True])
def test_lambertian_sampling(below):
    _check_bsdf(Lambertian([0.2, 0.5, 0.9]), _dir(40.0, below=below), seed=1)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
@pytest.mark.parametrize("theta", [30.0, 80.0])
def test_conductor_sampling(alpha, theta):
    b = RoughConductor(alpha, eta=[0.2, 0.9, 1.1], k=[3.9, 2.4, 2.2])
    _check_bsdf(b, _dir(theta), seed=int(alpha * 100 + theta))


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
@pytest.mark.parametrize("below", [False, True])
def test_dielectric_sampling(alpha, below):
    _check_bsdf(RoughDielectric(alpha, 1.5), _dir(50.0, below=below), seed=int(alpha * 100) + 7 * below)


@pytest.mark.parametrize("ior", [1.4 / 1.6, 2.4])
@pytest.mark.parametrize("below", [False, True])
def test_dielectric_sampling_relative_ior(ior, below):
    # interfaces between two media: relative ior < 1 (TIR seen from above) and a high one
    _check_bsdf(RoughDielectric(0.2, ior), _dir(70.0, below=below), seed=11 + 3 * below, mode=IMPORTANCE)


@pytest.mark.parametrize("below", [False, True])
def test_dielectric_reflection_only_sampling(below):
    b = RoughDielectric(0.3, 1.5, reflection_only=True)
    _check_bsdf(b, _dir(60.0, below=below), seed=5)


@pytest.mark.parametrize("below", [False, True])
@pytest.mark.parametrize("alpha", [0.05, 0.6])
def test_visible_normal_sampling(alpha, below):
    rng = np.random.default_rng(3)
    w = np.tile(_dir(65.0, below=below), (N_SAMPLES, 1))
    m = ggx.sample_visible_normal(w, alpha, rng.random((N_SAMPLES, 2)))
    assert np.all(m[:, 2] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(m, axis=1), 1.0, atol=1e-12)
    # m peaks at +z, where the (cos theta, phi) bins are too coarse for small alpha: bin with
    # the grid's pole on +y, which puts +z on the grid's equator
    res = chi2(
        m,
        np.ones(N_SAMPLES, bool),
        lambda g: ggx.pdf_visible_normal(np.tile(w[0], (g.shape[0], 1)), g, alpha),
        pole="y",
    )
    assert abs(res.pdf_integral - 1.0) < 2e-3
    assert res.pvalue > SIGNIFICANCE


@pytest.mark.parametrize("g", [-0.5, 0.0, 0.8])
def test_henyey_greenstein_sampling(g):
    rng = np.random.default_rng(4)
    wo = np.tile(_dir(20.0), (N_SAMPLES, 1))
    hg = HenyeyGreenstein(g)
    wi, pdf = hg.sample(wo, rng.random((N_SAMPLES, 2)))
    np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(pdf, hg.pdf(wi, wo), rtol=1e-9)
    res = chi2(wi, np.ones(N_SAMPLES, bool), lambda g: hg.pdf(g, np.tile(wo[0], (g.shape[0], 1))))
    assert abs(res.pdf_integral - 1.0) < 2e-3
    assert res.pvalue > SIGNIFICANCE
    # pbrt-v4 convention: both directions point away, so the mean of wi.wo is -g
    assert abs(np.mean(np.sum(wi * wo, axis=1)) + g) < 0.01


@pytest.mark.parametrize("pole", ["z", "y"])
def test_chi2_detects_a_wrong_density(pole):
    """The test itself has power: a sampler checked against a slightly different pdf fails, and
    passes against its own (with either pole of the binning grid)."""
    rng = np.random.default_rng(9)
    wo = np.tile(_dir(30.0), (N_SAMPLES, 1))
    s = RoughConductor(0.3, 1.0, 3.0).sample(wo, rng.random(N_SAMPLES), rng.random((N_SAMPLES, 2)))
    for alpha, detected in ((0.33, True), (0.3, False)):
        bsdf = RoughConductor(alpha, 1.0, 3.0)
        res = chi2(s.wi, s.valid, lambda g, b=bsdf: b.pdf(g, np.tile(wo[0], (g.shape[0], 1))), pole=pole)
        assert (res.pvalue < 1e-6) == detected, (alpha, res.pvalue)


def test_chi2_detects_samples_where_the_density_is_zero():
    """Samples in the lower hemisphere against a reflection-only density: rejected outright."""
    rng = np.random.default_rng(10)
    wo = np.tile(_dir(30.0), (20_000, 1))
    s = Lambertian(0.5).sample(wo, rng.random(20_000), rng.random((20_000, 2)))
    wi = s.wi.copy()
    wi[:100, 2] *= -1.0
    with pytest.raises(AssertionError, match="density is zero"):
        chi2(wi, s.valid, lambda g: Lambertian(0.5).pdf(g, np.tile(wo[0], (g.shape[0], 1))))


def test_chi2_direction_test_has_power():
    """The sample-drawing entry point (the proxy's and the sampling network's tests) rejects a
    cosine lobe checked against a slightly wider one."""
    wo1 = _dir(0.0)

    def sample_fn(n, rng):
        s = Lambertian(0.5).sample(np.tile(wo1, (n, 1)), rng.random(n), rng.random((n, 2)))
        return np.where(s.valid[:, None], s.wi, np.nan)

    def cos_power(k):
        return lambda g: np.where(g[:, 2] > 0.0, (k + 1) / (2 * np.pi) * np.maximum(g[:, 2], 0.0) ** k, 0.0)

    assert chi2_direction_test(sample_fn, cos_power(1.0), n=100_000, seed=2)[1] > SIGNIFICANCE
    assert chi2_direction_test(sample_fn, cos_power(1.1), n=100_000, seed=2)[1] < 1e-6

"""Every sampler against its own density: chi-square over a binned sphere (as Mitsuba 3's
chi2 tests), and the sample weight against f |cos| / pdf."""

import numpy as np
import pytest
from scipy import stats

from addon.core.bsdf import (
    IMPORTANCE,
    RADIANCE,
    HenyeyGreenstein,
    Lambertian,
    RoughConductor,
    RoughDielectric,
    ggx,
)

N_SAMPLES = 100_000
# equal-area bins in (cos theta, phi), each integrated with SUBZ x SUBPHI midpoints: fine, because
# rough transmission has a steep edge (the pdf grows toward the boundary of the reachable cone)
NZ, NPHI, SUBZ, SUBPHI = 40, 80, 24, 12
SIGNIFICANCE = 1e-3  # per test, on a seeded (deterministic) run


def _grid():
    z = -1.0 + (np.arange(NZ * SUBZ) + 0.5) * (2.0 / (NZ * SUBZ))
    phi = (np.arange(NPHI * SUBPHI) + 0.5) * (2.0 * np.pi / (NPHI * SUBPHI))
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1.0 - zz * zz)
    w = np.stack([r * np.cos(pp), r * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    dw = 4.0 * np.pi / w.shape[0]
    return w, dw


GRID, GRID_DW = _grid()


def _bin_index(w):
    iz = np.clip(((w[:, 2] + 1.0) * 0.5 * NZ).astype(int), 0, NZ - 1)
    phi = np.mod(np.arctan2(w[:, 1], w[:, 0]), 2.0 * np.pi)
    ip = np.clip((phi / (2.0 * np.pi) * NPHI).astype(int), 0, NPHI - 1)
    return iz * NPHI + ip


def chi2_pvalue(pdf_values_on_grid, wi, valid):
    """p-value that samples ``wi[valid]`` (with the rest counted as 'no sample') come from the
    density whose values on GRID are given. Bins expecting fewer than 5 samples are pooled."""
    n = wi.shape[0]
    p = pdf_values_on_grid.reshape(NZ, SUBZ, NPHI, SUBPHI).sum(axis=(1, 3)).ravel() * GRID_DW
    expected = np.append(p * n, max(n * (1.0 - p.sum()), 0.0))
    observed = np.append(np.bincount(_bin_index(wi[valid]), minlength=NZ * NPHI), n - valid.sum())
    low = expected < 5.0
    e = np.append(expected[~low], expected[low].sum())
    o = np.append(observed[~low], observed[low].sum())
    keep = e > 0.0
    assert np.all(o[~keep] == 0), "samples fall where the density is zero"
    e, o = e[keep], o[keep]
    e *= o.sum() / e.sum()  # the quadrature total is 1 only to O(1e-4)
    stat = np.sum((o - e) ** 2 / e)
    return stats.chi2.sf(stat, len(e) - 1), p.sum()


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
    grid_pdf = bsdf.pdf(GRID, np.tile(wo, (GRID.shape[0], 1)), mode=mode)
    pval, total = chi2_pvalue(grid_pdf, s.wi, v)
    assert pval > SIGNIFICANCE, f"chi-square p = {pval:.2e} (pdf integrates to {total:.4f})"
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
    # m peaks at +z, where the (cos theta, phi) bins are too coarse for small alpha: bin in a
    # rotated frame (a cyclic permutation of the axes) that puts +z on the grid's equator
    grid_m = GRID[:, [1, 2, 0]]
    grid_pdf = ggx.pdf_visible_normal(np.tile(w[0], (GRID.shape[0], 1)), grid_m, alpha)
    pval, total = chi2_pvalue(grid_pdf, m[:, [2, 0, 1]], np.ones(N_SAMPLES, bool))
    assert abs(total - 1.0) < 2e-3
    assert pval > SIGNIFICANCE


@pytest.mark.parametrize("g", [-0.5, 0.0, 0.8])
def test_henyey_greenstein_sampling(g):
    rng = np.random.default_rng(4)
    wo = np.tile(_dir(20.0), (N_SAMPLES, 1))
    hg = HenyeyGreenstein(g)
    wi, pdf = hg.sample(wo, rng.random((N_SAMPLES, 2)))
    np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(pdf, hg.pdf(wi, wo), rtol=1e-9)
    pval, total = chi2_pvalue(hg.pdf(GRID, np.tile(wo[0], (GRID.shape[0], 1))), wi, np.ones(N_SAMPLES, bool))
    assert abs(total - 1.0) < 2e-3
    assert pval > SIGNIFICANCE
    # pbrt-v4 convention: both directions point away, so the mean of wi.wo is -g
    assert abs(np.mean(np.sum(wi * wo, axis=1)) + g) < 0.01


def test_chi2_detects_a_wrong_density():
    """The test itself has power: a sampler checked against a slightly different pdf fails."""
    rng = np.random.default_rng(9)
    wo = np.tile(_dir(30.0), (N_SAMPLES, 1))
    s = RoughConductor(0.3, 1.0, 3.0).sample(wo, rng.random(N_SAMPLES), rng.random((N_SAMPLES, 2)))
    wrong = RoughConductor(0.33, 1.0, 3.0).pdf(GRID, np.tile(wo[0], (GRID.shape[0], 1)))
    pval, _ = chi2_pvalue(wrong, s.wi, s.valid)
    assert pval < 1e-6

"""The sampling proxy: sample() agrees with pdf() (chi-square), pdf integrates to the valid mass."""

import numpy as np
import pytest

from addon.core.neural import proxy
from tests.stats import chi2_direction_test


@pytest.mark.parametrize("theta_o", [0.0, 40.0, 75.0])
@pytest.mark.parametrize("sigma, w", [(0.08, 0.0), (0.3, 0.3), (0.7, 0.9), (0.02, 0.5)])
def test_sample_matches_pdf_chi_square(theta_o, sigma, w):
    t = np.radians(theta_o)
    wo1 = np.array([np.sin(t), 0.0, np.cos(t)])

    def sample(n, rng):
        wo = np.tile(wo1, (n, 1))
        wi, p = proxy.sample(wo, sigma, w, rng.random((n, 3)))
        wi[p <= 0] = np.nan  # below-horizon samples are rejected (pdf 0)
        return wi

    def density(wi):
        return proxy.pdf(np.tile(wo1, (len(wi), 1)), wi, sigma, w)

    stat, p = chi2_direction_test(sample, density, n=100_000, theta_bins=24, phi_bins=48)
    assert p > 1e-3, (stat, p)


def test_pdf_returned_by_sample_equals_pdf():
    rng = np.random.default_rng(1)
    wo = rng.normal(size=(1000, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    sigma = rng.uniform(0.01, 1.0, 1000)
    w = rng.random(1000)
    wi, p = proxy.sample(wo, sigma, w, rng.random((1000, 3)))
    assert np.allclose(p, proxy.pdf(wo, wi, sigma, w))
    assert np.isfinite(wi).all() and (p >= 0).all()


def test_bad_input():
    with pytest.raises(ValueError, match="finite"):
        proxy.pdf(np.array([[0, 0, 1.0]]), np.array([[0, 0, 1.0]]), np.nan, 0.5)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        proxy.sample(np.zeros((4, 2)), 0.1, 0.1, np.zeros((4, 3)))

"""Lobe images: geometry of the projected hemisphere, albedo integration, error metric."""

import numpy as np
import pytest

from addon.core import lobe


def lambert(albedo):
    return lambda wi, wo: np.full((len(wi), 3), albedo / np.pi)


def test_lambertian_lobe_integrates_to_its_albedo():
    img = lobe.lobe_image(lambert(0.7), theta_i_deg=30.0, res=256)
    assert np.allclose(lobe.albedo_from_lobe(img), 0.7, rtol=5e-3)


def test_lobe_grid_directions_are_unit_and_upper_hemisphere():
    wo, mask = lobe.lobe_grid(32)
    assert np.allclose(np.linalg.norm(wo, axis=1), 1.0)
    assert (wo[:, 2] >= 0).all()
    assert 0.7 < mask.mean() < 0.82  # pi/4 of the square


def test_incident_direction_and_mirror_side():
    wi = lobe.incident_direction(60.0)
    assert np.isclose(wi[2], 0.5) and wi[0] < 0  # mirror direction lands at +x


def test_relative_rmse():
    ref = np.ones((4, 4, 3))
    assert lobe.relative_rmse(ref * 1.1, ref) == pytest.approx(0.1)
    assert lobe.relative_rmse(ref * 0, ref * 0) == 0.0
    with pytest.raises(ValueError, match="shapes differ"):
        lobe.relative_rmse(ref, ref[:2])


def test_relative_rmse_and_albedo_per_image_match_one_image_at_a_time():
    rng = np.random.default_rng(0)
    est, ref = rng.random((3, 4, 8, 8, 3)), rng.random((3, 4, 8, 8, 3))
    ref[0, 0] = 0.0  # a black reference: inf, as for one image
    est[1, 1] = ref[1, 1] = 0.0  # both black: 0
    per = lobe.relative_rmse(est, ref, image_axes=3)
    one = np.array([[lobe.relative_rmse(est[i, j], ref[i, j]) for j in range(4)] for i in range(3)])
    assert per.shape == (3, 4) and np.array_equal(per, one)
    assert np.isinf(per[0, 0]) and per[1, 1] == 0.0
    alb = np.array([[lobe.albedo_from_lobe(est[i, j]) for j in range(4)] for i in range(3)])
    np.testing.assert_allclose(lobe.albedo_from_lobe(est), alb, rtol=1e-12)

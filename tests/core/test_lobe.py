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

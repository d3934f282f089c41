"""Point and spot lights of a radius and suns of an angle, as Cycles builds them: a sphere (Soft Falloff off) or a
disk facing the lit point (Soft Falloff on), a disk of the sky. Their sampling against their own density (the one
the intersection of a ray gives), the irradiance they give against its closed form, and their limits at radius and
angle 0 (the delta lights, which are kept as they were)."""

import math

import numpy as np
import pytest

from addon.core import kernels
from addon.core.render import PointLight, SpotLight, SunLight
from tests.stats import chi2_sphere

N = 200_000


def _samples(light, p, n=N, seed=0):
    return light.sample(np.tile(p, (n, 1)), np.random.default_rng(seed).random((n, 2)))


def _lights():
    """(name, light, point): each kind of soft light seen from the origin, the cone it fills about +z with the
    cosine 0.8 at its edge (an edge of the chi-square's grid: a density that steps there is binned exactly)."""
    sun_angle = 2.0 * math.acos(0.8)
    return [
        ("sphere", PointLight((0.0, 0.0, 1.0), 100.0, radius=0.6, soft_falloff=False), (0.0, 0.0, 0.0)),
        ("sphere-inside", PointLight((0.0, 0.0, 0.3), 100.0, radius=1.0, soft_falloff=False), (0.0, 0.0, 0.0)),
        ("facing-disk", PointLight((0.0, 0.0, 1.0), 100.0, radius=0.75), (0.0, 0.0, 0.0)),
        (
            "spot-sphere",
            SpotLight((0.0, 0.0, 1.0), 100.0, spot_size=0.8, blend=0.3, radius=0.6, soft_falloff=False),
            (0.0, 0.0, 0.0),
        ),
        ("spot-disk", SpotLight((0.0, 0.0, 1.0), 100.0, spot_size=0.8, blend=0.3, radius=0.75), (0.0, 0.0, 0.0)),
        ("sun-disk", SunLight((0.0, 0.0, -1.0), 3.0, angle=sun_angle), (0.0, 0.0, 0.0)),
    ]


@pytest.mark.parametrize("name, light, p", _lights(), ids=[c[0] for c in _lights()])
def test_a_soft_lights_samples_follow_the_density_its_intersection_gives(name, light, p):
    """Chi-square of the sampled directions against the solid-angle density a ray's intersection reports for
    them (the density multiple importance sampling weighs a BSDF ray that hits the light with), which integrates to
    1 over the cone the light fills; every sample lies where a ray toward it meets the light, at the sampled
    distance, with the share of the radiance the sample carries (a spot's cone)."""
    p = np.asarray(p, dtype=np.float64)
    ls = _samples(light, p)
    assert not ls.delta and np.all(ls.pdf > 0)
    res = chi2_sphere(ls.wi, np.ones(N, bool), lambda d: light.intersect(np.tile(p, (len(d), 1)), d)[1])
    assert res.pvalue > 1e-3, (name, res)
    assert res.pdf_integral == pytest.approx(1.0, abs=3e-3)
    t, pdf, share = light.intersect(np.tile(p, (N, 1)), ls.wi)
    np.testing.assert_allclose(pdf, ls.pdf, rtol=1e-9)
    if name != "sun-disk":
        np.testing.assert_allclose(t, ls.dist, rtol=1e-7)
    radiance = light.table_row()[1][3:6]
    np.testing.assert_allclose(ls.radiance, share[:, None] * radiance, rtol=1e-9)
    if name.startswith("spot"):
        assert 0.0 < share.mean() < 1.0  # the cone cuts the light


def _irradiance(light, p, normal, n=N, seed=1):
    """Monte Carlo irradiance on a surface at ``p`` facing ``normal``, and its standard error."""
    ls = _samples(light, np.asarray(p, dtype=np.float64), n, seed)
    e = ls.radiance[:, 0] * np.clip(ls.wi @ np.asarray(normal, dtype=np.float64), 0.0, None) / ls.pdf
    return e.mean(), e.std() / math.sqrt(n)


@pytest.mark.parametrize("radius", [0.3, 1.0, 1.5])
@pytest.mark.parametrize("tilt_deg", [0.0, 40.0])
def test_a_sphere_lights_irradiance_is_a_point_lights_of_its_power(radius, tilt_deg):
    """A sphere of even radiance I / (pi r^2) whose cone lies above the surface's horizon gives I cos / d^2 whatever
    its radius (Cycles' normalisation: its power over the sphere's area and pi)."""
    d, tilt = 2.0, math.radians(tilt_deg)
    light = PointLight((0.0, 0.0, d), 100.0, radius=radius, soft_falloff=False)
    e, se = _irradiance(light, (0.0, 0.0, 0.0), (math.sin(tilt), 0.0, math.cos(tilt)))
    want = 100.0 / (4 * math.pi) * math.cos(tilt) / d**2
    assert abs(e - want) < 4 * se + 1e-9 and abs(e / want - 1) < 0.01, (e, want, se)


@pytest.mark.parametrize("radius", [0.3, 1.0, 2.5])
def test_a_facing_disks_irradiance_on_its_axis_is_the_disks_closed_form(radius):
    """Soft Falloff (Blender's default): a disk of radius r and radiance I / (pi r^2) square to the line to the point,
    whose irradiance on its axis is I / (d^2 + r^2): softer than a point's near it (Cycles' 0.69 of it at d = 1.5,
    r = 1, where ours rendered the point's)."""
    d = 1.5
    light = PointLight((0.0, 0.0, d), 100.0, radius=radius)
    e, se = _irradiance(light, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    want = 100.0 / (4 * math.pi) / (d**2 + radius**2)
    assert abs(e - want) < 4 * se + 1e-9 and abs(e / want - 1) < 0.01, (e, want, se)


@pytest.mark.parametrize("angle_deg", [0.5, 10.0, 60.0])
def test_a_sun_disks_irradiance_is_its_strength(angle_deg):
    """A sun of an angle gives its strength to a surface facing it, and strength x cos to a tilted one whose horizon
    the disk clears (Cycles' radiance: the strength over the disk's area pi sin^2(angle / 2))."""
    sun = SunLight((0.0, 0.0, -1.0), 3.0, angle=math.radians(angle_deg))
    for tilt in (0.0, math.radians(50.0)):
        e, se = _irradiance(sun, (0.0, 0.0, 0.0), (math.sin(tilt), 0.0, math.cos(tilt)))
        assert abs(e - 3.0 * math.cos(tilt)) < 4 * se + 1e-9 and abs(e / (3.0 * math.cos(tilt)) - 1) < 0.01


@pytest.mark.parametrize("soft_falloff", [False, True])
def test_as_the_radius_goes_to_zero_a_sphere_or_disk_light_tends_to_the_point_light(soft_falloff):
    """At points near and far, in and out of a spot's cone, the irradiance of a light of radius r tends to the point
    light's (within 10% at r = 0.01, 0.1% at 0.0001: its samples' spread is O(r / d), its bias O(r^2 / d^2)); at
    radius 0 the light is the delta light it was (its kind, its row's intensity)."""
    rng = np.random.default_rng(4)
    points = rng.uniform(-1.0, 1.0, (6, 3))
    normal = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
    for make in (
        lambda r: PointLight((0.1, 0.2, 2.0), 100.0, radius=r, soft_falloff=soft_falloff),
        lambda r: SpotLight((0.1, 0.2, 2.0), 100.0, spot_size=1.2, blend=0.4, radius=r, soft_falloff=soft_falloff),
    ):
        point = make(0.0)
        kind, row = point.table_row()
        assert kernels.is_delta(kind) and kind in (kernels.POINT, kernels.SPOT)
        np.testing.assert_array_equal(row[3:6], point.intensity)
        for p in points:
            ls = _samples(point, p, n=4)
            want = ls.radiance[0, 0] * max(ls.wi[0] @ normal, 0.0)
            for r, rel in ((1e-2, 0.1), (1e-4, 1e-3)):
                e, _ = _irradiance(make(r), p, normal, n=2000)
                assert abs(e - want) <= rel * max(want, 1e-6), (r, e, want)


def test_as_the_angle_goes_to_zero_a_sun_disk_tends_to_the_sun():
    normal = np.array([0.5, 0.0, 0.8]) / np.linalg.norm([0.5, 0.0, 0.8])
    sun = SunLight((0.2, 0.1, -1.0), 3.0)
    assert sun.table_row()[0] == kernels.SUN
    want = 3.0 * float(-sun.direction @ normal)
    for angle in (1e-2, 1e-4):
        e, _ = _irradiance(SunLight((0.2, 0.1, -1.0), 3.0, angle=angle), (0.0, 0.0, 0.0), normal, n=2000)
        assert abs(e / want - 1) < angle


def test_normalize_off_is_cycles_power_over_pi():
    """Blender 5's Normalize on a point, spot or sun light: off, Cycles takes the power over pi as the radiance (a
    light of no radius: as its intensity, 4 times the normalised one; a sun of an angle: its strength as the disk's
    radiance). Cycles' images: 0.73 against 0.20 for a point light of 300 W with it off and on."""
    point = PointLight((0.0, 0.0, 1.0), 100.0, normalize=False)
    np.testing.assert_allclose(point.intensity, 100.0 / math.pi)
    soft = PointLight((0.0, 0.0, 1.0), 100.0, radius=0.5, normalize=False)
    np.testing.assert_allclose(soft.table_row()[1][3:6], 100.0 / math.pi)
    sun = SunLight((0.0, 0.0, -1.0), 3.0, angle=math.radians(10.0), normalize=False)
    np.testing.assert_allclose(sun.table_row()[1][3:6], 3.0)
    np.testing.assert_allclose(SunLight((0.0, 0.0, -1.0), 3.0, normalize=False).table_row()[1][3:6], 3.0)


def test_rays_meet_a_sphere_once_where_they_enter_it_and_miss_what_they_pass():
    light = PointLight((0.0, 0.0, 2.0), 100.0, radius=0.5, soft_falloff=False)
    o = np.zeros((3, 3))
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.3, 0.0, 1.0] / np.linalg.norm([0.3, 0.0, 1.0])])
    t, pdf, share = light.intersect(o, d)
    assert t[0] == pytest.approx(1.5) and share[0] == 1.0
    assert np.isinf(t[1]) and share[1] == 0.0  # away from it
    assert np.isinf(t[2]) and share[2] == 0.0  # past it: 0.29 rad off, its cone is asin(0.25) = 0.25
    with pytest.raises(ValueError, match="rays cannot hit it"):
        PointLight((0.0, 0.0, 2.0), 100.0).intersect(o, d)

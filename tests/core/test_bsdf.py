"""Analytic BSDFs: frames, Fresnel, GGX identities, energy (furnace), reciprocity, smooth
limits, per-row parameters, bad input and grazing directions."""

import numpy as np
import pytest
from scipy import integrate

from addon.core.bsdf import (
    IMPORTANCE,
    RADIANCE,
    SMOOTH_ALPHA,
    HenyeyGreenstein,
    Lambertian,
    RoughConductor,
    RoughDielectric,
    coordinate_system,
    fresnel_conductor,
    fresnel_dielectric,
    ggx,
    normalize,
    reflect,
    refract,
    to_local,
    to_world,
)

GOLD = dict(eta=[0.143, 0.374, 1.442], k=[3.983, 2.385, 1.603])


def random_dirs(rng, n, upper=None):
    v = normalize(rng.normal(size=(n, 3)))
    if upper is True:
        v[:, 2] = np.abs(v[:, 2])
    elif upper is False:
        v[:, 2] = -np.abs(v[:, 2])
    return v


def sphere_quadrature(nz=800, nphi=800):
    """Midpoint rule on (cos theta, phi): directions (M, 3) and the solid angle of each."""
    z = -1.0 + (np.arange(nz) + 0.5) * (2.0 / nz)
    phi = (np.arange(nphi) + 0.5) * (2.0 * np.pi / nphi)
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1.0 - zz * zz)
    w = np.stack([r * np.cos(pp), r * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    return w, 4.0 * np.pi / w.shape[0]


def all_bsdfs():
    return {
        "lambert": Lambertian([0.3, 0.6, 0.9]),
        "conductor": RoughConductor(0.3, **GOLD),
        "conductor_smooth": RoughConductor(0.0, **GOLD),
        "dielectric": RoughDielectric(0.3, 1.5),
        "dielectric_smooth": RoughDielectric(0.0, 1.5),
        "dielectric_rel": RoughDielectric(0.2, 1.4 / 1.6),
        "dielectric_base": RoughDielectric(0.3, 1.5, reflection_only=True),
        "index_matched": RoughDielectric(0.3, 1.0),
    }


# ----------------------------------------------------------------------------- frames


def test_coordinate_system_is_orthonormal_and_right_handed():
    rng = np.random.default_rng(0)
    n = np.concatenate([random_dirs(rng, 1000), [[0, 0, 1], [0, 0, -1], [1, 0, -0.0], [0, 1, 0.0]]])
    n = normalize(n)
    s, t = coordinate_system(n)
    for a, b in [(s, t), (s, n), (t, n)]:
        np.testing.assert_allclose(np.sum(a * b, axis=1), 0.0, atol=1e-12)
    for a in (s, t):
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(s, t), n, atol=1e-12)
    v = random_dirs(rng, n.shape[0])
    local = to_local(v, s, t, n)
    np.testing.assert_allclose(local[:, 2], np.sum(v * n, axis=1), atol=1e-12)
    np.testing.assert_allclose(to_world(local, s, t, n), v, atol=1e-12)


def test_reflect_and_refract_obey_the_laws():
    rng = np.random.default_rng(1)
    w = random_dirs(rng, 2000)
    n = np.tile([0.0, 0.0, 1.0], (2000, 1))
    r = reflect(w, n)
    np.testing.assert_allclose(r[:, 2], w[:, 2], atol=1e-12)
    np.testing.assert_allclose(r[:, :2], -w[:, :2], atol=1e-12)
    eta = 1.5
    wt, ok = refract(w, n, eta)
    above = w[:, 2] > 0
    # from above everything refracts; Snell: n_i sin_i = n_t sin_t
    assert np.all(ok[above])
    sin_i = np.linalg.norm(w[:, :2], axis=1)
    sin_t = np.linalg.norm(wt[:, :2], axis=1)
    n_i = np.where(above, 1.0, eta)
    n_t = np.where(above, eta, 1.0)
    np.testing.assert_allclose((n_i * sin_i)[ok], (n_t * sin_t)[ok], atol=1e-12)
    assert np.all(wt[ok, 2] * w[ok, 2] < 0)
    np.testing.assert_allclose(np.linalg.norm(wt[ok], axis=1), 1.0, atol=1e-12)
    # total internal reflection exactly beyond the critical angle (from inside)
    np.testing.assert_array_equal(ok[~above], sin_i[~above] < 1.0 / eta)
    # round trip: refracting the refracted direction gives back the original
    back, ok2 = refract(wt[ok], n[ok], eta)
    assert np.all(ok2)
    np.testing.assert_allclose(back, w[ok], atol=1e-9)


# ----------------------------------------------------------------------------- Fresnel


def test_fresnel_dielectric_known_values_and_symmetry():
    for eta in (1.33, 1.5, 2.4, 0.7):
        np.testing.assert_allclose(fresnel_dielectric(1.0, eta), ((eta - 1) / (eta + 1)) ** 2, rtol=1e-12)
        np.testing.assert_allclose(fresnel_dielectric(-1.0, eta), ((eta - 1) / (eta + 1)) ** 2, rtol=1e-12)
    np.testing.assert_allclose(fresnel_dielectric(np.linspace(0.01, 1, 50), 1.0), 0.0, atol=1e-15)
    assert fresnel_dielectric(0.0, 1.5) == pytest.approx(1.0)
    # the same interface seen from the refracted side has the same reflectance (Stokes)
    cos_i = np.linspace(0.02, 1.0, 100)
    eta = 1.5
    cos_t = np.sqrt(1 - (1 - cos_i**2) / eta**2)
    np.testing.assert_allclose(fresnel_dielectric(cos_i, eta), fresnel_dielectric(-cos_t, eta), rtol=1e-10)
    np.testing.assert_allclose(fresnel_dielectric(cos_i, 1 / eta), fresnel_dielectric(-cos_i, eta), rtol=1e-12)
    # TIR from inside beyond the critical angle
    crit = np.sqrt(1 - 1 / eta**2)
    assert np.all(fresnel_dielectric(-np.linspace(0.0, crit - 1e-6, 20), eta) == 1.0)
    # Brewster angle: the parallel polarisation vanishes, R = r_perp^2 / 2
    tb = np.arctan(eta)
    ct = np.cos(np.arcsin(np.sin(tb) / eta))
    r_perp = (np.cos(tb) - eta * ct) / (np.cos(tb) + eta * ct)
    assert fresnel_dielectric(np.cos(tb), eta) == pytest.approx(r_perp**2 / 2, rel=1e-10)


def test_fresnel_conductor_reduces_to_dielectric_and_is_bounded():
    cos_i = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(
        fresnel_conductor(cos_i, [1.5, 1.5, 1.5], [0, 0, 0])[:, 0], fresnel_dielectric(cos_i, 1.5), atol=1e-12
    )
    f = fresnel_conductor(cos_i, GOLD["eta"], GOLD["k"])
    assert f.shape == (101, 3) and np.all((f >= 0) & (f <= 1))
    n = np.array(GOLD["eta"]) + 1j * np.array(GOLD["k"])
    np.testing.assert_allclose(f[-1], np.abs((n - 1) / (n + 1)) ** 2, rtol=1e-12)
    np.testing.assert_allclose(f[0], 1.0, atol=1e-12)


def test_fresnel_conductor_equals_the_complex_formula():
    """The real-arithmetic form equals pbrt-v4's FrComplex written with complex numbers."""
    rng = np.random.default_rng(13)
    cos = np.concatenate([rng.random(3000), [0.0, 1.0]])
    eta = rng.uniform(0.01, 10.0, (cos.size, 3))
    k = rng.uniform(0.0, 20.0, (cos.size, 3))
    k[:500] = 0.0  # dielectric-like, including eta < 1 (total reflection beyond the critical angle)
    n = eta + 1j * k
    c = cos[:, None]
    cos_t = np.sqrt(1.0 - (1.0 - c * c) / (n * n))
    r_parl = (n * c - cos_t) / (n * c + cos_t)
    r_perp = (c - n * cos_t) / (c + n * cos_t)
    ref = 0.5 * (np.abs(r_parl) ** 2 + np.abs(r_perp) ** 2)
    np.testing.assert_allclose(fresnel_conductor(cos, eta, k), ref, rtol=1e-9, atol=1e-12)


# ----------------------------------------------------------------------------- GGX


@pytest.mark.parametrize("alpha", [0.01, 0.05, 0.3, 1.0])
def test_ndf_is_normalised(alpha):
    def f(z):
        return 2 * np.pi * ggx.ndf(np.array([[np.sqrt(1 - z * z), 0.0, z]]), alpha)[0] * z

    total, _ = integrate.quad(f, 0.0, 1.0, points=[1 - alpha**2, 1 - 4 * alpha**2], limit=200)
    assert total == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("alpha", [0.3, 1.0])
def test_smith_lambda_is_the_projected_area_identity(alpha):
    """integral of max(0, w.m) D(m) dm = (1 + Lambda(w)) cos(w): what makes the VNDF a pdf."""
    m, dm = sphere_quadrature(1000, 400)
    for theta in (0.0, 45.0, 80.0):
        w = np.array([[np.sin(np.radians(theta)), 0.0, np.cos(np.radians(theta))]])
        lhs = np.sum(np.maximum(0.0, m @ w[0]) * ggx.ndf(m, alpha)) * dm
        rhs = (1 + ggx.smith_lambda(w, alpha)[0]) * w[0, 2]
        assert lhs == pytest.approx(rhs, rel=2e-3)


def test_masking_bounds():
    rng = np.random.default_rng(2)
    wi, wo = random_dirs(rng, 1000), random_dirs(rng, 1000)
    for alpha in (1e-5, 0.1, 1.0):
        g1i, g1o, g2 = ggx.smith_g1(wi, alpha), ggx.smith_g1(wo, alpha), ggx.smith_g2(wi, wo, alpha)
        assert np.all(g2 <= np.minimum(g1i, g1o) + 1e-15)
        assert np.all(g2 >= g1i * g1o - 1e-15)
    graze = np.array([[1.0, 0.0, 0.0]])
    assert ggx.smith_g1(graze, 0.3)[0] == 0.0 and ggx.smith_g1(np.array([[0, 0, 1.0]]), 0.3)[0] == 1.0


# ----------------------------------------------------------------------------- energy


def test_lambertian_white_furnace():
    w, dw = sphere_quadrature(400, 200)
    for wo in ([0.0, 0.0, 1.0], normalize(np.array([0.6, 0.0, -0.3]))):
        f = Lambertian(1.0).eval(w, np.tile(wo, (w.shape[0], 1)))
        np.testing.assert_allclose(np.sum(f * np.abs(w[:, 2:3]), axis=0) * dw, 1.0, rtol=1e-4)


def _energy_by_sampling(bsdf, wo, mode, n=200_000, seed=0):
    rng = np.random.default_rng(seed)
    s = bsdf.sample(np.tile(wo, (n, 1)), rng.random(n), rng.random((n, 2)), mode=mode)
    return s.weight[:, 0].mean(), s.weight[:, 0].std() / np.sqrt(n), s


@pytest.mark.parametrize("below", [False, True])
def test_smooth_dielectric_conserves_energy_exactly(below):
    wo = normalize(np.array([0.5, 0.1, -0.6 if below else 0.6]))
    b = RoughDielectric(0.0, 1.5)
    e, _, s = _energy_by_sampling(b, wo, IMPORTANCE)
    assert e == pytest.approx(1.0, abs=1e-12)  # every event has weight 1: R + T = 1
    R = fresnel_dielectric(wo[2], 1.5)
    assert s.transmission.mean() == pytest.approx(1 - R, abs=4e-3)
    assert np.all(s.delta) and np.all(s.valid)
    np.testing.assert_allclose(s.pdf, np.where(s.transmission, 1 - R, R))
    # radiance mode: transmitted radiance is scaled by 1 / etap^2
    _, _, sr = _energy_by_sampling(b, wo, RADIANCE)
    etap = 1 / 1.5 if below else 1.5
    np.testing.assert_allclose(sr.weight[sr.transmission], 1 / etap**2)
    np.testing.assert_allclose(sr.weight[~sr.transmission], 1.0)


@pytest.mark.parametrize("alpha", [0.01, 0.3, 1.0])
@pytest.mark.parametrize("below", [False, True])
def test_rough_dielectric_energy(alpha, below):
    """R + T without radiance scaling is <= 1, about 1 when nearly smooth; the sampled
    estimate agrees with a quadrature of eval (an independent route)."""
    wo = normalize(np.array([0.4, 0.0, -0.7 if below else 0.7]))
    e, se, _ = _energy_by_sampling(RoughDielectric(alpha, 1.5), wo, IMPORTANCE)
    assert e <= 1.0 + 1e-12
    if alpha <= 0.01:
        assert e > 0.995
    else:
        # single scattering loses energy, most for rough interfaces seen from the dense side
        assert e > 0.4
        w, dw = sphere_quadrature(1600, 400)
        f = RoughDielectric(alpha, 1.5).eval(w, np.tile(wo, (w.shape[0], 1)), mode=IMPORTANCE)
        q = np.sum(f[:, 0] * np.abs(w[:, 2])) * dw
        assert q == pytest.approx(e, abs=5 * se + 3e-3)


def test_conductor_energy_matches_the_closed_form():
    """At alpha = 1, D = 1/pi and normal incidence, the height-correlated single-scattering
    albedo of a perfect mirror-metal is 1 - ln 2 (integral of 2c / (1 + c)); smoother is <= 1."""
    wo = np.array([0.0, 0.0, 1.0])
    b = RoughConductor(1.0, eta=1.0, k=1e4)  # F = 1 to 1e-8
    e, se, _ = _energy_by_sampling(b, wo, RADIANCE)
    assert e == pytest.approx(1.0 - np.log(2.0), abs=4 * se)
    for alpha in (0.05, 0.3):
        e, se, _ = _energy_by_sampling(RoughConductor(alpha, 1.0, 1e4), normalize(np.array([0.3, 0.0, 0.8])), RADIANCE)
        assert e <= 1.0
        assert e > (0.99 if alpha == 0.05 else 0.8)


# ----------------------------------------------------------------------------- reciprocity


def test_reflection_is_reciprocal():
    rng = np.random.default_rng(3)
    wi, wo = random_dirs(rng, 5000), random_dirs(rng, 5000)
    wi[:, 2] *= np.sign(wi[:, 2] * wo[:, 2])  # same side, either side
    for b in (RoughConductor(0.3, **GOLD), RoughDielectric(0.3, 1.5), RoughDielectric(0.2, 0.8), Lambertian(0.5)):
        for mode in (RADIANCE, IMPORTANCE):
            np.testing.assert_allclose(b.eval(wi, wo, mode), b.eval(wo, wi, mode), rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("ior", [1.5, 1.4 / 1.6])
def test_transmission_reciprocity_and_adjoint(ior):
    rng = np.random.default_rng(4)
    wo = random_dirs(rng, 5000)
    wi = random_dirs(rng, 5000)
    wi[:, 2] = -np.sign(wo[:, 2]) * np.abs(wi[:, 2])
    b = RoughDielectric(0.8, ior)
    f_rad = b.eval(wi, wo, RADIANCE)[:, 0]
    f_rev = b.eval(wo, wi, RADIANCE)[:, 0]
    assert np.count_nonzero(f_rad) > 200
    n_i = np.where(wi[:, 2] > 0, 1.0, ior)
    n_o = np.where(wo[:, 2] > 0, 1.0, ior)
    np.testing.assert_allclose(f_rad / n_o**2, f_rev / n_i**2, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(b.eval(wi, wo, IMPORTANCE)[:, 0], f_rev, rtol=1e-9, atol=1e-14)


def test_relative_ior_is_the_mirrored_interface():
    """An interface of relative index 1/eta is the eta interface seen upside down."""
    rng = np.random.default_rng(5)
    wi, wo = random_dirs(rng, 3000), random_dirs(rng, 3000)
    flip = np.array([1.0, 1.0, -1.0])
    a, b = RoughDielectric(0.25, 1.3), RoughDielectric(0.25, 1 / 1.3)
    for mode in (RADIANCE, IMPORTANCE):
        np.testing.assert_allclose(a.eval(wi, wo, mode), b.eval(wi * flip, wo * flip, mode), rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(a.pdf(wi, wo, mode), b.pdf(wi * flip, wo * flip, mode), rtol=1e-9, atol=1e-14)


# ----------------------------------------------------------------------------- smooth limits


def test_smooth_conductor_is_a_fresnel_mirror():
    rng = np.random.default_rng(6)
    wo = random_dirs(rng, 100, upper=True)
    b = RoughConductor(SMOOTH_ALPHA / 2, **GOLD)
    s = b.sample(wo, rng.random(100), rng.random((100, 2)))
    assert np.all(s.delta & s.valid) and np.all(s.pdf == 1.0)
    np.testing.assert_allclose(s.wi, wo * [-1, -1, 1], atol=1e-12)
    np.testing.assert_allclose(s.weight, fresnel_conductor(wo[:, 2], GOLD["eta"], GOLD["k"]), rtol=1e-12)
    assert np.all(b.eval(s.wi, wo) == 0) and np.all(b.pdf(s.wi, wo) == 0)
    # just above the threshold the rough lobe is nearly the same mirror
    r = RoughConductor(SMOOTH_ALPHA * 1.01, **GOLD).sample(wo, rng.random(100), rng.random((100, 2)))
    assert not np.any(r.delta)
    assert np.median(np.abs(r.weight - s.weight) / s.weight) < 0.01
    assert np.median(np.linalg.norm(r.wi - s.wi, axis=1)) < 0.005


def test_index_matched_interface_is_pure_transmission():
    rng = np.random.default_rng(7)
    wo = random_dirs(rng, 500)
    for alpha in (0.0, 0.5):
        b = RoughDielectric(alpha, 1.0)
        s = b.sample(wo, rng.random(500), rng.random((500, 2)))
        assert np.all(s.valid & s.transmission & s.delta)
        np.testing.assert_allclose(s.wi, -wo, atol=1e-12)
        np.testing.assert_allclose(s.weight, 1.0)
        wi = random_dirs(rng, 500)
        assert np.all(b.eval(wi, wo) == 0) and np.all(b.pdf(wi, wo) == 0)
    # within round-off of 1 the interface is index-matched; just outside, sample and pdf agree
    assert np.all(RoughDielectric(0.5, 1 + 1e-12).sample(wo, rng.random(500), rng.random((500, 2))).delta)
    for ior in (1 + 2e-7, 1 - 2e-7):
        b = RoughDielectric(0.01, ior)
        s = b.sample(wo, rng.random(500), rng.random((500, 2)))
        assert np.all(s.valid) and not np.any(s.delta)
        np.testing.assert_allclose(b.pdf(s.wi, wo), s.pdf, rtol=1e-3)


def test_reflection_only_base_loses_the_transmission():
    rng = np.random.default_rng(8)
    wo = random_dirs(rng, 4000, upper=True)
    wi = random_dirs(rng, 4000, upper=False)
    full, base = RoughDielectric(0.3, 1.5), RoughDielectric(0.3, 1.5, reflection_only=True)
    assert np.all(base.eval(wi, wo) == 0) and np.all(base.pdf(wi, wo) == 0)
    wr = random_dirs(rng, 4000, upper=True)
    np.testing.assert_allclose(base.eval(wr, wo), full.eval(wr, wo))
    s = base.sample(wo, rng.random(4000), rng.random((4000, 2)))
    assert not np.any(s.transmission)
    smooth = RoughDielectric(0.0, 1.5, reflection_only=True).sample(wo, rng.random(4000), rng.random((4000, 2)))
    np.testing.assert_allclose(smooth.weight[:, 0], fresnel_dielectric(wo[:, 2], 1.5), rtol=1e-12)
    assert np.all(smooth.pdf == 1.0)


# ----------------------------------------------------------------------------- per-row parameters


def test_per_row_parameters_match_scalar_instances():
    rng = np.random.default_rng(9)
    n = 600
    alpha = np.repeat([0.0, 0.05, 0.5], n // 3)
    ior = np.repeat([1.5, 0.8, 2.0], n // 3)
    wo, wi = random_dirs(rng, n), random_dirs(rng, n)
    u1, u2 = rng.random(n), rng.random((n, 2))
    batch = RoughDielectric(alpha, ior)
    f, p = batch.eval(wi, wo), batch.pdf(wi, wo)
    s = batch.sample(wo, u1, u2)
    for k in range(3):
        r = slice(k * n // 3, (k + 1) * n // 3)
        one = RoughDielectric(alpha[r][0], ior[r][0])
        np.testing.assert_array_equal(f[r], one.eval(wi[r], wo[r]))
        np.testing.assert_array_equal(p[r], one.pdf(wi[r], wo[r]))
        s1 = one.sample(wo[r], u1[r], u2[r])
        np.testing.assert_array_equal(s.weight[r], s1.weight)
        np.testing.assert_array_equal(s.delta[r], s1.delta)
        # take() restricts the per-row parameters
        np.testing.assert_array_equal(batch.take(r).eval(wi[r], wo[r]), f[r])
    cond = RoughConductor(alpha, eta=rng.uniform(0.2, 2, (n, 3)), k=3.0)
    assert cond.eval(wi, wo).shape == (n, 3)
    with pytest.raises(ValueError, match="alpha has 600 rows but the batch has 5"):
        cond.eval(wi[:5], wo[:5])


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: RoughConductor(-0.1, 1.0, 1.0), r"alpha = -0\.1 is outside"),
        (lambda: RoughConductor(np.nan, 1.0, 1.0), "alpha must be finite"),
        (lambda: RoughConductor(0.1, 0.0, 1.0), r"eta = 0\.0 is outside the valid range \(0"),
        (lambda: RoughConductor(0.1, 1.0, -1.0), "k = -1.0 is outside"),
        (lambda: RoughConductor(0.1, [1.0, 2.0], 1.0), r"RGB triple \(3,\)"),
        (lambda: RoughDielectric(0.1, 0.0), r"ior = 0\.0 is outside"),
        (lambda: RoughDielectric(0.1, -1.5), "ior"),
        (lambda: RoughDielectric(0.1, np.inf), "ior must be finite"),
        (lambda: RoughDielectric([[0.1]], 1.5), r"alpha must be a scalar or a per-row \(N,\)"),
        (lambda: RoughDielectric("rough", 1.5), "alpha must be a number"),
        (lambda: Lambertian(1.2), r"albedo = 1\.2 is outside the valid range \[0\.0, 1\.0\]"),
        (lambda: Lambertian([0.1, np.nan, 0.2]), "albedo must be finite"),
        (lambda: HenyeyGreenstein(1.0), "g = 1.0 is outside"),
        (lambda: HenyeyGreenstein(-1.0), "g = -1.0 is outside"),
    ],
)
def test_bad_parameters(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize("name", sorted(all_bsdfs()))
def test_bad_directions_and_random_numbers(name):
    b = all_bsdfs()[name]
    w = np.array([[0.0, 0.6, 0.8], [0.0, 0.0, 1.0]])
    bad_nan = w.copy()
    bad_nan[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"wi must be finite, row 1"):
        b.eval(bad_nan, w)
    with pytest.raises(ValueError, match=r"wo must be finite"):
        b.pdf(w, bad_nan)
    with pytest.raises(ValueError, match=r"wi must have shape \(N, 3\), got \(2, 2\)"):
        b.eval(w[:, :2], w)
    with pytest.raises(ValueError, match="wi has 1 rows but wo has 2"):
        b.eval(w[:1], w)
    with pytest.raises(ValueError, match="must be unit vectors"):
        b.eval(w * 2.0, w)
    with pytest.raises(ValueError, match="mode must be"):
        b.eval(w, w, mode="photons")
    with pytest.raises(ValueError, match=r"u must have shape \(2, 2\)"):
        b.sample(w, np.zeros(2), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"u_lobe must hold numbers in \[0, 1\)"):
        b.sample(w, np.array([0.5, 1.5]), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="wo must be finite"):
        b.sample(bad_nan, np.zeros(2), np.zeros((2, 2)))


def test_phase_bad_directions():
    with pytest.raises(ValueError, match=r"wo must have shape"):
        HenyeyGreenstein(0.3).sample(np.zeros((4, 2)), np.zeros((4, 2)))


# ----------------------------------------------------------------------------- grazing


def _edge_directions():
    rng = np.random.default_rng(10)
    edge = []
    for z in (0.0, -0.0, 1e-12, -1e-12, 1e-7, -1e-7, 1e-3, 1.0, -1.0):
        r = np.sqrt(1 - z * z)
        edge.append([r, 0.0, z])
        edge.append([0.0, -r, z])
    edge = np.array(edge)
    a = np.concatenate([np.repeat(edge, len(edge), axis=0), random_dirs(rng, 2000)])
    b = np.concatenate([np.tile(edge, (len(edge), 1)), random_dirs(rng, 2000)])
    return a, b


@pytest.mark.parametrize("name", sorted(all_bsdfs()))
@pytest.mark.parametrize("alpha_override", [None, 1e-4, 1.0])
def test_grazing_and_below_horizon_are_finite_and_non_negative(name, alpha_override):
    b = all_bsdfs()[name]
    if alpha_override is not None and hasattr(b, "alpha"):
        b.alpha = np.array([alpha_override])
    wi, wo = _edge_directions()
    rng = np.random.default_rng(11)
    for mode in (RADIANCE, IMPORTANCE):
        f, p = b.eval(wi, wo, mode), b.pdf(wi, wo, mode)
        assert f.shape == (len(wi), 3) and p.shape == (len(wi),)
        assert np.all(np.isfinite(f)) and np.all(f >= 0)
        assert np.all(np.isfinite(p)) and np.all(p >= 0)
        u = np.concatenate([rng.random((len(wo) - 4, 2)), [[0, 0], [0.999999, 0.999999], [0, 0.999999], [0.5, 0]]])
        s = b.sample(wo, rng.random(len(wo)), u, mode)
        for arr in (s.wi, s.weight, s.pdf):
            assert np.all(np.isfinite(arr))
        assert np.all(s.weight >= 0) and np.all(s.pdf >= 0)
        assert np.all(s.weight[~s.valid] == 0) and np.all(s.pdf[~s.valid] == 0)
        assert np.all(s.valid <= (s.pdf > 0))
        if mode == IMPORTANCE:
            # every sampler here is exact up to masking/Fresnel: a weight never exceeds 1
            assert np.all(s.weight <= 1.0 + 1e-12)


def test_float32_input_and_unchecked_path_agree():
    rng = np.random.default_rng(12)
    wi, wo = random_dirs(rng, 1000), random_dirs(rng, 1000)
    b = RoughDielectric(0.3, 1.5)
    ref = b.eval(wi, wo)
    np.testing.assert_allclose(b.eval(wi.astype(np.float32), wo.astype(np.float32)), ref, rtol=2e-3, atol=1e-6)
    np.testing.assert_array_equal(b.eval(wi, wo, check=False), ref)
    assert b.eval(wi[0], wo[0]).shape == (1, 3)


def test_a_lambertian_of_valid_rows_is_the_checked_one():
    """``Lambertian.of_valid_rows`` (the renderer's per-hit textures, valid by construction) skips the
    checks only: eval, pdf and sample are those of ``Lambertian(albedo)``."""
    rng = np.random.default_rng(12)
    n = 500
    albedo = rng.random((n, 3))
    wi, wo = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    wi /= np.linalg.norm(wi, axis=1)[:, None]
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    fast, checked = Lambertian.of_valid_rows(albedo), Lambertian(albedo)
    np.testing.assert_array_equal(fast.eval(wi, wo), checked.eval(wi, wo))
    np.testing.assert_array_equal(fast.pdf(wi, wo), checked.pdf(wi, wo))
    u_lobe, u = rng.random(n), rng.random((n, 2))
    np.testing.assert_array_equal(fast.sample(wo, u_lobe, u).weight, checked.sample(wo, u_lobe, u).weight)
    np.testing.assert_array_equal(fast.take(np.arange(0, n, 2)).albedo, albedo[::2])

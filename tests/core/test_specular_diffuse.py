"""Cycles' Principled BSDF without its extra lobes (``bsdf.SpecularDiffuse``): its sampler against its own density,
its albedo against an independent quadrature of its f, its energy, its metallic limits, the stored albedo table
and the material that renders it (``render.PrincipledMaterial``)."""

import numpy as np
import pytest

from addon.core.bsdf import (
    SMOOTH_ALPHA,
    RoughConductor,
    RoughDielectric,
    SpecularDiffuse,
    coordinate_system,
    fresnel_dielectric,
    specular_ior,
)
from addon.core.bsdf.specular_diffuse import (
    TABLE_SHAPE,
    albedo_table,
    dielectric_albedo,
    fresnel_dielectric_average,
    ggx_albedo,
    multiscatter_scale,
    schlick_average,
)
from addon.core.render import PrincipledMaterial, SurfaceHits
from addon.core.stack import k_from_f0
from tests.core.test_bsdf_sampling import _check_bsdf, _dir

GOLD = (1.0, 0.77, 0.34)  # the reviewer's metallic gold base colour


def _sphere_about(axis, n_theta, n_phi):
    """Quadrature over the sphere in polar coordinates about ``axis``, its nodes crowded toward the axis (theta =
    pi x^3, Gauss-Legendre in x) where a narrow lobe peaks: (directions (M, 3), weights (M,)) with sum(weight g(w))
    the integral of g over solid angle."""
    x, wx = np.polynomial.legendre.leggauss(n_theta)
    x, wx = 0.5 * (x + 1.0), 0.5 * wx
    theta, w_theta = np.pi * x**3, wx * 3.0 * np.pi * x**2 * np.sin(np.pi * x**3)
    phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    local = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    s, b = coordinate_system(axis[None])
    dirs = local[:, :1] * s + local[:, 1:2] * b + local[:, 2:3] * axis
    return dirs, (w_theta[:, None] * np.full(n_phi, 2.0 * np.pi / n_phi)).ravel()


def _albedo_by_quadrature(bsdf, wo, n_theta=512, n_phi=256):
    """Integral of f(wi, wo) cos(wi) over wi by quadrature of ``eval`` (no sampling) about wo's mirror direction,
    RGB (3,)."""
    wi, w = _sphere_about(np.array([-wo[0], -wo[1], wo[2]]), n_theta, n_phi)
    upper = wi[:, 2] > 0.0
    wi, w = wi[upper] / np.linalg.norm(wi[upper], axis=1)[:, None], w[upper]
    f = bsdf.eval(wi, np.tile(wo, (len(wi), 1)))
    return (f * (wi[:, 2] * w)[:, None]).sum(axis=0)


@pytest.mark.parametrize(
    "base, alpha, ior, metallic, theta",
    [
        ((0.0, 0.0, 0.0), 0.04, 1.5, 0.0, 30.0),  # black plastic, roughness 0.2
        ((0.02, 0.03, 0.1), 0.09, 1.5, 0.0, 70.0),  # dark blue plastic, roughness 0.3, seen near grazing
        ((0.8, 0.8, 0.8), 0.25, 1.5, 0.0, 45.0),  # the default Principled BSDF
        (GOLD, 0.09, 1.5, 1.0, 20.0),  # metallic gold
        ((0.5, 0.2, 0.1), 0.36, 2.0, 0.5, 60.0),  # half metal, rough
    ],
)
def test_samples_follow_the_pdf_and_weigh_f_cos_over_pdf(base, alpha, ior, metallic, theta):
    """The recorded pdf is pdf() of the sampled direction, the weight f |cos| / pdf, and the directions are
    distributed as pdf() says (chi-square), for views from above and from below (the surface is two-sided)."""
    bsdf = SpecularDiffuse(base, alpha, ior, metallic)
    _check_bsdf(bsdf, _dir(theta), seed=1)
    _check_bsdf(bsdf, _dir(theta, below=True), seed=2)


@pytest.mark.parametrize(
    "base, alpha, ior, metallic, theta",
    [
        ((0.0, 0.0, 0.0), 0.04, 1.5, 0.0, 30.0),
        ((0.02, 0.03, 0.1), 0.09, 1.5, 0.0, 70.0),
        ((0.8, 0.8, 0.8), 0.25, 1.5, 0.0, 45.0),
        ((0.8, 0.5, 0.2), 0.36, 1.45, 0.0, 10.0),
        (GOLD, 0.09, 1.5, 1.0, 40.0),
        ((0.5, 0.2, 0.1), 0.36, 2.0, 0.5, 60.0),
    ],
)
def test_the_mean_sample_weight_is_the_albedo_an_independent_quadrature_gives(base, alpha, ior, metallic, theta):
    """E[f cos / pdf] over the sampler equals the integral of f cos over the hemisphere by Gauss-Legendre
    quadrature of eval (which shares nothing with the sampler but f)."""
    bsdf = SpecularDiffuse(base, alpha, ior, metallic)
    wo = _dir(theta)
    n = 400_000
    rng = np.random.default_rng(7)
    s = bsdf.sample(np.tile(wo, (n, 1)), rng.random(n), rng.random((n, 2)))
    mean, err = s.weight.mean(axis=0), s.weight.std(axis=0) / np.sqrt(n)
    quadrature = _albedo_by_quadrature(bsdf, wo)
    assert np.all(np.abs(mean - quadrature) < 5.0 * err + 2e-3), (mean, quadrature, err)


def test_a_smooth_surface_samples_its_mirror_as_a_delta_event():
    """Below SMOOTH_ALPHA the specular layer is a mirror: its samples are delta events whose mean weight with the
    diffuse ones is F(mu) + (1 - E(mu)) base, E the table's (here F itself)."""
    base = np.array([0.5, 0.4, 0.1])
    bsdf = SpecularDiffuse(base, 0.0, 1.5)
    wo = _dir(50.0)
    n = 200_000
    rng = np.random.default_rng(3)
    s = bsdf.sample(np.tile(wo, (n, 1)), rng.random(n), rng.random((n, 2)))
    assert s.delta.any() and not s.delta.all()
    mirror = s.wi[s.delta]
    np.testing.assert_allclose(mirror, np.tile([-wo[0], -wo[1], wo[2]], (len(mirror), 1)), atol=1e-12)
    fresnel = RoughDielectric(0.0, 1.5, reflection_only=True).sample(wo[None], np.zeros(1), np.full((1, 2), 0.5))
    e = dielectric_albedo(np.array([wo[2]]), 0.0, 1.5)[0]
    assert abs(e - fresnel.weight[0, 0]) < 1e-3
    expected = fresnel.weight[0, 0] + (1.0 - e) * base
    assert np.all(np.abs(s.weight.mean(axis=0) - expected) < 5.0 * s.weight.std(axis=0) / np.sqrt(n) + 1e-3)


@pytest.mark.parametrize("alpha", [0.0004, 0.04, 0.09, 0.36, 1.0])
@pytest.mark.parametrize("ior", [1.2, 1.5, 2.5])
def test_a_white_base_under_its_specular_layer_reflects_all_light_and_never_more(alpha, ior):
    """Albedo scaling conserves energy: over a white base, specular E(mu) plus diffuse (1 - E(mu)) is 1 at every
    view cosine, to the table's accuracy; over a darker base it is less. (A smooth layer's mirror, a delta lobe
    that eval leaves out, adds its Fresnel reflectance.)"""
    for mu in (0.1, 0.2, 0.5, 0.8, 1.0):
        wo = np.array([np.sqrt(1.0 - mu * mu), 0.0, mu])
        mirror = fresnel_dielectric(mu, ior) if alpha < SMOOTH_ALPHA else 0.0
        white = _albedo_by_quadrature(SpecularDiffuse((1.0, 1.0, 1.0), alpha, ior), wo) + mirror
        assert np.all(np.abs(white - 1.0) < 4e-3), (mu, white)
        grey = _albedo_by_quadrature(SpecularDiffuse((0.5, 0.5, 0.5), alpha, ior), wo)
        assert np.all(grey < white)


@pytest.mark.parametrize("alpha", [0.04, 0.25, 1.0])
def test_a_white_rough_metal_loses_no_light_between_its_facets(alpha):
    """Cycles' Multiscatter GGX gives back the light a single-scattering microfacet model loses: with Fresnel 1 its
    factor is 1 / E1, all light; the whitest metal (F0 0.99, k_from_f0's cap) reflects at least 97% at every view
    cosine (single scattering alone: 0.30 at alpha 1, mu 1), never more than all; a coloured one more than single
    scattering does."""
    for mu in (0.2, 0.5, 1.0):
        wo = np.array([np.sqrt(1.0 - mu * mu), 0.0, mu])
        e1 = ggx_albedo(np.array([mu]), alpha)
        assert multiscatter_scale(np.array([mu]), alpha, np.ones(1)) * e1 == pytest.approx(1.0, abs=1e-9)
        white = _albedo_by_quadrature(SpecularDiffuse((1.0, 1.0, 1.0), alpha, 1.5, 1.0), wo)
        assert np.all((white > 0.97) & (white < 1.003)), (mu, white)
        single = _albedo_by_quadrature(RoughConductor(alpha, 1.0, k_from_f0(np.array(GOLD))), wo)
        assert np.all(_albedo_by_quadrature(SpecularDiffuse(GOLD, alpha, 1.5, 1.0), wo) >= single)


@pytest.mark.parametrize("alpha", [0.04, 0.3])
def test_metallic_mixes_the_conductor_and_the_dielectric_over_its_base(alpha):
    """Metallic 0 is the dielectric's reflection plus (1 - E(mu_o)) base / pi; 1 is the conductor whose F0 is the
    base colour; 0.5 their mean (each reflection with Cycles' multiple-scattering factor S(mu_o), E the layer's
    albedo with it)."""
    rng = np.random.default_rng(5)
    n = 2000
    wi, wo = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1)[:, None]
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    base = np.array(GOLD)
    mu = wo[:, 2]
    scale = multiscatter_scale(mu, alpha, fresnel_dielectric_average(1.5))[:, None]
    plastic = RoughDielectric(alpha, 1.5, reflection_only=True).eval(wi, wo) * scale
    plastic = plastic + (1.0 - dielectric_albedo(mu, alpha, 1.5)[:, None] * scale) * base / np.pi
    metal = RoughConductor(alpha, 1.0, k_from_f0(base)).eval(wi, wo)
    metal = metal * multiscatter_scale(mu, alpha, schlick_average(np.tile(base, (n, 1))))
    np.testing.assert_allclose(SpecularDiffuse(base, alpha, 1.5, 0.0).eval(wi, wo), plastic, rtol=1e-12)
    np.testing.assert_allclose(SpecularDiffuse(base, alpha, 1.5, 1.0).eval(wi, wo), metal, rtol=1e-12)
    np.testing.assert_allclose(
        SpecularDiffuse(base, alpha, 1.5, 0.5).eval(wi, wo), 0.5 * (plastic + metal), rtol=1e-12, atol=1e-15
    )


@pytest.mark.parametrize("mu", [0.1, 0.37, 0.9])
@pytest.mark.parametrize("alpha, ior", [(0.02, 1.5), (0.11, 1.33), (0.3, 1.9), (0.7, 1.5), (1.0, 3.0)])
def test_the_stored_albedo_table_is_the_dielectrics_albedo(mu, alpha, ior):
    """The table (built from the dielectric's sample weights) interpolated between its nodes is within 3e-3 of
    the albedo a quadrature of the dielectric's eval gives."""
    assert albedo_table().shape == TABLE_SHAPE
    wo = np.array([np.sqrt(1.0 - mu * mu), 0.0, mu])
    quadrature = _albedo_by_quadrature(RoughDielectric(alpha, ior, reflection_only=True), wo)[0]
    assert abs(dielectric_albedo(np.array([mu]), alpha, ior)[0] - quadrature) < 3e-3


def test_specular_ior_level_scales_the_normal_incidence_reflectance():
    """Cycles' rule: level 0.5 keeps the IOR, 1 doubles F0, 0 leaves no layer (index 1); an IOR below 1 stays
    below 1."""
    f0 = lambda n: ((n - 1.0) / (n + 1.0)) ** 2  # noqa: E731
    assert specular_ior(1.5, 0.5) == pytest.approx(1.5)
    assert f0(specular_ior(1.5, 1.0)) == pytest.approx(2.0 * f0(1.5))
    assert f0(specular_ior(1.45, 0.2)) == pytest.approx(0.4 * f0(1.45))
    assert specular_ior(1.5, 0.0) == 1.0
    assert specular_ior(1.0 / 1.5, 0.5) == pytest.approx(1.0 / 1.5)
    np.testing.assert_allclose(specular_ior(np.array([1.5, 2.0]), 0.5), [1.5, 2.0])


def test_a_principled_material_textures_its_base_colour_per_hit():
    """Bound to hits, a textured PrincipledMaterial's BSDF has one base colour a hit (the texels times the colour),
    and a constant one shares one; its specular layer is the adjusted index and roughness squared."""
    from addon.core.render import ImageTexture

    image = np.zeros((2, 2, 3), dtype=np.float32)
    image[:, 0] = (1.0, 0.0, 0.0)
    image[:, 1] = (0.0, 0.0, 1.0)
    material = PrincipledMaterial(
        (0.5, 0.5, 0.5), roughness=0.3, ior=1.5, specular_level=1.0, texture=ImageTexture(image)
    )
    hits = SurfaceHits(uv=np.array([[0.25, 0.5], [0.75, 0.5]]), footprint=np.zeros(2))
    bsdf = material.bind(hits).bsdf
    np.testing.assert_allclose(bsdf.base, [[0.5, 0.0, 0.0], [0.0, 0.0, 0.5]], atol=1e-6)
    assert bsdf.alpha[0] == pytest.approx(0.09) and bsdf.ior[0] == pytest.approx(specular_ior(1.5, 1.0))
    plain = PrincipledMaterial((0.2, 0.3, 0.4), metallic=0.7)
    assert plain.bind(hits) is plain.bind(hits) and plain.bind(hits).bsdf.metallic[0] == pytest.approx(0.7)

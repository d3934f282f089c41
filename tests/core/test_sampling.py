"""The sampling network at run time (z -> proxy sigma, w) and what it buys: lower one-bounce variance."""

import numpy as np
import pytest

from addon.core.neural import SIZES, encode_arrays, encode_stack, load_models, proxy, top_coat
from addon.core.stack import Coating, Conductor, Diffuse, Stack, StackArrays
from benchmarks.sampling_efficiency import (
    cosine_sampler,
    ggx_sampler,
    material_sampler,
    one_bounce_variance,
    sky_radiance,
)
from tests.stats import chi2_direction_test

ALUMINIUM = dict(eta=(1.657, 0.880, 0.521), k=(9.224, 6.270, 4.837))
# the held-out "specular" and "diffuse" stacks (onnx_export.heldout_layered.SPECULAR_INDEX / DIFFUSE_INDEX)
SPECULAR = Stack(Conductor(roughness=0.3, **ALUMINIUM), (Coating(roughness=0.03, ior=1.5),))
DIFFUSE = Stack(Diffuse((0.7, 0.4, 0.1)), (Coating(roughness=0.05, ior=1.5),))  # coated diffuse


@pytest.fixture(scope="module", params=SIZES)
def models(request):
    return load_models(request.param, threads=2)


def test_sampling_model_output_range_and_shapes(models):
    sampling = models
    rng = np.random.default_rng(0)
    z = rng.normal(scale=2.0, size=(64, 3, 32)).astype(np.float32)
    p = sampling.proxy_params(z)
    assert p.shape == (64, 2) and p.dtype == np.float32 and np.all(np.isfinite(p))
    assert np.all(p[:, 0] >= proxy.SIGMA_MIN) and np.all((p[:, 1] > 0) & (p[:, 1] <= 1))
    assert sampling.proxy_params(z[0]).shape == (1, 2)
    with pytest.raises(ValueError, match="finite"):
        sampling.proxy_params(np.full((2, 3, 32), np.nan, dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        sampling.proxy_params(np.zeros((2, 32), dtype=np.float32))


def test_proxy_is_glossier_under_a_smooth_coat_over_metal_than_under_a_rough_one_over_diffuse(models):
    rough = Stack(Diffuse((0.2, 0.5, 0.8)), (Coating(roughness=0.6, ior=1.4, albedo=(0.8, 0.8, 0.8), thickness=1.0),))
    p = models.proxy_params(encode_arrays(StackArrays.from_stacks([SPECULAR, rough]), models))
    (s_spec, w_spec), (s_rough, w_rough) = p
    if models.remainder:  # the proxy samples the remainder: a glossy metal under the coat, a diffuse base
        assert w_spec < w_rough and w_rough > 0.9, p
    else:  # the proxy samples the whole lobe, the smooth coat's highlight included
        assert s_spec < s_rough and w_spec < w_rough, p


@pytest.mark.parametrize("which", ["specular", "diffuse"])
def test_proxy_sample_agrees_with_its_pdf_at_the_networks_parameters(models, which):
    stack = SPECULAR if which == "specular" else DIFFUSE
    sigma, w = models.proxy_params(encode_stack(stack, models))[0]
    wo = np.array([0.5, 0.0, np.sqrt(0.75)])

    def sample_fn(n, rng):
        wi, pdf = proxy.sample(np.broadcast_to(wo, (n, 3)), sigma, w, rng.random((n, 3)))
        return np.where((pdf > 0)[:, None], wi, np.nan)

    def pdf_fn(wi):
        return proxy.pdf(np.broadcast_to(wo, wi.shape), wi, sigma, w)

    stat, p = chi2_direction_test(sample_fn, pdf_fn, n=100_000, seed=3)
    assert p > 1e-3, (which, sigma, w, stat, p)


@pytest.mark.parametrize("which", ["specular", "diffuse"])
def test_the_renderers_sampler_agrees_with_its_pdf(models, which):
    """The renderer's sampler of a neural material (for a remainder decoder: the proxy mixed with exact
    samples of the top lobe) draws directions by the density its pdf gives (chi-square test)."""
    from addon.core.render.neural_material import _BoundNeural

    stack = SPECULAR if which == "specular" else DIFFUSE
    z = encode_stack(stack, models)
    sigma, w = models.proxy_params(z)[0]
    bound = _BoundNeural(models, z, np.float64(sigma), np.float64(w), top=top_coat(stack))
    wo = np.array([0.5, 0.0, np.sqrt(0.75)])

    def sample_fn(n, rng):
        u = rng.random((n, 3))
        wi, pdf = bound.sample_direction(np.broadcast_to(wo, (n, 3)).copy(), u[:, 0], u[:, 1:])
        return np.where((pdf > 0)[:, None], wi, np.nan)

    def pdf_fn(wi):
        return bound.pdf(wi, np.broadcast_to(wo, wi.shape).copy())

    stat, p = chi2_direction_test(sample_fn, pdf_fn, n=100_000, seed=4)
    assert p > 1e-3, (which, stat, p)


def _variances(models, stack, n, seed):
    z = encode_stack(stack, models)
    sigma, w = models.proxy_params(z)[0]
    ct = np.array([0.3, 0.6, 0.9])
    wo = np.stack([np.sqrt(1 - ct**2), np.zeros(3), ct], axis=1)
    top = top_coat(stack)
    brdf = lambda wi, wo_: models.eval_brdf(z, wi, wo_, top)  # noqa: E731
    out = {}
    for name, smp in (  # "proxy": the renderer's sampler (mixed with the exact top lobe's for a remainder decoder)
        ("proxy", material_sampler(models, sigma, w, top)),
        ("cosine", cosine_sampler()),
        ("ggx_top", ggx_sampler(stack.coatings[-1].roughness)),
    ):
        mean, var = one_bounce_variance(brdf, wo, smp, n, seed=seed)
        out[name] = (mean, var)
    return out


@pytest.mark.parametrize("which", ["specular", "diffuse"])
def test_importance_sampling_with_the_proxy_lowers_variance(models, which):
    """Same sample count, same BRDF (the decoder), same light: the proxy's variance is lower than cosine
    sampling's and than sampling the top interface's GGX lobe (ratios measured in this run)."""
    stack = SPECULAR if which == "specular" else DIFFUSE
    v = _variances(models, stack, 4096, seed=5)
    # the three strategies estimate the same integral
    for name in ("cosine", "ggx_top"):
        se = np.sqrt(v[name][1] / 4096 + v["proxy"][1] / 4096)
        assert np.all(np.abs(v[name][0] - v["proxy"][0]) < 5 * se + 1e-3), (name, v[name][0], v["proxy"][0])
    rel = {k: np.mean(var / np.maximum(mean, 1e-12) ** 2) for k, (mean, var) in v.items()}
    assert rel["proxy"] < rel["cosine"], rel
    assert rel["proxy"] < rel["ggx_top"], rel


def test_sky_radiance_is_positive_and_finite():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(1000, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    L = sky_radiance(w)
    assert np.all(np.isfinite(L)) and np.all(L > 0)

"""The reference's closed-form routes under rough interfaces (``reference/walk.py``: ``_delta_routes``,
``_floor_routes``, ``_entry_reflections``) and its Russian roulette at grazing views: the estimates the former
estimator got wrong with tight error bars, reciprocity on random stacks with a glossy top over a smooth base, and
eval against the analog walk where the new strategies act."""

from __future__ import annotations

import numpy as np
import pytest

from addon.core import reference as R
from addon.core.bsdf import fresnel_dielectric
from addon.core.stack import Coating, Conductor, Dielectric, Diffuse, Stack
from tests.core.test_reference import GOLD, assert_eval_matches_analog_walk, coating_iors, direction

MILKY = dict(ior=1.5, albedo=0.9, thickness=1.0)  # a milky coat: ior 1.5, albedo 0.9, optical thickness 1
PAIRS = (
    np.concatenate([direction(40, 0), direction(10, 30), direction(70, 200)]),
    np.concatenate([direction(20, 90), direction(60, 250), direction(30, 45)]),
)


@pytest.mark.parametrize("alpha", [0.002, 0.01])
def test_a_glossy_top_over_a_mirror_is_continuous_with_a_smooth_one(alpha):
    """A milky coat over smooth gold under a top of alpha 0.002 (artist roughness 0.045) is within a few percent of
    the same coat at alpha 0.000999 (a delta interface; measured 0.6-3.7%, |z| <= 3.1 over 8 seeds), one of alpha
    0.01 within 10% (measured <= 5.3%, the lobe widening). The former estimator read them 5-27% dark (by channel)
    at z = -2 to -18: the light the mirror sends back to a medium vertex was made only by a connection at the top,
    which evaluates a lobe a few thousandths of a radian wide at a direction the phase function chose."""
    wi, wo = PAIRS
    smooth, s_se = R.eval_brdf(Stack(Conductor(0.0, **GOLD), (Coating(0.000999, **MILKY),)), wi, wo, 4000, seed=1)
    glossy, g_se = R.eval_brdf(Stack(Conductor(0.0, **GOLD), (Coating(alpha, **MILKY),)), wi, wo, 4000, seed=2)
    if alpha == 0.002:
        assert np.all(np.abs(glossy - smooth) < 5.0 * np.sqrt(s_se**2 + g_se**2)), (glossy, smooth)
    assert np.all(np.abs(glossy / smooth - 1.0) < (0.05 if alpha == 0.002 else 0.1)), glossy / smooth


@pytest.mark.parametrize(("alpha", "max_error"), [(0.002, 0.15), (0.01, 0.05), (0.03, 0.05)])
def test_a_glossy_top_over_a_milky_coat_over_a_mirror_is_reciprocal_and_converged(alpha, max_error):
    """f(wi, wo) = f(wo, wi) within 4 standard errors, each below ``max_error`` of f: measured 1.8% (alpha 0.01 and
    0.03) and up to 8% at alpha 0.002, whose paths that reflect inside the top before they reach a medium vertex
    keep a heavy tail (docs/reference.md). The former estimator's error at alpha 0.03 was 54% of f."""
    wi, wo = PAIRS
    stack = Stack(Conductor(0.0, **GOLD), (Coating(alpha, **MILKY),))
    f, se = R.eval_brdf(stack, wi, wo, walks=4000, seed=2)
    g, sg = R.eval_brdf(stack, wo, wi, walks=4000, seed=3)
    assert np.all(np.abs(f - g) < 4.0 * np.sqrt(se**2 + sg**2)), (f, g)
    assert np.all(se < max_error * f) and np.all(sg < max_error * g), (se / f, sg / g)


def smooth_coat_over_lambertian(cos_i: float, cos_o: float, n: float = 1.5, rho: float = 0.8) -> float:
    """The closed form of a smooth clear coat of index n over a Lambertian of albedo rho:
    T(wi) T(wo) rho / (pi n^2 (1 - rho F_dr)), F_dr the coat's internal diffuse reflectance."""
    mu = (np.arange(200000) + 0.5) / 200000
    f_dr = np.sum(fresnel_dielectric(-mu, np.full_like(mu, n)) * 2.0 * mu) / mu.shape[0]
    t = 1.0 - fresnel_dielectric(np.array([cos_i, cos_o]), np.full(2, n))
    return float(t[0] * t[1] * rho / (np.pi * n * n * (1.0 - rho * f_dr)))


def grazing(cos: float, phi: float) -> np.ndarray:
    s = np.sqrt(1.0 - cos * cos)
    return np.array([[s * np.cos(phi), s * np.sin(phi), cos]])


@pytest.mark.parametrize("cos_o", [1e-4, 1e-3])
def test_a_grazing_view_through_a_smooth_coat_matches_its_closed_form(cos_o):
    """The walk enters a smooth top by a forced transmission weighted 1 - F(wo), 4e-4 at cos(wo) = 1e-4: Russian
    roulette on that throughput ended nearly every walk after its second base bounce, and f read 0.77 of the
    closed form at z = -75 (or, for the few seeds where a survivor came back with weight 2500, 1.0-1.7 with a 23-57%
    error). Roulette leaves the entry's probability out: within 4 standard errors, each below 2% (measured 0.8%)."""
    exact = smooth_coat_over_lambertian(0.7, cos_o)
    stack = Stack(Diffuse(0.8), (Coating(0.0, 1.5),))
    for seed in (0, 1):
        f, se = R.eval_brdf(stack, grazing(0.7, 2.0), grazing(cos_o, 0.3), walks=4000, seed=seed)
        assert abs(f[0, 0] - exact) < 4.0 * se[0, 0] and se[0, 0] < 0.02 * exact, (f[0, 0] / exact, se[0, 0] / exact)


def test_a_grazing_view_of_a_milky_coat_over_a_mirror_is_reciprocal():
    """The same roulette over smooth gold: f(wi, grazing wo) read 0.65-2.2 of f(grazing wi, wo) (by channel and
    seed) with errors of 13-80%; now within 4 standard errors, each below 5% (measured 0.8-1.4%)."""
    stack = Stack(Conductor(0.0, **GOLD), (Coating(0.0, **MILKY),))
    near, far = grazing(0.7, 2.0), grazing(1e-4, 0.3)
    f, se = R.eval_brdf(stack, near, far, walks=4000, seed=0)
    g, sg = R.eval_brdf(stack, far, near, walks=4000, seed=10)
    assert np.all(np.abs(f - g) < 4.0 * np.sqrt(se**2 + sg**2)), f / g
    assert np.all(se < 0.05 * f) and np.all(sg < 0.05 * g), (se / f, sg / g)


# A rough interface transmits in a lobe about alpha |n1 - n2| / max(n1, n2) wide (test_reference.py).
MIN_TRANSMISSION_WIDTH = 0.03


def glossy_top_stack(rng: np.random.Generator) -> Stack:
    """A stack with a glossy top coat (alpha log-uniform in 1e-3..0.03, artist roughness 0.03-0.17) over a scattering
    slab (optical thickness 0.3-2), over a smooth conductor or dielectric base, with a second coating between half of
    the time (smooth or rough as ``test_reference.random_layered_stack`` draws them). A clear (non-scattering) glossy
    top right over a delta floor is left out: its paths through the top, a reflection inside it and the top again
    have one strategy fewer than they need, so they are heavy-tailed at pairs far from the mirror direction (where
    f is 1e-7 to 1e-5; docs/reference.md, Not done)."""
    if rng.integers(2) == 0:
        base = Conductor(0.0, eta=tuple(rng.uniform(0.1, 2.0, 3)), k=tuple(rng.uniform(1.0, 5.0, 3)))
    else:
        base = Dielectric(0.0, float(rng.uniform(1.2, 2.5)))
    iors = coating_iors(rng, 2)  # air, then the coatings from the top down
    coats = []
    for j in range(len(iors) - 1, 0, -1):  # bottom to top: coating j under iors[j - 1]
        n, above = iors[j], iors[j - 1]
        if j == 1:
            alpha = float(np.exp(rng.uniform(np.log(1e-3), np.log(0.03))))
        else:
            lo = max(0.05, MIN_TRANSMISSION_WIDTH * max(n, above) / abs(n - above))
            alpha = 0.0 if rng.random() < 0.5 or lo > 0.6 else float(rng.uniform(lo, 0.6))
        scattering = j == 1 or rng.random() < 0.6
        coats.append(
            Coating(
                alpha,
                n,
                tuple(rng.uniform(0.3, 1.0, 3)) if scattering else 0.0,
                float(rng.uniform(0.3, 2.0)) if j == 1 or rng.random() < 0.8 else 0.0,
                float(rng.uniform(-0.6, 0.6)),
            )
        )
    return Stack(base, tuple(coats))


@pytest.mark.parametrize("seed", range(24))
def test_reciprocity_on_random_stacks_with_a_glossy_top_over_a_smooth_base(seed):
    """f(wi, wo) = f(wo, wi) within 4.5 standard errors on 4 random pairs (measured |z| <= 3.1 over 60 stacks). The
    former estimator failed on 3 of these 24 stacks (|z| 6-11) and on 4 of 60: light that delta events bring back
    to a vertex under a glossy interface was made only by a connection at that interface."""
    rng = np.random.default_rng(5000 + seed)
    stack = glossy_top_stack(rng)
    z = 0.15 + 0.85 * rng.random((2, 4))
    phi = 2.0 * np.pi * rng.random((2, 4))
    s = np.sqrt(1.0 - z * z)
    d = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)
    wi, wo = d[0], d[1]
    f, se = R.eval_brdf(stack, wi, wo, walks=3000, seed=2 * seed)
    g, sg = R.eval_brdf(stack, wo, wi, walks=3000, seed=2 * seed + 1)
    assert np.all(f > 0.0) and np.all(g > 0.0)
    assert np.all(np.abs(f - g) <= 4.5 * np.sqrt(se**2 + sg**2)), (stack, f, g, se, sg)


# Stacks where the routes act under rough interfaces wide enough for eval's integral over cosine-distributed
# directions: a route's MIS weight and the walk's connection's must sum to one, else eval leaves the analog walk.
ROUTES = {
    # a medium vertex under two smooth interfaces under a rough top: entry reflections and delta routes
    "milky under two smooth coats under a rough top, over a mirror": Stack(
        Conductor(0.0, **GOLD), (Coating(0.0, 1.4, 0.8, 0.5), Coating(0.0, 1.7), Coating(0.2, 1.5))
    ),
    # a rough interface between smooth ones over a smooth dielectric base: floor routes, entry reflections
    "rough between smooth coats over a smooth dielectric": Stack(
        Dielectric(0.0, 1.8), (Coating(0.0, 1.3, 0.7, 0.4), Coating(0.15, 1.9, 0.5, 0.3), Coating(0.0, 1.5))
    ),
    # delta routes and floor routes under a rough top
    "rough top over a milky coat over a mirror": Stack(Conductor(0.0, **GOLD), (Coating(0.1, 1.5, 0.9, 1.0),)),
    # entry reflections under a rough top, with a Lambertian base
    "two smooth clear coats under a rough top": Stack(
        Diffuse(0.7), (Coating(0.0, 1.3), Coating(0.0, 2.2), Coating(0.25, 1.5, 0.8, 0.3))
    ),
}


@pytest.mark.parametrize("name", list(ROUTES))
def test_eval_matches_analog_walk_where_routes_cross_rough_interfaces(name):
    assert_eval_matches_analog_walk(ROUTES[name], 20000, 4.0)

"""Independent cross-check of the single interfaces against Mitsuba 3 (variant scalar_rgb).

Conventions reconciled here:
- Mitsuba's ``eval(ctx, si, wo)`` returns f * cos, with ``si.wi`` toward the viewer (our ``wo``)
  and its ``wo`` toward the light (our ``wi``): we compare ``f * |cos wi|``.
- Mitsuba masks with the separable Smith G1(wi) G1(wo); we use the height-correlated
  G2 = 1 / (1 + Lambda(wi) + Lambda(wo)) (pbrt-v4). Our value is converted to Mitsuba's
  convention by the factor G1(wi) G1(wo) / G2 computed with our own Smith functions, which
  are themselves checked against Mitsuba's ``MicrofacetDistribution`` below.
- The sampling densities do not involve G2 (visible normals from wo and a Fresnel lobe choice
  in both), so ``pdf`` is compared directly.
Mitsuba runs in float32: agreement is asked within 1% where values are not tiny.
"""

import numpy as np
import pytest

from addon.core.bsdf import (
    IMPORTANCE,
    RADIANCE,
    RoughConductor,
    RoughDielectric,
    fresnel_conductor,
    fresnel_dielectric,
    ggx,
    normalize,
    refract,
)

mi = pytest.importorskip("mitsuba")
mi.set_variant("scalar_rgb")

pytestmark = pytest.mark.mitsuba

N_PAIRS = 400
RTOL = 0.01
GOLD_ETA, GOLD_K = [0.143, 0.374, 1.442], [3.983, 2.385, 1.603]


def _ctx(mode):
    return mi.BSDFContext(mi.TransportMode.Radiance if mode == RADIANCE else mi.TransportMode.Importance)


def mitsuba_eval_pdf(bsdf, wi, wo, mode):
    """Mitsuba's (f cos(wi), pdf) for our (wi, wo) pairs, row by row (scalar variant)."""
    ctx = _ctx(mode)
    f = np.zeros((len(wi), 3))
    p = np.zeros(len(wi))
    si = mi.SurfaceInteraction3f()
    for r in range(len(wi)):
        si.wi = mi.Vector3f(*wo[r])
        v, pd = bsdf.eval_pdf(ctx, si, mi.Vector3f(*wi[r]))
        f[r] = np.array(v)
        p[r] = float(pd)
    return f, p


def separable_f_cos(ours, wi, wo, alpha):
    """Our f converted to Mitsuba's masking and cosine convention."""
    g2 = ggx.smith_g2(wi, wo, alpha)
    sep = ggx.smith_g1(wi, alpha) * ggx.smith_g1(wo, alpha)
    with np.errstate(invalid="ignore", divide="ignore"):
        conv = np.where(g2 > 0, sep / g2, 0.0)
    return ours * (conv * np.abs(wi[:, 2]))[:, None]


def _pairs(seed, wo_side, wi_side):
    """Random pairs with wo and wi on the requested sides (+1 above, -1 below), away from grazing."""
    rng = np.random.default_rng(abs(seed))

    def dirs(side):
        v = normalize(rng.normal(size=(N_PAIRS, 3)))
        v[:, 2] = side * np.maximum(np.abs(v[:, 2]), 0.05)
        return normalize(v)

    return dirs(wi_side), dirs(wo_side)


def _assert_close(ours, theirs, what):
    scale = max(np.max(np.abs(theirs)), 1e-30)
    big = (np.abs(theirs) > 1e-4 * scale) & (np.abs(ours) > 1e-4 * scale)
    assert big.sum() > N_PAIRS // 10, f"{what}: too few non-negligible values to compare ({big.sum()})"
    rel = np.abs(ours[big] - theirs[big]) / np.abs(theirs[big])
    assert rel.max() < RTOL, f"{what}: max relative difference {rel.max():.3g}"
    # where one side is negligible, so is the other
    np.testing.assert_allclose(ours[~big], theirs[~big], atol=2e-4 * scale, err_msg=what)


# ----------------------------------------------------------------------------- pieces


def test_fresnel_matches_mitsuba():
    cos = np.linspace(-1.0, 1.0, 201)
    for eta in (1.5, 1.33, 0.8):
        theirs = np.array([mi.fresnel(float(c), eta)[0] for c in cos])
        # Mitsuba is float32: skip the kink at the critical angle
        eta_side = np.where(cos < 0, 1 / eta, eta)
        away = np.abs((1 - cos**2) / eta_side**2 - 1) > 1e-3
        np.testing.assert_allclose(fresnel_dielectric(cos, eta)[away], theirs[away], atol=2e-6)
    cos = np.linspace(0.0, 1.0, 101)
    ours = fresnel_conductor(cos, GOLD_ETA, GOLD_K)
    for ch in range(3):
        theirs = np.array([mi.fresnel_conductor(float(c), mi.Complex2f(GOLD_ETA[ch], GOLD_K[ch])) for c in cos])
        np.testing.assert_allclose(ours[:, ch], theirs, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
def test_ggx_pieces_match_mitsuba(alpha):
    d = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, True)
    rng = np.random.default_rng(1)
    m = normalize(rng.normal(size=(300, 3)))
    m[:, 2] = np.abs(m[:, 2])
    # bias the normals toward +z so that small-alpha D is not all ~0
    m = normalize(m * [alpha, alpha, 1.0])
    w = normalize(rng.normal(size=(300, 3)))
    w[:, 2] = np.abs(w[:, 2])
    facing = np.sum(w * m, axis=1) > 0
    D = np.array([d.eval(mi.Vector3f(*x)) for x in m])
    np.testing.assert_allclose(ggx.ndf(m, alpha), D, rtol=2e-5)
    # Mitsuba's G1 takes the microfacet normal (0 for back-facing); ours the facing test lives in the BSDF
    G1 = np.array([d.smith_g1(mi.Vector3f(*a), mi.Vector3f(*b)) for a, b in zip(w, m, strict=True)])
    np.testing.assert_allclose(ggx.smith_g1(w, alpha)[facing], G1[facing], rtol=2e-5)
    P = np.array([d.pdf(mi.Vector3f(*a), mi.Vector3f(*b)) for a, b in zip(w, m, strict=True)])
    np.testing.assert_allclose(ggx.pdf_visible_normal(w, m, alpha)[facing], P[facing], rtol=2e-5)


# ----------------------------------------------------------------------------- interfaces


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
def test_rough_conductor_matches_mitsuba(alpha):
    theirs = mi.load_dict(
        {
            "type": "roughconductor",
            "distribution": "ggx",
            "alpha": alpha,
            "eta": {"type": "rgb", "value": GOLD_ETA},
            "k": {"type": "rgb", "value": GOLD_K},
        }
    )
    wi, wo = _pairs(int(alpha * 100), +1, +1)
    if alpha < 0.1:  # put wi near the mirror direction so the narrow lobe is sampled
        wi = normalize(wo * [-1, -1, 1] + 0.1 * np.random.default_rng(2).normal(size=wo.shape))
        wi[:, 2] = np.abs(wi[:, 2])
    ours = RoughConductor(alpha, GOLD_ETA, GOLD_K)
    f_m, p_m = mitsuba_eval_pdf(theirs, wi, wo, RADIANCE)
    _assert_close(separable_f_cos(ours.eval(wi, wo), wi, wo, alpha), f_m, f"conductor alpha={alpha} f")
    _assert_close(ours.pdf(wi, wo), p_m, f"conductor alpha={alpha} pdf")


@pytest.mark.parametrize("mode", [RADIANCE, IMPORTANCE])
@pytest.mark.parametrize("wo_side, wi_side", [(+1, +1), (+1, -1), (-1, -1), (-1, +1)])
@pytest.mark.parametrize(
    "alpha, int_ior, ext_ior", [(0.05, 1.5, 1.0), (0.3, 1.5, 1.0), (1.0, 1.5, 1.0), (0.3, 1.4, 1.6)]
)
def test_rough_dielectric_matches_mitsuba(alpha, int_ior, ext_ior, wo_side, wi_side, mode):
    """Reflection and transmission, lit and seen from both sides, both transport modes;
    ``int_ior / ext_ior`` < 1 is an interface between two media (relative ior 0.875)."""
    theirs = mi.load_dict(
        {"type": "roughdielectric", "distribution": "ggx", "alpha": alpha, "int_ior": int_ior, "ext_ior": ext_ior}
    )
    ior = int_ior / ext_ior
    ours = RoughDielectric(alpha, ior)
    wi, wo = _pairs(int(alpha * 100) + 10 * wo_side + wi_side, wo_side, wi_side)
    # aim half of the wi at the specular or refracted direction so that narrow lobes (small
    # alpha, ior near 1) are hit; keep the other half uniformly random
    rng = np.random.default_rng(3)
    if wo_side == wi_side:
        target = wo * [-1, -1, 1]
    else:
        target, ok = refract(wo, np.tile([0.0, 0.0, 1.0], (N_PAIRS, 1)), ior)
        target = np.where(ok[:, None], target, -wo)
    aimed = normalize(target + min(2 * alpha, 0.5) * rng.normal(size=wo.shape))
    aimed[:, 2] = wi_side * np.maximum(np.abs(aimed[:, 2]), 0.02)
    wi[: N_PAIRS // 2] = normalize(aimed)[: N_PAIRS // 2]
    f_m, p_m = mitsuba_eval_pdf(theirs, wi, wo, mode)
    what = f"dielectric alpha={alpha} eta={ior:.3f} wo {wo_side:+d} wi {wi_side:+d} {mode}"
    _assert_close(separable_f_cos(ours.eval(wi, wo, mode), wi, wo, alpha), f_m, what + " f")
    _assert_close(ours.pdf(wi, wo, mode), p_m, what + " pdf")


@pytest.mark.parametrize("mode", [RADIANCE, IMPORTANCE])
@pytest.mark.parametrize("below", [False, True])
def test_smooth_dielectric_events_match_mitsuba(mode, below):
    theirs = mi.load_dict({"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0})
    ours = RoughDielectric(0.0, 1.5)
    rng = np.random.default_rng(4)
    wo = normalize(rng.normal(size=(50, 3)))
    wo[:, 2] = (-1 if below else 1) * np.maximum(np.abs(wo[:, 2]), 0.05)
    wo = normalize(wo)
    si = mi.SurfaceInteraction3f()
    for u_lobe in (0.0, 0.999):  # first the reflection event, then transmission (if not TIR)
        s = ours.sample(wo, np.full(50, u_lobe), np.zeros((50, 2)), mode)
        for r in range(50):
            si.wi = mi.Vector3f(*wo[r])
            bs, w = theirs.sample(_ctx(mode), si, u_lobe, mi.Point2f(0.5, 0.5))
            np.testing.assert_allclose(s.wi[r], np.array(bs.wo), atol=1e-5)
            np.testing.assert_allclose(s.pdf[r], float(bs.pdf), rtol=1e-4, atol=1e-6)
            np.testing.assert_allclose(s.weight[r], np.array(w), rtol=1e-4)

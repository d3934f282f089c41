"""The Principled BSDF's compiled bounce (``kernels.principled_shade``, what ``render.PrincipledMaterial`` shades
with): the numpy ``bsdf.SpecularDiffuse`` it shares its formulas with, and the BSDF as it was written before those
formulas (kept below as an independent check), give the same f, pdf and samples on random directions and
parameters; its samples follow its pdf; it reflects no more light than it receives; a render through it is the
render through the numpy BSDF; and the formulas it compiles in are covered by the disk cache's digest."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from addon.core import kernels
from addon.core.bsdf import (
    SMOOTH_ALPHA,
    Lambertian,
    RoughConductor,
    RoughDielectric,
    SpecularDiffuse,
    frame,
    fresnel_conductor,
    fresnel_dielectric,
    ggx,
)
from addon.core.bsdf.lambert import sample_cosine_hemisphere
from addon.core.bsdf.specular_diffuse import TABLE_SHAPE, albedo_table, fresnel_dielectric_average
from addon.core.stack import k_from_f0
from tests.core.test_bsdf_sampling import BINS, SIGNIFICANCE, _dir
from tests.stats import chi2_sphere

ROOT = Path(__file__).resolve().parents[2]


# --- the BSDF as numpy shaded it before the compiled loop: the classes' eval and pdf, the table read by scipy -------


class _Previous:
    """SpecularDiffuse as it was written before its formulas were shared with the compiled loop: the dielectric's
    and the conductor's own classes, a Lambertian weighted by 1 - E S, Multiscatter GGX's factor written out, the
    albedo table interpolated by scipy, and the sampler's two candidates drawn with the array functions."""

    def __init__(self, base, alpha, ior, metallic):
        self.base = np.broadcast_to(
            np.asarray(base, dtype=np.float64), (1, 3) if np.ndim(base) == 1 else np.shape(base)
        )
        self.alpha, self.ior, self.metallic = float(alpha), float(ior), float(metallic)
        self.table = RegularGridInterpolator([np.linspace(0.0, 1.0, n) for n in TABLE_SHAPE], albedo_table())
        nodes = np.linspace(0.0, 1.0, TABLE_SHAPE[2])
        e1 = albedo_table()[-1]
        self.e1_avg = np.interp(
            np.sqrt(self.alpha),
            nodes,
            2.0 * np.trapz(e1 * nodes, nodes, axis=1),  # the cosine-weighted mean of E1 at each roughness node
        )
        self.f_avg = float(fresnel_dielectric_average(self.ior))

    def _albedo(self, z, mu):
        mu = np.abs(mu)
        return self.table(np.stack([np.full(mu.shape, z), np.full(mu.shape, np.sqrt(self.alpha)), mu], axis=-1))

    def _scale(self, mu, f_avg):
        e1 = self._albedo(1.0, mu)
        extra = (1.0 - e1) / np.maximum(e1, 1e-6)
        if np.ndim(f_avg) == 2:
            extra = extra[:, None]
        return 1.0 + f_avg * self.e1_avg / (1.0 - f_avg * (1.0 - self.e1_avg)) * extra

    def _probability(self, mu):
        e = self._albedo((self.ior - 1.0) / (self.ior + 1.0), mu) * self._scale(mu, self.f_avg)
        colour = np.clip(self.base, 0.0, 1.0).mean(axis=1)
        glossy = (1.0 - self.metallic) * e + self.metallic * colour
        total = glossy + (1.0 - self.metallic) * (1.0 - e) * colour
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(total > 0.0, glossy / total, 0.5)

    @staticmethod
    def _above(wi, wo):
        """Both mirrored where wo lies below: the surface is two-sided."""
        flip = np.where(wo[:, 2:3] < 0.0, [1.0, 1.0, -1.0], [1.0, 1.0, 1.0])
        return wi * flip, wo * flip

    def eval(self, wi, wo):
        wi, wo = self._above(wi, wo)
        mu = wo[:, 2]
        spec = RoughDielectric(self.alpha, self.ior, reflection_only=True).eval(wi, wo, check=False)
        scale = self._scale(mu, self.f_avg)[:, None]
        e = self._albedo((self.ior - 1.0) / (self.ior + 1.0), mu)[:, None] * scale
        diffuse = Lambertian.of_valid_rows(np.ascontiguousarray(self.base)).eval(wi, wo, check=False) * (1.0 - e)
        f = (1.0 - self.metallic) * (spec * scale + diffuse)
        if self.metallic > 0.0:
            metal = RoughConductor(self.alpha, 1.0, k_from_f0(self.base)).eval(wi, wo, check=False)
            f0 = np.clip(self.base, 0.0, 1.0)
            f = f + self.metallic * metal * self._scale(mu, np.broadcast_to(f0 + (1.0 - f0) / 21.0, metal.shape))
        return f

    def pdf(self, wi, wo):
        wi, wo = self._above(wi, wo)
        p = self._probability(wo[:, 2])
        glossy = RoughConductor(self.alpha, 1.0, 0.0).pdf(wi, wo, check=False)
        return p * glossy + (1.0 - p) * np.where(wi[:, 2] * wo[:, 2] > 0.0, np.abs(wi[:, 2]) / np.pi, 0.0)

    def sample(self, wo, u_lobe, u):
        """(wi, weight, pdf, delta, valid), invalid rows zeroed."""
        below = wo[:, 2] < 0.0
        up = np.where(below[:, None], wo * [1.0, 1.0, -1.0], wo)
        p = self._probability(up[:, 2])
        glossy = u_lobe < p
        smooth = self.alpha < SMOOTH_ALPHA
        m = np.tile([0.0, 0.0, 1.0], (len(wo), 1)) if smooth else ggx.sample_visible_normal(up, self.alpha, u)
        wi = np.where(glossy[:, None], frame.reflect(up, m), sample_cosine_hemisphere(u))
        with np.errstate(invalid="ignore", divide="ignore"):
            f = self.eval(wi, up)
            pdf = self.pdf(wi, up)
            weight = f * np.abs(wi[:, 2:3]) / pdf[:, None]
        delta = glossy & smooth
        if smooth:
            mirror = (1.0 - self.metallic) * fresnel_dielectric(up[:, 2], self.ior)[:, None]
            mirror = mirror + self.metallic * fresnel_conductor(up[:, 2], 1.0, k_from_f0(self.base))
            weight = np.where(delta[:, None], mirror / p[:, None], weight)
            pdf = np.where(delta, p, pdf)
        valid = (up[:, 2] > 0.0) & (wi[:, 2] > 0.0) & (pdf > 0.0) & np.isfinite(weight).all(axis=1)
        wi = np.where(below[:, None], wi * [1.0, 1.0, -1.0], wi)
        zero = ~valid
        return (
            np.where(zero[:, None], 0.0, wi), np.where(zero[:, None], 0.0, weight), np.where(zero, 0.0, pdf),
            delta & valid, valid,
        )  # fmt: skip


# --- random directions and parameters ------------------------------------------------------------------------------


def _directions(rng, n):
    """Unit directions over the whole sphere, a fifth of them within a degree of the horizon (grazing, above or
    below) and a few exactly on it."""
    w = frame.normalize(rng.normal(size=(n, 3)))
    grazing = rng.random(n) < 0.2
    z = np.where(rng.random(n) < 0.5, -1.0, 1.0) * 10.0 ** rng.uniform(-6.0, -1.8, n)
    xy = frame.normalize(np.concatenate([w[:, :2], np.zeros((n, 1))], axis=1)) * np.sqrt(1.0 - z * z)[:, None]
    w = np.where(grazing[:, None], xy + np.stack([0 * z, 0 * z, z], axis=-1), w)
    w[rng.random(n) < 0.01, 2] = 0.0
    return frame.normalize(w)


CASES = [  # base (None: a texture's, per hit), alpha, ior, metallic
    ((0.8, 0.8, 0.8), 0.25, 1.5, 0.0),  # Blender's default material
    ((0.02, 0.03, 0.1), 0.09, 1.5, 0.0),
    ((1.0, 0.77, 0.34), 0.09, 1.5, 1.0),  # gold
    ((0.5, 0.2, 0.1), 0.36, 2.0, 0.5),
    (None, 0.16, 1.45, 0.0),  # textured base colour
    (None, 0.49, 1.5, 0.5),  # textured, half metal
    (None, 1.0, 2.5, 1.0),
    ((0.3, 0.6, 0.2), 0.0, 1.5, 0.0),  # smooth: a delta mirror
    ((0.3, 0.6, 0.2), 0.5 * SMOOTH_ALPHA, 1.5, 0.5),  # smooth, half metal
    ((0.7, 0.7, 0.7), 0.3, 1.0, 0.0),  # Specular IOR Level 0: no layer
    ((0.0, 0.0, 0.0), 0.04, 1.5, 0.0),  # black plastic
]


def _case(rng, base, alpha, ior, metallic, n):
    if base is None:  # texels as the renderer makes them: >= 0, some above 1, some 0
        base = np.maximum(rng.uniform(-0.2, 1.4, (n, 3)), 0.0)
    return SpecularDiffuse(base, alpha, ior, metallic), _Previous(base, alpha, ior, metallic)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_the_compiled_bounce_is_the_numpy_bsdf_and_the_bsdf_as_it_was(case):
    """f and pdf at next-event directions (a random subset of the hits), and every hit's sample, from the compiled
    loop, against ``SpecularDiffuse``'s eval, pdf and sample on the same numbers (the same formulas: to rounding) and
    against the BSDF as numpy shaded it before (to the table interpolation's rounding; the compiled sampler's
    azimuth is its own series for cos and sin, to 1e-12)."""
    base, alpha, ior, metallic = CASES[case]
    rng = np.random.default_rng(case)
    n = 4000
    bsdf, previous = _case(rng, base, alpha, ior, metallic, n)
    wo = _directions(rng, n)
    rows = np.flatnonzero(rng.random(n) < 0.7)
    light_wi = _directions(rng, len(rows))
    u_lobe, u = rng.random(n), rng.random((n, 2))
    f, pdf, wi, weight, p, delta, valid = kernels.principled_shade(
        *bsdf.shading_arrays(), wo, light_wi, rows, u_lobe, u
    )
    assert np.isfinite(f).all() and (f >= 0.0).all() and np.isfinite(pdf).all() and (pdf >= 0.0).all()
    rows_bsdf = bsdf.take(rows)
    np.testing.assert_allclose(f, rows_bsdf.eval(light_wi, wo[rows], check=False), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(pdf, rows_bsdf.pdf(light_wi, wo[rows], check=False), rtol=1e-12, atol=1e-300)
    s = bsdf.sample(wo, u_lobe, u, check=False)
    assert np.array_equal(valid, s.valid) and np.array_equal(delta, s.delta)
    assert 0.5 < valid.mean() < 1.0
    np.testing.assert_allclose(wi, s.wi, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(weight, s.weight, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(p, s.pdf, rtol=1e-9, atol=1e-12)
    # the BSDF as it was
    old_rows = _Previous(
        np.asarray(previous.base)[rows] if previous.base.shape[0] > 1 else previous.base, alpha, ior, metallic
    )
    np.testing.assert_allclose(f, old_rows.eval(light_wi, wo[rows]), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(pdf, old_rows.pdf(light_wi, wo[rows]), rtol=1e-9, atol=1e-12)
    o_wi, o_weight, o_pdf, o_delta, o_valid = previous.sample(wo, u_lobe, u)
    assert np.array_equal(valid, o_valid) and np.array_equal(delta, o_delta)
    np.testing.assert_allclose(wi, o_wi, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(weight, o_weight, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(p, o_pdf, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(
    "base, alpha, metallic, theta, below",
    [
        ((0.8, 0.8, 0.8), 0.25, 0.0, 45.0, False),  # the default material
        ((0.8, 0.8, 0.8), 0.25, 0.0, 88.0, True),  # seen at grazing, from below
        ((1.0, 0.77, 0.34), 0.09, 1.0, 20.0, False),
        ((0.5, 0.2, 0.1), 0.36, 0.5, 70.0, True),
        ((0.05, 0.05, 0.05), 0.01, 0.0, 60.0, False),  # a dark glossy plastic
    ],
)
def test_the_compiled_samples_follow_the_compiled_pdf(base, alpha, metallic, theta, below):
    """The loop's samples from one view are distributed as its own pdf at next-event directions says (chi-square
    over the sphere, the harness of tests/core/test_bsdf_sampling.py), and each weighs its f |cos| / pdf as the
    loop evaluates them there."""
    bsdf = SpecularDiffuse(base, alpha, 1.5, metallic)
    arrays = bsdf.shading_arrays()
    wo = _dir(theta, below=below)
    n = 100_000
    rng = np.random.default_rng(int(theta))
    wos = np.tile(wo, (n, 1))
    _, _, wi, weight, pdf, delta, valid = kernels.principled_shade(
        *arrays, wos, np.zeros((0, 3)), np.zeros(0, np.int64), rng.random(n), rng.random((n, 2))
    )
    assert not delta.any() and valid.mean() > 0.5

    def at(directions):
        rows = np.arange(len(directions))
        m = len(directions)
        f, p, *_ = kernels.principled_shade(
            *arrays, np.tile(wo, (m, 1)), directions, rows, np.zeros(m), np.zeros((m, 2))
        )
        return f, p

    f, p = at(wi[valid])
    np.testing.assert_allclose(p, pdf[valid], rtol=1e-9)
    np.testing.assert_allclose(f * np.abs(wi[valid, 2:3]) / p[:, None], weight[valid], rtol=1e-9)
    res = chi2_sphere(wi, valid, lambda g: at(np.ascontiguousarray(g))[1], **BINS)
    assert res.pvalue > SIGNIFICANCE, f"chi-square p = {res.pvalue:.2e} (pdf integrates to {res.pdf_integral:.4f})"


@pytest.mark.parametrize("metallic", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("alpha", [0.0, 0.01, 0.09, 0.36, 1.0])
def test_a_white_principled_surface_reflects_no_more_light_than_it_receives(alpha, metallic):
    """White furnace: the mean sample weight of the compiled loop (its albedo, the delta mirror's weight included)
    over a white base is at most 1 at every view cosine, grazing ones too; a white plastic (metallic 0), whose
    Fresnel-weighted layer and albedo-scaled base keep all light, is 1 to the albedo table's accuracy, and a white
    metal above 0.9 (``stack.k_from_f0`` holds its F0 at 0.999, and the Fresnel of a conductor of index 1 + k i dips
    to 0.96 at a view cosine of 0.1)."""
    rng = np.random.default_rng(int(alpha * 100 + 10 * metallic))
    arrays = SpecularDiffuse((1.0, 1.0, 1.0), alpha, 1.5, metallic).shading_arrays()
    n = 200_000
    for mu in (0.02, 0.1, 0.3, 0.6, 1.0):
        wo = np.tile([np.sqrt(1.0 - mu * mu), 0.0, mu], (n, 1))
        *_, weight, _, _, valid = kernels.principled_shade(
            *arrays, wo, np.zeros((0, 3)), np.zeros(0, np.int64), rng.random(n), rng.random((n, 2))
        )
        mean, err = weight.mean(axis=0), weight.std(axis=0) / np.sqrt(n)
        assert np.all(mean <= 1.0 + 4.0 * err + 5e-3), (mu, mean, err)
        if metallic == 0.0 and mu >= 0.1:
            assert np.all(np.abs(mean - 1.0) < 4.0 * err + 5e-3), (mu, mean, err)
        assert np.all(mean > 0.9 - 4.0 * err), (mu, mean, err)


def test_a_white_principled_sphere_in_a_white_furnace_renders_the_sky():
    """A rendered white furnace: a white Principled sphere on a box (rough, and half metal) inside a uniform sky of
    0.5, many bounces: every pixel the sky's 0.5 to the paths' noise, never brighter on average."""
    from addon.core.render import Camera, Environment, Mesh, PrincipledMaterial, RenderSettings, Scene, render, shapes

    cam = Camera.look_at((0, -4, 1), (0, 0, 0.3), fov_deg=45, width=24, height=24)
    mesh = Mesh.concatenate(
        [shapes.uv_sphere((0, 0, 0.7), 0.7, segments=24, rings=12), shapes.box((0, 0, -0.2), (1.2, 1.2, 0.2), 1)]
    )
    materials = [PrincipledMaterial((1.0, 1.0, 1.0), roughness=0.5), PrincipledMaterial((1.0, 1.0, 1.0), 0.5, 0.3)]
    scene = Scene(cam, mesh, materials, [], Environment((0.5, 0.5, 0.5)))
    film, stats = render(scene, RenderSettings(samples=48, max_bounces=64, rr_depth=64))
    img, se = film.mean(), film.stderr()
    assert stats.nonfinite == 0
    assert img.mean() < 0.5 + 3e-3 and img.mean() > 0.48
    z = (img - 0.5) / np.maximum(se, 1e-3)
    assert np.sqrt((z**2).mean()) < 2.0


def test_a_principled_material_shades_in_the_compiled_loop_as_the_numpy_bsdf_does():
    """A render of constant and textured Principled materials (dielectric, metal, smooth) goes through the
    compiled loop, never the numpy BSDF's methods, and gives the image the numpy BSDF gives (the same numbers
    drawn, the same formulas: to rounding, which can tip a rare Russian roulette or lobe choice)."""
    from addon.core.bsdf import specular_diffuse
    from addon.core.render import (
        Camera,
        ImageTexture,
        Mesh,
        PointLight,
        PrincipledMaterial,
        RenderSettings,
        Scene,
        render,
        shapes,
    )
    from addon.core.render import materials as M
    from addon.core.render.shading import ShadeByParts

    cam = Camera.look_at((0.3, -5.0, 1.6), (0.0, 0.0, 0.5), fov_deg=40, width=32, height=24)
    mesh = Mesh.concatenate(
        [
            shapes.uv_sphere((-0.6, 0.0, 0.6), 0.6, material=1, segments=24, rings=12),
            shapes.uv_sphere((0.8, 0.2, 0.45), 0.45, material=2, segments=24, rings=12),
            shapes.quad((0, 0, 0), (3, 0, 0), (0, 3, 0), material=0),
        ]
    )
    texture = ImageTexture(np.random.default_rng(1).random((8, 8, 3)))
    materials = [
        PrincipledMaterial((1.0, 1.0, 1.0), roughness=0.6, texture=texture),
        PrincipledMaterial((1.0, 0.77, 0.34), metallic=0.7, roughness=0.3),
        PrincipledMaterial((0.2, 0.3, 0.6), roughness=0.0),
    ]
    scene = Scene(cam, mesh, materials, [PointLight((-2.0, -2.0, 3.0), power=300.0)], None)
    settings = RenderSettings(samples=8, max_bounces=4, seed=2, threads=1)

    def numpy_bound(bound):
        out = M._BoundBSDF(bound.bsdf)
        out.shade = lambda *a: ShadeByParts.shade(out, *a)
        return out

    class Numpy:
        kind, has_pdf = "analytic", True

        def __init__(self, m):
            self.m = m

        def bind(self, hits):
            return numpy_bound(self.m.bind(hits))

    reference = render(Scene(cam, mesh, [Numpy(m) for m in materials], scene.lights, None), settings)[0].mean()
    guard = pytest.MonkeyPatch()
    for name in ("eval", "pdf", "sample"):
        guard.setattr(specular_diffuse.SpecularDiffuse, name, lambda *a, **k: pytest.fail("shaded in numpy"))
    try:
        compiled = render(scene, settings)[0].mean()
    finally:
        guard.undo()
    assert np.mean(np.abs(compiled - reference) > 1e-9) < 0.02
    np.testing.assert_allclose(compiled.mean(), reference.mean(), rtol=2e-3)


def test_the_disk_caches_digest_covers_every_formula_the_principled_loop_compiles_in():
    """numba's disk cache keys a loop on kernels.py alone (``kernels._drop_stale_cache``): every formula the
    Principled loop compiles in lives in a file of ``kernels.FORMULA_SOURCES``, whose digest drops the cache."""
    import inspect

    from addon.core import formula
    from addon.core.bsdf import fresnel, lambert, specular_diffuse

    here = Path(kernels.__file__).resolve().parent
    covered = {p.resolve() for pattern in kernels.FORMULA_SOURCES for p in here.glob(pattern)}
    used = [
        specular_diffuse.curve_at, specular_diffuse.multiscatter_factor, specular_diffuse.schlick_mean,
        specular_diffuse.lobe_probability, specular_diffuse.lobe_mixture_pdf, specular_diffuse.principled_view,
        specular_diffuse.principled_eval, specular_diffuse.principled_sample, ggx.reflection_terms,
        ggx.visible_normal, fresnel.fresnel_conductor_cos, fresnel.fresnel_dielectric_cos, lambert.lambert_sample,
        formula.node_below,
    ]  # fmt: skip
    for fn in used:
        assert Path(inspect.getsourcefile(fn)).resolve() in covered, fn.__name__


_PRINCIPLED = """
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np
from addon.core import kernels
from addon.core.bsdf import SpecularDiffuse
arrays = SpecularDiffuse((0.5, 0.4, 0.3), 0.25, 1.5, 1.0).shading_arrays()
w = np.array([[0.0, 0.0, 1.0]])
f = kernels.principled_shade(*arrays, w, w, np.zeros(1, dtype=np.int64), np.zeros(1), np.full((1, 2), 0.5))[0]
print(repr(f[0, 0]))
"""


def test_a_changed_principled_formula_is_compiled_again_and_never_loaded_stale(tmp_path):
    """A copy of the add-on runs the Principled loop, its metal's multiple-scattering average (schlick_mean, in
    bsdf/specular_diffuse.py) is changed, and the loop run again computes with the changed formula."""
    import shutil

    shutil.copytree(ROOT / "addon", tmp_path / "addon", ignore=shutil.ignore_patterns("__pycache__", "models"))

    def run():
        out = subprocess.run(
            [sys.executable, "-c", _PRINCIPLED, str(tmp_path)], capture_output=True, text=True, timeout=600, check=True
        )
        return float(out.stdout.strip().splitlines()[-1])

    before = run()
    assert list((tmp_path / "addon" / "core" / "__pycache__").glob("kernels._principled_at_lights*.nbc"))
    src = tmp_path / "addon" / "core" / "bsdf" / "specular_diffuse.py"
    text = src.read_text()
    assert "return f0 + (1.0 - f0) / 21.0" in text
    src.write_text(text.replace("return f0 + (1.0 - f0) / 21.0", "return f0 + (1.0 - f0) / 2.0"))
    assert run() != before


def test_node_below_is_the_floor_held_to_the_table_on_arrays_and_in_a_loop():
    """``formula.node_below``, the table index of ``curve_at``: the floor of x in [0, last], last above it, 0 below
    0 and for nan (never an index from int(nan)), the same numbers on arrays and in a compiled loop."""
    from numba import njit

    from addon.core.formula import node_below

    x = np.array([0.0, 0.3, 1.0, 1.999, 2.0, 2.5, 30.9, 31.0, 31.5, 1e300, np.inf, -0.0, -0.5, -np.inf, np.nan])
    want = np.array([0, 0, 1, 1, 2, 2, 30, 30, 30, 30, 30, 0, 0, 0, 0])

    @njit
    def each(x, last):
        out = np.empty(len(x), np.int64)
        for i in range(len(x)):
            out[i] = node_below(x[i], last)
        return out

    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(node_below(x, 30), want)
    np.testing.assert_array_equal(each(x, 30), want)
    assert node_below(x, 30).dtype == np.int64

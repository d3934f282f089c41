"""The renderer's compiled loops (addon/core/kernels.py): compiled before a user waits on them."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from addon.core import kernels

ROOT = Path(__file__).resolve().parents[2]

# Run in a fresh interpreter: in the test process other tests may have compiled loops already.
_SCRIPT = """
import json, sys
import numba
from addon.core import kernels
from addon.core.render import RenderSettings, render
from addon.core.render.demo_scene import demo_scene
from addon.core.render.warm_up import warm_up

def signatures():
    return {name: len(obj.signatures) for name, obj in vars(kernels).items()
            if isinstance(obj, numba.core.registry.CPUDispatcher)}

warm_up()
before = signatures()
scene = demo_scene(16, 9)
for strategy in ("mis", "light", "bsdf"):
    render(scene, RenderSettings(samples=1, max_bounces=3, threads=2, strategy=strategy))
json.dump({"before": before, "after": signatures()}, sys.stdout)
"""


def test_the_warm_up_compiles_every_loop_a_render_of_the_demo_scene_runs():
    """After the warm-up, rendering the demo scene with default settings (neural materials with their
    albedo calibration and sampling proxy, an image texture, the sky, an area light; every strategy)
    compiles nothing more: the types the warm-up passes are the ones a real render passes."""
    run = subprocess.run(
        [sys.executable, "-c", _SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=600, check=True
    )
    got = json.loads(run.stdout.strip().splitlines()[-1])
    before, after = got["before"], got["after"]
    loops = ("surface_hits", "sample_lights", "trilinear", "proxy_pdf", "proxy_directions", "scale_by_table")
    for name in (*loops, "decoded_brdf", "neural_shading", "principled_shade"):
        assert before[name] >= 1, f"the warm-up did not compile {name}"
    assert before["trilinear"] >= 2, "the warm-up did not compile the taps of a half-float latent texture"
    assert before["halves_to_float32"] >= 1, "the warm-up did not compile the conversion from half floats"
    assert before["first_row_beyond"] >= 2, "the warm-up did not compile the range checks of halves and float32"
    if kernels.NATIVE_HALF:  # elsewhere numpy converts to half floats
        assert before["float32_to_halves"] >= 2, (
            "the warm-up did not compile the conversions to a chain and its columns"
        )
    assert after == before


def test_hits_by_material_is_a_stable_sort_of_the_hits_with_each_materials_start():
    @settings(max_examples=60, deadline=None)
    @given(st.lists(st.integers(-1, 7), max_size=200), st.integers(1, 4))
    def check(prims, n_materials):
        prim = np.array(prims, dtype=np.int64)
        material_of_triangle = np.arange(8, dtype=np.int64) % n_materials
        order, starts = kernels.hits_by_material(np.empty(len(prim), np.int64), prim, material_of_triangle, n_materials)
        hit = np.flatnonzero(prim >= 0)
        material = material_of_triangle[prim[hit]]
        np.testing.assert_array_equal(order, hit[np.argsort(material, kind="stable")])
        counts = np.bincount(material, minlength=n_materials)
        np.testing.assert_array_equal(starts, np.concatenate([[0], np.cumsum(counts)]))

    check()


def test_closest_hits_converts_an_embree_query_as_numpy_would_with_misses_at_infinity():
    from addon.core.render import shapes
    from addon.core.render.integrator import Tracer

    mesh = shapes.quad((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 2.0, 0.0), material=0)
    rng = np.random.default_rng(5)
    n = 400
    o = np.column_stack([rng.uniform(-3.0, 3.0, (n, 2)), np.full(n, 1.0)])  # over half of them miss the quad
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    r = Tracer(mesh).scene.run(o.astype(np.float32), d.astype(np.float32), output=1)
    assert r["primID"].dtype == np.int32 and r["tfar"].dtype == np.float32  # what the kernel is compiled for
    out = kernels.rows_of(kernels.CLOSEST_HITS_OUT, n)
    t, prim, bu, bv = kernels.closest_hits(out, r["primID"], r["tfar"], r["u"], r["v"])
    assert all(got is given for got, given in zip((t, prim, bu, bv), out, strict=True))  # written in place
    hit = r["primID"] >= 0
    assert 0 < hit.sum() < n
    np.testing.assert_array_equal(prim, r["primID"].astype(np.int64))
    np.testing.assert_array_equal(t, np.where(hit, r["tfar"].astype(np.float64), np.inf))
    np.testing.assert_allclose(t[hit], 1.0, rtol=1e-6)
    np.testing.assert_array_equal(bu, r["u"].astype(np.float64))
    np.testing.assert_array_equal(bv, r["v"].astype(np.float64))
    assert prim.dtype == np.int64 and t.dtype == bu.dtype == bv.dtype == np.float64


def test_take_paths_gathers_the_shadings_fields_as_fancy_indexing_does():
    rng = np.random.default_rng(2)
    n = 50
    fields = (np.arange(n), rng.random((n, 3)), rng.random((n, 3)), rng.random(n), rng.random(n))
    keep = np.flatnonzero(rng.random(n) < 0.6)[::-1].copy()
    for got, field in zip(
        kernels.take_paths(kernels.rows_of(kernels.HIT_PATHS_OUT, len(keep)), keep, *fields), fields, strict=True
    ):
        np.testing.assert_array_equal(got, field[keep])
        assert got.dtype == field.dtype


def _alias_masses(keep, alias):
    """The probability of each index under the alias table: its own cell's share plus what other
    cells give it."""
    n = len(keep)
    return (keep + np.bincount(alias, weights=1.0 - keep, minlength=n)) / n


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.one_of(st.just(0.0), st.floats(1e-12, 1.0), st.floats(1.0, 1e6)), min_size=1, max_size=300).filter(
        lambda w: sum(w) > 0
    )
)
def test_the_alias_table_gives_each_index_its_probability(weights):
    p = np.asarray(weights) / np.sum(weights)
    keep, alias = kernels.alias_table(p)
    assert ((keep >= 0.0) & (keep <= 1.0 + 1e-12)).all()
    assert ((alias >= 0) & (alias < len(p))).all()
    np.testing.assert_allclose(_alias_masses(keep, alias), p, rtol=1e-9, atol=1e-12)
    assert (_alias_masses(keep, alias)[p == 0.0] <= 1e-12).all()  # a black pixel is never drawn


def test_environment_samples_fall_in_each_pixel_as_often_as_its_probability_and_uniformly_inside_it():
    """The sky's importance sampling through the alias table: pixel frequencies match ``pixel_p``
    (chi-square), the one uniform that picks the cell also places the direction across the pixel
    uniformly (the rescaled remainder on either side of the cell's threshold), and the other places it
    down the pixel evenly in z, so that the density is one number per pixel."""
    from scipy import stats

    from addon.core.render.lights import Environment, direction_to_equirect

    rng = np.random.default_rng(3)
    image = rng.random((8, 16, 3)) ** 4
    image[2, 5] = 0.0  # a black pixel
    env = Environment(image=image)
    n = 400_000
    ls = env.sample(np.zeros((n, 3)), rng.random((n, 2)))
    uv = direction_to_equirect(ls.wi)
    x = np.minimum((uv[:, 0] * 16).astype(int), 15)
    y = np.minimum(((1.0 - uv[:, 1]) * 8).astype(int), 7)
    counts = np.bincount(y * 16 + x, minlength=128)
    assert counts[2 * 16 + 5] == 0
    seen = env.pixel_p > 0
    assert stats.chisquare(counts[seen], n * env.pixel_p[seen] / env.pixel_p[seen].sum()).pvalue > 1e-3
    across = uv[:, 0] * 16 - np.floor(uv[:, 0] * 16)  # the position across each pixel
    assert stats.kstest(across, "uniform").pvalue > 1e-3
    # down each pixel evenly in z (so in solid angle), with one density per pixel
    z_top, z_bottom = np.cos(y * np.pi / 8), np.cos((y + 1) * np.pi / 8)
    assert stats.kstest((z_top - ls.wi[:, 2]) / (z_top - z_bottom), "uniform").pvalue > 1e-3
    solid = 2 * np.pi / 16 * (z_top - z_bottom)
    np.testing.assert_allclose(ls.pdf, env.pixel_p[y * 16 + x] / solid, rtol=1e-9)


@pytest.mark.parametrize("shape", [(64, 128), (8, 16), (3, 5), (2, 1), (1, 1), (256, 512)])
def test_the_sky_lookup_finds_the_pixel_of_blenders_mapping_without_its_arc_tangents(shape):
    """``kernels._env_pixel`` (table guesses settled by comparisons with the pixels' edges) gives the pixel that
    ``direction_to_equirect`` and a floor give, for any direction not within rounding of an edge, at any image
    size; and a direction drawn inside a pixel is looked up in that pixel, with the density it was drawn with."""
    from addon.core.render.lights import Environment, direction_to_equirect

    h, w = shape
    rng = np.random.default_rng(h * 1000 + w)
    image = rng.random((h, w, 3)) + np.arange(h * w).reshape(h, w, 1)  # every pixel a distinct radiance
    env = Environment(image=image)
    d = rng.normal(size=(100_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    uv = direction_to_equirect(d)
    fx, fy = uv[:, 0] * w, (1.0 - uv[:, 1]) * h
    x, y = np.minimum(fx.astype(int), w - 1), np.minimum(fy.astype(int), h - 1)
    clear = (np.abs(fx - np.round(fx)) > 1e-9) & (np.abs(fy - np.round(fy)) > 1e-9)
    rad, pdf = env.radiance_and_pdf(d)
    np.testing.assert_array_equal(rad[clear], env.image[y[clear], x[clear]])
    np.testing.assert_array_equal(pdf[clear], env.pixel_pdf[y[clear] * w + x[clear]])
    ls = env.sample(np.zeros((50_000, 3)), rng.random((50_000, 2)))
    np.testing.assert_array_equal(env.pdf(ls.wi), ls.pdf)
    np.testing.assert_array_equal(env.radiance(ls.wi), ls.radiance)


def test_a_sky_of_one_colour_is_sampled_evenly_over_the_sphere():
    """A constant environment is the image of one pixel: uniform directions, density 1 / (4 pi) everywhere."""
    from scipy import stats

    from addon.core.render.lights import Environment

    env = Environment(color=(0.2, 0.3, 0.4), strength=2.0)
    rng = np.random.default_rng(4)
    ls = env.sample(np.zeros((100_000, 3)), rng.random((100_000, 2)))
    np.testing.assert_allclose(np.linalg.norm(ls.wi, axis=1), 1.0, atol=1e-12)
    assert stats.kstest(ls.wi[:, 2], "uniform", args=(-1, 2)).pvalue > 1e-3  # Archimedes: z is uniform
    assert stats.kstest(np.arctan2(ls.wi[:, 1], ls.wi[:, 0]), "uniform", args=(-np.pi, 2 * np.pi)).pvalue > 1e-3
    np.testing.assert_allclose(ls.pdf, 1 / (4 * np.pi), rtol=1e-12)
    np.testing.assert_allclose(ls.radiance, np.tile([0.4, 0.6, 0.8], (len(ls.pdf), 1)), rtol=1e-7)  # float32 pixels
    rad, pdf = env.radiance_and_pdf(rng.normal(size=(1000, 3)) * 3.0)  # any length: the lookup normalises
    np.testing.assert_allclose(pdf, 1 / (4 * np.pi), rtol=1e-12)
    np.testing.assert_allclose(rad, np.tile([0.4, 0.6, 0.8], (1000, 1)), rtol=1e-7)


@pytest.mark.parametrize("shape", [(16, 32), (64, 8), (4, 7), (3, 1)])
def test_an_image_of_one_colour_is_sampled_evenly_over_the_sphere_and_across_each_pixel(shape):
    """Constant pixels: uniform directions, and the azimuth even across each column too, both where the column's
    edge is turned by ``formula.quarter_cos_sin`` (:data:`kernels.SMALL_ANGLE_COLUMNS` columns or more) and where the
    azimuth's cos and sin are the C library's."""
    from scipy import stats

    from addon.core.render.lights import Environment

    h, w = shape
    env = Environment(image=np.full((h, w, 3), 0.5))
    rng = np.random.default_rng(h * 100 + w)
    ls = env.sample(np.zeros((100_000, 3)), rng.random((100_000, 2)))
    np.testing.assert_allclose(np.linalg.norm(ls.wi, axis=1), 1.0, atol=1e-15)
    assert stats.kstest(ls.wi[:, 2], "uniform", args=(-1, 2)).pvalue > 1e-3
    column = (np.pi - np.arctan2(ls.wi[:, 1], ls.wi[:, 0])) / (2 * np.pi) * w  # Blender's u, in columns
    assert stats.kstest(column / w, "uniform").pvalue > 1e-3
    assert stats.kstest(np.mod(column, 1.0), "uniform").pvalue > 1e-3
    np.testing.assert_allclose(ls.pdf, 1 / (4 * np.pi), rtol=1e-12)
    np.testing.assert_array_equal(env.pdf(ls.wi), ls.pdf)


def test_pseudo_angle_grows_with_the_angle_as_atan2_does():
    @kernels.njit
    def pseudo(x, y):
        out = np.empty(len(x))
        for i in range(len(x)):
            out[i] = kernels._pseudo_angle(x[i], y[i])
        return out

    angle = np.sort(np.random.default_rng(2).random(10_000) * 2 * np.pi)
    p = pseudo(np.cos(angle), np.sin(angle))
    assert ((p >= 0) & (p < 4)).all() and (np.diff(p) > 0).all()
    np.testing.assert_allclose(pseudo(np.array([1.0, 0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0, -1.0])), [0, 1, 2, 3])
    assert pseudo(np.array([0.0, np.nan]), np.array([0.0, 1.0]))[0] == 0.0


def test_the_shading_frame_at_a_hit_is_the_bsdf_package_basis_and_wo_the_ray_back_in_it():
    """surface_hits builds the frame with the formula ``frame.coordinate_system`` applies to arrays, and
    wo is ``to_local`` of the reversed ray: one formula, compiled and in numpy, agreeing to rounding."""
    from addon.core.bsdf import frame

    rng = np.random.default_rng(5)
    n = 400
    corners = np.zeros((n, 3, 8))
    corners[:, :, :3] = rng.normal(size=(n, 3, 3))
    corners[:, :, 3:6] = rng.normal(size=(n, 3, 3)) + np.array([0.0, 0.0, 2.0])  # mostly along +z
    corners[:, :, 6:8] = rng.random((n, 3, 2))
    face = np.tile([0.0, 0.0, 1.0], (n, 1))
    d = frame.normalize(rng.normal(size=(n, 3)) - np.array([0.0, 0.0, 2.0]))
    bu, bv = rng.random(n) * 0.5, rng.random(n) * 0.5
    hit, dist = rng.permutation(n), rng.uniform(0.5, 2.0, n)  # the rays' rows in the intersection's results
    rows = kernels.rows_of(kernels.SURFACE_HITS_OUT, n)
    tri_offset = kernels.triangle_offsets(corners)
    out = kernels.surface_hits(
        rows, corners, face, np.ones(n), tri_offset, hit, np.arange(n), bu, bv, d, dist, np.zeros(n), np.ones(n)
    )
    ns, ts, tt, wo = out[2], out[6], out[7], out[8]
    # the offset of the rays leaving: of the hit point's largest coordinate and of its triangle's extent
    expected = kernels.OFFSET_SCALE * np.abs(out[0]).max(axis=1)
    c = corners[hit, :, :3]
    expected += kernels.TRIANGLE_OFFSET_SCALE * np.abs(c - c[:, :1]).max(axis=(1, 2))
    np.testing.assert_allclose(out[11], expected, rtol=1e-12)
    np.testing.assert_array_equal(out[9], dist[hit])
    np.testing.assert_array_equal(out[4], dist[hit])  # the cone's width: 0 + 1 x the distance
    b = np.stack([1 - bu[hit] - bv[hit], bu[hit], bv[hit]], axis=1)
    np.testing.assert_allclose(out[0], np.einsum("ik,ikj->ij", b, corners[hit, :, :3]), rtol=1e-12)
    s, t = frame.coordinate_system(ns)
    np.testing.assert_allclose(ts, s, atol=1e-12)
    np.testing.assert_allclose(tt, t, atol=1e-12)
    np.testing.assert_allclose(wo, frame.to_local(-d, s, t, ns), atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", wo, wo), 1.0, atol=1e-12)
    front = -d[:, 2] >= 0.0  # the rays that came from the side the face normal (+z) points to
    assert 0 < front.sum() < n
    np.testing.assert_array_equal(out[10], front)


def test_the_compiled_lambert_shade_is_the_lambertian_bsdf_and_finish_proposals_is_build():
    """A Lambertian's bounce in one pass (``kernels.lambert_shade``) against the class's eval, pdf and sample
    (per-hit albedo; directions on both sides), and ``finish_proposals`` against ``BSDFSample.build``."""
    from addon.core.bsdf import BSDFSample, Lambertian, frame

    rng = np.random.default_rng(9)
    n = 3000
    wo = frame.normalize(rng.normal(size=(n, 3)))
    albedo = rng.random((n, 3))
    rows = np.flatnonzero(rng.random(n) < 0.7)
    light_wi = frame.normalize(rng.normal(size=(len(rows), 3)))
    u = rng.random((n, 2))
    f, pdf, wi, weight, p, valid = kernels.lambert_shade(albedo, wo, light_wi, rows, u)
    b = Lambertian(albedo)
    np.testing.assert_allclose(f, b.take(rows).eval(light_wi, wo[rows]), rtol=1e-15)
    np.testing.assert_allclose(pdf, b.take(rows).pdf(light_wi, wo[rows]), rtol=1e-15)
    s = b.sample(wo, rng.random(n), u)
    assert valid.all() and np.array_equal(valid, s.valid)
    np.testing.assert_allclose(wi, s.wi, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(weight, s.weight, rtol=1e-15)
    np.testing.assert_allclose(p, s.pdf, rtol=1e-12)
    # proposals, some with zero or negative pdf, below the horizon or with a non-finite f
    pdf_in = np.where(rng.random(n) < 0.1, 0.0, rng.random(n))
    f_in = rng.random((n, 3))
    f_in[rng.random(n) < 0.05, 1] = np.inf
    got = kernels.finish_proposals(wo, pdf_in, f_in)
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = f_in * (np.abs(wo[:, 2]) / pdf_in)[:, None]
    ok = (pdf_in > 0) & (wo[:, 2] > 0)
    want = BSDFSample.build(wo, np.where(ok[:, None], weight, 0.0), pdf_in, ok, ok, ok)
    assert 0.2 < want.valid.mean() < 0.6
    for a, b_ in zip(got, (want.wi, want.weight, want.pdf, want.valid), strict=True):
        np.testing.assert_array_equal(a, b_)


def test_a_textured_lambertians_albedo_is_the_non_negative_texels_times_its_colour():
    """Texels above 1 (an HDR image on a base colour) are kept, as Cycles keeps them; a negative one is 0."""
    rng = np.random.default_rng(4)
    texels = rng.uniform(-0.5, 1.5, (5000, 3)).astype(np.float32)
    texels[:4] = [0.0, 1.0, -0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [2.0, -2.0, 1.0]
    color = np.array([0.8, 0.35, 1.0])
    got = kernels.tinted_albedo(texels, color)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, np.maximum(texels, 0.0) * color)  # equal to the bit
    assert got.min() == 0.0 and got.max() == 2.0 * 0.8


def _unit_rows(rng, n, below=0.1):
    """n random unit directions, a share ``below`` of them under the horizon."""
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) * np.where(rng.random(n) < below, -1.0, 1.0)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_decoded_brdf_is_the_calibration_then_the_top_coat_in_one_pass():
    """``kernels.decoded_brdf`` (a decoder's output made the material's f) against its parts apart: the
    calibration's factor (``RowCalibration.apply``), the transmission factor (``top_lobe.remainder_scale``) and
    the exact lobe (``top_lobe.eval_pdf_top``); per-hit tables and coatings, some index-matched. Rows that read
    their hit's coating and table (``hit_of_row``) give the numbers of the same rows gathered first; a coating
    shared by every row (its transmittance read from one column) gives the same numbers as the same coating given
    per row; no calibration and no coating leave the decoder's output as it is."""
    from addon.core.neural import calibrate, top_lobe

    rng = np.random.default_rng(21)
    n = 4000
    wi, wo = _unit_rows(rng, n), _unit_rows(rng, n)
    k = len(calibrate.COSINES)
    cal = calibrate.RowCalibration(
        np.asarray(calibrate.COSINES), rng.uniform(0.5, 1.5, (3, k, k, 3)), rng.integers(0, 3, n)
    )
    top = np.column_stack([rng.uniform(0.01, 1.0, n), rng.uniform(1.0, 2.0, n)])
    top[rng.random(n) < 0.1, 1] = 1.0  # index-matched: no top interface
    decoded = rng.random((n, 3)).astype(np.float32)
    grids = top_lobe.transmittance_grids()

    want = cal.apply(decoded, wi, wo)
    want = want * top_lobe.remainder_scale(top, wi, wo, unit=True).astype(np.float32)[:, None]
    lobe, p_want = top_lobe.eval_pdf_top(top, wi, wo)
    want = want + lobe.astype(np.float32)[:, None]
    got = decoded.copy()
    p = kernels.decoded_brdf(got, wi, wo, cal.arrays(), top, grids, True, True, kernels.EVERY_ROW)
    np.testing.assert_allclose(got, want, rtol=2e-6)
    np.testing.assert_allclose(p, p_want, rtol=1e-12)
    assert (lobe > 0).mean() > 0.5 and (p > 0).mean() > 0.5

    every = kernels.EVERY_ROW
    # rows that read their coating and table through ``hit_of_row`` (a latent texture's hits, each queried
    # twice): the numbers of the same coatings and tables gathered first
    hit = rng.integers(0, n, 2 * n)
    gathered, through = decoded[hit], decoded[hit]
    p_gathered = kernels.decoded_brdf(
        gathered, wi[hit], wo[hit], cal.take(hit).arrays(), top[hit], grids, True, True, every
    )
    p_through = kernels.decoded_brdf(through, wi[hit], wo[hit], cal.arrays(), top, grids, True, True, hit)
    np.testing.assert_array_equal(through, gathered)
    np.testing.assert_array_equal(p_through, p_gathered)

    one = top[:1].copy()
    shared, per_row = decoded.copy(), decoded.copy()
    p_shared = kernels.decoded_brdf(shared, wi, wo, calibrate.NO_CALIBRATION, one, grids, True, True, every)
    p_rows = kernels.decoded_brdf(
        per_row, wi, wo, calibrate.NO_CALIBRATION, np.repeat(one, n, 0), grids, True, True, every
    )
    np.testing.assert_array_equal(shared, per_row)
    np.testing.assert_array_equal(p_shared, p_rows)

    untouched = decoded.copy()
    p_none = kernels.decoded_brdf(
        untouched, wi, wo, calibrate.NO_CALIBRATION, top_lobe.NO_TOP_ROWS, grids, True, True, every
    )
    np.testing.assert_array_equal(untouched, decoded)
    assert not p_none.any()


@pytest.mark.parametrize("per_hit", [False, True])
def test_neural_shading_is_the_mixture_density_and_finish_proposals(per_hit):
    """``kernels.neural_shading`` (a remainder material's bounce after its decoder batch) against the loops it
    replaced: ``mixture_pdf`` at the next-event directions and the proposals, a missed top-lobe sample's density
    0, and ``finish_proposals``; the lights' density zeros when not asked for."""
    rng = np.random.default_rng(22)
    n = 3000
    wo = _unit_rows(rng, n, below=0.0)
    rows = np.flatnonzero(rng.random(n) < 0.6)
    v = len(rows)
    index = np.concatenate([rows, np.arange(n)])
    wi = np.concatenate([_unit_rows(rng, v), _unit_rows(rng, n)])
    wo_all = wo[index]
    sigma, w = (rng.uniform(0.05, 0.8, n), rng.random(n)) if per_hit else (np.array([0.3]), np.array([0.4]))
    share, missed = rng.uniform(0.0, 0.9, n), rng.random(n) < 0.1
    p_top = np.where(rng.random(v + n) < 0.2, 0.0, rng.random(v + n) * 3.0)
    f = rng.random((v + n, 3)).astype(np.float32)
    f[rng.random(v + n) < 0.02, 1] = np.inf

    rows_sigma = (lambda a: a[index]) if per_hit else (lambda a: np.repeat(a, v + n))
    pdf = kernels.mixture_pdf(wo_all, wi, rows_sigma(sigma), rows_sigma(w), share[index], p_top)
    sample = kernels.finish_proposals(wi[v:], np.where(missed, 0.0, pdf[v:]), f[v:].astype(np.float64))
    for need_pdf in (True, False):
        got = kernels.neural_shading(f, p_top, wi, wo_all, index, v, sigma, w, share, missed, need_pdf)
        np.testing.assert_array_equal(got[0], f[:v].astype(np.float64))
        np.testing.assert_array_equal(got[1], pdf[:v] if need_pdf else np.zeros(v))
        for a, b in zip(got[2:], sample, strict=True):
            np.testing.assert_array_equal(a, b)
    assert 0.5 < sample[3].mean() < 0.95


_LAMBERT = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from addon.core import kernels
w = np.array([[0.0, 0.0, 1.0]])
f = kernels.lambert_shade(np.ones((1, 3)), w, w, np.zeros(1, dtype=np.int64), np.full((1, 2), 0.5))[0]
print(f[0, 0] * np.pi)
"""


def test_a_changed_formula_is_compiled_again_and_never_loaded_stale_from_the_cache(tmp_path):
    """numba's disk cache keys a loop on kernels.py alone; a formula edited in another file must still
    reach the loop (``kernels._drop_stale_cache``): a copy of the add-on, run, its Lambert formula doubled,
    run again."""
    import shutil

    shutil.copytree(ROOT / "addon", tmp_path / "addon", ignore=shutil.ignore_patterns("__pycache__", "models"))

    def run():
        out = subprocess.run(
            [sys.executable, "-c", _LAMBERT, str(tmp_path)], capture_output=True, text=True, timeout=600, check=True
        )
        return float(out.stdout.strip().splitlines()[-1])

    assert run() == 1.0
    assert list((tmp_path / "addon" / "core" / "__pycache__").glob("kernels.lambert_shade*.nbc"))
    src = tmp_path / "addon" / "core" / "bsdf" / "lambert.py"
    text = src.read_text()
    assert "albedo / math.pi, 0.0)" in text
    src.write_text(text.replace("albedo / math.pi, 0.0)", "2.0 * albedo / math.pi, 0.0)"))
    assert run() == 2.0


def test_nearest_rows_picks_the_centre_of_least_squared_distance():
    rng = np.random.default_rng(5)
    centres = rng.normal(size=(6, 96)).astype(np.float32)
    x = (centres[rng.integers(0, 6, 400)] + 0.3 * rng.normal(size=(400, 96))).astype(np.float32)
    d2 = ((x[:, None, :].astype(np.float64) - centres[None].astype(np.float64)) ** 2).sum(axis=2)
    np.testing.assert_array_equal(kernels.nearest_rows(x, centres), np.argmin(d2, axis=1))
    assert len(kernels.nearest_rows(np.zeros((0, 96), np.float32), centres)) == 0


def test_trilinear_writes_every_row_whatever_the_output_held():
    """The lookup's output arrays are passed uninitialised (``textures.mip.trilinear_lookup``): the loop must
    write each row, not add to it, on one level and between two; split into two arrays (a latent texture's
    latents and the rest), the rows are the same values."""
    rng = np.random.default_rng(6)
    c = 100
    levels = [rng.random((8, 8, c)).astype(np.float32), rng.random((4, 4, c)).astype(np.float32)]
    flat = np.concatenate([lv.ravel() for lv in levels])
    offsets = np.array([0, levels[0].size])
    heights = widths = np.array([8, 4])
    uv = rng.random((50, 2))
    lod = np.concatenate([np.zeros(25), rng.random(25)])  # level 0 alone, then blends of both
    clean, dirty = np.zeros((50, c), np.float32), np.full((50, c), np.nan, np.float32)
    for out in (clean, dirty):
        kernels.trilinear(flat, offsets, heights, widths, c, uv, lod, out, np.empty((50, 0), np.float32))
    np.testing.assert_array_equal(dirty, clean)
    assert np.isfinite(clean).all() and clean.min() >= 0.0 and clean.max() <= 1.0
    first, rest = np.full((50, 96), np.nan, np.float32), np.full((50, c - 96), np.nan, np.float32)
    kernels.trilinear(flat, offsets, heights, widths, c, uv, lod, first, rest)
    np.testing.assert_array_equal(np.concatenate([first, rest], axis=1), clean)


def test_a_picked_texel_is_one_of_the_taps_with_the_probability_of_its_weight():
    """Stochastic filtering (``pick_seed``): each row one texel of the lookup's taps (its channels as stored, on one
    of the two levels), the same for the same seed, and over seeds the lookup's blend on average."""
    from addon.core.textures.mip import MipChain, trilinear_lookup

    rng = np.random.default_rng(8)
    levels = MipChain([rng.random((8, 8, 5)).astype(np.float32), rng.random((4, 4, 5)).astype(np.float32)])
    uv = rng.random((6, 2))
    fp = np.full(6, 2.0**0.4 / 8)  # level 0.4: both levels in play
    blend = trilinear_lookup(levels, uv, fp)
    stored = np.concatenate([levels[0].reshape(-1, 5), levels[1].reshape(-1, 5)])
    picks = np.stack([trilinear_lookup(levels, uv, fp, pick_seed=seed) for seed in range(4000)])
    # every pick is a stored texel, whole
    assert (np.abs(picks.reshape(-1, 1, 5) - stored[None]).max(axis=2).min(axis=1) == 0).all()
    np.testing.assert_array_equal(trilinear_lookup(levels, uv, fp, pick_seed=17), picks[17])
    assert not np.array_equal(picks[17], picks[18])
    # the mean of 4,000 picks: the blend within its noise (the texels are uniform in [0, 1): sd 0.29 a pick)
    np.testing.assert_allclose(picks.mean(axis=0), blend, atol=4 * 0.29 / np.sqrt(4000))


def test_trilinear_repeats_the_texture_for_uv_outside_the_unit_square():
    """Repeat addressing: uv shifted by whole numbers (a texture tiled across a floor, and below zero) looks up
    what the same point inside [0, 1)^2 does, on every level and between them."""
    rng = np.random.default_rng(7)
    c = 3
    levels = [rng.random((8, 16, c)).astype(np.float32), rng.random((4, 8, c)).astype(np.float32)]
    flat = np.concatenate([lv.ravel() for lv in levels])
    offsets, heights, widths = np.array([0, levels[0].size]), np.array([8, 4]), np.array([16, 8])
    uv = rng.random((400, 2))
    lod = rng.random(400) * 1.5
    shift = rng.integers(-3, 11, (400, 2)).astype(np.float64)
    inside, outside = (np.empty((400, c), np.float32) for _ in range(2))
    none = np.empty((400, 0), np.float32)
    kernels.trilinear(flat, offsets, heights, widths, c, uv, lod, inside, none)
    kernels.trilinear(flat, offsets, heights, widths, c, uv + shift, lod, outside, none)
    np.testing.assert_allclose(outside, inside, rtol=0, atol=2e-6)  # the shift rounds uv's last bits


def test_half_floats_convert_exactly_in_the_compiled_loops():
    """Every finite half float, as a latent texture read from its file holds it, converts to the float32 numpy
    gives, sign of zero included: by the CPU where it can (``NATIVE_HALF``) and in integer operations elsewhere."""
    import numba

    bits = np.arange(1 << 16, dtype=np.uint16)
    bits = bits[np.isfinite(bits.view(np.float16))]
    want = bits.view(np.float16).astype(np.float32)
    converters = [kernels._half_bits_to_float32] + ([kernels._half_to_float32] if kernels.NATIVE_HALF else [])
    for convert in converters:

        @numba.njit
        def all_of(b, convert=convert):
            out = np.empty(len(b), np.float32)
            for i in range(len(b)):
                out[i] = convert(b[i])
            return out

        got = all_of(bits)
        assert np.array_equal(got.view(np.uint32), want.view(np.uint32)), convert


def test_a_grid_cell_found_from_a_guess_is_the_binary_searchs_whatever_the_guess():
    """The transmittance and calibration lookups walk to a value's grid cell from a guess made from the grid's
    spacing: the cell and weight are the binary search's (what the lookups used before) for any guess, on the
    shipped grids, at their nodes and beyond their ends."""
    import numba

    from addon.core.neural import calibrate, top_lobe

    @numba.njit
    def cells(grid, xs, guesses, spacing):
        out = np.empty((len(xs), 3))
        for n in range(len(xs)):
            for k, guess in enumerate((guesses[n], kernels._spacing_guess(grid, xs[n], spacing))):
                i, t = kernels._segment_near(grid, xs[n], guess)
                if k == 0:
                    out[n, 0], out[n, 1] = i, t
                else:
                    out[n, 2] = i
        return out

    rng = np.random.default_rng(11)
    grids = [
        (np.asarray(top_lobe.TRANSMITTANCE_IOR, float), 0),
        (np.asarray(top_lobe.TRANSMITTANCE_ALPHA, float), 1),
        (np.asarray(top_lobe.TRANSMITTANCE_COS, float), 2),
        (np.asarray(calibrate.COSINES, float)[::-1].copy(), 2),
        (np.sort(rng.random(9)), 2),  # a grid of no particular spacing
    ]
    for grid, spacing in grids:
        span = grid[-1] - grid[0]
        xs = np.concatenate([rng.uniform(grid[0] - span, grid[-1] + span, 2000), grid, [-np.inf, np.inf]])
        guesses = rng.uniform(-5.0, len(grid) + 5.0, len(xs))
        got = cells(grid, xs, guesses, spacing)
        x = np.clip(xs, grid[0], grid[-1])
        i = np.clip(np.searchsorted(grid, x, side="right") - 1, 0, len(grid) - 2)
        t = (x - grid[i]) / (grid[i + 1] - grid[i])
        np.testing.assert_array_equal(got[:, 0], i)
        np.testing.assert_array_equal(got[:, 1], t)
        np.testing.assert_array_equal(got[:, 2], i)


def _halfway_values():
    """float32 values where rounding to a half is hard: every tie between two adjacent finite halves (subnormal
    ones included), the float32 on either side of each, and random bit patterns within the half range."""
    bits = np.arange(1 << 15, dtype=np.uint16)  # the non-negative halves
    halves = bits.view(np.float16).astype(np.float32)
    halves = halves[np.isfinite(halves)]
    ties = (halves[:-1] + halves[1:]) / 2  # exact in float32: halves have 11 significant bits
    near = np.concatenate([ties, np.nextafter(ties, 0), np.nextafter(ties, np.inf), halves])
    rng = np.random.default_rng(5)
    random = rng.integers(0, 2**32, size=400_000, dtype=np.uint64).astype(np.uint32).view(np.float32)
    values = np.concatenate([near, -near, random[np.abs(random) <= 65504.0]])
    return values[: len(values) // 8 * 8].reshape(-1, 8)


@pytest.mark.skipif(not kernels.NATIVE_HALF, reason="the loop needs the CPU's half conversions (x86 F16C, ARM64)")
def test_float32_rounds_to_the_half_numpy_gives_in_the_compiled_loop():
    """``float32_to_halves``: numpy's rounding of each float32 to a half (to nearest, ties to even, into the
    subnormals) at ties and beside them; a value past the limit (inf, nan, beyond it) anywhere refuses the whole
    array, naming its row, with nothing written; and a strided output (columns of a wider array) is written in
    place."""
    values = _halfway_values()
    out = np.zeros(values.shape, np.uint16)
    assert kernels.float32_to_halves(values, 65504.0, out) == -1
    np.testing.assert_array_equal(out, values.astype(np.float16).view(np.uint16))
    for bad in (np.inf, -np.inf, np.nan, 65504.0039):
        spoilt = values.copy()
        spoilt[77, 3] = bad
        held = np.zeros(values.shape, np.uint16)
        assert kernels.float32_to_halves(spoilt, 65504.0, held) == 77
        assert not held.any()
    edge = np.array([[65504.0039, 65519.996, -65519.996]], np.float32)
    wide = np.zeros((1, 5), np.uint16)
    assert kernels.float32_to_halves(edge, float(np.float32(65519.996)), wide[:, 1:4]) == -1
    np.testing.assert_array_equal(wide[0, 1:4].view(np.float16), [65504.0, 65504.0, -65504.0])
    assert wide[0, 0] == wide[0, 4] == 0


def test_halves_convert_to_the_float32_numpy_gives_in_the_compiled_loop():
    """``halves_to_float32``: every finite half, as numpy converts it (the texture taps' conversion, by the CPU
    where it can)."""
    bits = np.arange(1 << 16, dtype=np.uint16)
    bits = bits[np.isfinite(bits.view(np.float16))]
    out = np.empty(len(bits), np.float32)
    kernels.halves_to_float32(bits, out)
    np.testing.assert_array_equal(out.view(np.uint32), bits.view(np.float16).astype(np.float32).view(np.uint32))


def test_take_half_channels_reorders_and_counts_what_is_not_finite():
    """The read's channel reorder: numpy's take of the same bit patterns, and the count and first place (in the
    output's order) of the halves that are inf or nan, whatever their sign and payload; finite ones (the largest
    half, subnormals, -0) are not counted."""
    rng = np.random.default_rng(11)
    src = rng.integers(0, 2**16, size=(300, 7), dtype=np.uint16)
    src[(src & 0x7C00) == 0x7C00] &= 0x3FFF  # every value finite first
    src[0, :4] = np.array([65504.0, 6e-8, -0.0, -65504.0], np.float16).view(np.uint16)
    order = np.array([6, 2, 0, 5, 1], dtype=np.int64)
    out = np.zeros((300, 5), np.uint16)
    assert kernels.take_half_channels(src, order, out) == (0, -1, -1)
    np.testing.assert_array_equal(out, np.take(src, order, axis=1))
    for (row, col), value in {(40, 0): np.inf, (17, 5): -np.inf, (251, 2): np.nan}.items():
        src[row, col] = np.float16(value).view(np.uint16)
    src[3, 4] = 0x7E01  # a nan with a payload, in a channel the order leaves out
    assert kernels.take_half_channels(src, order, out) == (3, 17, 3)  # (17, 5) is out[:, 3], the first row
    assert np.isnan(out[251, 1:2].view(np.float16)).all() and np.isinf(out[40, 2:3].view(np.float16)).all()


@njit(cache=False)
def _roots(x):
    out = np.empty_like(x)
    for i in range(len(x)):
        out[i] = kernels._sqrt(x[i])
    return out


@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=1, max_size=64))
@settings(max_examples=60, deadline=None)
def test_the_loops_square_root_is_maths(values):
    """The loops' square root (the CPU's instruction, never a call into the C library) gives math.sqrt's value,
    bit for bit, and nan below zero as numpy does."""
    x = np.array(values)
    with np.errstate(invalid="ignore"):
        expected = np.sqrt(x)
    got = _roots(x)
    assert np.array_equal(got.view(np.int64)[~np.isnan(got)], expected.view(np.int64)[~np.isnan(expected)])
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    assert all(math.sqrt(v) == g for v, g in zip(values, got, strict=True) if v >= 0.0)


def test_an_environment_image_is_kept_in_float32_with_what_cannot_shine_as_zero():
    """``Environment`` keeps its image as Blender's pixels are, float32 (an 8K sky was 805 MB in float64, and
    its tables took 7.8 s, 5 of them numpy's copies): strength applied, a NaN, an infinity, a negative value or one
    the strength takes past float32's range as 0, in one compiled pass that also gives each pixel's luminance."""
    from addon.core.render.lights import Environment

    src = np.array([[[1.0, np.nan, -2.0, 9.0], [np.inf, 0.5, 3e38, 1.0]]], dtype=np.float32)
    env = Environment(image=src, strength=2.0)
    assert env.image.dtype == np.float32
    np.testing.assert_array_equal(env.image, [[[2.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    image, lum = np.empty((1, 2, 3), np.float32), np.empty((1, 2))
    kernels.clean_environment(src, 2.0, image, lum)
    np.testing.assert_allclose(lum, [[2.0 * 0.2126, 0.7152]])
    # its sampling is the image's: a pixel twice as bright is chosen twice as often (same solid angle)
    two = Environment(image=np.array([[[1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]], dtype=np.float32))
    np.testing.assert_allclose(two.pixel_p, [1 / 3, 2 / 3])


def test_an_environment_from_blenders_rgba_pixels_takes_the_warmed_up_loop():
    """The export hands the RGB of Blender's RGBA pixels, a strided view: ``clean_environment`` compiled a loop of its
    own for it on the first F12 with a sky image. The image is made contiguous first: one loop, the warm-up's."""
    from addon.core.render.lights import Environment

    rgba = np.random.default_rng(1).random((4, 8, 4)).astype(np.float32)
    Environment(image=np.ascontiguousarray(rgba[..., :3]))
    before = len(kernels.clean_environment.signatures)
    strided = Environment(image=rgba[..., :3])
    assert len(kernels.clean_environment.signatures) == before
    np.testing.assert_array_equal(strided.image, rgba[..., :3])

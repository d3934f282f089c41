"""Renderer materials: reference mode, neural materials, resolution of stacks, textures."""

import dataclasses

import numpy as np
import pytest

from addon.core.render import (
    AreaLight,
    Camera,
    Environment,
    ImageTexture,
    LambertMaterial,
    LayeredSpec,
    Mesh,
    ReferenceLayered,
    RenderSettings,
    Scene,
    SurfaceHits,
    neural_material,
    render,
    shapes,
)
from addon.core.render import materials as M
from addon.core.stack import PRESETS, Coating, Conductor, Diffuse, Stack
from tests.core.test_render import block_stats, mixed_scene

COPPER = Stack(Conductor(roughness=0.3, eta=(0.2, 0.9, 1.1), k=(3.9, 2.4, 2.2)))


def compare(a, b):
    """rms z of block differences, the z of the image means' difference, and their relative difference."""
    (ma, sa), (mb, sb) = a, b
    z = (ma - mb) / np.sqrt(sa**2 + sb**2 + 1e-12)
    z_mean = (ma.mean() - mb.mean()) / (np.sqrt((sa**2).sum() + (sb**2).sum()) / sa.size)
    return np.sqrt((z**2).mean()), abs(z_mean), abs(ma.mean() / mb.mean() - 1)


def test_stacks_resolve_to_exact_neural_or_reference_materials():
    assert isinstance(M.resolve(Stack(Diffuse((0.5, 0.5, 0.5))), "reference"), LambertMaterial)
    assert isinstance(M.resolve(COPPER, "neural"), M.BSDFMaterial)
    layered = PRESETS["coated_gold"]
    assert isinstance(M.resolve(layered, "reference"), ReferenceLayered)
    assert isinstance(M.resolve(LayeredSpec(layered), "reference"), ReferenceLayered)
    # Neural mode uses the neural runtime where it can serve the stack, else the reference.
    assert M.resolve(layered, "neural").kind in ("neural", "reference")
    with pytest.raises(ValueError, match="render mode"):
        M.resolve(layered, "fast")
    with pytest.raises(ValueError, match="Stack"):
        M.resolve("gold", "neural")


def test_a_stack_is_encoded_once_per_model_set_and_kept_read_only(monkeypatch):
    """``neural_material.make`` keeps each stack's latent, proxy parameters and top coating with the model set
    (``ModelSet.encodings``): a second material of the same stack encodes nothing, gets the same numbers, and
    cannot change them for the next one; another stack, or a given latent, is encoded as before."""
    from addon import core
    from addon.core.neural import load_models
    from addon.core.render import neural_material

    models = load_models("tiny")
    models.encodings.clear()
    calls = []
    real = core.neural.encode_stack

    def counting(stack, m=None):
        calls.append(stack)
        return real(stack, m)

    monkeypatch.setattr(core.neural, "encode_stack", counting)
    stack, other = PRESETS["coated_gold"], PRESETS["red_car_paint"]
    first = neural_material.make(stack, size="tiny")
    second = neural_material.make(stack, size="tiny")
    assert calls == [stack]
    np.testing.assert_array_equal(first.z, second.z)
    assert (first.sigma, first.w) == (second.sigma, second.w)
    np.testing.assert_array_equal(first.top, second.top)
    z, proxy, top = models.encodings[stack]
    np.testing.assert_array_equal(z, real(stack, models))
    with pytest.raises(ValueError, match="read-only"):
        z[0, 0] = 1.0
    neural_material.make(other, size="tiny")
    assert calls == [stack, other]
    given = neural_material.make(stack, latent=(np.zeros((3, 32)), "tiny"))
    assert not given.z.any() and calls == [stack, other]


def test_reference_mode_without_pdf_matches_the_exact_analytic_material():
    # The same rough conductor as an exact BSDF and through the position-free estimator, which
    # has no pdf: next-event estimation alone must carry its rough part.
    scene = mixed_scene(24, 16)
    scene.materials[1] = M.analytic_for_stack(COPPER)
    exact = block_stats(render(scene, RenderSettings(samples=48, max_bounces=2, seed=1))[0])
    scene.materials[1] = ReferenceLayered(COPPER, walks=2)
    film, stats = render(scene, RenderSettings(samples=48, max_bounces=2, seed=2))
    assert stats.seconds["reference"] > 0 and stats.nonfinite == 0
    rms, z_mean, _ = compare(block_stats(film), exact)
    assert rms < 1.8 and z_mean < 4, (rms, z_mean)


@pytest.mark.mitsuba
def test_reference_mode_matches_mitsuba_plastic():
    """A smooth clear coat over a Lambertian base (delta events included) against Mitsuba's exact
    ``plastic`` (nonlinear), lit by an area light and a constant sky."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    width, height = 32, 24
    eye, target = (0.0, -4.0, 1.5), (0.0, 0.0, 0.5)
    mesh = Mesh.concatenate(
        [
            shapes.uv_sphere((0, 0, 0.8), 0.8, material=1, segments=32, rings=16),
            shapes.quad((0, 0, 0), (3, 0, 0), (0, 3, 0), material=0),
        ]
    )
    light_m = np.array([[1, 0, 0, 1.0], [0, 1, 0, -1.0], [0, 0, 1, 2.5], [0, 0, 0, 1]])
    area = AreaLight(light_m, power=100.0, size=1.0)
    sky, base = (0.4, 0.45, 0.5), (0.2, 0.5, 0.8)
    stack = Stack(Diffuse(base), (Coating(roughness=0.0, ior=1.5),))
    scene = Scene(
        Camera.look_at(eye, target, fov_deg=35, width=width, height=height),
        mesh,
        [LambertMaterial((0.5, 0.5, 0.5)), LayeredSpec(stack)],
        [area],
        Environment(sky),
    )
    film, _ = render(scene, RenderSettings(samples=48, max_bounces=2, mode="reference", reference_walks=2))

    def rgb(v):
        return {"type": "rgb", "value": [float(x) for x in v]}

    def mi_mesh(index, bsdf):
        sel = mesh.material_index == index
        p, n = mesh.positions[sel].reshape(-1, 3), mesh.normals[sel].reshape(-1, 3)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(bsdf)
        m = mi.Mesh(f"m{index}", len(p), len(p) // 3, props, has_vertex_normals=True)
        params = mi.traverse(m)
        params["vertex_positions"] = p.ravel().tolist()
        params["vertex_normals"] = n.ravel().tolist()
        params["faces"] = np.arange(len(p)).tolist()
        params.update()
        return m

    T = mi.ScalarTransform4f
    ref = np.array(
        mi.render(
            mi.load_dict(
                {
                    "type": "scene",
                    "integrator": {"type": "path", "max_depth": 4},  # vertices: max_bounces + 2
                    "sensor": {
                        "type": "perspective",
                        "fov": 35,
                        "fov_axis": "larger",
                        "to_world": T().look_at(origin=list(eye), target=list(target), up=[0, 0, 1]),
                        "film": {
                            "type": "hdrfilm",
                            "width": width,
                            "height": height,
                            "rfilter": {"type": "box"},
                            "pixel_format": "rgb",
                        },
                        "sampler": {"type": "independent", "sample_count": 512},
                    },
                    "sky": {"type": "constant", "radiance": rgb(sky)},
                    "light": {
                        "type": "rectangle",
                        "to_world": T().translate([1.0, -1.0, 2.5])
                        @ T().rotate([1, 0, 0], 180)
                        @ T().scale([0.5, 0.5, 1]),
                        "emitter": {"type": "area", "radiance": rgb(area.radiance)},
                    },
                    "floor": mi_mesh(0, {"type": "diffuse", "reflectance": rgb((0.5, 0.5, 0.5))}),
                    "ball": mi_mesh(
                        1, {"type": "plastic", "diffuse_reflectance": rgb(base), "int_ior": 1.5, "nonlinear": True}
                    ),
                }
            )
        ),
        dtype=np.float64,
    )
    ours, se = block_stats(film, 8)
    theirs = ref.reshape(3, 8, 4, 8, 3).mean(axis=(1, 3))
    assert np.all(np.abs(ours - theirs) < 4 * se + 0.02 * theirs), np.abs(ours - theirs) / (4 * se + 0.02 * theirs)
    # The area light's mirror image is carried by rare specular paths: a heavy-tailed estimate.
    assert abs(ours.mean() / theirs.mean() - 1) < 0.03


def test_neural_material_agrees_with_the_exact_brdf_within_decoder_error():
    material = neural_material.make(COPPER)
    assert material is not None, "the shipped models must serve this stack"
    scene = mixed_scene(24, 16)
    scene.materials[1] = M.analytic_for_stack(COPPER)
    exact = block_stats(render(scene, RenderSettings(samples=32, max_bounces=2, seed=1))[0])
    scene.materials[1] = material
    film, stats = render(scene, RenderSettings(samples=32, max_bounces=2, seed=2))
    assert stats.seconds["network"] > 0 and stats.nonfinite == 0
    rms, _, rel = compare(block_stats(film), exact)
    print(f"neural vs exact: rms z {rms:.2f}, image mean differs by {100 * rel:.2f}%")
    # The tiny decoder's lobe error is several percent: blocks may differ beyond the noise, but
    # the image mean stays close.
    assert rms < 4 and rel < 0.03, (rms, rel)


def test_neural_sampling_weights_match_eval_over_pdf():
    material = neural_material.make(COPPER)
    assert material is not None, "the shipped models must serve this stack"
    n = 4000
    rng = np.random.default_rng(0)
    bound = material.bind(SurfaceHits(np.zeros((n, 2)), np.zeros(n)))
    wo = np.tile([[0.3, 0.1, np.sqrt(1 - 0.1)]], (n, 1))
    s = bound.sample(wo, rng.random(n), rng.random((n, 2)))
    ok = s.valid
    assert ok.mean() > 0.9
    assert np.allclose(s.pdf[ok], bound.pdf(s.wi[ok], wo[ok]), rtol=1e-6)
    f = bound.eval(s.wi[ok], wo[ok])
    assert np.allclose(s.weight[ok], f * (s.wi[ok, 2] / s.pdf[ok])[:, None], rtol=1e-5)


def test_image_texture_footprint_selects_coarser_mip_levels():
    checker = np.indices((64, 64)).sum(axis=0) % 2
    tex = ImageTexture(np.repeat(checker[:, :, None], 3, axis=2).astype(np.float32))
    uv = (np.random.default_rng(0).integers(0, 64, (500, 2)) + 0.5) / 64  # texel centres
    sharp = tex.lookup(uv, np.full(500, 1 / 64 / 4))
    blurred = tex.lookup(uv, np.full(500, 1.0))
    assert sharp.std() > 0.3  # texel values survive at the finest level
    assert np.allclose(blurred, 0.5, atol=1e-3)  # the footprint covers the whole texture
    m = LambertMaterial((1.0, 0.5, 0.25), texture=tex)
    bound = m.bind(SurfaceHits(uv, np.full(500, 1.0)))
    wi = np.tile([[0.0, 0.0, 1.0]], (500, 1))
    assert np.allclose(bound.eval(wi, wi), 0.5 * np.array([1.0, 0.5, 0.25]) / np.pi, atol=1e-3)


def test_demo_scene_renders_in_both_modes_without_nan():
    from addon.core.render.demo_scene import DEMO_PRESETS, demo_scene

    scene = demo_scene(24, 14)
    assert scene.material_names == ["tiles", *DEMO_PRESETS]
    for mode in ("reference", "neural"):
        film, stats = render(scene, RenderSettings(samples=1, max_bounces=2, mode=mode, reference_walks=1))
        assert stats.nonfinite == 0 and np.isfinite(film.mean()).all() and film.mean().mean() > 0
        assert stats.material_kinds[0] == "analytic"
        assert set(stats.material_kinds[1:]) <= {"neural", "reference"}


@pytest.mark.parametrize("stack", [COPPER, PRESETS["coated_gold"]], ids=["copper", "coated_gold"])
def test_latent_texture_material_matches_its_constant_latent(stack):
    """A texture of one latent (with its proxy and top-coat channels) shades as that latent does:
    evaluation and the sampler's pdf (for a remainder decoder: the exact top lobe's mixture too)."""
    from addon.core.neural import top_coat
    from addon.core.textures import LatentTexture

    material = neural_material.make(stack)
    assert material is not None, "the shipped models must serve this stack"
    sigma, w = material.sigma, material.w
    texels = np.concatenate(
        [
            np.tile(material.z.reshape(1, 1, 96), (8, 8, 1)),
            np.tile([[[sigma, w]]], (8, 8, 1)),
            np.tile(top_coat(stack).reshape(1, 1, 2), (8, 8, 1)),
        ],
        axis=2,
    ).astype(np.float32)
    textured = neural_material.NeuralMaterial(material.models, None, (sigma, w), LatentTexture.from_texels(texels))
    n = 300
    rng = np.random.default_rng(3)
    hits = SurfaceHits(rng.random((n, 2)), rng.random(n) * 0.5)
    wo = np.tile([[0.0, 0.6, 0.8]], (n, 1))
    a, b = material.bind(hits), textured.bind(hits)
    sa = a.sample(wo, rng.random(n), rng.random((n, 2)))
    ok = sa.valid
    assert np.allclose(a.eval(sa.wi[ok], wo[ok]), b.eval(sa.wi[ok], wo[ok], np.nonzero(ok)[0]), rtol=1e-2, atol=1e-4)
    assert np.allclose(a.pdf(sa.wi[ok], wo[ok]), b.pdf(sa.wi[ok], wo[ok], np.nonzero(ok)[0]), rtol=1e-3)


def test_neural_and_reference_renders_of_a_layered_scene_agree():
    """Encoder + layering network + decoder against the position-free estimator on a coated
    sphere. The tiny layering network's held-out albedo error is 2-4% (its model card), so the
    image means may differ by a few percent, not more."""
    stack = PRESETS["lacquered_plastic"]
    material = neural_material.make(stack)
    assert material is not None, "the shipped models must serve this stack"
    scene = mixed_scene(24, 16)
    scene.materials[1] = LayeredSpec(stack)
    ref = block_stats(
        render(scene, RenderSettings(samples=32, max_bounces=2, mode="reference", reference_walks=2, seed=1))[0]
    )
    film, stats = render(scene, RenderSettings(samples=32, max_bounces=2, mode="neural", seed=2))
    assert "neural" in stats.material_kinds
    _, _, rel = compare(block_stats(film), ref)
    assert rel < 0.05, rel
    assert stats.seconds["network"] > 0


def _baked(stack, size, **metadata):
    """A constant latent texture of ``stack`` baked by ``bake_stack`` with the shipped models of ``size``."""
    from addon.core.textures.bake import bake_stack, neural_encoder
    from addon.core.textures.spatial import SpatialStack

    top = len(stack.coatings) - 1
    maps = {f"coatings[{top}].roughness": np.full((2, 2), stack.coatings[top].roughness)}
    tex, _ = bake_stack(SpatialStack(stack, maps), neural_encoder(size), metadata=metadata or None)
    return tex


def test_a_baked_texture_is_decoded_with_the_size_it_was_baked_for():
    """bake_stack records the decoder size and digest; make decodes with that size, not the default."""
    from addon.core.neural import encode_stack, load_models, top_coat

    stack = PRESETS["coated_gold"]
    tex = _baked(stack, "small")
    assert tex.metadata["model"] == "small" and tex.metadata["model_digest"] == load_models("small").digest
    material = neural_material.make(stack, tex)
    assert material.models.size == "small" and material.size == "small"
    hits = SurfaceHits(np.full((4, 2), 0.5), np.zeros(4))
    wi = np.tile([[0.0, 0.0, 1.0]], (4, 1))
    got = material.bind(hits).eval(wi, wi, np.arange(4))
    small = load_models("small")
    want = small.eval_brdf(encode_stack(stack, small), wi, wi, top_coat(stack))
    # the texture holds the latent and the top coating at half precision
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-4)


def test_make_raises_on_textures_it_cannot_place_and_on_unknown_sizes():
    stack = PRESETS["coated_gold"]
    tex = _baked(stack, "tiny")
    with pytest.raises(ValueError, match="baked for decoder size 'tiny', not 'small'"):
        neural_material.make(stack, tex, size="small")
    tex.metadata["model"] = "huge"
    with pytest.raises(ValueError, match="'huge'"):
        neural_material.make(stack, tex)
    del tex.metadata["model"]
    with pytest.raises(ValueError, match="records no decoder size"):
        neural_material.make(stack, tex)
    with pytest.raises(ValueError, match="unknown decoder size 'huge'"):
        neural_material.make(stack, size="huge")
    with pytest.raises(ValueError, match="needs a Stack"):
        neural_material.make("coated_gold")


def test_make_falls_back_with_a_reason_for_stale_textures_and_damaged_models(tmp_path, monkeypatch):
    import shutil

    from addon.core.neural import models as model_files

    stack = PRESETS["coated_gold"]
    tex = _baked(stack, "tiny")
    tex.metadata["model_digest"] = "0" * 64
    with pytest.warns(neural_material.NeuralFallbackWarning, match="baked with another decoder_tiny.onnx"):
        assert neural_material.make(stack, tex) is None
    for f in model_files.MODEL_DIR.glob("*_tiny*"):
        shutil.copy(f, tmp_path / f.name)
    (tmp_path / "layering_tiny.onnx").write_text("version https://git-lfs.github.com/spec/v1\n")
    monkeypatch.setattr(model_files, "MODEL_DIR", tmp_path)
    monkeypatch.setattr(model_files, "_CACHE", {})
    with pytest.warns(neural_material.NeuralFallbackWarning, match="layering_tiny.onnx is a Git LFS pointer"):
        assert neural_material.make(stack) is None
    # the renderer then shades the stack with the reference
    with pytest.warns(neural_material.NeuralFallbackWarning):
        assert isinstance(M.resolve(LayeredSpec(stack), "neural"), ReferenceLayered)


def test_a_given_latent_is_decoded_as_it_is_and_keeps_its_size_through_the_decoder_choice():
    """A LayeredSpec carrying a latent (a refined one) renders that latent on its size: make decodes it
    instead of encoding the stack, and quality.assign_decoders leaves it as it is."""
    from addon.core import quality
    from addon.core.neural import encode_stack, load_models

    stack = PRESETS["coated_gold"]
    z = encode_stack(stack, load_models("tiny")) + np.float32(0.05)  # not what the encoder gives
    made = M.resolve(M.LayeredSpec(stack, None, "gold", latent=(z, "tiny")), "neural")
    assert made.size == "tiny" and np.array_equal(made.z, z)
    assert not np.array_equal(M.resolve(M.LayeredSpec(stack, None, "gold"), "neural").z, z)
    with pytest.raises(ValueError, match="3 x 32 finite numbers; got shape \\(5,\\)"):
        neural_material.make(stack, latent=(np.zeros(5), "tiny"))
    with pytest.raises(ValueError, match="non-finite"):
        neural_material.make(stack, latent=(np.full((3, 32), np.nan), "tiny"))
    with pytest.raises(ValueError, match="belongs to decoder size 'tiny', not 'small'"):
        neural_material.make(stack, size="small", latent=(z, "tiny"))
    spec = M.LayeredSpec(stack, None, "gold", latent=(z, "tiny"))
    scene = mixed_scene()
    scene = Scene(scene.camera, scene.mesh, [spec], scene.lights, scene.environment, ["gold"])
    materials, choices, _ = quality.assign_decoders(scene, "small")
    assert materials == [spec] and not choices


def test_spatial_stacks_are_addressed_as_latent_textures_are():
    """``SpatialStack.stacks_at`` (reference mode's per-hit stacks) picks the texel a latent texture of the
    same maps holds at that uv: repeat addressing, v = 0 at the bottom row."""
    from addon.core.textures.spatial import SpatialStack

    rough = np.arange(12, dtype=np.float32).reshape(3, 4) * 0.05 + 0.05
    spatial = SpatialStack(PRESETS["coated_gold"], {"coatings[0].roughness": rough})
    row, col = np.divmod(np.arange(12), 4)
    uv = np.stack([(col + 0.5) / 4, 1.0 - (row + 0.5) / 3], axis=1)
    np.testing.assert_allclose(spatial.stacks_at(uv).coat_roughness[:, 0], rough.reshape(-1))
    np.testing.assert_allclose(spatial.stacks_at(uv + [[2.0, -1.0]]).coat_roughness[:, 0], rough.reshape(-1))
    # the latent texture's bilinear tap at a texel centre is that texel alone
    from addon.core.textures import LatentTexture

    texels = np.zeros((3, 4, 100), np.float32)
    texels[..., 0] = rough
    tap = LatentTexture.from_texels(texels).lookup(uv, np.zeros(12))[0][:, 0, 0]
    np.testing.assert_allclose(tap, rough.reshape(-1), rtol=1e-3)
    assert len(SpatialStack(PRESETS["coated_gold"]).stacks_at(uv)) == 12  # a constant stack
    with pytest.raises(ValueError, match="uv must be finite"):
        spatial.stacks_at(np.array([[np.nan, 0.0]]))


def test_reference_mode_shades_each_hit_with_its_texels_stack():
    """A latent-textured material in reference mode: each hit's f is the estimator's for its own texel's
    stack (a glossy and a rough coat on the two halves), not the constant stack's; a smooth texel anywhere
    turns on the sampler's delta part; a spatial stack of another stack is refused."""
    from addon.core.textures.spatial import SpatialStack

    stack = PRESETS["coated_gold"]
    rough = np.full((2, 2), 0.05, np.float32)
    rough[:, 1] = 0.5
    spatial = SpatialStack(stack, {"coatings[0].roughness": rough})
    material = M.resolve(LayeredSpec(stack, None, "gold", spatial=spatial), "reference", reference_walks=64)
    assert isinstance(material, ReferenceLayered) and material.spatial is spatial and material.q == 1.0
    n = 4000
    uv = np.where((np.arange(n) % 2 == 0)[:, None], [[0.25, 0.5]], [[0.75, 0.5]])  # left, right, left, ...
    wi = np.tile([[0.3, 0.0, 0.954]], (n, 1))
    wo = np.tile([[-0.3, 0.0, 0.954]], (n, 1))  # near the specular direction: the coats differ most here
    f = material.bind(SurfaceHits(uv, np.zeros(n), seed=5)).eval(wi, wo).mean(axis=1)
    for half, r in ((0, 0.05), (1, 0.5)):
        own = ReferenceLayered(Stack(stack.base, (dataclasses.replace(stack.coatings[0], roughness=r),)), 64)
        g = own.bind(SurfaceHits(uv[:2000], np.zeros(2000), seed=9)).eval(wi[:2000], wo[:2000]).mean(axis=1)
        mine = f[half::2]
        se = np.sqrt(mine.var() / len(mine) + g.var() / len(g))
        assert abs(mine.mean() - g.mean()) < 4 * se, (half, mine.mean(), g.mean(), se)
    assert f[0::2].mean() > 3 * f[1::2].mean()  # the glossy half's highlight, the rough half's spread
    smooth = rough.copy()
    smooth[0, 0] = 0.0
    assert ReferenceLayered(stack, 4, SpatialStack(stack, {"coatings[0].roughness": smooth})).q == 0.5
    with pytest.raises(ValueError, match="must vary its own stack"):
        ReferenceLayered(PRESETS["red_car_paint"], 4, spatial)


def test_reference_mode_samples_the_delta_lobe_under_a_rough_index_matched_top_coat():
    """An index-matched top coat is a delta interface (light passes straight through it) whatever its roughness, so
    a smooth coat below it reflects a delta lobe. Reference mode decided by the top's roughness alone and never
    sampled that lobe: a lacquer under a rough ior-1 haze layer rendered (0.020, 0.113, 0.361) of its
    (0.060, 0.154, 0.403)."""
    from addon.core import reference
    from addon.core.render.materials import ReferenceLayered, SurfaceHits

    n = 4000
    theta = np.radians(40.0)
    wo = np.tile([np.sin(theta), 0.0, np.cos(theta)], (n, 1))
    stack = Stack(Diffuse((0.05, 0.25, 0.6)), (Coating(0.0, 1.5), Coating(0.3, 1.0)))
    truth, _ = reference.albedo(stack, wo[:1], samples=8000, seed=1)
    material = M.resolve(stack, "reference")
    assert isinstance(material, ReferenceLayered) and material.q == 0.5
    bound = material.bind(SurfaceHits(uv=np.zeros((n, 2)), footprint=np.zeros(n), seed=3))
    rng = np.random.default_rng(0)
    shaded = bound.shade(wo, np.zeros((0, 3)), np.zeros(0, dtype=np.int64), rng.random(n), rng.random((n, 2)), False)
    np.testing.assert_allclose(shaded.sample.weight.mean(axis=0), truth[0], atol=0.02)  # it was 0.04 short


@pytest.mark.parametrize("extension", ["EXTEND", "CLIP", "MIRROR"])
def test_an_image_textures_extension_holds_when_minified(extension):
    """Extend, Clip and Mirror never show the far edge: looked up on a coarser mip level, the taps wrapped round to
    it (a white-left, black-right image extended to its left read 0.53 for 1 at a 16-texel footprint)."""
    from addon.core.render.materials import ImageTexture

    img = np.zeros((64, 64, 3), np.float32)
    img[:, :32] = 1.0  # left half white
    tex = ImageTexture(img, extension=extension)
    uv = np.array([[-0.3, 0.5], [0.02, 0.5], [0.98, 0.5], [1.3, 0.5]])
    got = tex.lookup(uv, np.full(4, 16.0 / 64.0))[:, 0]
    want = {"EXTEND": (1.0, 1.0, 0.0, 0.0), "CLIP": (0.0, 1.0, 0.0, 0.0), "MIRROR": (1.0, 1.0, 0.0, 0.0)}[extension]
    np.testing.assert_allclose(got, want, atol=1e-6)

"""The decoder's latents through its first layer outside the graph (``ModelSet.project_latents``), and latent
textures held that way (``LatentTexture.projected``): the same f as the latents themselves."""

from types import SimpleNamespace

import numpy as np
import pytest

from addon.core.neural import MODEL_DIR, SIZES, load_models
from addon.core.neural.models import ModelFileError, ModelSet
from addon.core.render import neural_material
from addon.core.stack import preset
from addon.core.textures import LatentTexture
from addon.core.textures import calibration as tc
from addon.core.textures.bake import bake_stack, neural_encoder
from addon.core.textures.spatial import SpatialStack


def _unit_rows(rng, n):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("size", SIZES)
def test_projection_is_the_first_layer_of_the_shipped_weights(size):
    """The latent graph against the numpy decoder's weights file (exported from the scalar graph on its own), in
    float64 with numpy's product: each channel's 32 latents times the first layer's latent columns, plus its
    bias, the channels side by side."""
    models = load_models(size)
    with np.load(MODEL_DIR / f"decoder_{size}_weights.npz") as npz:
        w, b = npz["w0_latent"].astype(np.float64), npz["b0"].astype(np.float64)
    z = np.random.default_rng(1).normal(size=(257, 3, 32)).astype(np.float32)
    want = (z.astype(np.float64) @ w.T + b).reshape(257, -1)
    got = models.project_latents(z)
    assert got.dtype == np.float32 and got.shape == (257, 3 * models.width)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(models.project_latents(z[0]), got[:1])  # one latent (3, 32): one row


def test_eval_brdf_takes_projected_latents_as_it_takes_latents():
    models = load_models("tiny")
    rng = np.random.default_rng(2)
    n, m = 3000, 40
    wi, wo = _unit_rows(rng, n), _unit_rows(rng, n)
    z = (rng.normal(size=(m, 3, 32)) * 0.5).astype(np.float32)
    rows = rng.integers(0, m, n)
    zc = models.project_latents(z)
    top = np.array([0.1, 1.5])
    want = models.eval_brdf(z, wi, wo, top, z_rows=rows)
    np.testing.assert_array_equal(models.eval_brdf(None, wi, wo, top, z_rows=rows, zc=zc), want)
    np.testing.assert_array_equal(models.eval_brdf(None, wi, wo, top, zc=zc[rows]), want)
    with pytest.raises(ValueError, match="projected latents"):
        models.eval_brdf(None, wi, wo, zc=zc[:, :64], z_rows=rows)
    with pytest.raises(ValueError, match="give z_rows"):
        models.eval_brdf(None, wi, wo, zc=zc)
    with pytest.raises(ValueError, match="integer rows"):
        models.eval_brdf(None, wi, wo, zc=zc, z_rows=rows + m)
    with pytest.raises(ValueError, match="finite"):
        models.eval_brdf(None, wi, wo, zc=np.full_like(zc, np.nan), z_rows=rows)


@pytest.fixture(scope="module")
def baked():
    rough = np.full((8, 16), 0.02, np.float32)
    rough[:, 8:] = 0.3
    encode = neural_encoder("tiny", threads=2)
    tex, _ = bake_stack(SpatialStack(preset("coated_gold"), {"coatings[0].roughness": rough}), encode, threads=2)
    return tex, encode.models


def _lookups(tex, models, n=5000, seed=3):
    rng = np.random.default_rng(seed)
    uv, fp = rng.random((n, 2)) * 2 - 0.5, 10 ** rng.uniform(-3, 0, n)  # every level, and repeat addressing
    projected = tex.projected((models.size, str(models.model_dir)), models.project_latents, models.width)
    return tex.lookup(uv, fp), projected.lookup(uv, fp)


def test_a_projected_texture_looks_up_the_projection_of_its_latents(baked):
    """The product is affine and the filter's weights sum to 1: on float32 levels the lookups agree to float32
    rounding, on the half floats a texture holds to the one more rounding the products take."""
    tex, models = baked
    exact = LatentTexture([np.asarray(level, np.float32) for level in tex.levels], tex.metadata)
    for texture, rtol in ((exact, 1e-5), (tex, 2.0**-10)):
        (z, prox, top), (zc, prox_p, top_p) = _lookups(texture, models)
        want = models.project_latents(z)
        scale = np.abs(want).max()
        assert np.abs(zc - want).max() <= rtol * scale
        np.testing.assert_array_equal(prox_p, prox)
        np.testing.assert_array_equal(top_p, top)
    key = (models.size, str(models.model_dir))
    assert tex.projected(key, models.project_latents, models.width) is tex.projected(
        key, models.project_latents, models.width
    )  # made once per decoder


def test_a_textured_material_decodes_the_projected_texture(baked):
    tex, models = baked
    material = neural_material.make(preset("coated_gold"), tex, calibrate=True)
    rng = np.random.default_rng(4)
    n = 2000
    hits = SimpleNamespace(uv=rng.random((n, 2)), footprint=10 ** rng.uniform(-3, -1, n))
    bound = material.bind(hits)
    assert bound.z is None and bound.zc.shape == (n, 3 * models.width)
    # each hit's table is that of the centroid nearest its latents, found among the projected centroids
    z, _, top = tex.lookup(hits.uv, hits.footprint)
    which = material.calibration.at(z).which
    assert (bound.calibration.which == which).mean() > 0.99
    wi, wo = _unit_rows(rng, n), _unit_rows(rng, n)
    same = bound.calibration.which == which
    want = models.eval_brdf(z, wi, wo, top, material.calibration.at(z), unit=True)
    got = bound.eval(wi, wo)
    np.testing.assert_allclose(got[same], want[same], rtol=2e-3, atol=1e-6)


def test_texel_centres_choose_their_clusters_table_by_the_projected_centroids(baked):
    tex, models = baked
    calibration = tc.TextureCalibration.from_text(tex.metadata["calibration"])
    h, w = tex.height, tex.width
    v, u = np.mgrid[0:h, 0:w]
    uv = np.stack([(u.ravel() + 0.5) / w, 1.0 - (v.ravel() + 0.5) / h], axis=1)
    z = tex.lookup(uv, np.zeros(len(uv)))[0]
    zc = tex.projected((models.size, str(models.model_dir)), models.project_latents, models.width).lookup(
        uv, np.zeros(len(uv))
    )[0]
    by_latents = calibration.at(z).which
    assert len(set(by_latents)) == 2
    np.testing.assert_array_equal(
        calibration.at(zc, models.project_latents(calibration.centroids.reshape(-1, 3, 32))).which, by_latents
    )


def test_a_card_that_names_the_fused_graph_must_name_its_latent_graph(tmp_path):
    import json
    import shutil

    for f in MODEL_DIR.glob("*_tiny*"):
        shutil.copy(f, tmp_path / f.name)
    card_path = tmp_path / "decoder_tiny.json"
    card = json.loads(card_path.read_text())
    del card["files"]["decoder_tiny_latents.onnx"]
    card_path.write_text(json.dumps(card))
    with pytest.raises(ModelFileError, match="decoder_tiny_latents.onnx"):
        ModelSet("tiny", model_dir=tmp_path)


def test_a_texture_and_its_projection_go_with_the_texture_s_last_reference():
    """No reference cycle: a released texture (up to a gigabyte, with as much again projected) is freed at once,
    not left to the cyclic collector."""
    import gc
    import weakref

    models = load_models("tiny")
    texture = LatentTexture.from_texels(np.zeros((4, 4, 100), np.float32))
    texture.projected((models.size, str(models.model_dir)), models.project_latents, models.width)
    gone = weakref.ref(texture)
    gc.disable()
    try:
        del texture
        assert gone() is None
    finally:
        gc.enable()

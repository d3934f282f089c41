"""The neural runtime (numpy + ONNX Runtime): API, input validation, robustness, model cards."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from addon.core import lobe
from addon.core.neural import (
    MODEL_DIR,
    N_FEATURES,
    SIZES,
    ClampWarning,
    ModelSet,
    calibrate,
    encode_arrays,
    encode_stack,
    load_models,
)
from addon.core.neural.features import layer_features
from addon.core.stack import Coating, Conductor, Dielectric, Diffuse, Stack, StackArrays, coating_interface

SHIPPED = [s for s in SIZES if (MODEL_DIR / f"decoder_{s}.onnx").exists()]
HELDOUT = Path(__file__).resolve().parents[1] / "data" / "heldout_single.npz"


def test_models_are_shipped():
    assert "tiny" in SHIPPED, f"no tiny decoder under {MODEL_DIR}"


@pytest.fixture(scope="module", params=SHIPPED)
def models(request):
    return load_models(request.param, threads=2)


def encode_layer(models, layer):
    """The latent of one layer as a stack of its own (a coating: its interface)."""
    return encode_stack(Stack(coating_interface(layer) if isinstance(layer, Coating) else layer), models)


def _dirs(rng, n):
    w = rng.normal(size=(n, 3))
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def test_encode_shapes_and_types(models):
    for layer in (Diffuse((0.2, 0.5, 0.8)), Conductor(0.2), Dielectric(0.1, 1.5), Coating(0.05, 1.5)):
        z = encode_layer(models, layer)
        assert z.shape == (3, 32) and z.dtype == np.float32 and np.all(np.isfinite(z))
    # the three channels of a coloured diffuse differ; those of a dielectric are equal
    zd = encode_layer(models, Diffuse((0.1, 0.5, 0.9)))
    assert np.abs(zd[0] - zd[2]).max() > 1e-3
    zg = encode_layer(models, Dielectric(0.3, 1.5))
    assert np.abs(zg[0] - zg[2]).max() < 1e-5


def test_eval_finite_nonnegative_everywhere(models):
    rng = np.random.default_rng(0)
    z = encode_layer(models, Conductor(0.01))
    n = 4000
    wi = _dirs(rng, n)
    wo = _dirs(rng, n)
    wi[:500, 2] = 1e-7  # grazing
    wo[500:1000, 2] = 0.0  # exactly on the horizon
    wi[1000:1500] *= 7.0  # not unit length
    wo[1500:1600] = 0.0  # zero length
    f = models.eval_brdf(z, wi, wo)
    assert f.shape == (n, 3) and f.dtype == np.float32
    assert np.all(np.isfinite(f)) and np.all(f >= 0.0)
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0) | np.all(wo == 0, axis=1)
    assert np.all(f[below] == 0.0)
    # scaling a direction does not change the value
    np.testing.assert_allclose(f[1000:1500], models.eval_brdf(z, wi[1000:1500] / 7.0, wo[1000:1500]), rtol=1e-5)
    # extreme latents still give finite values
    fz = models.eval_brdf(np.full((3, 32), 1e4, np.float32), wi, wo)
    assert np.all(np.isfinite(fz)) and np.all(fz >= 0.0)


def test_direction_lengths_float32_cannot_square_give_the_unit_directions_values(models):
    """The RGB graph normalises in float32; lengths whose square under- or overflows there are
    scaled on the way in, so any finite nonzero length gives the value of the unit direction."""
    rng = np.random.default_rng(3)
    wi, wo = _dirs(rng, 400), _dirs(rng, 400)
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]) + 0.05, np.abs(wo[:, 2]) + 0.05
    z = encode_layer(models, Conductor(0.1))
    unit = models.eval_brdf(z, wi, wo)
    assert unit.max() > 0.0
    scale_i = np.repeat([1e-20, 1e25, 3e-15, 1e17], 100)[:, None]
    scale_o = np.repeat([1e22, 1e-30, 1.0, 1e-16], 100)[:, None]
    np.testing.assert_allclose(models.eval_brdf(z, wi * scale_i, wo * scale_o), unit, rtol=2e-5, atol=1e-7)


def test_per_row_latents_match_single(models):
    rng = np.random.default_rng(1)
    wi, wo = _dirs(rng, 300), _dirs(rng, 300)
    wi[:, 2] = np.abs(wi[:, 2])
    wo[:, 2] = np.abs(wo[:, 2])
    za, zb = encode_layer(models, Diffuse(0.5)), encode_layer(models, Dielectric(0.2, 1.7))
    rows = np.stack([za] * 150 + [zb] * 150)
    f = models.eval_brdf(rows, wi, wo)
    np.testing.assert_allclose(f[:150], models.eval_brdf(za, wi[:150], wo[:150]), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(f[150:], models.eval_brdf(zb, wi[150:], wo[150:]), rtol=1e-5, atol=1e-7)


def test_latents_by_row_index_equal_the_gathered_latents(models):
    """``z_rows`` (the renderer's query of a latent texture's hits) decodes ``z[z_rows]`` without gathering it
    first: the same values, chunk by chunk, also with the hits' own coatings and calibration tables, which are
    read through ``z_rows`` too; rows outside z, and coatings or tables not one per row of z, are refused."""
    rng = np.random.default_rng(4)
    n = 9000  # more than one chunk of the runtime
    wi, wo = _dirs(rng, n), _dirs(rng, n)
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    z = np.stack([encode_layer(models, Diffuse(a)) for a in (0.2, 0.5, 0.8)] * 10)  # (30, 3, 32)
    rows = rng.integers(0, len(z), n)
    np.testing.assert_array_equal(models.eval_brdf(z, wi, wo, z_rows=rows), models.eval_brdf(z[rows], wi, wo))
    k = len(calibrate.COSINES)
    tables = calibrate.RowCalibration(
        np.asarray(calibrate.COSINES), rng.uniform(0.5, 1.5, (3, k, k, 3)), rng.integers(0, 3, len(z))
    )
    top = np.column_stack([rng.uniform(0.05, 0.5, len(z)), rng.uniform(1.3, 1.7, len(z))])
    f_through, p_through = models.eval_brdf(z, wi, wo, top, tables, top_pdf=True, z_rows=rows)
    f_gathered, p_gathered = models.eval_brdf(z[rows], wi, wo, top[rows], tables.take(rows), top_pdf=True)
    np.testing.assert_array_equal(f_through, f_gathered)
    np.testing.assert_array_equal(p_through, p_gathered)
    assert (p_through > 0).any() == models.remainder
    with pytest.raises(ValueError, match="calibration has 9000 rows"):
        models.eval_brdf(z, wi, wo, calibration=tables.take(rows), z_rows=rows)
    if models.remainder:  # a whole-BRDF decoder reads no coating
        with pytest.raises(ValueError, match=r"top must have shape \(2,\) or \(30, 2\)"):
            models.eval_brdf(z, wi, wo, top[rows], z_rows=rows)
    with pytest.raises(ValueError, match="z_rows must index"):
        models.eval_brdf(z, wi[:2], wo[:2], z_rows=np.array([0, 30]))
    with pytest.raises(ValueError, match="z_rows must be 2 integer rows"):
        models.eval_brdf(z, wi[:2], wo[:2], z_rows=np.array([0.0, 1.0]))


def test_fused_rgb_graph_equals_scalar_graph(models):
    assert models._rgb is not None, f"decoder_{models.size}_rgb.onnx is not shipped"
    rng = np.random.default_rng(2)
    wi, wo = _dirs(rng, 500), _dirs(rng, 500)
    wi[:, 2] = np.abs(wi[:, 2])
    wo[:, 2] = np.abs(wo[:, 2])
    z = encode_layer(models, Conductor(0.1))
    fused = models.eval_brdf(z, wi, wo)
    scalar = models._decoder.run(
        ["f"],
        {
            "z": np.tile(z, (500, 1)),
            "wi": np.repeat(wi, 3, 0).astype(np.float32),
            "wo": np.repeat(wo, 3, 0).astype(np.float32),
        },
    )[0].reshape(500, 3)
    np.testing.assert_allclose(fused, scalar, rtol=1e-4, atol=1e-6)


def test_bad_inputs_raise_clear_errors(models):
    z = encode_layer(models, Diffuse(0.5))
    w = np.array([[0.0, 0.0, 1.0]] * 4)
    with pytest.raises(ValueError, match="wi must be finite"):
        models.eval_brdf(z, np.array([[np.nan, 0, 1]] * 4), w)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        models.eval_brdf(z, np.zeros((4, 2)), w)
    with pytest.raises(ValueError, match="rows"):
        models.eval_brdf(z, w, w[:3])
    with pytest.raises(ValueError, match="z must have shape"):
        models.eval_brdf(np.zeros((3, 16)), w, w)
    with pytest.raises(ValueError, match="z must be finite"):
        models.eval_brdf(np.full((3, 32), np.nan), w, w)
    with pytest.raises(ValueError, match="encoder features"):
        models.run_encoder(np.zeros((2, 3, N_FEATURES + 1)))
    with pytest.raises(ValueError, match="wi must be real"):
        models.eval_brdf(z, w * (1 + 1j), w)
    with pytest.raises(ValueError, match="z must be real"):
        models.eval_brdf(z * 1j, w, w)
    with pytest.raises(ValueError, match="encode_stack needs a Stack"):
        encode_stack(Diffuse(0.5), models)


def test_encode_stack_layers_coatings_with_the_sizes_layering_network(models):
    coated = Stack(Diffuse(0.5), (Coating(roughness=0.2, thickness=0.5), Coating(roughness=0.05)))
    z = encode_stack(coated, models)
    np.testing.assert_array_equal(z, encode_arrays(StackArrays.from_stacks([coated]), models)[0])
    assert not np.allclose(z, encode_layer(models, coated.base))


@pytest.mark.parametrize("coatings", [0, 2])
def test_empty_batches_give_empty_arrays(models, coatings):
    one = StackArrays.repeat(Stack(Diffuse(0.5), (Coating(),) * coatings), 3)
    z = encode_arrays(one.take(slice(0, 0)), models)
    assert z.shape == (0, 3, 32) and z.dtype == np.float32
    assert models.proxy_params(z).shape == (0, 2)
    f = models.eval_brdf(encode_layer(models, Diffuse(0.5)), np.zeros((0, 3)), np.zeros((0, 3)))
    assert f.shape == (0, 3)


def test_clamps_out_of_range_with_a_warning(models):
    with pytest.warns(ClampWarning, match="roughness"):
        z = encode_layer(models, Conductor(roughness=0.0))
    np.testing.assert_allclose(z, encode_layer(models, Conductor(roughness=0.01)), atol=1e-6)
    with pytest.warns(ClampWarning, match="ior"):
        encode_layer(models, Dielectric(0.2, ior=3.5))
    one = StackArrays.repeat(Stack(Conductor(roughness=0.002), (Coating(),)), 5)
    arrays = StackArrays(
        **{f: (getattr(one, f)[:, :0] if f.startswith("coat_") else getattr(one, f)) for f in StackArrays.FIELDS}
    )
    with pytest.warns(ClampWarning, match="5 rows"):
        za = encode_arrays(arrays, models)
    assert za.shape == (5, 3, 32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        encode_layer(models, Conductor(roughness=0.5))  # in range: silent


def test_missing_model_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="decoder_tiny.onnx"):
        ModelSet("tiny", model_dir=tmp_path)
    with pytest.raises(ValueError, match="unknown decoder size"):
        ModelSet("huge")
    with pytest.raises(ValueError, match="threads"):
        ModelSet("tiny", threads=0)


@pytest.mark.parametrize("size", SHIPPED)
def test_model_cards_match_the_files(size):
    import onnx

    for name in (f"decoder_{size}", f"encoder_{size}"):
        card = json.loads((MODEL_DIR / f"{name}.json").read_text())
        m = onnx.load(str(MODEL_DIR / f"{name}.onnx"))
        count = sum(int(np.prod(t.dims)) for t in m.graph.initializer if len(t.dims) > 0)
        assert card["parameters"] == count, f"{name}: card says {card['parameters']}, file holds {count}"
        assert card["onnx_runtime_vs_torch_max_relative_difference"] <= 1e-4
        for key in ("architecture", "macs_per_rgb_eval", "training"):
            assert key in card, f"{name}.json lacks {key!r}"
        names = [i.name for i in m.graph.input]
        assert names == (["z", "wi", "wo"] if name.startswith("decoder") else ["x"])
        assert m.graph.input[0].type.tensor_type.shape.dim[0].dim_param  # dynamic batch axis


@pytest.mark.parametrize("size", SHIPPED)
def test_encoded_heldout_error_not_worse_than_the_card(size):
    """Encode the held-out single-layer configurations (no optimisation) and compare the lobe
    images with the stored exact references; the card states what to expect."""
    card = json.loads((MODEL_DIR / f"encoder_{size}.json").read_text())
    if "encoder_heldout_single" not in card:
        pytest.skip(f"encoder_{size}.json has no held-out figures")
    expect = card["encoder_heldout_single"]
    d = np.load(HELDOUT)
    stacks = [Stack.from_json(str(s)) for s in d["stacks"]]
    m = load_models(size)
    res = d["lobe"].shape[2]
    errs = []
    for i, s in enumerate(stacks):
        z = encode_layer(m, s.base)
        for a, t in enumerate(d["angles"]):
            img = lobe.lobe_image(lambda wi, wo: m.eval_brdf(z, wi, wo), float(t), res)
            errs.append(lobe.relative_rmse(img, d["lobe"][i, a]))
    assert np.median(errs) <= expect["lobe_error_median"] * 1.05 + 1e-3
    assert np.percentile(errs, 90) <= expect["lobe_error_p90"] * 1.05 + 1e-3


def test_features_of_a_coating_are_its_interface():
    np.testing.assert_array_equal(
        layer_features(Coating(0.2, 1.4, albedo=(0.5, 0.5, 0.5), thickness=2.0)), layer_features(Dielectric(0.2, 1.4))
    )


@pytest.mark.parametrize("n", [0, 1, 2047, 2048, 2049, 9000])
def test_chunked_threaded_decoding_equals_one_call(n):
    """eval_brdf cuts a batch into chunks run on a thread pool; across chunk edges, for one
    latent and per-row latents, it must equal one single-threaded ONNX Runtime call."""
    from addon.core.neural.session import ChunkedSession

    models = load_models("tiny", threads=2)
    assert models._rgb.chunk < 9000  # the larger cases span several chunks
    rng = np.random.default_rng(n)
    wi, wo = _dirs(rng, n), _dirs(rng, n)
    wi[:, 2] = np.abs(wi[:, 2]) + 1e-3
    wo[:, 2] = np.abs(wo[:, 2]) + 1e-3
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    whole = ChunkedSession(models._rgb.path, threads=1, chunk=max(n, 1))
    z = encode_layer(models, Conductor(0.1))
    zr = np.stack([encode_layer(models, Diffuse(a)) for a in (0.1, 0.9)])[rng.integers(0, 2, n)]
    for zz, feeds in ((z, {"zc": models.project_latents(z)}), (zr, {"zc": models.project_latents(zr)})):
        f = models.eval_brdf(zz, wi, wo)
        ref = whole.run_once(["f"], {**feeds, "wi": wi.astype(np.float32), "wo": wo.astype(np.float32)})[0]
        assert f.shape == (n, 3)
        np.testing.assert_allclose(f, ref, rtol=1e-5, atol=1e-7)
    # the generic row-split run agrees with one call too, and checks its inputs
    two = ChunkedSession(models._rgb.path, threads=2, chunk=1000)
    zc = models.project_latents(z)
    got = two.run(["f"], {"wi": wi.astype(np.float32), "wo": wo.astype(np.float32)}, {"zc": zc})[0]
    ref = whole.run_once(["f"], {"zc": zc, "wi": wi.astype(np.float32), "wo": wo.astype(np.float32)})[0]
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="disagree"):
        two.run(["f"], {"wi": wi.astype(np.float32), "wo": np.zeros((n + 1, 3), np.float32)}, {"zc": zc})


def test_chunked_session_rejects_bad_settings(tmp_path):
    from addon.core.neural.session import ChunkedSession

    with pytest.raises(FileNotFoundError, match="missing.onnx"):
        ChunkedSession(tmp_path / "missing.onnx")
    with pytest.raises(ValueError, match="threads"):
        ChunkedSession(MODEL_DIR / "decoder_tiny_rgb.onnx", threads=0)
    with pytest.raises(ValueError, match="chunk"):
        ChunkedSession(MODEL_DIR / "decoder_tiny_rgb.onnx", chunk=0)


def test_batched_encoding_of_shared_and_distinct_layers_equals_each_stack_alone(models):
    """encode_arrays computes the features of each distinct base and interface once: stacks that share a
    base (or a coat) get exactly the latent they get alone, whether their batch repeats layers or not."""
    bases = [Conductor(0.2, (0.2, 0.4, 1.4), (3.9, 2.4, 1.6)), Diffuse((0.6, 0.3, 0.1))]
    stacks = [
        Stack(bases[b], (Coating(roughness=r, ior=1.5, albedo=(0.9, 0.8, 0.7), thickness=t),))
        for b, r, t in [(0, 0.1, 0.5), (0, 0.1, 0.5), (1, 0.3, 0.5), (0, 0.1, 1.0), (1, 0.05, 0.2), (0, 0.3, 1.0)]
    ]
    batch = encode_arrays(StackArrays.from_stacks(stacks), models)
    alone = np.stack([encode_stack(s, models) for s in stacks])
    np.testing.assert_allclose(batch, alone, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(batch[0], batch[1])  # the same stack twice
    bare = encode_arrays(StackArrays.from_stacks([Stack(b) for b in [bases[0]] * 3 + [bases[1]]]), models)
    np.testing.assert_array_equal(bare[0], bare[2])
    np.testing.assert_allclose(bare[3], encode_stack(Stack(bases[1]), models), rtol=1e-6, atol=1e-7)

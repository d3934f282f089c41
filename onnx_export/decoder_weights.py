"""Export the weights of shipped decoders for the numpy decoder of ``addon.core.neural.refine``.

    python -m onnx_export.decoder_weights --sizes tiny small medium paper

writes ``addon/models/decoder_<size>_weights.npz`` beside each ``decoder_<size>.onnx``: the
weight matrices and biases of the MLP (``w0``, ``b0``, ... in layer order, ``w0`` split as
``w0_latent`` (W, 32) and ``w0_directions`` (W, F)), the architecture (width, depth, direction
features, output activation, the bump sharpnesses and the exp clamp), and the sha256 of the ONNX
file they were read from (``onnx_sha256``): the runtime refuses weights whose ONNX file changed, so
after retraining a decoder this command must be run again. Afterwards it checks that the numpy
forward pass equals ONNX Runtime's on random latents and directions (grazing ones included) and
prints the largest relative difference.

The weights are read from the ONNX initializers (no checkpoint, no torch): what is exported is
exactly what the runtime evaluates.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from addon.core.neural.models import file_digest
from onnx_export.nets import BUMP_SHARPNESS, LATENT, MAX_LOG_F

MODEL_DIR = Path(__file__).resolve().parents[1] / "addon" / "models"


def decoder_arrays(onnx_path: Path, card: dict) -> dict[str, np.ndarray]:
    """The npz contents for one decoder file and its model card."""
    arch = card["architecture"]
    if arch.get("features") != "iso_bumps" or arch.get("activation") != "exp":
        raise ValueError(
            f"{onnx_path.name}: the numpy decoder implements features 'iso_bumps' and activation "
            f"'exp', the card says {arch.get('features')!r} / {arch.get('activation')!r}"
        )
    init = {t.name: numpy_helper.to_array(t) for t in onnx.load(str(onnx_path)).graph.initializer}
    depth = int(arch["depth"])
    out: dict[str, np.ndarray] = {}
    for i in range(depth + 1):
        w = init[f"net.{2 * i}.weight"].astype(np.float32)
        b = init[f"net.{2 * i}.bias"].astype(np.float32)
        if i == 0:
            out["w0_latent"], out["w0_directions"] = w[:, :LATENT].copy(), w[:, LATENT:].copy()
        else:
            out[f"w{i}"] = w
        out[f"b{i}"] = b
    expected = init["net.0.weight"].shape[1] - LATENT
    if expected != 6 + len(BUMP_SHARPNESS):
        raise ValueError(
            f"{onnx_path.name}: first layer takes {expected} direction features, expected {6 + len(BUMP_SHARPNESS)}"
        )
    out["width"] = np.array(int(arch["width"]))
    out["depth"] = np.array(depth)
    out["bump_sharpness"] = np.array(BUMP_SHARPNESS, dtype=np.float64)
    out["max_log_f"] = np.array(MAX_LOG_F)
    out["onnx_sha256"] = np.array(file_digest(onnx_path))
    out["onnx_file"] = np.array(onnx_path.name)
    return out


def forward_parity(size: str, model_dir: Path, n: int = 4096, seed: int = 0) -> float:
    """Max relative difference (floor 1e-6) between ``refine.NumpyDecoder`` and the ONNX decoder."""
    import onnxruntime as ort

    from addon.core.neural.refine import NumpyDecoder
    from onnx_export.export import max_relative_difference, random_directions

    rng = np.random.default_rng(seed)
    dec = NumpyDecoder.load(size, model_dir)
    wi = np.concatenate([random_directions(rng, n // 2), random_directions(rng, n - n // 2, grazing=True)])
    wo = random_directions(rng, n)
    z = (rng.standard_normal((3, LATENT)) * 0.5).astype(np.float32)
    s = ort.InferenceSession(str(model_dir / f"decoder_{size}.onnx"), providers=["CPUExecutionProvider"])
    ref = s.run(["f"], {"z": np.tile(z, (n, 1)), "wi": np.repeat(wi, 3, 0), "wo": np.repeat(wo, 3, 0)})[0]
    got = dec.forward(z, wi, wo)
    return max_relative_difference(got, ref.reshape(n, 3))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["tiny", "small", "medium", "paper"])
    ap.add_argument("--models", type=Path, default=MODEL_DIR)
    a = ap.parse_args(argv)
    for size in a.sizes:
        print(json.dumps(export_weights(size, a.models)))


def export_weights(size: str, model_dir: Path = MODEL_DIR) -> dict:
    """Write ``decoder_<size>_weights.npz`` from ``decoder_<size>.onnx`` and check the numpy forward pass."""
    path = model_dir / f"decoder_{size}.onnx"
    card = json.loads(path.with_suffix(".json").read_text())
    out = model_dir / f"decoder_{size}_weights.npz"
    np.savez(out, **decoder_arrays(path, card))
    return {
        "size": size,
        "weights": out.name,
        "bytes": out.stat().st_size,
        "numpy_vs_onnx_max_relative_difference": forward_parity(size, model_dir),
    }


if __name__ == "__main__":
    main()

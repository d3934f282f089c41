"""Training beyond one process: every trainer under ``torchrun`` (two CPU processes, gloo) follows the
one-process run step for step (``onnx_export.distributed``)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from onnx_export import data as datamod  # noqa: E402
from onnx_export import layered_data  # noqa: E402
from onnx_export.distributed import Processes  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TWO = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]


def _run(module_args: list[str], launcher: list[str]) -> None:
    """``python [launcher] -m module_args`` from the repository, outside any torchrun of its own."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
    }
    env |= {"OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    r = subprocess.run(
        [sys.executable, *launcher, "-m", *module_args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-3000:]


def _assert_same_weights(one: dict, two: dict, what: str) -> None:
    assert one.keys() == two.keys()
    for k, w in one.items():
        np.testing.assert_allclose(two[k].numpy(), w.numpy(), rtol=1e-4, atol=1e-5, err_msg=f"{what}: {k}")


def _train_decoder(out: Path, data: Path, launcher: list[str]) -> dict:
    _run(
        [
            "onnx_export.train_decoder",
            *("--size", "tiny", "--data", str(data), "--steps", "6", "--batch", "8", "--pairs", "16"),
            *("--lr", "3e-3", "--clip", "1", "--grazing-floor", "0.2", "--every", "6", "--threads", "1"),
            *("--seed", "3", "--out", str(out)),
        ],
        launcher,
    )
    return torch.load(out / "ckpt.pt", weights_only=False)


@pytest.fixture(scope="module")
def decoder_runs(tmp_path_factory):
    """A small single-layer data set and the decoder trained on it by one process and by two."""
    tmp = tmp_path_factory.mktemp("distributed")
    data = tmp / "single"
    datamod.generate("single", data, materials=16, pairs=64, chunk=8, seed=5, log=lambda s: None)
    return data, _train_decoder(tmp / "one", data, []), _train_decoder(tmp / "two", data, TWO), tmp


def test_train_decoder_two_processes_agree_with_one(decoder_runs):
    _, one, two, _ = decoder_runs
    assert one["step"] == two["step"] == 6
    assert (one["world_size"], one["channels_per_process"]) == (1, 8)
    assert (two["world_size"], two["channels_per_process"]) == (2, 4)  # each process computed half the batch
    _assert_same_weights(one["decoder"], two["decoder"], "decoder")
    np.testing.assert_allclose(two["latents"].numpy(), one["latents"].numpy(), rtol=1e-4, atol=1e-5)
    assert abs(two["loss"] - one["loss"]) <= 1e-4 * abs(one["loss"])
    # the runs trained: the latents left their random start (std 0.01) by more than the tolerance
    start = torch.randn(one["latents"].shape, generator=torch.Generator().manual_seed(3)) * 0.01
    assert float((one["latents"] - start).abs().max()) > 1e-3


def test_train_encoder_two_processes_agree_with_one(decoder_runs):
    data, _, _, tmp = decoder_runs
    runs = {}
    for name, launcher in (("one", []), ("two", TWO)):
        out = tmp / f"encoder_{name}.pt"
        _run(
            [
                "onnx_export.train_encoder",
                *("--ckpt", str(tmp / "one" / "ckpt.pt"), "--data", str(data), "--distill", "4", "--finetune", "3"),
                *("--batch-units", "16", "--batch", "8", "--pairs", "16", "--lr", "3e-3", "--seed", "2"),
                *("--out", str(out)),
            ],
            launcher,
        )
        runs[name] = torch.load(out, weights_only=False)
    assert (runs["one"]["world_size"], runs["two"]["world_size"]) == (1, 2)
    _assert_same_weights(runs["one"]["encoder"], runs["two"]["encoder"], "encoder")
    assert runs["two"]["history"]["finetuned"] == pytest.approx(runs["one"]["history"]["finetuned"], rel=1e-3)


def test_layering_train_two_processes_agree_with_one(tmp_path):
    for c in (1, 2):
        layered_data.generate(tmp_path / f"c{c}", c, 8, 2, 8, 2, 8, seed=11, log=lambda s: None)
    runs = {}
    for name, launcher in (("one", []), ("two", TWO)):
        out = tmp_path / name
        _run(
            [
                "onnx_export.layering",
                "train",
                *("--size", "tiny", "--init-from", "tiny", "--c1", str(tmp_path / "c1"), "--c2", str(tmp_path / "c2")),
                *("--heldout", "none", "--decoded-steps", "2", "--decoded-target", "data"),
                *("--decoded-reciprocal", "--steps", "2", "--finetune", "2", "--batch", "4", "--pairs", "8"),
                *("--lr", "3e-3", "--decoded-lr", "3e-3", "--seed", "1", "--out", str(out)),
            ],
            launcher,
        )
        runs[name] = torch.load(out / "ckpt.pt", weights_only=False)
    one, two = runs["one"], runs["two"]
    assert (one["world_size"], two["world_size"]) == (1, 2)
    assert one["step"] == two["step"] == 4 and two["history"]["decoded"]["step"] == 2
    _assert_same_weights(one["net"], two["net"], "layering network")
    assert two["loss"] == pytest.approx(one["loss"], rel=1e-4)


def test_sampling_net_two_processes_agree_with_one(tmp_path):
    models = {}
    for name, launcher in (("one", []), ("two", TWO)):
        d = models[name] = tmp_path / f"models_{name}"
        d.mkdir()
        for role in ("decoder", "encoder", "layering"):
            for f in (ROOT / "addon" / "models").glob(f"{role}_tiny*"):
                shutil.copy(f, d / f.name)
        _run(
            [
                "onnx_export.sampling_net",
                *("--size", "tiny", "--materials", "100", "--heldout", "10", "--samples", "10", "--steps", "3"),
                *("--batch", "8", "--seed", "4", "--models", str(d), "--out", str(tmp_path / f"run_{name}")),
            ],
            launcher,
        )
    one, two = (np.load(tmp_path / f"run_{n}" / "tables.npz") for n in ("one", "two"))
    for k in ("table", "table_ho"):  # 100 materials = 3 batches of 48: both processes computed some
        np.testing.assert_array_equal(two[k], one[k], err_msg=k)
    import onnxruntime as ort

    z = np.random.default_rng(0).normal(size=(16, 3, 32)).astype(np.float32)
    out = [ort.InferenceSession(str(models[n] / "sampling_tiny.onnx")).run(None, {"z": z}) for n in ("one", "two")]
    for a, b in zip(*out, strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-6)


class _Part(Processes):
    """One process of ``world`` without a process group: ``total`` keeps this process's part."""

    def total(self, x):
        return x.detach().clone()


def test_kl_table_shards_add_up_to_the_one_process_table():
    from addon.core.neural.models import ModelSet
    from onnx_export import sampling_net

    models = ModelSet("tiny")
    z = np.random.default_rng(1).normal(scale=0.5, size=(7, 3, 32)).astype(np.float32)
    whole = sampling_net.kl_tables(models, z, samples=10, seed=3, batch=2)
    parts = [sampling_net.kl_tables(models, z, samples=10, seed=3, batch=2, procs=_Part(r, 3)) for r in range(3)]
    assert all(np.count_nonzero(p.reshape(7, -1).any(axis=1)) in (2, 3) for p in parts)  # 4 batches over 3
    np.testing.assert_array_equal(sum(parts), whole)


def test_a_batch_the_processes_cannot_split_is_refused(tmp_path, monkeypatch):
    from onnx_export import train_decoder

    monkeypatch.setattr(train_decoder, "processes", lambda: Processes(0, 3))
    args = train_decoder.parser().parse_args(["--data", str(tmp_path), "--batch", "8", "--out", str(tmp_path / "o")])
    with pytest.raises(ValueError, match="batches of 8: it must be a multiple of the 3 processes"):
        train_decoder.train(args, log=lambda s: None)

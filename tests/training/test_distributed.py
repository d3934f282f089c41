"""Training beyond one process: ``train_decoder`` under ``torchrun`` (DistributedDataParallel, gloo on CPU)
follows the one-process run step for step."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from onnx_export import data as datamod  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def _train(out: Path, data: Path, extra_env: dict, launcher: list[str]) -> dict:
    args = [
        "-m",
        "onnx_export.train_decoder",
        "--size",
        "tiny",
        "--data",
        str(data),
        "--steps",
        "6",
        "--batch",
        "8",
        "--pairs",
        "16",
        "--lr",
        "3e-3",
        "--clip",
        "1",
        "--grazing-floor",
        "0.2",
        "--every",
        "6",
        "--threads",
        "1",
        "--seed",
        "3",
        "--out",
        str(out),
    ]
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
    }
    env |= {"OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)} | extra_env
    r = subprocess.run(
        [sys.executable, *launcher, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return torch.load(out / "ckpt.pt", weights_only=False)


def test_two_processes_under_torchrun_agree_with_one(tmp_path):
    data = tmp_path / "single"
    datamod.generate("single", data, materials=16, pairs=64, chunk=8, seed=5, log=lambda s: None)
    one = _train(tmp_path / "one", data, {}, [])
    two = _train(tmp_path / "two", data, {}, ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"])
    assert one["step"] == two["step"] == 6
    assert (one["world_size"], one["channels_per_process"]) == (1, 8)
    assert (two["world_size"], two["channels_per_process"]) == (2, 4)  # each process computed half the batch
    for k, w in one["decoder"].items():
        np.testing.assert_allclose(two["decoder"][k].numpy(), w.numpy(), rtol=1e-4, atol=1e-5, err_msg=k)
    np.testing.assert_allclose(two["latents"].numpy(), one["latents"].numpy(), rtol=1e-4, atol=1e-5)
    assert abs(two["loss"] - one["loss"]) <= 1e-4 * abs(one["loss"])
    # the runs trained: the latents left their random start (std 0.01) by more than the tolerance
    assert (
        float(
            (one["latents"] - torch.randn(one["latents"].shape, generator=torch.Generator().manual_seed(3)) * 0.01)
            .abs()
            .max()
        )
        > 1e-3
    )


def test_a_batch_the_processes_cannot_split_is_refused(tmp_path, monkeypatch):
    from onnx_export import train_decoder

    monkeypatch.setattr(train_decoder, "distributed", lambda: (0, 3))
    args = train_decoder.parser().parse_args(["--data", str(tmp_path), "--batch", "8", "--out", str(tmp_path / "o")])
    with pytest.raises(ValueError, match="multiple of the 3 processes"):
        train_decoder.train(args, log=lambda s: None)

"""Fault injection: bakes killed (SIGKILL, SIGTERM) at random moments while encoding bands,
assembling, publishing (the atomic renames) and cleaning up, or at any time after start; then
rerun. Every rerun gives the uninterrupted bake's texture bit for bit and leaves nothing else;
after SIGTERM nothing temporary is left even before the rerun, and at no point does a finished
name hold a half-written file. The moments are drawn from a fixed seed."""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from addon.core.textures import LatentTexture, files
from addon.core.textures.latent_texture import oiio_module
from tests.faults.bake_driver import stand_in_encoder
from tests.faults.tally import fault

ROOT = Path(__file__).resolve().parents[2]
DRIVER = ROOT / "tests" / "faults" / "bake_driver.py"
sys.path.insert(0, str(ROOT / "bake"))
import bake as bake_cli  # noqa: E402

SEED = 21
BANDS = 10  # 40 rows in bands of 4
# phase -> how many times its marker shows in one uninterrupted bake (one is picked at random)
PHASES = {"band": BANDS, "assemble": 1, "publish": BANDS + 2, "cleanup": 1, "any time": 0}
ROUNDS = 2


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    oiio = oiio_module()
    root = tmp_path_factory.mktemp("kill")
    img = np.zeros((40, 24))
    img[10:30, 5:20] = 1.0
    img[:, :3] = 0.5
    path = root / "rough.png"
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(24, 40, 1, "uint8"))
    out.write_image(np.ascontiguousarray(img, dtype=np.float32).reshape(40, 24, 1))
    out.close()
    ref = root / "reference"
    t0 = time.perf_counter()
    assert (
        subprocess.run(
            [sys.executable, str(DRIVER), "--", *argv(path, ref)], capture_output=True, timeout=120
        ).returncode
        == 0
    )
    return path, ref, time.perf_counter() - t0


def argv(rough: Path, out: Path) -> list[str]:
    return [
        "--preset",
        "varnished_wood",
        "--map",
        f"coatings[0].roughness={rough}:0.05:0.5",
        "--out",
        str(out),
        "--band-rows",
        "4",
    ]


def kill_at(rng: random.Random, phase: str, sig: int, cmd: list[str], duration: float) -> int:
    p = subprocess.Popen(
        [sys.executable, str(DRIVER), "--markers", "--", *cmd],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    if phase == "any time":
        time.sleep(rng.uniform(0.0, duration))
    else:
        wanted, seen = rng.randint(1, PHASES[phase]), 0
        for line in p.stdout:
            seen += line.strip() == f"@{phase}"
            if seen == wanted:
                time.sleep(rng.uniform(0.0, 0.005))  # just before, inside, or just after the step
                break
    p.send_signal(sig)
    code = p.wait(timeout=60)
    p.stdout.close()
    return code


def texture_bits(path: Path):
    tex = LatentTexture.read_exr(path)
    return [level.view(np.uint32) for level in tex.levels], tex.metadata["key"]


def assert_nothing_half_written(out: Path) -> None:
    """Every file under a finished name is whole (temporary names may remain after SIGKILL)."""
    for p in out.rglob("*"):
        if p.is_dir() or files.is_temp(p):
            continue
        if p.suffix == ".exr":
            LatentTexture.read_exr(p)
        elif p.suffix == ".json":
            assert json.loads(p.read_text())["key"]
        elif p.suffix == ".npy":
            assert np.isfinite(np.load(p)).all()
        else:
            raise AssertionError(f"unexpected file {p}")


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_a_bake_killed_at_random_moments_reruns_to_the_uninterrupted_texture(inputs, tmp_path, sig):
    rough, ref, duration = inputs
    rng = random.Random(f"{SEED}-{sig}")
    want_levels, want_key = texture_bits(ref / "varnished_wood.exr")
    for round_ in range(ROUNDS):
        for phase in PHASES:
            out = tmp_path / f"{round_}-{phase.replace(' ', '-')}"
            code = kill_at(rng, phase, sig, argv(rough, out), duration)
            fault(f"{signal.Signals(sig).name} during {phase}")
            if sig == signal.SIGTERM:
                # 0: it had finished before the signal came; -SIGTERM: it came before the command had started
                # (Python still starting, nothing written), which a shell reports as 143 too
                assert code in (0, 143, -signal.SIGTERM), (phase, code)
                assert not [p for p in out.rglob("*") if files.is_temp(p)], phase
            else:
                assert code in (0, -signal.SIGKILL), (phase, code)
            if out.exists():
                assert_nothing_half_written(out)
            assert bake_cli.main(argv(rough, out), encode=stand_in_encoder()) == 0, phase
            levels, key = texture_bits(out / "varnished_wood.exr")
            assert key == want_key and all(np.array_equal(a, b) for a, b in zip(levels, want_levels, strict=True))
            assert sorted(p.name for p in out.rglob("*")) == ["varnished_wood.exr", "varnished_wood.json"], phase

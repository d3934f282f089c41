"""Runs the batch bake command (``bake/bake.py``) in its own process with the tests' stand-in encoder.

    python tests/faults/bake_driver.py [--markers] [--barrier FOLDER:N] -- <bake.py arguments>

The stand-in encoder is a fixed linear map of each texel's parameters, so a bake is fast and
deterministic while every parameter still shows in the latents. ``--markers`` prints a line
``@<phase>`` (flushed) as the bake enters each phase: ``band`` (encoding a band), ``assemble``,
``publish`` (an atomic rename of a finished file) and ``cleanup`` (removing bands), so a test
can stop the process at a chosen moment. ``--barrier FOLDER:N`` makes each of N processes wait,
when it has baked its bands and is about to assemble, until all N have got there: they then all
find every band present and assemble at once.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "bake")]

import numpy as np  # noqa: E402


def stand_in_encoder():
    proj = np.random.default_rng(3).normal(size=(64, 98))

    def encode(arrays):
        m = arrays.to_matrix()
        v = m @ proj[: m.shape[1]]
        return v[:, :96], v[:, 96:]

    return encode


def _marker(name: str) -> None:
    sys.stdout.write(f"@{name}\n")
    sys.stdout.flush()


def _with_marker(owner, attr: str, name: str) -> None:
    inner = getattr(owner, attr)

    def wrapped(*args, **kwargs):
        _marker(name)
        return inner(*args, **kwargs)

    setattr(owner, attr, wrapped)


def _barrier(bake, spec: str) -> None:
    folder, n = spec.rsplit(":", 1)
    inner = bake.ProgressBar.close  # the bands are done, assembly comes next
    arrived = Path(folder, str(os.getpid()))

    def wait_then_assemble(*args, **kwargs):
        if not arrived.exists():
            arrived.touch()
            deadline = time.monotonic() + 60
            while len(list(Path(folder).iterdir())) < int(n) and time.monotonic() < deadline:
                time.sleep(0.005)
        return inner(*args, **kwargs)

    bake.ProgressBar.close = wait_then_assemble


def main(argv: list[str]) -> int:
    split = argv.index("--") if "--" in argv else len(argv)
    own, bake_argv = argv[:split], argv[split + 1 :]
    import bake

    if "--markers" in own:
        from addon.core.textures import files

        _with_marker(bake, "_bake_band", "band")
        _with_marker(bake, "assemble", "assemble")
        _with_marker(bake, "_remove_bands", "cleanup")
        _with_marker(files.os, "replace", "publish")
    if "--barrier" in own:
        _barrier(bake, own[own.index("--barrier") + 1])
    return bake.main(bake_argv, encode=stand_in_encoder())


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

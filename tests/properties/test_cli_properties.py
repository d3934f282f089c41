"""Property-based tests of the command-line tools (``bake/bake.py``, ``bake/demo.py``): any
argument list exits 0, 1 or 2, an error is one line starting ``error:``, nothing is a traceback,
and nothing is written outside the output folder. Seeded and bounded; the bake uses the tests'
stand-in encoder and the demo's work functions are replaced by recorders (their arguments are
what is under test), so an example takes milliseconds."""

from __future__ import annotations

import contextlib
import io
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example as also
from hypothesis import given
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bake"))
import demo as demo_cli  # noqa: E402

import bake as bake_cli  # noqa: E402
from tests.faults.bake_driver import stand_in_encoder  # noqa: E402
from tests.faults.tally import bounded, example  # noqa: E402

HOSTILE = [
    "/../../x",
    "..",
    ".",
    "",
    "-",
    "--",
    "a b",
    "é",
    "\t",
    "x" * 300,
    "-1",
    "0",
    "1e9",
    "nan",
    "inf",
    "3/3",
    "1/0",
    "a/b",
    "0.5",
    "small",
    "tiny",
    "bogus",
]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    from addon.core.textures.latent_texture import oiio_module

    oiio = oiio_module()
    root = tmp_path_factory.mktemp("cli-properties")
    for name, img in {"rough.png": np.tile(np.linspace(0, 1, 6), (4, 1)), "mask.png": np.eye(4, 6)}.items():
        out = oiio.ImageOutput.create(str(root / name))
        out.open(str(root / name), oiio.ImageSpec(6, 4, 1, "uint8"))
        out.write_image(np.ascontiguousarray(img, dtype=np.float32).reshape(4, 6, 1))
        out.close()
    (root / "text.png").write_text("not an image")
    yield root


def bake_arguments(root: Path):
    files = [str(root / n) for n in ("rough.png", "mask.png", "text.png", "missing.png")] + [str(root)]
    value = st.one_of(
        st.sampled_from(HOSTILE), st.sampled_from(files), st.text(max_size=8), st.integers(-3, 50).map(str)
    )
    option = st.sampled_from(
        [
            "--preset",
            "--blend",
            "--material",
            "--map",
            "--name",
            "--mix",
            "--mask",
            "--resolution",
            "--model",
            "--shard",
            "--band-rows",
            "--no-dedup",
            "--help",
            "--bogus",
        ]
    )
    maps = st.builds(
        lambda p, f, r: f"{p}={f}{r}",
        st.sampled_from(["coatings[0].roughness", "base.albedo", "coatings[5].g", "base.x", "nonsense"]),
        st.sampled_from(files),
        st.sampled_from(["", ":0.05:0.5", ":-1:2", ":a:b"]),
    )
    preset = st.sampled_from(["varnished_wood", "coated_gold", "frosted_copper", "velvet"])
    pieces = st.lists(
        st.one_of(
            st.tuples(option),
            st.tuples(option, value),
            st.tuples(st.just("--map"), maps),
            st.tuples(st.just("--preset"), preset),
            st.tuples(st.just("--resolution"), value, value),
        ),
        max_size=6,
    )
    return pieces.map(lambda ps: [x for p in ps for x in p])


def run_cli(main, argv):
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def error_lines(text: str) -> list[str]:
    return [line for line in text.replace("\r", "\n").splitlines() if line.strip() and not line.startswith("[")]


def files_under(root: Path) -> set[Path]:
    return {p for p in root.rglob("*")}


@bounded(80)
@given(data=st.data())
@also(data=None)
def test_bake_command_exits_0_1_or_2_with_one_line_and_writes_only_into_out(workspace, data):
    example()
    argv = data.draw(bake_arguments(workspace), label="argv") if data is not None else []
    out = workspace / "out"
    with_out = argv + ["--out", str(out)] if data is None or data.draw(st.booleans(), label="--out") else argv
    before = files_under(workspace) - files_under(out)
    code, stdout, stderr = run_cli(lambda a: bake_cli.main(a, encode=stand_in_encoder()), with_out)
    assert code in (0, 1, 2), (with_out, code, stderr)
    assert "Traceback" not in stderr + stdout
    if code:
        lines = error_lines(stderr)
        assert len(lines) == 1 and lines[0].startswith("error: "), (with_out, stderr)
    elif "--help" not in with_out:
        assert stdout.strip().splitlines()[-1].startswith("baked ")
    assert files_under(workspace) - files_under(out) <= before | {out}, with_out  # nothing outside --out


def demo_arguments():
    value = st.one_of(
        st.sampled_from(HOSTILE + ["320x180", "0x0", "8x", "x8", "-4x4", "4x4"]),
        st.integers(-3, 20).map(str),
        st.text(max_size=6),
    )
    option = st.sampled_from(
        [
            "--out",
            "--lobe-res",
            "--walks",
            "--seed",
            "--render-size",
            "--samples",
            "--bounces",
            "--mode",
            "--skip-lobes",
            "--help",
            "--bogus",
        ]
    )
    return st.lists(st.one_of(st.tuples(option), st.tuples(option, value)), max_size=6).map(
        lambda ps: [x for p in ps for x in p]
    )


@bounded(60)
@given(argv=demo_arguments())
@also(argv=["--lobe-res", "0"])
@also(argv=["--walks", "-1"])
@also(argv=["--mode", "bogus"])
def test_demo_command_exits_0_1_or_2_with_one_line(workspace, monkeypatch_module, argv):
    example()
    calls = []
    monkeypatch_module.setattr(demo_cli, "preset_lobes", lambda out, res, walks, seed: calls.append(res) or [])
    monkeypatch_module.setattr(demo_cli, "render_demo", lambda *a: calls.append(a))
    out = workspace / "demo"
    if "--out" not in argv:
        argv = argv + ["--out", str(out)]
    else:
        i = argv.index("--out")
        argv = argv[: i + 1] + [str(out / "sub")] + argv[i + 2 :] if i + 1 < len(argv) else argv
    code, stdout, stderr = run_cli(demo_cli.main, argv)
    assert code in (0, 1, 2), (argv, code, stderr)
    assert "Traceback" not in stderr + stdout
    if code:
        lines = error_lines(stderr)
        assert len(lines) == 1 and lines[0].startswith("error: "), (argv, stderr)


@pytest.fixture(scope="module")
def monkeypatch_module():
    with pytest.MonkeyPatch.context() as mp:
        yield mp

"""The batch bake command under faults and hostile input: .blend files baked both ways, shards
racing on one folder, hostile material names, bad masks, damaged bands, interrupts, leftovers.

Bakes that need their own process run ``tests/faults/bake_driver.py`` (the bake command with a
stand-in encoder); the .blend bakes run ``bake/bake.py`` itself with the shipped ``tiny`` models.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
bpy.utils.expose_bundled_modules()
oiio = pytest.importorskip("OpenImageIO")

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bake"))
import bake as bake_cli  # noqa: E402
from addon.core.textures import LatentTexture, files  # noqa: E402
from tests.blender.helpers import run_operator  # noqa: E402
from tests.faults.bake_driver import stand_in_encoder  # noqa: E402

DRIVER = ROOT / "tests" / "faults" / "bake_driver.py"


def write_png(path, array):
    h, w = array.shape[:2]
    c = 1 if array.ndim == 2 else array.shape[2]
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, c, "uint8"))
    out.write_image(np.ascontiguousarray(array, dtype=np.float32).reshape(h, w, c))
    out.close()
    return path


def write_exr(path, array):
    h, w = array.shape[:2]
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, 1, "float"))
    out.write_image(np.ascontiguousarray(array, dtype=np.float32).reshape(h, w, 1))
    out.close()
    return path


@pytest.fixture()
def rough_png(tmp_path):
    img = np.zeros((40, 24))
    img[10:30, 5:20] = 1.0
    img[:, :3] = 0.5
    return write_png(tmp_path / "rough.png", img)


def preset_argv(rough_png, out, *extra):
    return [
        "--preset",
        "varnished_wood",
        "--map",
        f"coatings[0].roughness={rough_png}:0.05:0.5",
        "--out",
        str(out),
        "--band-rows",
        "4",
        *extra,
    ]


def texture_bits(path):
    """The texels of every mip level as raw bits, and the header's bake key."""
    tex = LatentTexture.read_exr(path)
    return [lvl.view(np.uint32).copy() for lvl in tex.levels], tex.metadata.get("key")


def assert_same_texture(a, b):
    la, ka = texture_bits(a)
    lb, kb = texture_bits(b)
    assert ka == kb and len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        assert np.array_equal(x, y)


def listing(folder):
    return sorted(str(p.relative_to(folder)) for p in Path(folder).rglob("*"))


def driver(*argv, **kw):
    return subprocess.Popen(
        [sys.executable, str(DRIVER), *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, **kw
    )


# --- item 1: .blend files -------------------------------------------------------------------------


@pytest.fixture()
def wood_blend(bpy_addon, material, tmp_path):
    """A .blend with the material "Wood" (varnished wood stack), one named like a path, and a plain one."""
    assert run_operator(bpy_addon.ops.neural_layers.preset_apply, preset="varnished_wood").finished
    material.name = "Wood"
    hostile = bpy_addon.data.materials.new("/../../x")
    bpy_addon.context.object.data.materials.append(hostile)
    bpy_addon.context.object.active_material_index = len(bpy_addon.context.object.data.materials) - 1
    assert run_operator(bpy_addon.ops.neural_layers.preset_apply, preset="coated_gold").finished
    bpy_addon.data.materials.new("Plain").use_fake_user = True  # no stack: not baked
    path = tmp_path / "scene.blend"
    bpy_addon.ops.wm.save_as_mainfile(filepath=str(path))
    bpy_addon.ops.wm.read_homefile(app_template="")
    return path


def tiny_latent(name):
    from addon.core.neural import encode_stack
    from addon.core.stack import preset

    return encode_stack(preset(name), "tiny").reshape(-1)


def check_blend_outputs(out: Path):
    hostile = files.safe_file_name("/../../x")
    made = sorted(p.name for p in out.iterdir())
    assert made == sorted([f"{hostile}.exr", f"{hostile}.json", "Wood.exr", "Wood.json"])
    assert not list(out.parent.glob("x.*")) and not list(out.parent.parent.glob("x.*"))
    wood = LatentTexture.read_exr(out / "Wood.exr").levels[0]
    gold = LatentTexture.read_exr(out / f"{hostile}.exr").levels[0]
    assert np.allclose(wood[0, 0, :96], tiny_latent("varnished_wood"), atol=2e-3)
    assert np.allclose(gold[0, 0, :96], tiny_latent("coated_gold"), atol=2e-3)
    assert json.loads((out / f"{hostile}.json").read_text())["material"] == "/../../x"


def test_a_blend_bakes_with_the_plain_bpy_module(wood_blend, tmp_path):
    """``python bake/bake.py --blend``: nothing is registered there, so the bake registers this checkout."""
    out = tmp_path / "a" / "b" / "out"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["BLENDER_USER_EXTENSIONS"] = str(tmp_path / "no-extensions")
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bake" / "bake.py"),
            "--blend",
            str(wood_blend),
            "--out",
            str(out),
            "--model",
            "tiny",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    check_blend_outputs(out)
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bake" / "bake.py"),
            "--blend",
            str(wood_blend),
            "--out",
            str(out),
            "--material",
            "Plain",
            "--model",
            "tiny",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert r.returncode == 2 and "'Plain' has no layer stack" in r.stderr


ENABLED_EXTENSION = textwrap.dedent(
    """
    import os, shutil, sys
    root, blend, out = sys.argv[1:4]
    repo = os.path.join(os.environ["BLENDER_USER_EXTENSIONS"], "user_default", "neural_layered_materials")
    shutil.copytree(os.path.join(root, "addon"), os.path.join(repo, "addon"),
                    ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("__init__.py", "blender_manifest.toml"):
        shutil.copy(os.path.join(root, name), repo)
    import bpy
    bpy.ops.extensions.repo_refresh_all()
    module = "bl_ext.user_default.neural_layered_materials"
    bpy.ops.preferences.addon_enable(module=module)
    assert module in bpy.context.preferences.addons, "the extension did not enable"
    # what `blender -b --python bake/bake.py -- ...` does once Blender has enabled its extensions:
    sys.argv = ["blender", "-b", "--python", "bake/bake.py", "--", "--blend", blend, "--out", out, "--model", "tiny"]
    sys.path.insert(0, os.path.join(root, "bake"))
    import bake
    code = bake.main()
    used = sorted(m for m in sys.modules if m.endswith(".bake_inputs"))
    print("RESULT", code, used, "addon.blender.properties" in sys.modules)
    """
)


def test_a_blend_bakes_inside_blender_with_the_extension_enabled(wood_blend, tmp_path):
    """With the extension enabled, its registered properties and its reader are used; the checkout's
    add-on is not registered a second time."""
    script = tmp_path / "enabled.py"
    script.write_text(ENABLED_EXTENSION)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["BLENDER_USER_EXTENSIONS"] = str(tmp_path / "extensions")
    out = tmp_path / "out"
    r = subprocess.run(
        [sys.executable, str(script), str(ROOT), str(wood_blend), str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        env=env,
    )
    line = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")]
    assert r.returncode == 0 and line, r.stdout[-2000:] + r.stderr[-2000:]
    assert line[-1] == ("RESULT 0 ['bl_ext.user_default.neural_layered_materials.addon.blender.bake_inputs'] False")
    check_blend_outputs(out)


def test_a_file_that_is_not_a_blend_is_bad_input(tmp_path, capsys):
    fake = tmp_path / "fake.blend"
    fake.write_bytes(b"not a blend file")
    assert bake_cli.main(["--blend", str(fake), "--out", str(tmp_path / "o")], encode=stand_in_encoder()) == 2
    err = capsys.readouterr().err
    assert "cannot open it as a .blend" in err and "Traceback" not in err


# --- item 2: shards at the same time on one folder ---------------------------------------------------


@pytest.mark.parametrize("race", ["barrier", "free"])
def test_concurrent_shards_on_one_folder_equal_the_single_bake_bit_for_bit(rough_png, tmp_path, race):
    """N shard processes at once: all exit 0; the texture equals the one-process bake bit for bit.
    With the barrier all of them find every band present and assemble at the same moment."""
    n = 4
    single = tmp_path / "single"
    assert bake_cli.main(preset_argv(rough_png, single), encode=stand_in_encoder()) == 0
    shared = tmp_path / "shared"
    gate = tmp_path / "gate"
    gate.mkdir()
    own = ["--barrier", f"{gate}:{n}"] if race == "barrier" else []
    procs = [driver(*own, "--", *preset_argv(rough_png, shared, "--shard", f"{i}/{n}")) for i in range(n)]
    results = [(p.wait(timeout=120), p.stderr.read()) for p in procs]
    for p in procs:
        p.stdout.close()
        p.stderr.close()
    assert [code for code, _ in results] == [0] * n, [err[-600:] for _, err in results]
    if race == "barrier":
        assert len(list(gate.iterdir())) == n  # every shard got to assembly
    assert_same_texture(single / "varnished_wood.exr", shared / "varnished_wood.exr")
    assert listing(shared) == ["varnished_wood.exr", "varnished_wood.json"]


def test_a_shard_that_finds_the_bands_gone_after_another_published_succeeds(rough_png, tmp_path, monkeypatch):
    """The interleaving behind the race: shard B saw all bands, then shard A published and removed them."""
    out = tmp_path / "out"
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "0/2"), encode=stand_in_encoder()) == 0
    real_assemble, real_load = bake_cli.assemble, bake_cli._load_band
    state = {"other_published": False}

    def load_after_another_shard_finished(path, rows, width):
        if not state["other_published"]:
            state["other_published"] = True
            monkeypatch.setattr(bake_cli, "_load_band", real_load)
            job = bake_cli.preset_job(bake_cli.parse_args(preset_argv(rough_png, out)))[0]
            stats = {"texels": 0, "unique": 0, "seconds": 0}
            assert real_assemble(out, job, job.key("auto"), "auto", 4, stats, rebake=None)
        return real_load(path, rows, width)

    monkeypatch.setattr(bake_cli, "_load_band", load_after_another_shard_finished)
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "1/2"), encode=stand_in_encoder()) == 0
    assert state["other_published"]
    assert listing(out) == ["varnished_wood.exr", "varnished_wood.json"]


# --- item 3 (issue item 5): names choose where the command writes ------------------------------------


HOSTILE_NAMES = [
    "/../../x",
    "../x",
    "..",
    ".",
    "a/b",
    "a_b",
    "a\\b",
    "C:\\x",
    "CON",
    "nul.txt",
    " x ",
    ".hidden",
    "x" * 300,
    "tab\there",
    "new\nline",
    "é/ü",
    'a:b*c?d"e<f>g|h',
]


def test_hostile_names_write_inside_out_and_stay_distinct(tmp_path):
    stems = [files.safe_file_name(n) for n in HOSTILE_NAMES]
    assert len(set(stems)) == len(stems)
    for stem in stems:
        assert "/" not in stem and "\\" not in stem and not stem.startswith(".") and stem not in ("", ".", "..")
        assert len(stem.encode()) <= 130 and stem.isprintable()
    assert files.safe_file_name("Wood") == "Wood" and files.safe_file_name("Holz Eiche (2)") == "Holz Eiche (2)"
    out = tmp_path / "deep" / "out"
    for name in ["/../../x", "../x", "..", "a/b", "a_b"]:
        assert (
            bake_cli.main(["--preset", "coated_gold", "--name", name, "--out", str(out)], encode=stand_in_encoder())
            == 0
        )
    made = sorted(p.name for p in out.iterdir())
    assert len(made) == 10 and all(p.parent == out for p in out.iterdir())
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == made  # nothing outside --out
    names = {json.loads((out / m).read_text())["material"] for m in made if m.endswith(".json")}
    assert names == {"/../../x", "../x", "..", "a/b", "a_b"}


def test_names_equal_but_for_case_are_refused(tmp_path, capsys):
    job = bake_cli.preset_job(bake_cli.parse_args(["--preset", "coated_gold", "--out", str(tmp_path)]))[0]
    other = bake_cli.Job("Coated_Gold", job.spatial, job.resolution, {})
    with pytest.raises(bake_cli.BadInput, match="ignores case"):
        bake_cli.run([job, other], tmp_path, stand_in_encoder(), "small", (0, 1), 4)


# --- item 5 (issue item 7): masks ------------------------------------------------------------------


@pytest.mark.parametrize("value, shown", [(2.0, "2.0"), (-0.5, "-0.5"), (np.nan, "nan"), (np.inf, "inf")])
def test_a_mask_outside_0_1_is_bad_input_naming_file_value_and_range(tmp_path, capsys, value, shown):
    mask = np.full((6, 10), 0.5)
    mask[2, 7] = value
    path = write_exr(tmp_path / "mask.exr", mask)
    out = tmp_path / "out"
    code = bake_cli.main(
        [
            "--preset",
            "coated_gold",
            "--mix",
            "frosted_copper",
            "--mask",
            str(path),
            "--out",
            str(out),
            "--band-rows",
            "2",
        ],
        encode=stand_in_encoder(),
    )
    err = capsys.readouterr().err
    assert code == 2, err
    assert str(path) in err and shown in err and "[0, 1]" in err and "(x=7, y=2)" in err
    assert not out.exists() or listing(out) == []  # checked before anything is baked


@pytest.mark.parametrize("shard_rerun", [True, False])
def test_an_invalid_kept_band_is_baked_again_never_reused(rough_png, tmp_path, capsys, shard_rerun):
    out = tmp_path / "out"
    ref = tmp_path / "ref"
    assert bake_cli.main(preset_argv(rough_png, ref), encode=stand_in_encoder()) == 0
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "0/2"), encode=stand_in_encoder()) == 0
    bands = sorted((out / ".varnished_wood.bands").glob("*.npy"))
    assert len(bands) == 5  # 10 bands of 4 rows, every other one
    np.save(bands[0], np.full(np.load(bands[0]).shape, np.nan, np.float32))  # NaN
    np.save(bands[1], np.zeros((3, 98), np.float32))  # wrong shape
    bands[2].write_bytes(b"\x93NUMPY truncated")  # damaged
    capsys.readouterr()
    rerun = "0/2" if shard_rerun else "1/2"  # the damaged bands' own shard keeps nothing; the other assembles
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", rerun), encode=stand_in_encoder()) == 0
    err = capsys.readouterr()
    assert "non-finite" in err.out and "expected float32" in err.out and "unreadable" in err.out
    if shard_rerun:
        assert bake_cli.main(preset_argv(rough_png, out, "--shard", "1/2"), encode=stand_in_encoder()) == 0
    assert_same_texture(ref / "varnished_wood.exr", out / "varnished_wood.exr")
    assert listing(out) == ["varnished_wood.exr", "varnished_wood.json"]


def test_bands_of_other_inputs_are_not_reused_and_are_cleaned(rough_png, tmp_path):
    out = tmp_path / "out"
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "0/2"), encode=stand_in_encoder()) == 0
    old = sorted((out / ".varnished_wood.bands").glob("*.npy"))
    other = write_png(tmp_path / "other.png", np.full((40, 24), 0.25))
    assert bake_cli.main(preset_argv(other, out), encode=stand_in_encoder()) == 0
    ref = tmp_path / "ref"
    assert bake_cli.main(preset_argv(other, ref), encode=stand_in_encoder()) == 0
    assert_same_texture(ref / "varnished_wood.exr", out / "varnished_wood.exr")
    assert old and not any(p.exists() for p in old)
    assert listing(out) == ["varnished_wood.exr", "varnished_wood.json"]


# --- item 6 (issue item 9): leftovers, signals, exit codes -------------------------------------------


def test_a_texture_written_to_a_folder_name_is_an_error_and_leaves_nothing(tmp_path):
    tex = LatentTexture.from_texels(np.zeros((2, 3, 100), np.float32))
    (tmp_path / "folder.exr").mkdir()
    with pytest.raises(IsADirectoryError, match="is a folder"):
        tex.write_exr(tmp_path / "folder.exr")
    with pytest.raises(IsADirectoryError):
        tex.write_exr(tmp_path)
    assert listing(tmp_path) == ["folder.exr"]


def test_a_failed_texture_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "t.exr"
    LatentTexture.from_texels(np.zeros((2, 3, 100), np.float32)).write_exr(path)
    before = path.read_bytes()

    def fail(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(LatentTexture, "_write_levels", fail)
    with pytest.raises(KeyboardInterrupt):
        LatentTexture.from_texels(np.ones((2, 3, 100), np.float32)).write_exr(path)
    assert path.read_bytes() == before and listing(tmp_path) == ["t.exr"]


def _stop_at(marker, argv, sig, tmp_path, occurrence=1):
    p = driver("--markers", "--", *argv)
    seen = 0
    for line in p.stdout:
        if line.strip() == f"@{marker}":
            seen += 1
            if seen == occurrence:
                p.send_signal(sig)
                break
    code = p.wait(timeout=60)
    err = p.stderr.read()
    p.stdout.close()
    p.stderr.close()
    return code, err


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_sigterm_and_ctrl_c_exit_with_their_codes_one_line_and_no_temporary_files(rough_png, tmp_path, sig, code):
    out = tmp_path / "out"
    got, err = _stop_at("band", preset_argv(rough_png, out), sig, tmp_path, occurrence=3)
    assert got == code, err
    lines = [x for x in err.replace("\r", "\n").splitlines() if x.startswith("error")]
    assert "Traceback" not in err and len(lines) == 1 and "interrupted by" in lines[0] and "resume" in lines[0]
    assert not [p for p in out.rglob("*") if files.is_temp(p)]
    kept = sorted((out / ".varnished_wood.bands").glob("*.npy"))
    assert 1 <= len(kept) <= 3 and not (out / "varnished_wood.exr").exists()
    assert bake_cli.main(preset_argv(rough_png, out), encode=stand_in_encoder()) == 0  # resumes
    assert listing(out) == ["varnished_wood.exr", "varnished_wood.json"]


def test_temporary_files_of_a_killed_writer_are_removed_by_the_next_run_and_live_ones_kept(rough_png, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = out / f".varnished_wood.exr.{files._HOST}-{dead.pid}-0123abcd.partial.exr"
    stale.write_bytes(b"half")
    live = files.temp_path(out / "varnished_wood.json")  # this process: alive
    live.write_bytes(b"{")
    foreign = out / f".varnished_wood.exr.otherhost-{dead.pid}-0123abcd.partial.exr"  # cannot be checked from here
    foreign.write_bytes(b"")
    assert bake_cli.main(preset_argv(rough_png, out), encode=stand_in_encoder()) == 0
    assert not stale.exists() and live.exists() and foreign.exists()
    live.unlink()
    foreign.unlink()
    assert listing(out) == ["varnished_wood.exr", "varnished_wood.json"]


def test_keyboard_interrupt_in_process_is_exit_130_without_a_traceback(rough_png, tmp_path, capsys, monkeypatch):
    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(bake_cli, "_bake_band", interrupted)
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    assert bake_cli.main(preset_argv(rough_png, tmp_path / "o"), encode=stand_in_encoder()) == 130
    err = capsys.readouterr().err
    assert "interrupted by SIGINT" in err and "Traceback" not in err
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before  # handlers restored


def test_argument_errors_are_one_line(tmp_path, capsys):
    for argv in (
        ["--out"],
        ["--preset", "coated_gold", "--out", str(tmp_path), "--band-rows", "x"],
        ["--bogus"],
        ["--blend", "a.blend", "--name", "n", "--out", str(tmp_path)],
        ["--preset", "coated_gold", "--map", "coatings[0].roughness=r.png:0.1:-", "--out", str(tmp_path)],
        ["--preset", "coated_gold", "--refine", "-5", "--out", str(tmp_path)],
    ):
        assert bake_cli.main(argv, encode=stand_in_encoder()) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("error: "), err
        assert "--model" not in err  # a bad --refine named --model


def test_bands_and_textures_of_another_decoder_file_are_not_reused(rough_png, tmp_path):
    """The key holds the decoder's digest: after a model is retrained nothing baked with the old one is kept."""

    def encoder(digest, seed):
        proj = np.random.default_rng(seed).normal(size=(64, 98))

        def encode(arrays):
            v = arrays.to_matrix() @ proj[: arrays.to_matrix().shape[1]]
            return v[:, :96], v[:, 96:]

        encode.metadata = {"model": "tiny", "model_digest": digest}
        return encode

    out, ref = tmp_path / "out", tmp_path / "ref"
    assert bake_cli.main(preset_argv(rough_png, ref), encode=encoder("new", 2)) == 0
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "0/2"), encode=encoder("old", 1)) == 0
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "1/2"), encode=encoder("new", 2)) == 0
    assert not (out / "varnished_wood.exr").exists()  # shard 0's bands are of the old decoder
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "0/2"), encode=encoder("new", 2)) == 0
    assert_same_texture(ref / "varnished_wood.exr", out / "varnished_wood.exr")
    assert LatentTexture.read_exr(out / "varnished_wood.exr").metadata["model_digest"] == "new"
    assert bake_cli.main(preset_argv(rough_png, out), encode=encoder("newer", 3)) == 0  # not "up to date"
    assert LatentTexture.read_exr(out / "varnished_wood.exr").metadata["model_digest"] == "newer"
    assert listing(out) == ["varnished_wood.exr", "varnished_wood.json"]


def test_a_kept_band_beyond_the_half_range_is_a_clear_error_and_is_kept(rough_png, tmp_path, capsys):
    """A band that loads (finite float32) but holds a latent the half-float texture cannot store is no damaged file:
    the texture is refused with that value named, and the band is neither deleted nor baked again."""
    out = tmp_path / "out"
    assert bake_cli.main(preset_argv(rough_png, out, "--shard", "0/2"), encode=stand_in_encoder()) == 0
    band = sorted((out / ".varnished_wood.bands").glob("*.npy"))[0]
    texels = np.load(band)
    texels[1, 3] = 1e5
    np.save(band, texels)
    capsys.readouterr()
    code = bake_cli.main(preset_argv(rough_png, out, "--shard", "1/2"), encode=stand_in_encoder())
    captured = capsys.readouterr()
    assert code != 0
    assert "half-float range" in captured.err and "100000" in captured.err, captured
    assert "baking it again" not in captured.out
    assert band.is_file() and np.load(band)[1, 3] == np.float32(1e5)
    assert not (out / "varnished_wood.exr").exists()


def test_a_map_from_the_trained_minimum_is_not_clamped(rough_png, tmp_path):
    """LO taken as written (float64): the guide's 0.01 is the trained minimum, where float32's 0.0099999998 fell
    below it and was clamped with a warning."""
    import warnings

    from addon.core.stack import ClampWarning

    argv = ["--preset", "varnished_wood", "--map", f"coatings[0].roughness={rough_png}:0.01:0.4", "--no-calibrate"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert bake_cli.main([*argv, "--model", "tiny", "--out", str(tmp_path / "out")]) == 0  # the encoder clamps
    assert not [w for w in caught if issubclass(w.category, ClampWarning)], [str(w.message) for w in caught]


# --- bands, published textures and maps checked for what they are ---------------------------------


def test_bands_kept_by_a_run_of_other_band_rows_are_not_reused(rough_png, tmp_path):
    """Band files were named by the key and index alone and checked by shape: a resume with another --band-rows
    took a kept band of the same shape but other rows (40 rows: band 1 of 24 rows is rows 24-39, of 16 rows 16-31)
    and published it out of place."""
    ref, out = tmp_path / "ref", tmp_path / "out"
    assert bake_cli.main(preset_argv(rough_png, ref), encode=stand_in_encoder()) == 0
    assert bake_cli.main([*preset_argv(rough_png, out, "--shard", "1/2"), "--band-rows", "24"], stand_in_encoder()) == 0
    assert len(list((out / ".varnished_wood.bands").glob("*.npy"))) == 1  # band 1: rows 24-39
    assert bake_cli.main([*preset_argv(rough_png, out), "--band-rows", "16"], encode=stand_in_encoder()) == 0
    assert_same_texture(ref / "varnished_wood.exr", out / "varnished_wood.exr")
    assert listing(out) == ["varnished_wood.exr", "varnished_wood.json"]


def test_a_texture_cut_short_is_baked_again_not_taken_as_up_to_date(rough_png, tmp_path, capsys):
    """Only the sidecar's key and the header's were compared: a texture cut short (a full disk, a copy that
    stopped) with its header whole was skipped as up to date, and failed only when rendered."""
    out, ref = tmp_path / "out", tmp_path / "ref"
    assert bake_cli.main(preset_argv(rough_png, ref), encode=stand_in_encoder()) == 0
    assert bake_cli.main(preset_argv(rough_png, out), encode=stand_in_encoder()) == 0
    exr = out / "varnished_wood.exr"
    whole = exr.read_bytes()
    exr.write_bytes(whole[: len(whole) * 3 // 4])
    assert bake_cli._exr_key(exr) == texture_bits(ref / "varnished_wood.exr")[1]  # its header still reads
    capsys.readouterr()
    assert bake_cli.main(preset_argv(rough_png, out), encode=stand_in_encoder()) == 0
    assert "up to date" not in capsys.readouterr().out
    assert_same_texture(ref / "varnished_wood.exr", exr)
    assert bake_cli.main(preset_argv(rough_png, out), encode=stand_in_encoder()) == 0  # whole again: skipped
    assert "up to date, skipped" in capsys.readouterr().out


def test_a_folder_given_as_a_map_is_said_to_be_a_folder(tmp_path, capsys):
    folder = tmp_path / "maps"
    folder.mkdir()
    argv = ["--preset", "varnished_wood", "--map", f"coatings[0].roughness={folder}", "--out", str(tmp_path / "o")]
    assert bake_cli.main(argv, encode=stand_in_encoder()) == 2
    err = capsys.readouterr().err
    assert "is a folder, not an image" in err and "not found" not in err, err


# --- a .blend's bakes attached to its materials ------------------------------------------------------


@pytest.fixture()
def mapped_blend(bpy_addon, material, tmp_path):
    """A saved .blend whose material "Wood" (varnished wood) has its coat's roughness driven by a PNG beside it."""
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="varnished_wood").finished
    material.name = "Wood"
    s = material.neural_layers
    s.active_index = 1
    assert run_operator(bpy.ops.neural_layers.map_add, parameter="ROUGHNESS").finished
    rough = np.zeros((8, 16))
    rough[:, 8:] = 1.0
    image = bpy.data.images.load(str(write_png(tmp_path / "rough.png", rough)))
    image.colorspace_settings.name = "Non-Color"
    pmap = s.layers[1].maps[0]
    pmap.image, pmap.low, pmap.high = image, 0.2, 0.6
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(app_template="")
    return path


def test_a_blend_bake_attached_to_its_material_is_current_there(mapped_blend, bpy_addon, tmp_path, capsys):
    """A --blend bake never matched the material's own key (the add-on keyed its calibrated bakes uncalibrated) and
    nothing pointed the material at it. ``--attach`` does, and saves the .blend: the material then renders the
    command's texture, its maps' images present or not, and a bake keyed otherwise than the material's settings
    is refused by name."""
    from addon.blender import bake_state

    bpy = bpy_addon
    out = tmp_path / "textures"
    argv = ["--blend", str(mapped_blend), "--out", str(out), "--attach"]
    assert bake_cli.main(argv) == 0, capsys.readouterr()  # the shipped models at the default size, calibrated
    bpy.ops.wm.open_mainfile(filepath=str(mapped_blend))
    mat = bpy.data.materials["Wood"]
    assert mat.neural_layers.texture_path == "//textures/Wood.exr"
    assert tuple(mat.neural_layers.texture_size) == (8, 16)
    path, state, spatial = bake_state.current_texture(mat)
    assert path == str(out / "Wood.exr") and spatial is not None, state
    (tmp_path / "rough.png").unlink()  # the maps left behind: the bake renders, as the add-on's own would
    bpy.ops.wm.open_mainfile(filepath=str(mapped_blend))
    path, state, _ = bake_state.current_texture(bpy.data.materials["Wood"])
    assert path == str(out / "Wood.exr") and "is missing" in state, state
    write_png(tmp_path / "rough.png", np.zeros((8, 16)))
    capsys.readouterr()
    argv = ["--blend", str(mapped_blend), "--out", str(tmp_path / "other"), "--attach", "--no-calibrate"]
    assert bake_cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "--attach: 'Wood': its Model Size and Refine (s) key its bakes" in err, err
    bpy.ops.wm.open_mainfile(filepath=str(mapped_blend))
    assert bpy.data.materials["Wood"].neural_layers.texture_path == "//textures/Wood.exr"  # left as it was
    assert bake_cli.main(["--preset", "varnished_wood", "--out", str(tmp_path / "p"), "--attach"]) == 2
    assert "--attach goes with --blend" in capsys.readouterr().err

"""The batch bake command: outputs, sharding, resuming, and bad input (exit code 2).

Uses a stand-in encoder (a fixed linear map of each texel's parameters) so that the command's
behaviour is tested apart from the networks; the real encoder is tested with the neural runtime.
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
bpy.utils.expose_bundled_modules()
oiio = pytest.importorskip("OpenImageIO")

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bake"))
import bake as bake_cli  # noqa: E402
from addon.core.textures import LatentTexture  # noqa: E402


def encoder():
    proj = np.random.default_rng(3).normal(size=(64, 98))

    def encode(arrays):
        m = arrays.to_matrix()
        v = m @ proj[: m.shape[1]]
        return v[:, :96], v[:, 96:]

    return encode


def write_png(path, array):
    h, w = array.shape[:2]
    c = 1 if array.ndim == 2 else array.shape[2]
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, c, "uint8"))
    out.write_image(np.ascontiguousarray(array, dtype=np.float32).reshape(h, w, c))
    out.close()
    return path


@pytest.fixture()
def rough_png(tmp_path):
    img = np.zeros((40, 24))
    img[10:30, 5:20] = 1.0
    return write_png(tmp_path / "rough.png", img)


def bake(tmp_path, rough_png, *extra, out="out"):
    argv = [
        "--preset",
        "varnished_wood",
        "--map",
        f"coatings[0].roughness={rough_png}:0.05:0.5",
        "--out",
        str(tmp_path / out),
        "--band-rows",
        "8",
        *extra,
    ]
    return bake_cli.main(argv, encode=encoder())


def test_bake_writes_texture_and_sidecar(tmp_path, rough_png):
    assert bake(tmp_path, rough_png) == 0
    out = tmp_path / "out"
    tex = LatentTexture.read_exr(out / "varnished_wood.exr")
    assert (tex.height, tex.width) == (40, 24) and len(tex.levels) == 6
    side = json.loads((out / "varnished_wood.json").read_text())
    assert side["resolution"] == [24, 40] and "coatings[0].roughness" in side["maps"]
    assert sorted(p.name for p in out.iterdir()) == ["varnished_wood.exr", "varnished_wood.json"]
    # two distinct roughness values -> two distinct latents
    assert len(np.unique(tex.levels[0].reshape(-1, 100).round(2), axis=0)) == 2


def test_union_of_shards_equals_the_single_bake_and_resumes(tmp_path, rough_png):
    assert bake(tmp_path, rough_png, out="single") == 0
    assert bake(tmp_path, rough_png, "--shard", "0/3", out="sharded") == 0
    assert not (tmp_path / "sharded" / "varnished_wood.exr").exists()  # bands still missing
    assert bake(tmp_path, rough_png, "--shard", "2/3", out="sharded") == 0
    assert bake(tmp_path, rough_png, "--shard", "1/3", out="sharded") == 0
    a = LatentTexture.read_exr(tmp_path / "single" / "varnished_wood.exr")
    b = LatentTexture.read_exr(tmp_path / "sharded" / "varnished_wood.exr")
    for la, lb in zip(a.levels, b.levels, strict=False):
        assert np.array_equal(la, lb)
    # finished outputs are skipped on a rerun
    mtime = (tmp_path / "single" / "varnished_wood.exr").stat().st_mtime_ns
    assert bake(tmp_path, rough_png, out="single") == 0
    assert (tmp_path / "single" / "varnished_wood.exr").stat().st_mtime_ns == mtime


def test_shards_run_one_after_another_bake_every_material(tmp_path, rough_png):
    """Items are numbered over every material, published or not: numbered over the unpublished ones, shards 1-3
    run after shard 0 had published the first material found their items shifted, and the second was never
    baked (each exited 0 saying "up to date")."""
    out = tmp_path / "out"

    def shard(i):
        args = bake_cli.parse_args(["--preset", "varnished_wood", "--out", str(out), "--shard", f"{i}/4"])
        jobs = bake_cli.preset_job(args)
        jobs.append(bake_cli.Job("gold", bake_cli.SpatialStack(bake_cli.preset("coated_gold")), (1, 1), {}))
        bake_cli.run(jobs, out, encoder(), "tiny", bake_cli.parse_shard(f"{i}/4"), 8, log=lambda *a: None)

    for i in range(4):
        shard(i)
    assert sorted(p.name for p in out.glob("*.exr")) == ["gold.exr", "varnished_wood.exr"]


def test_a_roughness_map_is_linear_in_the_sidebars_roughness(tmp_path):
    """``--map`` takes a roughness's ends as GGX alphas and goes between them as the sidebar's maps do, linearly in
    the artist's roughness (sqrt(alpha)): one image gives one material whichever way it is baked."""
    grey = write_png(tmp_path / "grey.png", np.tile(np.array([0.0, 64.0, 128.0, 191.0, 255.0]) / 255.0, (2, 1)))
    spec = f"coatings[0].roughness={grey}:0.01:0.4"
    args = bake_cli.parse_args(["--preset", "varnished_wood", "--map", spec, "--out", str(tmp_path / "o")])
    alpha = bake_cli.preset_job(args)[0].spatial.maps["coatings[0].roughness"][0].ravel()
    t = np.array([0.0, 64.0, 128.0, 191.0, 255.0]) / 255.0
    assert np.allclose(alpha, (0.1 + (np.sqrt(0.4) - 0.1) * t) ** 2, rtol=1e-6)
    assert alpha[0] == pytest.approx(0.01) and alpha[-1] == pytest.approx(0.4)
    # a field other than a roughness stays linear
    assert np.allclose(bake_cli.map_range("albedo", t, 0.2, 0.6, "--map"), 0.2 + 0.4 * t)


def test_bad_inputs_exit_with_code_2_and_a_clear_message(tmp_path, rough_png, capsys):
    cases = [
        (["--preset", "velvet", "--out", str(tmp_path)], "unknown preset"),
        (
            [
                "--preset",
                "varnished_wood",
                "--map",
                f"coatings[0].roughness={tmp_path / 'nope.png'}",
                "--out",
                str(tmp_path),
            ],
            "not found",
        ),
        (
            ["--preset", "varnished_wood", "--map", f"coatings[3].roughness={rough_png}", "--out", str(tmp_path)],
            "coating",
        ),
        (
            [
                "--preset",
                "varnished_wood",
                "--map",
                f"coatings[0].roughness={rough_png}",
                "--resolution",
                "80",
                "48",
                "--out",
                str(tmp_path),
            ],
            "between 1x1",
        ),
        (["--preset", "varnished_wood", "--shard", "3/3", "--out", str(tmp_path)], "--shard"),
        (
            ["--preset", "varnished_wood", "--map", f"coatings[0].roughness={rough_png}:-0.1:0.4"]
            + ["--out", str(tmp_path)],
            "must not be negative",
        ),
        (["--blend", str(tmp_path / "missing.blend"), "--out", str(tmp_path)], "file not found"),
        (["--out", str(tmp_path)], ""),
    ]
    for argv, message in cases:
        assert bake_cli.main(argv, encode=encoder()) == 2, argv
        assert message in capsys.readouterr().err
    # a grey roughness map saved as RGB (every JPEG) drives it by its luminance, as in the add-on: it was refused
    rgb = write_png(tmp_path / "rgb.png", np.full((40, 24, 3), 0.3))
    assert (
        bake_cli.main(
            ["--preset", "varnished_wood", "--map", f"coatings[0].roughness={rgb}", "--out", str(tmp_path / "rgb")],
            encode=encoder(),
        )
        == 0
    )
    capsys.readouterr()
    small = write_png(tmp_path / "small.png", np.zeros((8, 8)))
    assert (
        bake_cli.main(
            [
                "--preset",
                "varnished_wood",
                "--map",
                f"coatings[0].roughness={rough_png}",
                "--map",
                f"coatings[0].thickness={small}",
                "--out",
                str(tmp_path),
            ],
            encode=encoder(),
        )
        == 2
    )
    assert "share a resolution" in capsys.readouterr().err
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert bake(tmp_path, rough_png, out="file/sub") == 2
    assert "not writable" in capsys.readouterr().err


def test_script_entry_point_reports_bad_input_with_exit_code_2(tmp_path):
    import subprocess

    r = subprocess.run(
        [sys.executable, str(ROOT / "bake" / "bake.py"), "--preset", "velvet", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "unknown preset 'velvet'" in r.stderr


def test_mix_through_a_mask_blends_latents(tmp_path):
    mask = np.zeros((6, 10))
    mask[:, 5:] = 1.0
    mask[:, 4] = 0.5
    m = write_png(tmp_path / "mask.png", mask)
    out = tmp_path / "mix"
    assert (
        bake_cli.main(
            [
                "--preset",
                "coated_gold",
                "--mix",
                "frosted_copper",
                "--mask",
                str(m),
                "--out",
                str(out),
                "--band-rows",
                "4",
            ],
            encode=encoder(),
        )
        == 0
    )
    tex = LatentTexture.read_exr(out / "coated_gold.exr").levels[0]
    left, right, mid = tex[0, 0], tex[0, -1], tex[0, 4]
    assert not np.allclose(left, right)
    assert np.allclose(mid, 0.5 * (left + right), atol=0.02)  # half-float texels, mask 0.5 -> 128/255
    assert (
        bake_cli.main(["--preset", "coated_gold", "--mix", "frosted_copper", "--out", str(out)], encode=encoder()) == 2
    )


def test_the_real_encoders_textures_carry_their_calibration_and_no_calibrate_leaves_it_out(tmp_path, rough_png):
    """With the shipped networks (no stand-in), an assembled texture stores its albedo calibration, one table
    per cluster of texels; ``--no-calibrate`` bakes the same texels without one, keyed apart."""
    from addon.core.textures.calibration import TextureCalibration

    argv = ["--preset", "varnished_wood", "--map", f"coatings[0].roughness={rough_png}:0.05:0.5", "--model", "tiny"]
    assert bake_cli.main([*argv, "--out", str(tmp_path / "cal")]) == 0
    tex = LatentTexture.read_exr(tmp_path / "cal" / "varnished_wood.exr")
    calibration = TextureCalibration.from_text(tex.metadata["calibration"])
    assert len(calibration.tables) == 2 and calibration.is_current()  # two roughness values, two clusters
    side = json.loads((tmp_path / "cal" / "varnished_wood.json").read_text())
    assert side["seconds_calibration"] > 0
    assert bake_cli.main([*argv, "--no-calibrate", "--out", str(tmp_path / "cal")]) == 0  # not "up to date"
    plain = LatentTexture.read_exr(tmp_path / "cal" / "varnished_wood.exr")
    assert "calibration" not in plain.metadata and plain.metadata["key"] != tex.metadata["key"]
    np.testing.assert_array_equal(plain.levels[0], tex.levels[0])

"""The bake command reads driving images by one colour-space rule, the one the add-on follows:
an sRGB byte image driving albedo is decoded to linear (byte 128 -> 0.216, as in Blender and
Cycles), the same image driving roughness reads raw (0.502); ``@SPACE`` overrides the rule."""

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


def write(path, value, fmt="uint8", channels=3):
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(4, 2, channels, fmt))
    out.write_image(np.full((2, 4, channels), value, np.float32))
    out.close()
    return path


def driving(tmp_path, *maps):
    args = bake_cli.parse_args(
        ["--preset", "varnished_wood", *[a for m in maps for a in ("--map", m)], "--out", str(tmp_path / "out")]
    )
    return bake_cli.preset_job(args)[0].spatial.maps


def test_srgb_byte_albedo_is_linearised_as_in_the_addon_and_roughness_reads_raw(tmp_path):
    png = write(tmp_path / "grey.png", 128 / 255)
    one = write(tmp_path / "one.png", 128 / 255, channels=1)  # the same byte, one channel for a scalar field
    maps = driving(tmp_path, f"base.albedo={png}", f"coatings[0].roughness={one}")
    np.testing.assert_allclose(maps["base.albedo"], 0.2158605, atol=1e-6)
    # the image's raw 0.502 as the sidebar's roughness (from 0 to 1): alpha its square (``bake.map_range``)
    np.testing.assert_allclose(maps["coatings[0].roughness"][..., 0], (128 / 255) ** 2, atol=1e-6)
    from addon.blender import images

    image = bpy.data.images.load(str(png))  # Blender's default for a byte PNG: sRGB
    assert image.colorspace_settings.name == "sRGB"
    np.testing.assert_allclose(images.linear_pixels(image)[..., :3], maps["base.albedo"], atol=1e-4)


def test_float_and_linear_tagged_albedo_read_raw_and_the_override_wins(tmp_path):
    exr = write(tmp_path / "grey.exr", 0.5, "float")
    png = write(tmp_path / "grey.png", 128 / 255)
    spec = oiio.ImageSpec(4, 2, 3, "uint8")
    spec.attribute("oiio:ColorSpace", "linear")
    tagged = tmp_path / "tagged.png"
    out = oiio.ImageOutput.create(str(tagged))
    out.open(str(tagged), spec)
    out.write_image(np.full((2, 4, 3), 128 / 255, np.float32))
    out.close()
    np.testing.assert_allclose(driving(tmp_path, f"base.albedo={exr}")["base.albedo"], 0.5)
    np.testing.assert_allclose(driving(tmp_path, f"base.albedo={tagged}")["base.albedo"], 128 / 255, atol=1e-6)
    np.testing.assert_allclose(driving(tmp_path, f"base.albedo={png}@linear")["base.albedo"], 128 / 255, atol=1e-6)
    np.testing.assert_allclose(
        driving(tmp_path, f"base.albedo={png}@Non-Color:0:0.5")["base.albedo"], 0.5 * 128 / 255, atol=1e-6
    )
    one = write(tmp_path / "one.png", 128 / 255, channels=1)
    rough = driving(tmp_path, f"coatings[0].roughness={one}@srgb")["coatings[0].roughness"]
    np.testing.assert_allclose(rough[..., 0], 0.2158605**2, atol=1e-6)  # decoded from sRGB, then squared


def test_an_unknown_colour_space_exits_2_with_one_line(tmp_path, capsys):
    png = write(tmp_path / "grey.png", 0.5)
    for argv in (["--map", f"base.albedo={png}@rec2020"], ["--mix", "frosted_copper", "--mask", f"{png}@rec2020"]):
        assert bake_cli.main(["--preset", "varnished_wood", *argv, "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "unknown colour space 'rec2020'" in err and "srgb" in err, err

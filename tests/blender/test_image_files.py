"""Images the add-on writes (Render Preview's PNG and EXR) are written without Pillow, which Blender
does not ship, and read back as the values they were given."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from addon.core.render.film import from_srgb, to_srgb, write_exr, write_png
from addon.core.textures.latent_texture import read_image


@pytest.fixture()
def no_pillow(monkeypatch):
    """Make ``import PIL`` fail, as in Blender's Python."""
    for name in [n for n in sys.modules if n == "PIL" or n.startswith("PIL.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "PIL", None)


def test_png_is_written_without_pillow_as_8_bit_srgb(tmp_path, no_pillow):
    rng = np.random.default_rng(1)
    linear = rng.uniform(0.0, 1.0, (12, 20, 3))
    write_png(tmp_path / "a.png", linear)
    back = read_image(tmp_path / "a.png")
    assert back.shape == (12, 20, 3)
    expected = np.round(to_srgb(linear) * 255) / 255
    np.testing.assert_allclose(back, expected, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(from_srgb(back), linear, atol=0.02)
    assert not list(tmp_path.glob("*partial*"))


def test_exr_round_trips_float_values(tmp_path, no_pillow):
    rgba = np.random.default_rng(2).uniform(0.0, 40.0, (9, 7, 4)).astype(np.float32)
    write_exr(tmp_path / "a.exr", rgba)
    np.testing.assert_allclose(read_image(tmp_path / "a.exr"), rgba, rtol=1e-6)


def test_unwritable_path_raises_with_the_path(tmp_path):
    (tmp_path / "a file").write_text("")
    with pytest.raises(RuntimeError, match="cannot write .*cannot make its folder"):
        write_png(tmp_path / "a file" / "a.png", np.zeros((2, 2, 3)))


def test_a_folder_not_there_yet_is_made(tmp_path):
    """As F12 makes its output's folder (Render Preview into "//renders/" failed, with an empty reason)."""
    write_png(tmp_path / "new" / "deeper" / "a.png", np.zeros((2, 2, 3)))
    assert (tmp_path / "new" / "deeper" / "a.png").is_file()


def test_writing_to_a_folder_name_refuses_up_front_and_leaves_nothing(tmp_path):
    folder = tmp_path / "renders"
    folder.mkdir()
    for write, name in ((write_exr, "EXR"), (write_png, "PNG")):
        with pytest.raises(IsADirectoryError, match="it is a folder"):
            write(folder, np.ones((3, 4, 3), dtype=np.float32))
        assert sorted(p.name for p in tmp_path.iterdir()) == ["renders"], name
        assert not list(folder.iterdir()), name


class _FailingOutput:
    """An OpenImageIO output that writes the image, then is interrupted before it returns."""

    def __init__(self, real):
        self.real = real

    def open(self, *args):
        return self.real.open(*args)

    def write_image(self, pixels):
        self.real.write_image(pixels)
        raise KeyboardInterrupt("interrupted mid-write")

    def close(self):
        return self.real.close()

    def geterror(self):
        return self.real.geterror()


@pytest.mark.parametrize("write, suffix", [(write_exr, ".exr"), (write_png, ".png")])
def test_an_interrupted_write_leaves_the_previous_file_and_no_temporary(tmp_path, monkeypatch, write, suffix):
    import types

    from addon.core.textures import latent_texture

    path = tmp_path / f"frame{suffix}"
    before = np.full((5, 6, 3), 0.25, dtype=np.float32)
    write(path, before)
    real = latent_texture.oiio_module()
    created = []

    def create(name):
        created.append(name)
        return _FailingOutput(real.ImageOutput.create(name))

    fake = types.SimpleNamespace(
        ImageSpec=real.ImageSpec,
        ImageOutput=types.SimpleNamespace(create=create),
        FLOAT=real.FLOAT,
        UINT8=real.UINT8,
        geterror=real.geterror,
    )
    monkeypatch.setattr(latent_texture, "oiio_module", lambda: fake)
    with pytest.raises(KeyboardInterrupt):
        write(path, np.full((5, 6, 3), 0.75, dtype=np.float32))
    monkeypatch.undo()
    assert created and created[0] != str(path)  # it wrote under a temporary name ...
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # ... and removed it
    expected = before if suffix == ".exr" else np.round(to_srgb(before) * 255) / 255
    np.testing.assert_allclose(read_image(path), expected, atol=1e-6)  # the previous file, round-tripped


def test_an_image_with_transparency_is_read_as_stored_not_multiplied_by_its_alpha(tmp_path):
    """A parameter map or mask with alpha below 1 (PNG keeps colour and alpha apart): its colour is read as stored,
    as Blender reads it, where OpenImageIO multiplied it by the alpha (0.502 stored, 0.126 read at alpha 1/4)."""
    from addon.core.textures.latent_texture import oiio_module

    oiio = oiio_module()
    path = tmp_path / "map.png"
    pixels = np.zeros((2, 2, 4), np.float32)
    pixels[..., :3] = 128 / 255
    pixels[0, :, 3], pixels[1, :, 3] = 1.0, 0.25
    spec = oiio.ImageSpec(2, 2, 4, "uint8")
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    out.write_image(pixels)
    out.close()
    read = read_image(path)
    np.testing.assert_allclose(read[..., :3], 128 / 255, atol=1e-6)
    np.testing.assert_allclose(read[:, 0, 3], [1.0, 64 / 255], atol=1e-6)

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
    with pytest.raises(RuntimeError, match="cannot write"):
        write_png(tmp_path / "missing folder" / "a.png", np.zeros((2, 2, 3)))

"""Latent-texture files that are not what they claim: read fails with one clear, typed error
(``LatentTextureError``, a ``ValueError``) so a renderer can fall back; writes never leave a
half-written or out-of-range file."""

import numpy as np
import pytest

from addon.core.textures import CHANNEL_NAMES, LatentTexture, LatentTextureError, files


@pytest.fixture(scope="module")
def oiio():
    from addon.core.textures.latent_texture import oiio_module

    return oiio_module()


def raw_latent_exr(oiio, path, levels):
    """An EXR holding ``levels`` as they are (no checks), like a damaged or foreign writer; the channels are
    named as a latent texture's first ones (all of them for 100 channels, 98: a file from before the top coat)."""
    out = oiio.ImageOutput.create(str(path))
    for i, level in enumerate(levels):
        spec = oiio.ImageSpec(level.shape[1], level.shape[0], level.shape[2], "half")
        spec.channelnames = tuple(CHANNEL_NAMES[: level.shape[2]])
        if len(levels) > 1:
            spec.tile_width = spec.tile_height = 64
            if i == 0:
                spec.attribute("textureformat", "Plain Texture")
                spec.attribute("openexr:levelmode", 1)
                spec.attribute("openexr:roundingmode", 0)
        assert out.open(str(path), spec, "Create" if i == 0 else "AppendMIPLevel")
        assert out.write_image(np.ascontiguousarray(level, dtype=np.float32))
    out.close()
    return path


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_texture_fails_at_read_naming_level_texel_and_channel(tmp_path, oiio, bad):
    levels = LatentTexture.from_texels(np.zeros((4, 6, 100), np.float32)).levels
    levels[1] = levels[1].copy()
    levels[1][1, 2, 97] = bad
    path = raw_latent_exr(oiio, tmp_path / "bad.exr", levels)
    with pytest.raises(LatentTextureError, match=r"non-finite value\(s\) in mip level 1.*\(x=2, y=1\).*proxy\.w"):
        LatentTexture.read_exr(path)


def test_a_nan_filled_texture_is_refused(tmp_path, oiio):
    levels = [
        np.full(lvl.shape, np.nan, np.float32)
        for lvl in LatentTexture.from_texels(np.zeros((8, 8, 100), np.float32)).levels
    ]
    with pytest.raises(ValueError, match="latent texels must be finite"):
        LatentTexture.read_exr(raw_latent_exr(oiio, tmp_path / "nan.exr", levels))


def test_a_mip_chain_that_stops_early_is_refused(tmp_path, oiio):
    path = raw_latent_exr(oiio, tmp_path / "flat.exr", [np.zeros((4, 4, 100), np.float32)])
    with pytest.raises(LatentTextureError, match="stops at 4x4"):
        LatentTexture.read_exr(path)


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9])
def test_a_truncated_texture_is_refused(tmp_path, keep):
    path = tmp_path / "t.exr"
    rng = np.random.default_rng(0)
    LatentTexture.from_texels(rng.normal(size=(70, 50, 100)).astype(np.float32)).write_exr(path)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(LatentTextureError, match=str(path)):
        LatentTexture.read_exr(path)


def test_values_a_half_float_cannot_hold_are_refused_at_write(tmp_path):
    texels = np.zeros((2, 2, 100), np.float32)
    texels[1, 1, 5] = 1e5  # would be stored as inf
    with pytest.raises(ValueError, match="half-float range"):
        LatentTexture.from_texels(texels).write_exr(tmp_path / "big.exr")
    assert list(tmp_path.iterdir()) == []


def test_publishing_removes_its_temporary_file_on_failure_and_renames_on_success(tmp_path):
    target = tmp_path / "a.json"
    with pytest.raises(RuntimeError):
        with files.publishing(target) as tmp:
            tmp.write_text("half")
            assert files.is_temp(tmp) and tmp.parent == tmp_path
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []
    files.write_bytes(target, b"{}")
    assert target.read_bytes() == b"{}" and list(tmp_path.iterdir()) == [target]
    a, b = files.temp_path(target), files.temp_path(target)
    assert a != b and a.suffix == ".json"  # unique per call; the suffix kept for writers that go by it


def test_safe_file_names_keep_plain_names_and_separate_the_rest():
    assert files.safe_file_name("Wood") == "Wood"
    assert files.safe_file_name("Lack (glänzend)") == "Lack (glänzend)"
    a, b = files.safe_file_name("a/b"), files.safe_file_name("a_b")
    assert a != b and a.startswith("a_b-") and b == "a_b"
    assert files.safe_file_name("").startswith("unnamed-")
    with pytest.raises(TypeError, match="must be a string"):
        files.safe_file_name(None)


def test_a_texture_is_read_band_by_band_as_at_once(monkeypatch, tmp_path, oiio):
    """A level is read in bands of whole tiles (only a band is held besides the texture): the same texels as one
    band, a non-finite texel in a later band named at its row, and an untiled (scanline) file read too."""
    from addon.core.textures import latent_texture

    rng = np.random.default_rng(4)
    texels = rng.normal(size=(150, 20, 100)).astype(np.float32)
    path = tmp_path / "tall.exr"
    LatentTexture.from_texels(texels).write_exr(path)
    whole = LatentTexture.read_exr(path)
    monkeypatch.setattr(latent_texture, "READ_BAND_BYTES", 1)  # one row of 64-texel tiles per band: 3 bands
    banded = LatentTexture.read_exr(path)
    for a, b in zip(whole.levels, banded.levels, strict=True):
        np.testing.assert_array_equal(a.view(np.uint16), b.view(np.uint16))
    np.testing.assert_array_equal(banded.levels[0], texels.astype(np.float16))

    levels = [np.asarray(level, np.float32) for level in banded.levels]
    levels[0][130, 3, 97] = np.nan
    bad = raw_latent_exr(oiio, tmp_path / "bad.exr", levels)
    with pytest.raises(LatentTextureError, match=r"in mip level 0.*\(x=3, y=130\).*proxy\.w"):
        LatentTexture.read_exr(bad)

    one = raw_latent_exr(oiio, tmp_path / "one.exr", [np.full((1, 1, 100), 0.25, np.float32)])  # untiled
    assert oiio.ImageInput.open(str(one)).spec().tile_width == 0
    np.testing.assert_array_equal(LatentTexture.read_exr(one).levels[0], np.full((1, 1, 100), 0.25, np.float16))


def test_a_latent_texture_is_whole_and_closed_when_it_is_renamed_into_place(tmp_path, monkeypatch):
    """A writer of several mip levels finishes its file only when it is destroyed: ``write_exr`` flushed and renamed
    the temporary file while the writer still held it open and short (1,007,616 of 1,009,501 bytes at 64 x 64), so a
    kill right after a bake, or another process reading it, met a truncated texture under its final name."""
    import contextlib
    import os

    from addon.core.textures.latent_texture import LatentTexture

    seen = {}
    real_replace = os.replace

    def replace(src, dst):
        fds = []
        for fd in os.listdir("/proc/self/fd"):
            with contextlib.suppress(OSError):  # the listing's own descriptor is gone by now
                fds.append(os.readlink(f"/proc/self/fd/{fd}"))
        seen["size"], seen["open"] = os.path.getsize(src), any(str(src) in f for f in fds)
        return real_replace(src, dst)

    monkeypatch.setattr(files.os, "replace", replace)
    rng = np.random.default_rng(0)
    texture = LatentTexture.from_texels(rng.normal(size=(64, 64, 100)).astype(np.float32), {"model": "tiny"})
    path = tmp_path / "whole.exr"
    texture.write_exr(path)
    assert seen == {"size": os.path.getsize(path), "open": False}

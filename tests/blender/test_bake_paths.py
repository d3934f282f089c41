"""Where the sidebar's bake writes its latent texture, and that it never writes over another file's or material's bake.

Every new .blend file's material is called "Material", and the Bake Folder was ``//textures/`` for every file: two
files in one folder baked to the same ``textures/Material.exr``, the second over the first's, and the first then
rendered its constant stack with a warning that named neither file. A Bake Folder typed without "//" was resolved
against Blender's working folder, wherever Blender was started.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from tests.blender.helpers import run_operator
from tests.blender.test_bake_addon import stand_in_encoder

ops = pytest.importorskip("bpy").ops.neural_layers


@pytest.fixture()
def bake(bpy_addon, monkeypatch):
    """``bake(path, preset, folder=None)``: a new file saved at ``path`` whose material "Material" is ``preset`` with
    Bake Folder ``folder`` (None: the default), baked and saved; returns the material."""
    from addon.blender import bake_ops

    monkeypatch.setattr(bake_ops, "neural_encoder", stand_in_encoder)
    bpy = bpy_addon

    def made(path, preset, folder=None):
        bpy.ops.wm.read_homefile(app_template="")
        assert run_operator(ops.preset_apply, preset=preset).finished
        mat = bpy.data.materials["Material"]
        if folder is not None:
            mat.neural_layers.bake_directory = folder
        bpy.ops.wm.save_as_mainfile(filepath=str(path))
        r = run_operator(ops.bake_texture)
        assert r.finished, r.error
        bpy.ops.wm.save_mainfile()
        return mat

    return made


def _rendered(bpy, path):
    """``(texture used, warnings, the texture's file)`` of "Material" of the .blend file at ``path``, opened."""
    from addon.blender import scene_export

    bpy.ops.wm.open_mainfile(filepath=str(path))
    mat = bpy.data.materials["Material"]
    warnings = []
    spec = scene_export.export_material(mat, warnings)
    return spec.latent_texture is not None, warnings, Path(bpy.path.abspath(mat.neural_layers.texture_path))


def _info(capfd):
    return [line for line in capfd.readouterr().out.splitlines() if line.startswith("Info: ")]


def test_two_files_in_one_folder_bake_into_a_folder_each(bake, bpy_addon, tmp_path):
    """The default Bake Folder is one folder per .blend file: ``//textures/<file name>/``."""
    bake(tmp_path / "shot01.blend", "varnished_wood")
    bake(tmp_path / "shot02.blend", "coated_gold")
    assert sorted(str(p.relative_to(tmp_path)) for p in (tmp_path / "textures").rglob("*.exr")) == [
        os.path.join("textures", "shot01", "Material.exr"),
        os.path.join("textures", "shot02", "Material.exr"),
    ]
    for shot in ("shot01", "shot02"):
        used, warnings, texture = _rendered(bpy_addon, tmp_path / f"{shot}.blend")
        assert used and not warnings and texture == tmp_path / "textures" / shot / "Material.exr"
        assert bpy_addon.data.materials["Material"].neural_layers.texture_path == f"//textures/{shot}/Material.exr"


def test_a_bake_keeps_another_files_bake_in_a_shared_folder_and_says_so(bake, bpy_addon, tmp_path, capfd):
    """Two files whose Bake Folder is one folder: the second's bake takes "Material (2).exr" and says why; each
    file's header records the .blend file and material that baked it, and baking again writes over its own file."""
    from addon.blender import bake_state

    bake(tmp_path / "shot01.blend", "varnished_wood", "//shared/")
    capfd.readouterr()
    bake(tmp_path / "shot02.blend", "coated_gold", "//shared/")
    assert any(
        "Material.exr holds the bake of material 'Material' in shot01.blend" in line and "Material (2).exr" in line
        for line in _info(capfd)
    )
    first, second = tmp_path / "shared" / "Material.exr", tmp_path / "shared" / "Material (2).exr"
    for path, blend in ((first, "shot01.blend"), (second, "shot02.blend")):
        header = bake_state.texture_header(str(path))
        assert (header["blend"], header["material"]) == (blend, "Material")

    for shot, path in (("shot01", first), ("shot02", second)):
        used, warnings, texture = _rendered(bpy_addon, tmp_path / f"{shot}.blend")
        assert used and not warnings and texture == path
        before = path.stat().st_mtime_ns
        bpy_addon.data.materials["Material"].neural_layers.layers[1].thickness = 0.7  # a new bake of its own
        capfd.readouterr()
        assert run_operator(ops.bake_texture).finished
        lines = _info(capfd)
        assert not any("holds" in line for line in lines), lines
        assert path.stat().st_mtime_ns != before
        assert bake_state.baked_texture_state(bpy_addon.data.materials["Material"])[0] == str(path)
    assert sorted(p.name for p in (tmp_path / "shared").glob("*.exr")) == ["Material (2).exr", "Material.exr"]


def test_a_file_that_is_not_a_latent_texture_is_kept(bake, bpy_addon, tmp_path, capfd):
    (tmp_path / "shared").mkdir()
    mine = tmp_path / "shared" / "Material.exr"
    mine.write_bytes(b"an image of the user's, not a bake")
    mat = bake(tmp_path / "shot01.blend", "varnished_wood", "//shared/")
    assert mine.read_bytes() == b"an image of the user's, not a bake"
    assert mat.neural_layers.texture_path == "//shared/Material (2).exr"
    assert any("Material.exr holds a file that is not a latent texture" in line for line in _info(capfd))


def test_the_warning_for_a_file_holding_another_bake_names_the_file_that_baked_it(bake, bpy_addon, tmp_path):
    bake(tmp_path / "shot01.blend", "varnished_wood")
    bake(tmp_path / "shot02.blend", "coated_gold")
    ours = tmp_path / "textures" / "shot01" / "Material.exr"
    shutil.copyfile(tmp_path / "textures" / "shot02" / "Material.exr", ours)  # as a file manager copies it over
    used, warnings, _ = _rendered(bpy_addon, tmp_path / "shot01.blend")
    assert not used
    assert any(
        str(ours) in w and "holds another bake (of material 'Material' in shot02.blend)" in w for w in warnings
    ), warnings


def test_a_texture_baked_before_files_were_recorded_keeps_rendering_and_a_new_bake_goes_beside_it(
    bake, bpy_addon, tmp_path, capfd
):
    """A .blend file saved by an earlier version: its material points at ``//textures/Material.exr``, whose header
    records no .blend file. It renders as it did; a new bake goes to the file's own folder and keeps it."""
    from addon.core.textures import LatentTexture

    bpy = bpy_addon
    bake(tmp_path / "old.blend", "varnished_wood")
    old = tmp_path / "textures" / "Material.exr"
    texture = LatentTexture.read_exr(str(tmp_path / "textures" / "old" / "Material.exr"))
    del texture.metadata["blend"]
    texture.write_exr(str(old))  # as an earlier version wrote it
    shutil.rmtree(tmp_path / "textures" / "old")
    mat = bpy.data.materials["Material"]
    mat.neural_layers.texture_path, mat.neural_layers.texture_file = "//textures/Material.exr", str(old)
    bpy.ops.wm.save_mainfile()

    used, warnings, texture_file = _rendered(bpy, tmp_path / "old.blend")
    assert used and not warnings and texture_file == old
    kept = old.read_bytes()
    assert run_operator(ops.bake_texture).finished
    assert bpy.data.materials["Material"].neural_layers.texture_path == "//textures/old/Material.exr"
    assert old.read_bytes() == kept

    # its Bake Folder set to the old one: the material's own bake (it renders it, the key is its): written over
    bpy.data.materials["Material"].neural_layers.texture_path = "//textures/Material.exr"
    bpy.data.materials["Material"].neural_layers.bake_directory = "//textures/."
    capfd.readouterr()
    assert run_operator(ops.bake_texture).finished
    assert bpy.data.materials["Material"].neural_layers.texture_path == "//textures/Material.exr"
    assert old.read_bytes() != kept and not any("holds" in line for line in _info(capfd))


def test_a_bake_folder_without_double_slash_is_relative_to_the_blend_file(bpy_addon, material, tmp_path, monkeypatch):
    """ "rel_textures/" is the folder beside the .blend file, as "//rel_textures/" is (it was Blender's working
    folder's); an unsaved file refuses it as it refuses "//"."""
    from addon.blender import bake_ops

    monkeypatch.setattr(bake_ops, "neural_encoder", stand_in_encoder)
    bpy = bpy_addon
    elsewhere = tmp_path / "started_here"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert run_operator(ops.preset_apply, preset="varnished_wood").finished
    material.neural_layers.bake_directory = "rel_textures/"
    r = run_operator(ops.bake_texture)
    assert not r.finished and "'rel_textures/' is relative to the .blend file" in r.error and "save the file" in r.error
    (tmp_path / "project").mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "project" / "scene.blend"))
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    assert material.neural_layers.texture_path == "//rel_textures/Material.exr"
    assert (tmp_path / "project" / "rel_textures" / "Material.exr").is_file()
    assert list(elsewhere.iterdir()) == []

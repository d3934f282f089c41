"""Baking from the add-on: parameter maps on layers, the bake operator, and the renderer using
the baked texture while it is current. The networks are replaced by a stand-in encoder (a fixed
linear map of each texel's parameters) except in the last test, which uses the shipped models."""

from pathlib import Path

import numpy as np
import pytest

from tests.blender.helpers import run_operator

ops = pytest.importorskip("bpy").ops.neural_layers


def stand_in_encoder(size, threads=2, refine_s=0.0, refine_cache=None):
    proj = np.random.default_rng(5).normal(size=(64, 98)) * 0.1

    def encode(arrays):
        v = arrays.to_matrix() @ proj[: arrays.to_matrix().shape[1]]
        return v[:, :96].reshape(-1, 3, 32), v[:, 96:]

    return encode


@pytest.fixture()
def wood(bpy_addon, material, tmp_path, monkeypatch):
    """The cube's material as varnished wood whose coat roughness is driven by a 16 x 8 image."""
    from addon.blender import bake_ops

    monkeypatch.setattr(bake_ops, "neural_encoder", stand_in_encoder)
    bpy = bpy_addon
    assert run_operator(ops.preset_apply, preset="varnished_wood").finished
    s = material.neural_layers
    s.active_index = 1  # the coating
    assert run_operator(ops.map_add, parameter="ROUGHNESS").finished
    img = bpy.data.images.new("rough", width=16, height=8, float_buffer=True)
    px = np.zeros((8, 16, 4), np.float32)
    px[:, 8:, :] = 1.0  # right half rough
    img.pixels.foreach_set(px.ravel())
    pmap = s.layers[1].maps[0]
    pmap.image, pmap.low, pmap.high = img, 0.1, 0.6
    s.bake_directory = str(tmp_path)
    return material


def test_maps_become_a_spatial_stack_in_core_units(wood):
    from addon.blender.bake_inputs import spatial_stack_from_material

    spatial, sources = spatial_stack_from_material(wood)
    rough = spatial.maps["coatings[0].roughness"][..., 0]
    assert rough.shape == (8, 16)
    assert np.allclose(rough[:, :8], 0.1**2) and np.allclose(rough[:, 8:], 0.6**2)  # artist roughness -> alpha
    assert sources == {"coatings[0].roughness": "rough [0.1, 0.6]"}


def test_map_on_a_parameter_the_layer_lacks_is_reported(wood):
    wood.neural_layers.active_index = 0  # the diffuse base
    # The menu offers what the layer has (a map of any other parameter failed only at the bake); a script's value
    # outside it is refused.
    with pytest.raises(TypeError, match="THICKNESS"):
        ops.map_add(parameter="THICKNESS")
    with pytest.raises(TypeError, match="THICKNESS"):  # the material named: its active layer's parameters
        ops.map_add(parameter="THICKNESS", material=wood.name)
    base = wood.neural_layers.layers[0]
    assert len(base.maps) == 0
    pmap = base.maps.add()  # set from Python, past the operator: the bake still says it
    pmap.parameter, pmap.image = "THICKNESS", wood.neural_layers.layers[1].maps[0].image
    r = run_operator(ops.bake_texture)
    assert r.error and "has no thickness" in r.error


def test_the_map_menu_offers_each_layers_own_parameters_and_a_diffuse_base_shows_its_maps(wood):
    """A diffuse base had no Add Parameter Map (its box returned before the maps), and a coating's menu offered an
    Albedo map that failed at the bake: each layer now offers the parameters it has, a diffuse base its albedo."""
    from types import SimpleNamespace

    import bpy

    from addon.blender import bake_ops, ui

    s = wood.neural_layers
    offered = {}
    for index in range(len(s.layers)):
        s.active_index = index
        items = bake_ops._map_parameter_items(SimpleNamespace(material=""), bpy.context)
        offered[s.layers[index].layer_type] = [item[0] for item in items]
    assert offered == {"DIFFUSE": ["ALBEDO"], "COATING": ["ROUGHNESS", "IOR", "MEDIUM_ALBEDO", "THICKNESS"]}

    class Layout:  # records what the layer's box draws
        def __init__(self):
            self.calls = []

        def __getattr__(self, name):
            def call(*args, **kwargs):
                self.calls.append((name, args))
                return self

            return call

        def __setattr__(self, name, value):
            if name == "calls":
                object.__setattr__(self, name, value)

    layout = Layout()
    ui._draw_layer(layout, s.layers[0])
    assert ("operator_menu_enum", ("neural_layers.map_add", "parameter")) in layout.calls
    s.active_index = 0
    assert run_operator(ops.map_add, parameter="ALBEDO").finished and len(s.layers[0].maps) == 1


def test_bake_writes_the_texture_and_the_renderer_uses_it_while_current(wood, bpy_addon):
    from addon.blender import bake_ops, scene_export

    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    path, state = bake_ops.baked_texture_state(wood)
    assert path is not None and path.endswith(".exr"), state
    warnings = []
    spec = scene_export.export_material(wood, warnings)
    assert spec.latent_texture is not None and not warnings
    assert (spec.latent_texture.height, spec.latent_texture.width) == (8, 16)
    # reference mode shades the same spatially varying stack, texel by texel (the maps the bake read)
    from addon.core.render.materials import ReferenceLayered, resolve

    assert spec.spatial is not None and spec.spatial.stack == spec.stack
    np.testing.assert_allclose(spec.spatial.maps["coatings[0].roughness"][0, [0, 15], 0], [0.1**2, 0.6**2], rtol=1e-5)
    assert (
        isinstance(resolve(spec, "reference"), ReferenceLayered) and resolve(spec, "reference").spatial is spec.spatial
    )
    # editing the stack makes the texture stale: the renderer warns and uses the constant stack
    wood.neural_layers.layers[1].thickness = 1.0
    assert bake_ops.baked_texture_state(wood)[0] is None
    spec = scene_export.export_material(wood, warnings)
    assert spec.latent_texture is None and any("out of date" in w for w in warnings)
    assert run_operator(ops.texture_clear).finished and wood.neural_layers.texture_path == ""


def test_a_bake_keeps_the_file_a_renamed_material_renders_and_a_file_holding_another_bake_is_not_rendered(
    wood, bpy_addon, capfd
):
    """A renamed material and a new one of its old name bake to the same file name: the second's bake went over the
    first's file, whose key still matched its own inputs, so the first rendered the other's texture. The second now
    bakes beside it ("Material (2).exr") and says so, and each renders its own. A file that holds another bake all
    the same (copied over it) is not rendered, and the warning says whose bake it holds."""
    import shutil

    from addon.blender import scene_export

    bpy = bpy_addon
    assert run_operator(ops.bake_texture).finished
    wood.name = "Oak"
    other = bpy.data.materials.new("Material")
    other.neural_layers.bake_directory = wood.neural_layers.bake_directory
    bpy.context.view_layer.objects.active.active_material = other
    assert run_operator(ops.preset_apply, preset="coated_gold").finished
    capfd.readouterr()
    assert run_operator(ops.bake_texture).finished
    oak, gold = (Path(bpy.path.abspath(m.neural_layers.texture_path)) for m in (wood, other))
    assert (oak.name, gold.name) == ("Material.exr", "Material (2).exr") and oak.parent == gold.parent
    assert any(
        "Material.exr holds the bake that material 'Oak' of this file renders" in line and "Material (2).exr" in line
        for line in capfd.readouterr().out.splitlines()
    )
    for mat in (wood, other):
        warnings = []
        assert scene_export.export_material(mat, warnings).latent_texture is not None and not warnings

    shutil.copyfile(gold, oak)  # the other's bake over Oak's file, as a file manager copies it
    warnings = []
    spec = scene_export.export_material(wood, warnings)
    assert spec.latent_texture is None and any("holds another bake" in w and "'Material'" in w for w in warnings)


def _evaluated_spec(bpy):
    """The cube's material as the viewport and the render operators export it: from the evaluated depsgraph."""
    from addon.blender import scene_export

    bpy.context.view_layer.update()
    scene, warnings = scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), 8, 8)
    return scene.materials[0], warnings


def test_the_evaluated_depsgraph_sees_a_bake_and_a_clear(wood, bpy_addon):
    """The bake sets the material's texture path and key from Python, which alone does not reach the evaluated
    copies: the viewport kept rendering the constant stack after a bake until another edit."""
    assert _evaluated_spec(bpy_addon)[0].latent_texture is None
    assert run_operator(ops.bake_texture).finished
    spec, warnings = _evaluated_spec(bpy_addon)
    assert spec.latent_texture is not None and not warnings
    assert run_operator(ops.texture_clear).finished
    assert _evaluated_spec(bpy_addon)[0].latent_texture is None


def test_a_texture_is_read_once_per_version_of_its_file(wood, bpy_addon, monkeypatch):
    """The viewport exports the scene at every edit and view change; a 1024 x 1024 texture takes seconds to read,
    so the export reads each file once, again when the file changes, and lets go of it once unused."""
    from addon.blender import scene_export
    from addon.core.textures import LatentTexture

    reads = []
    real = LatentTexture.read_exr.__func__

    def counting(cls, path):
        reads.append(path)
        return real(cls, path)

    monkeypatch.setattr(LatentTexture, "read_exr", classmethod(counting))
    assert run_operator(ops.bake_texture).finished
    first = _evaluated_spec(bpy_addon)[0].latent_texture
    assert _evaluated_spec(bpy_addon)[0].latent_texture is first and len(reads) == 1
    wood.neural_layers.layers[1].maps[0].high = 0.7  # new maps: the bake writes a new file in place
    assert run_operator(ops.bake_texture).finished
    second = _evaluated_spec(bpy_addon)[0].latent_texture
    assert second is not first and len(reads) == 2
    assert list(scene_export._TEXTURES) == [reads[-1]]
    assert run_operator(ops.texture_clear).finished
    _evaluated_spec(bpy_addon)
    assert scene_export._TEXTURES == {}
    assert run_operator(ops.bake_texture).finished and _evaluated_spec(bpy_addon)[0].latent_texture is not None
    assert scene_export._TEXTURES
    bpy_addon.ops.wm.read_homefile(app_template="")  # another file: its exports start afresh
    assert scene_export._TEXTURES == {}


def test_bake_resolution_is_capped_by_the_images_and_images_must_match(wood, bpy_addon):
    from addon.blender import bake_ops
    from addon.core.textures import LatentTexture

    wood.neural_layers.bake_resolution = 8
    assert run_operator(ops.bake_texture).finished
    tex = LatentTexture.read_exr(bake_ops.baked_texture_state(wood)[0])
    assert (tex.height, tex.width) == (4, 8)
    wood.neural_layers.bake_resolution = 4096  # never finer than the images
    assert run_operator(ops.bake_texture).finished
    tex = LatentTexture.read_exr(bake_ops.baked_texture_state(wood)[0])
    assert (tex.height, tex.width) == (8, 16)
    s = wood.neural_layers
    assert run_operator(ops.map_add, parameter="THICKNESS").finished
    s.layers[1].maps[1].image = bpy_addon.data.images.new("thick", width=4, height=4)
    r = run_operator(ops.bake_texture)
    assert r.error and "share a resolution" in r.error


def test_bake_resolution_defaults_to_2048_and_a_bake_too_large_for_memory_is_refused(wood, bpy_addon, monkeypatch):
    """The default Bake Resolution caps the driving images at 2048 texels a side (a 4096 x 4096 bake takes up to
    25 GB); a bake larger than three quarters of the computer's memory is refused with what fits."""
    from addon.core.textures import bake

    assert wood.neural_layers.bake_resolution == bake.DEFAULT_MAX_SIDE == 2048
    monkeypatch.setattr(bake, "physical_memory_bytes", lambda: 200 * 2**10)  # 200 kB: 8 x 16 texels do not fit
    r = run_operator(ops.bake_texture)
    assert r.error and "8 texels takes about" in r.error and "lower Bake Resolution" in r.error, r.error
    assert wood.neural_layers.texture_path == ""


def test_duplicating_a_layer_copies_its_maps(wood):
    wood.neural_layers.active_index = 1
    assert run_operator(ops.layer_duplicate).finished
    copy = wood.neural_layers.layers[2]
    assert len(copy.maps) == 1 and copy.maps[0].image.name == "rough" and copy.maps[0].high == pytest.approx(0.6)


def test_bake_with_the_shipped_models_at_the_default_auto_size(bpy_addon, material, tmp_path):
    """The default model size, Auto, bakes (it is resolved once, by the neural runtime) and the texture
    records the size and decoder digest the renderer decodes it with."""
    from addon.blender import bake_ops
    from addon.core.neural import DEFAULT_SIZE, encode_stack, load_models
    from addon.core.render import neural_material
    from addon.core.stack import preset
    from addon.core.textures import LatentTexture

    assert run_operator(ops.preset_apply, preset="lacquered_plastic").finished
    material.neural_layers.bake_directory = str(tmp_path)
    assert material.neural_layers.model_size == "AUTO"
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    path, state = bake_ops.baked_texture_state(material)
    assert path is not None, state
    tex = LatentTexture.read_exr(path)
    models = load_models(DEFAULT_SIZE)
    assert tex.metadata["model"] == DEFAULT_SIZE and tex.metadata["model_digest"] == models.digest
    z = encode_stack(preset("lacquered_plastic"), models)
    assert np.allclose(tex.levels[0][0, 0, :96], z.reshape(-1), atol=2e-3)
    # the bake calibrated the texture (one stack: one cluster) and found every level filterable (one latent)
    from addon.core.textures.calibration import TextureCalibration

    assert len(TextureCalibration.from_text(tex.metadata["calibration"]).tables) == 1
    assert tex.filter_levels == len(tex.levels)
    assert neural_material.make(preset("lacquered_plastic"), tex, calibrate=True).calibration is not None
    assert neural_material.make(preset("lacquered_plastic"), tex).models.size == DEFAULT_SIZE


def test_fit_to_camera_bakes_no_finer_than_the_on_screen_footprint(wood, bpy_addon):
    from addon.blender import bake_ops

    bpy = bpy_addon
    big = bpy.data.images.new("rough_big", width=256, height=256, float_buffer=True)
    big.pixels.foreach_set(np.random.default_rng(0).random(256 * 256 * 4).astype(np.float32))
    wood.neural_layers.layers[1].maps[0].image = big
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 36, 100
    wood.neural_layers.bake_fit_camera = True
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    small = tuple(wood.neural_layers.texture_size)
    assert 1 <= small[0] < 256 and small[0] == small[1]  # the cube covers a few dozen pixels
    assert bake_ops.baked_texture_state(wood)[0] is not None  # current at the size it was baked at
    scene.render.resolution_x, scene.render.resolution_y = 1920, 1080
    assert run_operator(ops.bake_texture).finished
    assert tuple(wood.neural_layers.texture_size)[0] > small[0]  # a closer look needs more texels


def test_bake_in_an_unsaved_file_refuses_a_folder_relative_to_it(wood, bpy_addon, tmp_path, monkeypatch):
    bpy = bpy_addon
    assert bpy.data.filepath == ""
    monkeypatch.chdir(tmp_path)
    wood.neural_layers.bake_directory = "//textures/"
    r = run_operator(ops.bake_texture)
    assert not r.finished and "save the file first" in r.error, r.error
    assert list(tmp_path.iterdir()) == []  # nothing in the process's working folder
    assert wood.neural_layers.texture_path == ""
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "saved.blend"))
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    assert wood.neural_layers.texture_path == "//textures/saved/Material.exr"  # the default: a folder per file
    assert (tmp_path / "textures" / "saved" / "Material.exr").is_file()


@pytest.mark.parametrize("colorspace, expected", [("sRGB", 0.2158605), ("Non-Color", 128 / 255)])
def test_maps_and_base_colour_textures_decode_the_colour_space_as_cycles(bpy_addon, material, colorspace, expected):
    """An 8-bit image holding 128 drives albedo 0.216 in sRGB and 0.502 as Non-Color, in a bake
    and as the base-colour texture of an ordinary material alike (one path, as Cycles decodes)."""
    bpy = bpy_addon
    from addon.blender import scene_export
    from addon.blender.bake_inputs import spatial_stack_from_material

    img = bpy.data.images.new("half", width=4, height=2)  # an 8-bit image
    assert not img.is_float
    img.colorspace_settings.name = colorspace
    px = np.full((2, 4, 4), 128 / 255, np.float32)
    px[..., 3] = 1.0  # opaque: a texel's alpha scales the colour Cycles' Image Texture node gives
    img.pixels.foreach_set(px.ravel())
    assert run_operator(ops.preset_apply, preset="white_diffuse").finished
    s = material.neural_layers
    s.active_index = 0
    assert run_operator(ops.map_add, parameter="ALBEDO").finished
    s.layers[0].maps[0].image = img
    spatial, _ = spatial_stack_from_material(material)
    np.testing.assert_allclose(spatial.maps["base.albedo"], expected, rtol=2e-3)

    plain = bpy.data.materials.new("plain")  # 5.0: a new material has its node tree
    tex = plain.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = img
    principled = plain.node_tree.nodes["Principled BSDF"]
    plain.node_tree.links.new(tex.outputs["Color"], principled.inputs["Base Color"])
    lambert = scene_export.unmanaged_material(plain, [])
    np.testing.assert_allclose(lambert.texture.levels[0], expected, rtol=2e-3)


def test_materials_whose_names_differ_only_in_unsafe_characters_bake_to_different_files(wood, bpy_addon, tmp_path):
    """The operator names files as the bake CLI does (``textures.files.safe_file_name``): "a/b" and "a_b"
    must not overwrite each other, and no name leaves the bake folder."""
    from addon.blender import bake_ops
    from addon.core.textures.files import safe_file_name

    paths = []
    for name in ("a/b", "a_b", "../../x"):
        wood.name = name
        assert wood.name == name
        r = run_operator(ops.bake_texture)
        assert r.finished, r.error
        path, state = bake_ops.baked_texture_state(wood)
        assert path is not None, state
        paths.append(path)
        assert path == str(tmp_path / f"{safe_file_name(name)}.exr")
    assert len(set(paths)) == 3
    assert sorted(p.name for p in tmp_path.glob("*.exr")) == sorted(
        f"{safe_file_name(n)}.exr" for n in ("a/b", "a_b", "../../x")
    )


def test_a_texture_baked_with_another_decoder_file_is_out_of_date(wood, bpy_addon, monkeypatch):
    """The freshness key holds the decoder file's digest, as the bake CLI's does: a texture baked
    before the decoder of its size was replaced is not rendered."""
    from addon.blender import bake_ops
    from addon.core.neural.models import ModelSet

    assert run_operator(ops.bake_texture).finished
    assert bake_ops.baked_texture_state(wood)[0] is not None
    monkeypatch.setattr(ModelSet, "digest", property(lambda self: "0" * 64))  # a retrained decoder
    path, state = bake_ops.baked_texture_state(wood)
    assert path is None and "out of date" in state
    assert run_operator(ops.bake_texture).finished  # baking again with it makes it current
    assert bake_ops.baked_texture_state(wood)[0] is not None


def test_bake_refine_option_refines_the_distinct_texels_and_keys_the_bake_apart(bpy_addon, material, tmp_path):
    """Refine (s) > 0 passes the budget to the core bake as the bake command's --refine does: the texture
    records it and the refined count, the refinement is cached beside the texture, and the budget is part
    of the freshness key (changing it makes the texture out of date)."""
    from addon.blender import bake_ops
    from addon.core.textures import LatentTexture

    # not the Refine button tests' stack: refinements share one in-memory cache, whatever their budget
    assert run_operator(ops.preset_apply, preset="lacquered_plastic").finished
    s = material.neural_layers
    s.bake_directory, s.model_size = str(tmp_path), "TINY"
    assert s.bake_refine == 0.0  # off by default
    assert run_operator(ops.bake_texture).finished
    plain_key = s.texture_key
    assert "refined" not in LatentTexture.read_exr(bake_ops.baked_texture_state(material)[0]).metadata
    s.bake_refine = 0.01
    assert bake_ops.baked_texture_state(material)[0] is None  # another budget: out of date
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    path, state = bake_ops.baked_texture_state(material)
    assert path is not None and s.texture_key != plain_key, state
    tex = LatentTexture.read_exr(path)
    assert tex.metadata["refined"] == "1" and float(tex.metadata["refine_s"]) == 0.01
    assert len(list((tmp_path / ".refine").glob("refine_*.npz"))) == 1
    s.bake_refine = 0.0
    assert bake_ops.baked_texture_state(material)[0] is None


def test_save_as_into_another_folder_keeps_the_baked_texture_and_save_copy_keeps_the_open_files_paths(
    wood, bpy_addon, tmp_path
):
    """The texture path is relative to the .blend file: Save As into another folder remaps it, as Blender remaps
    its own relative paths (the bake was reported missing after it); a Save Copy remaps the copy's only."""
    import os

    from addon.blender import bake_ops

    bpy = bpy_addon
    for sub in ("one", "two", "three/deeper"):
        (tmp_path / sub).mkdir(parents=True)
    wood.neural_layers.bake_directory = "//textures/"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "one" / "scene.blend"))
    assert run_operator(ops.bake_texture).finished
    assert wood.neural_layers.texture_path == "//textures/scene/Material.exr"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "two" / "scene.blend"))
    assert wood.neural_layers.texture_path == "//../one/textures/scene/Material.exr"
    assert bake_ops.baked_texture_state(wood)[0] is not None
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "three" / "deeper" / "copy.blend"), copy=True)
    assert wood.neural_layers.texture_path == "//../one/textures/scene/Material.exr"  # the open file is still two's
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "three" / "deeper" / "copy.blend"))
    copied = bpy.data.materials["Material"]
    assert copied.neural_layers.texture_path == "//../../one/textures/scene/Material.exr"
    assert os.path.isfile(bpy.path.abspath(copied.neural_layers.texture_path))


def test_the_add_ons_bake_removes_what_a_killed_writer_left_in_its_folder(wood, bpy_addon, tmp_path):
    """A Blender killed while it wrote a texture leaves a hidden temporary file beside it: the next bake into that
    folder removes it (a live process's is kept), as the bake command does."""
    import subprocess
    import sys

    from addon.core.textures import files

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".Material.exr.{files._HOST}-{dead.pid}-0123abcd.partial.exr"
    stale.write_bytes(b"half")
    live = files.temp_path(tmp_path / "Other.exr")
    live.write_bytes(b"")
    assert run_operator(ops.bake_texture).finished
    assert not stale.exists() and live.exists()


def test_a_baked_material_appended_from_another_folder_keeps_its_texture(wood, bpy_addon, tmp_path):
    """File > Append: the material's "//" texture path was its file's; Blender rebases its own paths as it
    appends, not this one, so the bake read as missing in the file it was appended to."""
    import os

    from addon.blender import bake_ops

    bpy = bpy_addon
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    wood.neural_layers.bake_directory = "//textures/"
    wood.neural_layers.layers[1].maps[0].image.pack()  # the map's pixels travel with the material
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "a.blend"))
    assert run_operator(ops.bake_texture).finished
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "a.blend"))
    bpy.ops.wm.read_homefile(app_template="")
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "b" / "b.blend"))
    library = str(tmp_path / "a" / "a.blend")
    bpy.ops.wm.append(directory=library + "/Material/", filename="Material")
    (appended,) = [m for m in bpy.data.materials if m.name != "Material" and m.neural_layers.texture_path]
    assert appended.neural_layers.texture_path == "//../a/textures/a/Material.exr"
    assert os.path.isfile(bpy.path.abspath(appended.neural_layers.texture_path))
    path, state = bake_ops.baked_texture_state(appended)
    assert path is not None, state


def test_a_linked_baked_material_made_local_keeps_its_texture(wood, bpy_addon, tmp_path):
    """Make Local turns a linked material into the open file's own: its "//" texture path, its library's, then
    led into the open file's folder (no handler sees Make Local), and the bake read as missing. The bake's
    absolute path (``texture_file``) finds it again."""
    import os

    from addon.blender import bake_ops

    bpy = bpy_addon
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    wood.neural_layers.bake_directory = "//textures/"
    wood.neural_layers.layers[1].maps[0].image.pack()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "a.blend"))
    assert run_operator(ops.bake_texture).finished
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "a.blend"))
    bpy.ops.wm.read_homefile(app_template="")
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "b" / "b.blend"))
    with bpy.data.libraries.load(str(tmp_path / "a" / "a.blend"), link=True) as (_, linked):
        linked.materials = ["Material"]
    local = linked.materials[0].make_local()
    assert local.library is None and local.neural_layers.texture_path == "//textures/a/Material.exr"
    assert not os.path.isfile(bpy.path.abspath(local.neural_layers.texture_path))
    path, state = bake_ops.baked_texture_state(local)
    assert path is not None and os.path.samefile(path, tmp_path / "a" / "textures" / "a" / "Material.exr"), state


def test_a_bake_is_undone_and_offers_no_redo_panel_that_would_run_it_on_blenders_thread(wood, bpy_addon):
    """Bake and Refine had REGISTER and UNDO, so Blender's Adjust Last Operation panel re-ran them through execute():
    the whole job on Blender's thread, with no progress and no Esc. They keep their undo step, without the panel."""
    from addon.blender import bake_ops, refine_ops

    bpy = bpy_addon
    for op in (bake_ops.NLM_OT_bake_texture, refine_ops.NLM_OT_refine_latent):
        assert op.bl_options == {"UNDO"}
    bpy.ops.ed.undo_push(message="before the bake")
    assert run_operator(ops.bake_texture, "EXEC_DEFAULT", True).finished
    assert bpy.data.materials["Material"].neural_layers.texture_path
    bpy.ops.ed.undo()
    assert bpy.data.materials["Material"].neural_layers.texture_path == ""


def test_a_bake_finishes_on_the_material_as_it_is_after_an_undo_during_it(wood, bpy_addon, monkeypatch):
    """An undo while a bake runs replaces every data-block: its finish wrote to the material its preparation read,
    which was gone (ReferenceError, the texture written and not used). It now finds the material again by name."""
    from addon.blender import bake_ops

    bpy = bpy_addon
    real = bake_ops.bake_stack

    def undone_meanwhile(*args, **kwargs):
        bpy.ops.ed.undo()  # the user's Ctrl+Z while the job runs
        return real(*args, **kwargs)

    bpy.ops.ed.undo_push(message="before the bake")
    bpy.ops.ed.undo_push(message="again")
    monkeypatch.setattr(bake_ops, "bake_stack", undone_meanwhile)
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    assert bpy.data.materials["Material"].neural_layers.texture_path


def test_a_bake_finishes_on_its_material_renamed_during_it(wood, bpy_addon, monkeypatch):
    """Found again by name alone, a material renamed during its bake was 'gone' and another material given that name
    took its texture. The material itself is kept while it lives; only an undo's replacement is found by name."""
    from addon.blender import bake_ops

    bpy = bpy_addon
    real = bake_ops.bake_stack

    def renamed_meanwhile(*args, **kwargs):
        wood.name = "Renamed"
        bpy.data.materials.new("Material")  # another one takes the old name
        return real(*args, **kwargs)

    monkeypatch.setattr(bake_ops, "bake_stack", renamed_meanwhile)
    assert run_operator(ops.bake_texture).finished
    assert bpy.data.materials["Renamed"].neural_layers.texture_path
    assert bpy.data.materials["Material"].neural_layers.texture_path == ""


def test_an_export_reads_a_baked_materials_maps_once_until_they_change(wood, bpy_addon, monkeypatch):
    """Every export checks every baked material's key, and the viewport exports at every edit: its maps were
    read and hashed each time (0.4-1.2 s for a 4096-pixel map). They are read again only when something they are
    read from changed: an image painted or reloaded, a map's range, the stack."""
    from addon.blender import bake_inputs, bake_state

    bpy = bpy_addon
    pmap = wood.neural_layers.layers[1].maps[0]
    pmap.image.filepath_raw = str(Path(wood.neural_layers.bake_directory) / "rough.exr")
    pmap.image.file_format = "OPEN_EXR"
    pmap.image.save()  # a map from a file, as a user's are (a generated one written by a script has unsaved changes)
    assert not pmap.image.is_dirty
    assert run_operator(bpy.ops.neural_layers.bake_texture).finished
    reads = []
    real = bake_inputs.spatial_stack_from_material
    monkeypatch.setattr(bake_inputs, "spatial_stack_from_material", lambda m: reads.append(m.name) or real(m))
    bake_state._INPUTS.clear()
    path, state, _ = bake_state.current_texture(wood)
    assert path is not None, state
    for _ in range(3):
        assert bake_state.current_texture(wood)[0] == path
    assert len(reads) == 1
    pmap.high += 0.1  # the map's range: a stale bake
    assert bake_state.current_texture(wood)[0] is None and len(reads) == 2
    pmap.high -= 0.1
    assert bake_state.current_texture(wood)[0] == path
    image = pmap.image
    image.pixels[0] = 1.0 - image.pixels[0]  # painted: its pixels are new, and read once
    before = len(reads)
    assert bake_state.current_texture(wood)[0] is None  # stale
    bake_state.current_texture(wood)
    assert len(reads) == before + 1


def test_a_map_edited_outside_blender_makes_its_bake_stale(wood, bpy_addon, tmp_path):
    """A map file saved again by another program, checked (a redraw) before Image > Reload: the old pixels were
    kept under the new file's time, and after the reload the stale bake still read as current. A map is read from
    its file (as a bake reads it), so its bake is stale as soon as the file is another, and stays so after the
    reload."""
    import time

    from addon.blender import bake_state

    bpy = bpy_addon
    pmap = wood.neural_layers.layers[1].maps[0]
    path = Path(wood.neural_layers.bake_directory) / "rough.exr"
    pmap.image.filepath_raw, pmap.image.file_format = str(path), "OPEN_EXR"
    pmap.image.save()
    assert run_operator(bpy.ops.neural_layers.bake_texture).finished
    bake_state._INPUTS.clear()
    assert bake_state.current_texture(wood)[0] is not None
    time.sleep(0.05)
    other = bpy.data.images.new("other", width=16, height=8, float_buffer=True)
    other.pixels.foreach_set(np.full(16 * 8 * 4, 0.25, np.float32))
    other.filepath_raw, other.file_format = str(path), "OPEN_EXR"
    other.save()  # the map's file, written again elsewhere
    assert bake_state.current_texture(wood)[1] == "baked texture is out of date: bake again"  # before a reload too
    pmap.image.reload()
    pixels = np.empty(16 * 8 * 4, np.float32)
    pmap.image.pixels.foreach_get(pixels)  # an Image Editor showing it: the pixels loaded again before the check
    assert bake_state.current_texture(wood)[1] == "baked texture is out of date: bake again"


def test_a_maps_alpha_mode_is_part_of_what_its_bake_was_made_from(wood, bpy_addon):
    from addon.blender import bake_state

    bpy = bpy_addon
    pmap = wood.neural_layers.layers[1].maps[0]
    source = bpy.data.images.new("rgba", 16, 8, alpha=True)
    px = np.zeros((8, 16, 4), np.float32)
    px[:, :, :3], px[:, 8:, :3], px[..., 3] = 0.3, 0.6, 0.5
    source.pixels.foreach_set(px.ravel())
    path = Path(wood.neural_layers.bake_directory) / "rough.png"
    source.filepath_raw, source.file_format = str(path), "PNG"
    source.save()
    pmap.image = bpy.data.images.load(str(path))
    assert run_operator(bpy.ops.neural_layers.bake_texture).finished
    bake_state._INPUTS.clear()
    assert bake_state.current_texture(wood)[0] is not None
    pmap.image.alpha_mode = "PREMUL"  # other pixels
    assert bake_state.current_texture(wood)[1] == "baked texture is out of date: bake again"


def bake_state_current(mat):
    from addon.blender import bake_state

    return bake_state.current_texture(mat)[0]


def test_a_material_driven_by_maps_previews_its_most_common_texel_and_refuses_refine(wood, bpy_addon):
    """Its sliders alone are a stack F12 never renders (a coat the map made glossy previewed 67 times too dark),
    and Refine fitted a latent F12 did not use, saying it was kept."""
    from addon.blender import bake_inputs, stack_io

    bpy = bpy_addon
    pmap = wood.neural_layers.layers[1].maps[0]
    px = np.zeros((8, 16, 4), np.float32)
    px[:, 4:, :] = 1.0  # three quarters rough
    pmap.image.pixels.foreach_set(px.ravel())
    stack, share = bake_inputs.representative_stack(wood)
    spatial, _ = bake_inputs.spatial_stack_from_material(wood)
    rough = spatial.maps["coatings[0].roughness"][..., 0]
    assert share == pytest.approx(0.75)
    assert stack.coatings[0].roughness == pytest.approx(rough.max(), rel=1e-6)
    assert stack != stack_io.stack_from_material(wood)  # not the sliders' stack
    # not baked: F12 renders the sliders' stack (and says the maps are not), which Refine may refine
    from addon.blender import scene_export

    warnings = []
    assert scene_export._baked_texture(wood, warnings) == (None, None)
    assert any("maps are not baked" in w for w in warnings)
    assert bake_state_current(wood) is None
    # baked: F12 renders the bake, not a latent, and Refine says so
    assert run_operator(bpy.ops.neural_layers.bake_texture).finished
    assert bake_state_current(wood) is not None
    report = run_operator(bpy.ops.neural_layers.refine_latent, budget=1.0)
    assert not report.finished and "maps drive it" in report.error
    for item in wood.neural_layers.layers:
        item.maps.clear()
    assert bake_inputs.representative_stack(wood) is None


def _map_from_file(bpy, wood, path):
    """The wood's roughness map saved to ``path`` (a PNG) and loaded from it, as a user's maps are."""
    pmap = wood.neural_layers.layers[1].maps[0]
    pmap.image.filepath_raw, pmap.image.file_format = str(path), "PNG"
    pmap.image.save()
    pmap.image = bpy.data.images.load(str(path))
    pmap.image.colorspace_settings.name = "Non-Color"
    return pmap


def test_a_bake_renders_while_its_maps_images_are_missing_until_its_settings_change(wood, bpy_addon, tmp_path):
    """A bake makes the material independent of its maps' images, as a Cycles bake does: with them missing (not
    copied to the render machine) it rendered the constant stack. It renders while its texture is the material's
    own and the material's settings are those it was baked with, and says so; an edit of the stack or a map's range
    (still readable) makes it stale."""
    from addon.blender import bake_state, scene_export

    bpy = bpy_addon
    pmap = _map_from_file(bpy, wood, tmp_path / "maps" / "rough.png")
    assert run_operator(ops.bake_texture).finished
    baked = scene_export.export_material(wood, [])
    assert baked.latent_texture is not None and baked.spatial is not None
    (tmp_path / "maps" / "rough.png").unlink()
    pmap.image.reload()  # as a reopened file finds it: no pixels
    bake_state._INPUTS.clear()
    path, state, spatial = bake_state.current_texture(wood)
    assert path is not None and spatial is None, state
    assert "rough.png' is missing" in state and "cannot be checked against them" in state, state
    assert "reference mode shades its constant stack" in state
    warnings = []
    spec = scene_export.export_material(wood, warnings)
    assert spec.latent_texture is baked.latent_texture and spec.spatial is None
    assert warnings == [f"material 'Material': {state}"]  # F12 says so
    # edits of what is still readable: stale
    pmap.high += 0.1
    path, state, _ = bake_state.current_texture(wood)
    assert path is None and state.startswith("baked texture is out of date") and "is missing" in state, state
    pmap.high -= 0.1
    assert bake_state.current_texture(wood)[0] is not None
    wood.neural_layers.layers[1].thickness = 1.0
    assert bake_state.current_texture(wood)[0] is None
    assert scene_export.export_material(wood, []).latent_texture is None


def test_a_bake_with_missing_maps_is_not_rendered_where_its_file_is_another_bake(wood, bpy_addon, tmp_path):
    """Only the material's own bake: the header's key must be the one the material recorded, and a texture that
    records no settings (``inputs``, made before bakes recorded them) cannot be checked."""
    from addon.blender import bake_state
    from addon.core.textures import LatentTexture

    bpy = bpy_addon
    pmap = _map_from_file(bpy, wood, tmp_path / "maps" / "rough.png")
    assert run_operator(ops.bake_texture).finished
    path = bake_state.current_texture(wood)[0]
    tex = LatentTexture.read_exr(path)
    (tmp_path / "maps" / "rough.png").unlink()
    pmap.image.reload()
    bake_state._INPUTS.clear()
    assert bake_state.current_texture(wood)[0] == path
    LatentTexture(tex.levels, {k: v for k, v in tex.metadata.items() if k != "inputs"}).write_exr(path)
    found, state, _ = bake_state.current_texture(wood)
    assert found is None and "records no settings" in state, state
    LatentTexture(tex.levels, {**tex.metadata, "key": "0123456789abcdef"}).write_exr(path)
    found, state, _ = bake_state.current_texture(wood)
    assert found is None and "out of date" in state, state


def test_a_map_file_that_is_not_an_image_says_so(wood, bpy_addon, tmp_path):
    bpy = bpy_addon
    text = tmp_path / "notes.png"
    text.write_text("not a picture\n")
    pmap = wood.neural_layers.layers[1].maps[0]
    pmap.image = bpy.data.images.load(str(text))
    r = run_operator(ops.bake_texture)
    assert r.error and "is not an image Blender can read" in r.error and "missing" not in r.error, r.error


@pytest.mark.parametrize("bits", ["uint8", "uint16"])
def test_colour_maps_with_alpha_read_straight_as_the_bake_command_reads_them(bpy_addon, material, tmp_path, bits):
    """A 16-bit PNG albedo map of alpha 0.5 drove half its albedo (Blender's float buffer is premultiplied), and
    none at alpha 0, where an 8-bit one and the bake command read the colour as stored: all read it so now."""
    import sys

    bpy = bpy_addon
    bpy.utils.expose_bundled_modules()
    import OpenImageIO as oiio

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bake"))
    import bake as bake_cli
    from addon.blender.bake_inputs import spatial_stack_from_material

    rgba = np.zeros((2, 4, 4), np.float32)
    rgba[..., :3], rgba[:, :2, 3], rgba[:, 2:, 3] = 0.8, 0.5, 0.0
    path = tmp_path / f"albedo_{bits}.png"
    spec = oiio.ImageSpec(4, 2, 4, bits)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(rgba)
    out.close()
    assert run_operator(ops.preset_apply, preset="white_diffuse").finished
    s = material.neural_layers
    s.active_index = 0
    assert run_operator(ops.map_add, parameter="ALBEDO").finished
    s.layers[0].maps[0].image = bpy.data.images.load(str(path))  # sRGB, Straight: Blender's defaults
    addon = spatial_stack_from_material(material)[0].maps["base.albedo"]
    cli = bake_cli.read_map(path, "albedo", "auto")[0][..., :3]
    np.testing.assert_allclose(addon, cli, rtol=2e-3)
    np.testing.assert_allclose(addon, 0.6038, rtol=2e-3)  # sRGB 0.8, whatever the alpha


def test_a_bake_folder_that_cannot_be_written_is_refused_before_the_work(wood, bpy_addon, tmp_path, monkeypatch):
    """A Bake Folder that is a file, or not writable, failed only after the whole bake, with a raw error."""
    import os

    from addon.blender import bake_ops

    started = []
    monkeypatch.setattr(bake_ops, "bake_stack", lambda *a, **k: started.append(1))
    a_file = tmp_path / "rough.png"
    a_file.write_bytes(b"")
    for folder, said in ((a_file, "is a file, not a folder"), (a_file / "sub", "Not a directory")):
        wood.neural_layers.bake_directory = str(folder)
        r = run_operator(ops.bake_texture)
        assert not r.finished and f"the Bake Folder {str(folder)!r}" in r.error and said in r.error, r.error
    if os.geteuid() != 0:  # root writes into any folder
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
        try:
            wood.neural_layers.bake_directory = str(locked)
            r = run_operator(ops.bake_texture)
            assert not r.finished and "cannot be written" in r.error and "Permission denied" in r.error, r.error
        finally:
            locked.chmod(0o700)
    assert not started and wood.neural_layers.texture_path == ""
    wood.neural_layers.bake_directory = str(tmp_path / "new" / "folder")  # made where it is not there
    monkeypatch.undo()
    monkeypatch.setattr(bake_ops, "neural_encoder", stand_in_encoder)
    assert run_operator(ops.bake_texture).finished
    assert (tmp_path / "new" / "folder" / "Material.exr").is_file()
    assert [p.name for p in (tmp_path / "new" / "folder").iterdir()] == ["Material.exr"]  # no probe left

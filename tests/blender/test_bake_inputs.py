"""A material's parameter maps as the bake reads them (addon.blender.bake_inputs): a colour image's white is white,
a new map starts where the neural models were trained, and a map the bake refuses is named as the sidebar names it,
with what to change."""

from __future__ import annotations

import numpy as np
import pytest

from tests.blender.helpers import run_operator

ops = pytest.importorskip("bpy").ops.neural_layers


def _grey(bpy, name: str, value: float, size=(8, 8), colour_space="Non-Color"):
    image = bpy.data.images.new(name, width=size[0], height=size[1])
    image.colorspace_settings.name = colour_space
    image.pixels.foreach_set(np.full(size[0] * size[1] * 4, value, np.float32))
    return image


def test_a_white_texel_of_an_srgb_colour_image_is_white_and_its_albedo_map_bakes(
    bpy_addon, material, tmp_path, monkeypatch
):
    """OpenColorIO's fast power function decoded an 8-bit sRGB 255 to 1.000024, outside an albedo's valid range: an
    albedo map with a white texel, painted or loaded, could not be baked."""
    from addon.blender import bake_ops, images
    from addon.blender.bake_inputs import spatial_stack_from_material
    from tests.blender.test_bake_addon import stand_in_encoder

    bpy = bpy_addon
    assert run_operator(ops.preset_apply, preset="varnished_wood").finished
    s = material.neural_layers
    s.active_index = 0
    assert run_operator(ops.map_add, parameter="ALBEDO").finished
    px = np.ones((2, 4, 4), np.float32)
    px[0, :2, :3] = 128 / 255  # two mid-grey texels beside the white ones
    painted = bpy.data.images.new("painted", width=4, height=2)  # 8-bit sRGB: Blender's pixels
    painted.pixels.foreach_set(px.ravel())
    saved = bpy.data.images.new("saved", width=4, height=2)
    saved.pixels.foreach_set(px.ravel())
    saved.filepath_raw, saved.file_format = str(tmp_path / "white.png"), "PNG"
    saved.save()
    loaded = bpy.data.images.load(str(tmp_path / "white.png"))  # read from its file
    assert images.pixels_file(loaded) is not None and images.pixels_file(painted) is None
    srgb_128 = ((128 / 255 + 0.055) / 1.055) ** 2.4  # the exact sRGB curve, Cycles' decoding
    for image in (painted, loaded):
        assert image.colorspace_settings.name == "sRGB" and not image.is_float
        s.layers[0].maps[0].image = image
        albedo = spatial_stack_from_material(material)[0].maps["base.albedo"]
        assert albedo.max() == 1.0 and np.count_nonzero(albedo == 1.0) == 6 * 3
        np.testing.assert_allclose(albedo.min(), srgb_128, atol=3e-5)
    # a Principled BSDF's base-colour texture reads the file alike (``images.file_pixels``, as Cycles reads it)
    assert images.file_pixels(loaded, images.pixels_file(loaded))[..., :3].max() == 1.0

    monkeypatch.setattr(bake_ops, "neural_encoder", stand_in_encoder)
    s.bake_directory = str(tmp_path)
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error


def test_a_float_map_holding_values_past_its_range_is_refused_naming_its_layer_and_map(bpy_addon, material):
    """A float image's values are its own: one past 1 in an albedo map, even by a half float's step, is refused, in
    the sidebar's words (the core named ``base.albedo`` and the value there)."""
    from addon.blender.bake_inputs import spatial_stack_from_material

    bpy = bpy_addon
    assert run_operator(ops.preset_apply, preset="varnished_wood").finished
    s = material.neural_layers
    s.active_index = 0
    assert run_operator(ops.map_add, parameter="ALBEDO").finished
    hdr = bpy.data.images.new("hdr", width=4, height=2, float_buffer=True)
    px = np.full((2, 4, 4), 0.5, np.float32)
    px[1, 3, :3] = (0.2, 1.0 + 1 / 1024, 0.3)  # the top row's last texel: x=3, y=1
    hdr.pixels.foreach_set(px.ravel())
    s.layers[0].maps[0].image = hdr
    with pytest.raises(ValueError) as refused:
        spatial_stack_from_material(material)
    message = str(refused.value)
    base = s.layers[0].name
    assert f"layer {base!r}: its Albedo map (image 'hdr', Low 0, High 1) gives 1 of its 8 texel(s)" in message
    assert "valid Albedo range 0 to 1 (the first: (0.2, 1.001, 0.3) at pixel x=3, y=1)" in message
    assert "its image holds values outside 0 to 1 there" in message and "edit the image" in message
    assert "base.albedo" not in message


@pytest.mark.parametrize(
    "preset, layer, mode, parameter, trained",
    [
        ("varnished_wood", 1, None, "IOR", (1.05, 2.0)),
        ("varnished_wood", 1, None, "ROUGHNESS", (0.1, 1.0)),  # artist roughness: GGX alpha 0.01 to 1
        ("varnished_wood", 1, None, "THICKNESS", (0.0, 5.0)),
        ("varnished_wood", 1, None, "MEDIUM_ALBEDO", (0.0, 1.0)),
        ("varnished_wood", 0, None, "ALBEDO", (0.0, 1.0)),
        ("coated_gold", 0, "ETA_K", "ETA", (0.01, 10.0)),
        ("coated_gold", 0, "ETA_K", "K", (0.0, 20.0)),
        ("coated_gold", 0, "F0", "F0", (0.0, 1.0)),
        ("coated_gold", 0, "F0", "ROUGHNESS", (0.1, 1.0)),
    ],
)
def test_a_new_map_spans_its_parameters_trained_range_and_bakes_as_added(
    bpy_addon, material, preset, layer, mode, parameter, trained
):
    """Add Parameter Map gave every map Low 0, High 1: a new IOR map was an invalid IOR (below 1) at every texel, a
    new Eta map below eta's 0.01 where the image is black."""
    from addon.blender.bake_inputs import spatial_stack_from_material

    bpy = bpy_addon
    assert run_operator(ops.preset_apply, preset=preset).finished
    s = material.neural_layers
    s.active_index = layer
    if mode is not None:
        s.layers[layer].conductor_mode = mode
    assert run_operator(ops.map_add, parameter=parameter).finished
    pmap = s.layers[layer].maps[0]
    np.testing.assert_allclose((pmap.low, pmap.high), trained, rtol=1e-6)
    for value in (0.0, 1.0):  # black and white: the range's ends
        pmap.image = _grey(bpy, f"grey {value}", value)
        spatial, _ = spatial_stack_from_material(material)
        assert len(spatial.maps) == 1


def test_a_map_outside_the_valid_range_says_which_layer_and_map_and_what_to_change(bpy_addon, material):
    from addon.blender.bake_inputs import spatial_stack_from_material

    bpy = bpy_addon
    assert run_operator(ops.preset_apply, preset="varnished_wood").finished
    s = material.neural_layers
    s.active_index = 1
    assert run_operator(ops.map_add, parameter="IOR").finished
    pmap = s.layers[1].maps[0]
    pmap.image = _grey(bpy, "grey", 0.5)
    pmap.low, pmap.high = 0.0, 1.0  # every texel an IOR of 0.502: below 1
    with pytest.raises(ValueError) as refused:
        spatial_stack_from_material(material)
    message = str(refused.value)
    coat = s.layers[1].name
    assert f"layer {coat!r}: its IOR map (image 'grey', Low 0, High 1) gives 64 of its 64 texel(s)" in message
    assert message.endswith("set the IOR map's Low and High within 1 to 4")
    assert "coatings[0]" not in message
    r = run_operator(ops.bake_texture)  # the bake says it in the same words
    assert r.error and "set the IOR map's Low and High within 1 to 4" in r.error
    pmap.low, pmap.high = 1.3, 1.6
    assert spatial_stack_from_material(material) is not None


def test_two_maps_of_one_parameter_say_to_remove_one(bpy_addon, material):
    from addon.blender.bake_inputs import spatial_stack_from_material

    bpy = bpy_addon
    assert run_operator(ops.preset_apply, preset="varnished_wood").finished
    s = material.neural_layers
    s.active_index = 1
    for name in ("rough a", "rough b"):
        assert run_operator(ops.map_add, parameter="ROUGHNESS").finished
        s.layers[1].maps[-1].image = _grey(bpy, name, 0.5)
    with pytest.raises(ValueError, match="remove one of them") as refused:
        spatial_stack_from_material(material)
    assert "'rough a'" in str(refused.value) and "'rough b'" in str(refused.value)
    assert run_operator(ops.map_remove, index=1).finished
    assert spatial_stack_from_material(material) is not None

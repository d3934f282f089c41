"""Keyframes and drivers on a layer's settings follow the layer through the stack editor's edits.

Blender keys them by the layer's position (``neural_layers.layers[1].thickness``): an edit that inserted, removed or
moved a layer left them on whichever layer took the position, so a coat's animation jumped to another coat and a
driver overwrote another layer's value.
"""

from __future__ import annotations

import pytest

from tests.blender.helpers import run_operator

pytest.importorskip("bpy")


def _paths(mat):
    """The data paths of the material's action F-curves (its slot's) and of its drivers, each sorted."""
    anim = mat.animation_data
    curves = []
    if anim.action is not None:
        for layer in anim.action.layers:
            for strip in layer.strips:
                bag = strip.channelbag(anim.action_slot)
                curves += [c.data_path for c in bag.fcurves] if bag is not None else []
    return sorted(curves), sorted(d.data_path for d in anim.drivers)


def _values_at(bpy, mat, frame):
    """Each layer's (thickness, roughness) at ``frame``, by layer name."""
    bpy.context.scene.frame_set(frame)
    return {l.name: (round(l.thickness, 3), round(l.roughness, 3)) for l in mat.neural_layers.layers}


def _animated_red_car_paint(bpy, mat):
    """Red car paint whose red coat ('Red paint') has its thickness keyed 0 -> 5 over frames 1 to 10 and whose clear
    coat ('Clear coat') has its roughness driven to 0.5."""
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    layers = mat.neural_layers.layers
    red, clear = layers[1], layers[2]
    red.name, clear.name = "Red paint", "Clear coat"
    red.thickness = 0.0
    red.keyframe_insert("thickness", frame=1)
    red.thickness = 5.0
    red.keyframe_insert("thickness", frame=10)
    clear.driver_add("roughness").driver.expression = "0.5"
    return layers


def _reports(capfd, kind):
    """The reports of ``kind`` ("Warning", "Info") printed since the last call (background Blender prints them)."""
    out = capfd.readouterr().out
    return [line.removeprefix(f"{kind}: ") for line in out.splitlines() if line.startswith(f"{kind}: ")]


def test_keyframes_and_drivers_stay_on_their_layer_when_layers_are_added_moved_and_removed(bpy_addon, material, capfd):
    bpy = bpy_addon
    ops = bpy.ops.neural_layers
    layers = _animated_red_car_paint(bpy, material)
    s = material.neural_layers
    rough_red = round(layers[1].roughness, 3)

    s.active_index = 0  # a coating inserted right above the base: every coat moves up one place
    assert run_operator(ops.layer_add, layer_type="COATING").finished
    new_rough = round(s.layers[1].roughness, 3)
    assert _values_at(bpy, material, 10) == {
        "Conductor": (0.0, round(s.layers[0].roughness, 3)),
        "Coating": (0.0, new_rough),  # neither keyed nor driven: its defaults
        "Red paint": (5.0, rough_red),
        "Clear coat": (0.0, 0.5),
    }
    assert _values_at(bpy, material, 1)["Red paint"] == (0.0, rough_red)
    assert _paths(material) == (["neural_layers.layers[2].thickness"], ["neural_layers.layers[3].roughness"])

    s.active_index = 2  # 'Red paint' moves above 'Clear coat'
    assert run_operator(ops.layer_move, direction="UP").finished
    assert [l.name for l in s.layers] == ["Conductor", "Coating", "Clear coat", "Red paint"]
    assert _values_at(bpy, material, 10)["Red paint"] == (5.0, rough_red)
    assert _values_at(bpy, material, 10)["Clear coat"][1] == 0.5
    assert _values_at(bpy, material, 1)["Clear coat"][0] == pytest.approx(0.0)

    s.active_index = 1  # removing the plain coating below them moves both down
    assert run_operator(ops.layer_remove).finished
    assert _paths(material) == (["neural_layers.layers[2].thickness"], ["neural_layers.layers[1].roughness"])
    assert _reports(capfd, "Info") == []  # nothing of the removed layer was animated

    s.active_index = 2  # removing the keyed layer removes its keyframes, and says so
    assert run_operator(ops.layer_remove).finished
    assert _paths(material) == ([], ["neural_layers.layers[1].roughness"])
    assert any("removed 1 animation curve" in r and "'Red paint'" in r for r in _reports(capfd, "Info"))
    assert _values_at(bpy, material, 10)["Clear coat"][1] == 0.5


def test_the_animation_of_a_parameter_map_follows_its_layer(bpy_addon, material):
    """A map's Low and High are keyed on the layer too (``layers[1].maps[0].low``)."""
    bpy = bpy_addon
    ops = bpy.ops.neural_layers
    assert run_operator(ops.preset_apply, preset="red_car_paint").finished
    s = material.neural_layers
    s.active_index = 1
    assert run_operator(ops.map_add, parameter="ROUGHNESS").finished
    s.layers[1].maps[0].keyframe_insert("low", frame=1)
    assert run_operator(ops.layer_move, direction="UP").finished
    assert _paths(material)[0] == ["neural_layers.layers[2].maps[0].low"]


def test_removing_a_parameter_map_keeps_the_next_maps_animation_on_it(bpy_addon, material, capfd):
    """A layer's maps are keyed by position too (``maps[1].low``): removing the first handed the second's keys to
    the map that took its place; they now follow it, and the removed map's keys go with it."""
    bpy = bpy_addon
    ops = bpy.ops.neural_layers
    assert run_operator(ops.preset_apply, preset="red_car_paint").finished
    s = material.neural_layers
    s.active_index = 1
    for parameter in ("ROUGHNESS", "THICKNESS"):
        assert run_operator(ops.map_add, parameter=parameter).finished
    s.layers[1].maps[0].keyframe_insert("low", frame=1)
    s.layers[1].maps[1].keyframe_insert("high", frame=1)
    capfd.readouterr()
    assert run_operator(ops.map_remove, index=0).finished
    assert s.layers[1].maps[0].parameter == "THICKNESS"
    assert _paths(material)[0] == ["neural_layers.layers[1].maps[0].high"]
    assert any("removed 1 animation curve" in line for line in _reports(capfd, "Info"))


def test_a_duplicate_animates_as_its_source(bpy_addon, material, capfd):
    """Duplicate copies the layer's keyframes and drivers onto the copy (the same layer twice, through time too)."""
    bpy = bpy_addon
    _animated_red_car_paint(bpy, material)
    s = material.neural_layers
    s.active_index = 1
    assert run_operator(bpy.ops.neural_layers.layer_duplicate).finished
    copy = s.layers[2].name
    assert copy != "Red paint" and s.layers[3].name == "Clear coat"
    assert _paths(material) == (
        ["neural_layers.layers[1].thickness", "neural_layers.layers[2].thickness"],
        ["neural_layers.layers[3].roughness"],
    )
    at_10 = _values_at(bpy, material, 10)
    assert at_10["Red paint"][0] == at_10[copy][0] == 5.0 and at_10["Clear coat"][1] == 0.5
    assert _values_at(bpy, material, 1)[copy][0] == 0.0
    assert any("1 animation curve" in r and "copied" in r for r in _reports(capfd, "Info"))

    s.active_index = 3  # a driven layer's copy is driven as well
    assert run_operator(bpy.ops.neural_layers.layer_duplicate).finished
    assert _paths(material)[1] == ["neural_layers.layers[3].roughness", "neural_layers.layers[4].roughness"]


def test_undo_takes_the_animation_back_with_the_edit(bpy_addon, material):
    bpy = bpy_addon
    _animated_red_car_paint(bpy, material)
    material.neural_layers.active_index = 1
    before = _paths(material)
    bpy.ops.ed.undo_push(message="animated")
    # Python callers ask for the operator's undo push explicitly (second argument)
    assert run_operator(bpy.ops.neural_layers.layer_move, "EXEC_DEFAULT", True, direction="UP").finished
    assert _paths(bpy.data.materials["Material"]) != before
    bpy.ops.ed.undo()
    mat = bpy.data.materials["Material"]  # undo replaces the data-blocks
    assert _paths(mat) == before
    assert [l.name for l in mat.neural_layers.layers] == ["Conductor", "Red paint", "Clear coat"]

    mat.neural_layers.active_index = 1
    assert run_operator(bpy.ops.neural_layers.layer_remove, "EXEC_DEFAULT", True).finished
    assert _paths(bpy.data.materials["Material"])[0] == []
    bpy.ops.ed.undo()
    assert _paths(bpy.data.materials["Material"]) == before
    assert _values_at(bpy, bpy.data.materials["Material"], 10)["Red paint"][0] == 5.0


def test_a_stack_replaced_keeps_the_curves_of_positions_it_has_and_warns(bpy_addon, material, capfd):
    """A preset (or an applied or pasted stack) replaces every layer: nothing ties the old layers to the new ones,
    so the curves on positions the new stack has stay there, the others go, and a warning says both."""
    bpy = bpy_addon
    _animated_red_car_paint(bpy, material)
    capfd.readouterr()
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished  # 2 layers
    assert _paths(material) == (["neural_layers.layers[1].thickness"], [])
    (warning,) = _reports(capfd, "Warning")
    assert "animated" in warning and "1 kept" in warning and "1 removed" in warning

    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    (warning,) = _reports(capfd, "Warning")  # still animated: said again
    material.animation_data_clear()
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    assert _reports(capfd, "Warning") == []  # no animation, no warning


def test_the_curves_of_nla_strips_follow_too(bpy_addon, material):
    """An action pushed down to an NLA strip still animates the layers by position."""
    bpy = bpy_addon
    _animated_red_car_paint(bpy, material)
    anim = material.animation_data
    action = anim.action
    strip = anim.nla_tracks.new().strips.new("paint", 1, action)
    anim.action = None
    material.neural_layers.active_index = 1
    assert run_operator(bpy.ops.neural_layers.layer_move, direction="UP").finished
    bag = action.layers[0].strips[0].channelbag(strip.action_slot)
    assert [c.data_path for c in bag.fcurves] == ["neural_layers.layers[2].thickness"]
    assert _values_at(bpy, material, 10)["Red paint"][0] == 5.0

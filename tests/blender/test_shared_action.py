"""A layer edit on a material whose action slot another material uses too leaves the other's animation as it was.

Blender keys a layer's animation by its position (``neural_layers.layers[1].thickness``) and the stack editor moves
those curves with their layers. A material copied with its action shared (``Material.copy()``, Shift+D with
Preferences > Editing > Duplicate Data > Action off, or one slot assigned to two materials) animates from the same
curves: an edit of the copy's layers moved, removed and copied the original's keyframes too, and the original's
layers, unchanged, were animated by curves meant for other layers. The edited material now gets its own copy of the
action, as Blender's "make single user" of an action makes one.
"""

from __future__ import annotations

import pytest

from tests.blender.helpers import run_operator

pytest.importorskip("bpy")


def _keys(action, slot):
    """``{data path: ((frame, value), ...)}`` of the curves of ``slot`` in ``action``."""
    found = {}
    for layer in action.layers:
        for strip in layer.strips:
            bag = strip.channelbag(slot)
            for curve in bag.fcurves if bag is not None else ():
                found[curve.data_path] = tuple((round(k.co[0], 4), round(k.co[1], 4)) for k in curve.keyframe_points)
    return found


def _animation(mat):
    """The keys of the material's action (its slot) and of each of its NLA strips, by the action's name."""
    anim = mat.animation_data
    held = {"action": (anim.action.name, _keys(anim.action, anim.action_slot)) if anim.action else None}
    for track in anim.nla_tracks:
        for strip in track.strips:
            held[strip.name] = (strip.action.name, _keys(strip.action, strip.action_slot))
    return held


def _layer_values(bpy, mat, frame):
    """Each layer's (thickness, roughness) at ``frame``, by layer name."""
    bpy.context.scene.frame_set(frame)
    return {l.name: (round(l.thickness, 3), round(l.roughness, 3)) for l in mat.neural_layers.layers}


def _animated_pair(bpy, mat, share: str):
    """Red car paint on ``mat`` with its red coat's thickness keyed 0 -> 5 (frames 1, 10) and its clear coat's roughness
    keyed 0.2 -> 0.8; and a second material animated by the same action and slot: ``mat.copy()`` (``share`` "copy"),
    or a material of its own whose action and slot are set to ``mat``'s ("assigned")."""
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    layers = mat.neural_layers.layers
    layers[1].name, layers[2].name = "Red paint", "Clear coat"
    for frame, thickness, roughness in ((1, 0.0, 0.2), (10, 5.0, 0.8)):
        layers[1].thickness, layers[2].roughness = thickness, roughness
        layers[1].keyframe_insert("thickness", frame=frame)
        layers[2].keyframe_insert("roughness", frame=frame)
    if share == "copy":
        other = mat.copy()
    else:
        other = bpy.data.materials.new("Other")
        assert run_operator(bpy.ops.neural_layers.preset_apply, material=other.name, preset="red_car_paint").finished
        for item, name in zip(other.neural_layers.layers, ["Conductor", "Red paint", "Clear coat"], strict=True):
            item.name = name
        anim = other.animation_data_create()
        anim.action = mat.animation_data.action
        anim.action_slot = mat.animation_data.action_slot
    bpy.context.object.data.materials.append(other)  # in the scene: its animation is evaluated at a frame change
    assert other.animation_data.action == mat.animation_data.action
    assert other.animation_data.action_slot.handle == mat.animation_data.action_slot.handle
    return other


def _edit(bpy, mat, edit):
    """Run the stack editor's ``edit`` on ``mat`` (its 'Red paint' coat active)."""
    ops = bpy.ops.neural_layers
    mat.neural_layers.active_index = 1
    if edit == "add":
        mat.neural_layers.active_index = 0
        return run_operator(ops.layer_add, material=mat.name, layer_type="COATING")
    if edit == "move":
        return run_operator(ops.layer_move, material=mat.name, direction="UP")
    if edit == "remove":
        return run_operator(ops.layer_remove, material=mat.name)
    return run_operator(ops.layer_duplicate, material=mat.name)


# The edited material's layers, bottom to top, after each edit
_AFTER = {
    "add": ["Conductor", "Coating", "Red paint", "Clear coat"],
    "move": ["Conductor", "Clear coat", "Red paint"],
    "remove": ["Conductor", "Clear coat"],
    "duplicate": ["Conductor", "Red paint", "Coating", "Clear coat"],
}


@pytest.mark.parametrize("share", ["copy", "assigned"])
@pytest.mark.parametrize("edit", ["add", "move", "remove", "duplicate"])
def test_a_layer_edit_leaves_the_animation_of_a_material_sharing_the_action_as_it_was(
    bpy_addon, material, share, edit, capfd
):
    from tests.blender.test_stack_animation import _reports

    bpy = bpy_addon
    other = _animated_pair(bpy, material, share)
    before, values_before = _animation(material), _layer_values(bpy, material, 10)
    values_at_1 = _layer_values(bpy, material, 1)
    action = material.animation_data.action
    other_layers = [l.name for l in other.neural_layers.layers]
    assert _layer_values(bpy, other, 10) == values_before  # the same animation

    _reports(capfd, "Info")
    assert _edit(bpy, other, edit).finished
    # the edit says so: the edited material now has an action of its own
    assert any(f"'{action.name}'" in r and f"'{action.name}.001'" in r for r in _reports(capfd, "Info"))
    added = round(other.neural_layers.layers[1].thickness, 3), round(other.neural_layers.layers[1].roughness, 3)
    # the original: the same action, the same curves on the same paths with the same keys, the same values
    assert material.animation_data.action == action
    assert _animation(material) == before
    assert _layer_values(bpy, material, 10) == values_before
    assert _layer_values(bpy, material, 1) == values_at_1

    # the edited one: its own copy of the action, named as Blender names copies, in its slot, following its layers
    anim = other.animation_data
    assert anim.action != action and anim.action.name == f"{action.name}.001"
    assert anim.action_slot.identifier == material.animation_data.action_slot.identifier
    assert [u.name for u in material.animation_data.action_slot.users()] == [material.name]
    assert [l.name for l in other.neural_layers.layers] == _AFTER[edit] != other_layers
    for frame, thickness, roughness in ((1, 0.0, 0.2), (10, 5.0, 0.8)):
        values = _layer_values(bpy, other, frame)
        assert values["Clear coat"][1] == roughness
        if edit != "remove":
            assert values["Red paint"][0] == thickness
        if edit == "duplicate":
            assert values["Coating"][0] == thickness  # the duplicate animates as its source
        elif edit == "add":  # not animated: its defaults
            assert values["Coating"] == added


@pytest.mark.parametrize("tweaking", [False, True])
def test_the_nla_strips_of_a_material_sharing_their_action_keep_their_animation(bpy_addon, material, tweaking):
    """A copy's NLA strip shares its action with the original's strip: the edited one's strip gets its own copy, also
    while the strip is in tweak mode (where Blender refuses a change of action: it is left and entered again)."""
    bpy = bpy_addon
    other = _animated_pair(bpy, material, "copy")
    action = material.animation_data.action
    for mat in (material, other):
        anim = mat.animation_data
        anim.nla_tracks.new().strips.new("paint", 1, action)
        anim.action = None
    before, values_before = _animation(material), _layer_values(bpy, material, 10)
    anim = other.animation_data
    strip = anim.nla_tracks[0].strips[0]
    if tweaking:
        anim.nla_tracks.active, strip.select = anim.nla_tracks[0], True
        anim.use_tweak_mode = True
        assert anim.action == action

    assert _edit(bpy, other, "move").finished
    assert _animation(material) == before
    assert _layer_values(bpy, material, 10) == values_before
    assert strip.action != action and strip.action.name == f"{action.name}.001"
    assert anim.use_tweak_mode == tweaking and anim.action == (strip.action if tweaking else None)
    for frame, thickness, roughness in ((1, 0.0, 0.2), (10, 5.0, 0.8)):
        values = _layer_values(bpy, other, frame)
        assert values["Red paint"][0] == thickness and values["Clear coat"][1] == roughness


def test_an_action_is_copied_only_when_the_curves_of_a_shared_slot_change(bpy_addon, material):
    """No copy where nothing is shared, nor where the shared curves stay as they are (a coating added on top): one
    when an edit moves them."""
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    material.neural_layers.layers[1].keyframe_insert("thickness", frame=1)
    action = material.animation_data.action
    assert _edit(bpy, material, "move").finished
    assert material.animation_data.action == action and len(bpy.data.actions) == 1

    other = material.copy()
    before = _keys(action, material.animation_data.action_slot)
    assert list(before) == ["neural_layers.layers[2].thickness"]
    other.neural_layers.active_index = len(other.neural_layers.layers) - 1
    assert run_operator(bpy.ops.neural_layers.layer_add, material=other.name, layer_type="COATING").finished
    assert other.animation_data.action == action and len(bpy.data.actions) == 1

    other.neural_layers.active_index = 2
    assert run_operator(bpy.ops.neural_layers.layer_move, material=other.name, direction="DOWN").finished
    assert other.animation_data.action != action and len(bpy.data.actions) == 2
    assert _keys(action, material.animation_data.action_slot) == before

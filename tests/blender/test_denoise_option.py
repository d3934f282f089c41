"""The *Denoise* option's compositor once a user has built on it: the option completes it, and never clears it or
deletes it with the user's nodes (it cleared every node at each set, and turning it off deleted the group)."""

import pytest

bpy = pytest.importorskip("bpy")


def _denoise_on(scene):
    scene.render.engine = "NEURAL_LAYERED"
    scene.neural_render.denoise = True
    group = scene.compositing_node_group
    (denoise,) = [n for n in group.nodes if n.bl_idname == "CompositorNodeDenoise"]
    (out,) = [n for n in group.nodes if n.bl_idname == "NodeGroupOutput"]
    return group, denoise, out


def _glare_after_denoise(group, denoise, out):
    """A Glare node put between the Denoise node and the output, as a user adds one."""
    glare = group.nodes.new("CompositorNodeGlare")
    glare.name = "My glare"
    group.links.new(denoise.outputs["Image"], glare.inputs["Image"])
    group.links.new(glare.outputs["Image"], out.inputs[0])
    return glare


def _chain(group) -> set:
    return {(k.from_node.name, k.from_socket.name, k.to_node.name, k.to_socket.name) for k in group.links}


def test_nodes_a_user_added_survive_denoise_set_again_off_and_on(fresh_scene):
    from addon.blender import render_properties

    scene = fresh_scene.scene
    group, denoise, out = _denoise_on(scene)
    glare = _glare_after_denoise(group, denoise, out)
    links = _chain(group)
    assert {("Denoise", "Image", "My glare", "Image"), ("My glare", "Image", "Group Output", "Image")} <= links
    scene.neural_render.denoise = True  # the same value again: a script, a preset
    assert scene.compositing_node_group == group and "My glare" in group.nodes and _chain(group) == links
    scene.neural_render.denoise = False
    # kept, with the user's nodes and links; the Denoise node muted (the image passes through undenoised)
    assert scene.compositing_node_group == group and group.name in bpy.data.node_groups
    assert "My glare" in group.nodes and _chain(group) == links and denoise.mute and not glare.mute
    note = render_properties.denoise_off_note(scene)
    assert note is not None and group.name in note and "muted" in note
    scene.neural_render.denoise = True
    assert scene.compositing_node_group == group and not denoise.mute and _chain(group) == links
    assert render_properties.denoise_off_note(scene) is None and render_properties.denoise_note(scene) is None
    assert [n.bl_idname for n in group.nodes].count("CompositorNodeDenoise") == 1  # completed, not doubled
    # the option's edits are data edits of its update: the undo step a click makes gives them back
    bpy.ops.ed.undo_push(message="Denoise on")
    scene.neural_render.denoise = False
    bpy.ops.ed.undo_push(message="Denoise off")
    assert bpy.ops.ed.undo() == {"FINISHED"}
    group = bpy.context.scene.compositing_node_group  # undo read the data again: the old references are gone
    assert bpy.context.scene.neural_render.denoise and _chain(group) == links and not group.nodes["Denoise"].mute


def test_turning_denoise_off_removes_its_compositor_only_while_it_holds_nothing_else(fresh_scene):
    scene = fresh_scene.scene
    group, denoise, out = _denoise_on(scene)
    scene.neural_render.denoise = True  # set again: still the option's alone
    name = group.name
    scene.neural_render.denoise = False
    assert scene.compositing_node_group is None and name not in bpy.data.node_groups
    # a setting of its Denoise node changed, or a node added without a link: the user's, kept
    for edit in (
        lambda group, denoise: setattr(denoise.inputs["Prefilter"], "default_value", "None"),
        lambda group, denoise: group.nodes.new("CompositorNodeOutputFile"),
    ):
        group, denoise, out = _denoise_on(scene)
        edit(group, denoise)
        scene.neural_render.denoise = False
        assert scene.compositing_node_group == group and denoise.mute
        scene.compositing_node_group = None  # (the user's to remove)


def test_denoise_on_adds_back_only_what_its_compositor_lacks(fresh_scene):
    """A user deleted the Render Layers node, or a guide's link, and kept a node of theirs: Denoise set again adds
    them back, and keeps the rest."""
    scene = fresh_scene.scene
    group, denoise, out = _denoise_on(scene)
    glare = _glare_after_denoise(group, denoise, out)
    group.nodes.remove(next(n for n in group.nodes if n.bl_idname == "CompositorNodeRLayers"))
    assert not denoise.inputs["Image"].is_linked and not denoise.inputs["Albedo"].is_linked
    scene.neural_render.denoise = True
    assert "My glare" in group.nodes  # (read before the nodes it holds: a cleared group's are gone)
    (layers,) = [n for n in group.nodes if n.bl_idname == "CompositorNodeRLayers"]
    assert layers.scene == scene and all(denoise.inputs[s].is_linked for s in ("Image", "Normal", "Albedo"))
    assert out.inputs[0].links[0].from_node == glare  # its output stays the glare's


def test_a_compositor_the_option_made_before_it_recorded_its_contents_goes_when_it_is_turned_off(fresh_scene):
    """Files saved before the option recorded what it made: their group, untouched, still goes with the option; one
    the user added to stays."""
    from addon.blender import render_properties

    scene = fresh_scene.scene
    group, denoise, out = _denoise_on(scene)
    del group[render_properties._MADE_KEY]
    scene.neural_render.denoise = False
    assert scene.compositing_node_group is None
    group, denoise, out = _denoise_on(scene)
    del group[render_properties._MADE_KEY]
    _glare_after_denoise(group, denoise, out)
    scene.neural_render.denoise = False
    assert scene.compositing_node_group == group and "My glare" in group.nodes


def test_what_f12_advises_about_denoise_keeps_the_users_nodes(fresh_scene):
    """F12 said 'turn Denoise off and on again to link them' (the guides), the action that deleted a user's nodes;
    the advice now keeps them, and a muted Denoise node is said."""
    from addon.blender import render_properties

    scene = fresh_scene.scene
    group, denoise, out = _denoise_on(scene)
    _glare_after_denoise(group, denoise, out)
    for socket in ("Normal", "Albedo"):
        group.links.remove(denoise.inputs[socket].links[0])
    note = render_properties.denoise_note(scene)
    assert "guides" in note and "kept" in note
    scene.neural_render.denoise = False  # as the note advises
    scene.neural_render.denoise = True
    assert render_properties.denoise_note(scene) is None and "My glare" in group.nodes
    denoise.mute = True
    assert "muted" in render_properties.denoise_note(scene)

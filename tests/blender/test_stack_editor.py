"""The layer-stack editor: registration, editing operators, save/reload, undo, edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from addon.core.stack import PRESETS, Coating, Diffuse, Stack, alpha_from_artist_roughness
from tests.blender.helpers import run_operator

pytest.importorskip("bpy")


def _names(mat):
    return [(l.name, l.layer_type) for l in mat.neural_layers.layers]


def _snapshot(bpy):
    """Registered type names and the RNA properties of the data types an add-on may extend."""
    ids = ("Material", "Scene", "Object", "World", "Light", "WindowManager", "Image")
    props = {t: frozenset(getattr(bpy.types, t).bl_rna.properties.keys()) for t in ids}
    return frozenset(dir(bpy.types)), props


def test_register_is_idempotent_and_unregister_leaves_no_trace(bpy_addon):
    bpy = bpy_addon
    from addon import blender
    from addon.blender.properties import NLM_Layer, NLM_MaterialSettings

    registered = _snapshot(bpy)
    try:
        blender.unregister()
        bare = _snapshot(bpy)
        assert not hasattr(bpy.types.Material, "neural_layers")
        assert not NLM_Layer.is_registered and not NLM_MaterialSettings.is_registered
        blender.unregister()  # unregistering twice is harmless
        blender.register()
        blender.register()  # registering twice re-registers cleanly
        assert _snapshot(bpy) == registered
        blender.unregister()
        assert _snapshot(bpy) == bare  # no trace
    finally:
        blender.register()
    assert _snapshot(bpy) == registered
    added_types = registered[0] - bare[0]
    for name in (
        "NEURAL_LAYERS_OT_layer_add",
        "NEURAL_LAYERS_OT_preview_lobe",
        "NLM_UL_layers",
        "NLM_MT_presets",
        "NLM_PT_view3d_stack",
        "NLM_PT_shader_stack",
    ):
        assert name in added_types
    assert "neural_layers" in registered[1]["Material"] - bare[1]["Material"]
    assert bpy.types.NLM_PT_view3d_stack.bl_category == "Layers"
    assert bpy.types.NLM_PT_shader_stack.bl_space_type == "NODE_EDITOR"


def test_add_builds_base_then_coatings_and_refuses_invalid_orders(material, bpy_addon):
    ops = bpy_addon.ops.neural_layers
    r = run_operator(ops.layer_add, layer_type="COATING")
    assert r.error and "add a base layer first" in r.error
    assert run_operator(ops.layer_add, layer_type="CONDUCTOR").finished
    r = run_operator(ops.layer_add, layer_type="DIFFUSE")
    assert r.error and "already has a base" in r.error
    assert run_operator(ops.layer_add, layer_type="COATING").finished
    assert run_operator(ops.layer_add, layer_type="COATING").finished
    assert _names(material) == [("Conductor", "CONDUCTOR"), ("Coating", "COATING"), ("Coating.001", "COATING")]
    assert material.neural_layers.active_index == 2

    from addon.blender.stack_io import stack_from_material

    stack = stack_from_material(material)
    assert len(stack.coatings) == 2
    # the UI shows artist roughness; the core gets alpha = roughness^2
    item = material.neural_layers.layers[1]
    assert stack.coatings[0].roughness == pytest.approx(alpha_from_artist_roughness(item.roughness), rel=1e-6)


def test_move_duplicate_rename_remove(material, bpy_addon):
    ops = bpy_addon.ops.neural_layers
    assert run_operator(ops.preset_apply, preset="red_car_paint").finished
    s = material.neural_layers
    assert _names(material) == [("Conductor", "CONDUCTOR"), ("Coating", "COATING"), ("Coating.001", "COATING")]
    thick = s.layers[1].thickness
    s.active_index = 1
    assert run_operator(ops.layer_move, direction="UP").finished
    assert s.layers[2].thickness == pytest.approx(thick) and s.active_index == 2
    r = run_operator(ops.layer_move, direction="UP")
    assert r.error and "already at the top" in r.error
    s.active_index = 1
    r = run_operator(ops.layer_move, direction="DOWN")
    assert r.error and "stays at the bottom" in r.error

    s.active_index = 2
    assert run_operator(ops.layer_duplicate).finished
    assert len(s.layers) == 4 and s.layers[3].thickness == pytest.approx(thick) and s.active_index == 3
    s.active_index = 0
    r = run_operator(ops.layer_duplicate)
    assert r.error and "one base" in r.error

    s.active_index = 3
    assert run_operator(ops.layer_rename, name="Tinted coat").finished
    assert s.layers[3].name == "Tinted coat"
    r = run_operator(ops.layer_rename, name="   ")
    assert r.error and "cannot be empty" in r.error

    assert run_operator(ops.layer_remove).finished
    assert len(s.layers) == 3 and s.active_index == 2


def test_presets_match_core(material, bpy_addon):
    from addon.blender.stack_io import stack_from_material

    for name, stack in PRESETS.items():
        assert run_operator(bpy_addon.ops.neural_layers.preset_apply, preset=name).finished
        got = stack_from_material(material)
        assert len(got.layers) == len(stack.layers)
        for a, b in zip(got.layers, stack.layers, strict=True):
            assert type(a) is type(b)
            for key, va in vars(a).items():
                assert va == pytest.approx(getattr(b, key), rel=1e-5, abs=1e-6), (name, key)


def test_stack_survives_save_and_reload(material, bpy_addon, tmp_path):
    bpy = bpy_addon
    from addon.blender.stack_io import stack_from_material

    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="three_layer").finished
    material.neural_layers.layers[2].name = "Yellow"
    material.neural_layers.layers[2].thickness = 0.75
    before = stack_from_material(material)
    names = _names(material)
    path = tmp_path / "stack.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(app_template="")
    assert stack_from_material(bpy.data.materials["Material"]) is None
    bpy.ops.wm.open_mainfile(filepath=str(path))
    mat = bpy.data.materials["Material"]
    assert _names(mat) == names
    assert stack_from_material(mat) == before
    assert stack_from_material(mat).coatings[1].thickness == pytest.approx(0.75)


def test_undo_restores_a_removed_layer(material, bpy_addon):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    bpy.ops.ed.undo_push(message="three layers")
    material.neural_layers.active_index = 1
    # Python callers ask for the operator's undo push explicitly (second argument)
    assert run_operator(bpy.ops.neural_layers.layer_remove, "EXEC_DEFAULT", True).finished
    assert len(bpy.data.materials["Material"].neural_layers.layers) == 2
    bpy.ops.ed.undo()
    layers = bpy.data.materials["Material"].neural_layers.layers  # undo replaces the data blocks
    assert [l.layer_type for l in layers] == ["CONDUCTOR", "COATING", "COATING"]
    assert layers[1].thickness == pytest.approx(1.5)


def test_stack_conversion_round_trip_and_validation(material, bpy_addon):
    from addon.blender import stack_io

    stack = Stack(Diffuse((0.1, 0.2, 0.3)), (Coating(roughness=0.04, ior=1.3, albedo=(0.5, 0.6, 0.7), thickness=2.0),))
    stack_io.stack_to_material(stack, material)
    got = stack_io.stack_from_material(material)
    assert got.base.albedo == pytest.approx(stack.base.albedo)
    assert got.coatings[0].roughness == pytest.approx(0.04, rel=1e-5)
    assert got.coatings[0].ior == pytest.approx(1.3)

    material.neural_layers.layers[0].layer_type = "COATING"
    with pytest.raises(ValueError, match="bottom layer must be a base"):
        stack_io.stack_from_material(material)
    material.neural_layers.layers[0].layer_type = "DIFFUSE"
    material.neural_layers.layers[1].layer_type = "DIELECTRIC"
    with pytest.raises(ValueError, match="only Coating layers can go above the base"):
        stack_io.stack_from_material(material)
    assert stack_io.stack_from_material(None) is None


def test_typed_values_are_held_to_the_valid_range(material, bpy_addon):
    ops = bpy_addon.ops.neural_layers
    assert run_operator(ops.preset_apply, preset="coated_gold").finished
    coat = material.neural_layers.layers[1]
    coat.ior = 10.0
    coat.thickness = -3.0
    coat.roughness = 7.0
    assert coat.ior == pytest.approx(4.0) and coat.thickness == 0.0 and coat.roughness == 1.0
    # valid but outside the trained range: kept, the runtime clamps and says so
    coat.ior = 3.0
    from addon.blender.stack_io import stack_from_material

    assert stack_from_material(material).coatings[0].ior == pytest.approx(3.0)
    # soft limits are the trained ranges
    prop = coat.bl_rna.properties["ior"]
    assert (prop.soft_min, prop.soft_max) == pytest.approx((1.05, 2.0))
    assert prop.hard_max == pytest.approx(4.0)
    assert coat.bl_rna.properties["roughness"].soft_min == pytest.approx(math.sqrt(0.01))

    # NaN passes Blender's limits (scripts can set it): every operator names the layer and value
    coat.ior = float("nan")
    for op in ("evaluate_latent", "preview_lobe", "preview_sphere", "compare_reference"):
        r = run_operator(getattr(bpy_addon.ops.neural_layers, op))
        assert r.error and "layer 'Coating'" in r.error and "ior = nan" in r.error, (op, r.error)


@pytest.mark.parametrize(
    "op, kwargs",
    [
        ("layer_add", {"layer_type": "DIFFUSE"}),
        ("layer_remove", {}),
        ("layer_move", {"direction": "UP"}),
        ("layer_duplicate", {}),
        ("layer_rename", {"name": "x"}),
        ("preset_apply", {"preset": "coated_gold"}),
        ("evaluate_latent", {}),
        ("preview_lobe", {}),
        ("preview_sphere", {}),
        ("compare_reference", {}),
    ],
)
def test_every_operator_reports_edge_cases(bpy_addon, fresh_scene, op, kwargs):
    bpy = bpy_addon
    fn = getattr(bpy.ops.neural_layers, op)
    ob = fresh_scene.view_layer.objects.active

    fresh_scene.view_layer.objects.active = None
    r = run_operator(fn, **kwargs)
    assert r.error and "no active object" in r.error

    fresh_scene.view_layer.objects.active = ob
    ob.data.materials.clear()
    r = run_operator(fn, **kwargs)
    assert r.error and f"object {ob.name!r} has no material" in r.error

    r = run_operator(fn, material="Does not exist", **kwargs)
    assert r.error and "no material named 'Does not exist'" in r.error

    # empty stack: only adding a base or applying a preset can succeed
    mat = bpy.data.materials["Material"]
    ob.data.materials.append(mat)
    r = run_operator(fn, **kwargs)
    if op in ("layer_add", "preset_apply"):
        assert r.finished
    else:
        assert r.error and ("empty layer stack" in r.error or "has no layers" in r.error or "no layer stack" in r.error)


def test_enums_come_from_the_one_table_of_each_kind(bpy_addon):
    """Layer types from ``layer_types.LAYER_TYPES`` (the list's icons, Add Layer's defaults and the
    conversion's labels read it too) and model sizes from the model set's ``SIZES``."""
    bpy = bpy_addon
    from addon.blender import layer_types
    from addon.blender.properties import NLM_Layer, NLM_MaterialSettings
    from addon.core.neural import SIZES

    layer_enum = NLM_Layer.bl_rna.properties["layer_type"].enum_items
    assert [(e.identifier, e.name, e.description, e.icon) for e in layer_enum] == [
        (t.identifier, t.label, t.description, t.icon) for t in layer_types.LAYER_TYPES
    ]
    add_enum = bpy.ops.neural_layers.layer_add.get_rna_type().properties["layer_type"].enum_items
    assert [e.identifier for e in add_enum] == [t.identifier for t in layer_types.LAYER_TYPES]
    sizes = NLM_MaterialSettings.bl_rna.properties["model_size"].enum_items
    assert [e.identifier for e in sizes] == ["AUTO"] + [s.upper() for s in SIZES]
    assert all("parameters" in e.description for e in sizes if e.identifier != "AUTO")
    render = bpy.types.Scene.bl_rna.properties["neural_render"].fixed_type.properties["decoder_quality"].enum_items
    assert [e.identifier for e in render] == ["AUTO"] + [s.upper() for s in SIZES]


def test_buttons_grey_out_where_they_cannot_run(bpy_addon, fresh_scene, material, monkeypatch):
    """In the UI, poll() refuses (with the reason) what cannot run: no material, an empty stack,
    no baked texture; in background mode scripts may name any material, so poll lets them run."""
    import types

    from addon.blender import bake_ops, operator_base, operators

    bpy = bpy_addon
    ob = fresh_scene.view_layer.objects.active
    ctx = types.SimpleNamespace(object=ob)
    no_object = types.SimpleNamespace(object=None)
    assert operators.NLM_OT_preview_lobe.poll(no_object)  # background: scripts get a report instead
    monkeypatch.setattr(operator_base, "scripted", lambda: False)
    assert not operators.NLM_OT_layer_add.poll(no_object)
    assert operators.NLM_OT_layer_add.poll(ctx) and operators.NLM_OT_preset_apply.poll(ctx)
    needs_stack = (
        operators.NLM_OT_layer_remove,
        operators.NLM_OT_evaluate_latent,
        operators.NLM_OT_preview_lobe,
        operators.NLM_OT_preview_sphere,
        operators.NLM_OT_compare_reference,
        bake_ops.NLM_OT_bake_texture,
        bake_ops.NLM_OT_map_add,
    )
    assert not any(op.poll(ctx) for op in needs_stack)
    assert "empty" in operator_base.poll_problem(ctx, "stack")
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    assert all(op.poll(ctx) for op in needs_stack)
    assert not bake_ops.NLM_OT_texture_clear.poll(ctx)
    assert "no baked latent texture" in operator_base.poll_problem(ctx, "texture")
    ob.data.materials.clear()
    assert "has no material" in operator_base.poll_problem(ctx, "material")
    assert not operators.NLM_OT_preset_apply.poll(ctx)


def _addon_rna_structs(bpy):
    """Every property group and operator the add-on registers, as RNA structs."""
    from addon.blender import bake_ops, operators, properties, refine_ops, render_operators

    groups = [cls.bl_rna for cls in properties._CLASSES]
    groups += [
        bpy.types.Scene.bl_rna.properties["neural_render"].fixed_type,
        bpy.types.Material.bl_rna.properties["neural_refine"].fixed_type,
    ]
    ops = [
        c
        for m in (operators, bake_ops, render_operators, refine_ops)
        for c in m._CLASSES
        if issubclass(c, bpy.types.Operator)
    ]
    groups += [
        getattr(bpy.ops, c.bl_idname.split(".")[0]).__getattr__(c.bl_idname.split(".")[1]).get_rna_type() for c in ops
    ]
    return groups, ops


def test_every_property_enum_item_and_operator_has_a_tooltip(bpy_addon):
    bpy = bpy_addon
    groups, ops = _addon_rna_structs(bpy)
    missing = []
    for rna in groups:
        for key, prop in rna.properties.items():
            if key in ("rna_type", "name") and not prop.description:
                continue  # Blender's own
            if not prop.description.strip():
                missing.append(f"{rna.identifier}.{key}")
            if prop.type == "ENUM":
                missing += [f"{rna.identifier}.{key}[{e.identifier}]" for e in prop.enum_items if not e.description]
    missing += [c.__name__ for c in ops if not (c.__doc__ or "").strip()]
    assert missing == [], "\n".join(missing)


def test_users_save_share_and_apply_their_own_layer_presets(bpy_addon, material, tmp_path, monkeypatch):
    """Blender's preset system: + saves the stack as a preset file in the user's scripts folder,
    the presets menu lists it beside the bundled stacks, and choosing it restores the stack (on
    another material too: the file holds the stack as JSON)."""
    import os

    from addon.blender.operators import PRESET_SUBDIR
    from addon.core.stack import PRESETS

    bpy = bpy_addon
    monkeypatch.setitem(os.environ, "BLENDER_USER_SCRIPTS", str(tmp_path / "scripts"))
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    material.neural_layers.layers[1].thickness = 0.75  # an edit of the user's own
    saved = __import__("addon.blender.stack_io", fromlist=["x"]).stack_from_material(material)
    r = run_operator(bpy.ops.neural_layers.preset_add, name="My Paint")
    assert r.finished, r.error
    files = list((tmp_path / "scripts" / "presets" / PRESET_SUBDIR).glob("*.py"))
    assert [f.name for f in files] == ["My_Paint.py"]
    assert "neural_layers.stack_apply" in files[0].read_text()
    assert [str(files[0].parent)] == bpy.utils.preset_paths(PRESET_SUBDIR)

    other = bpy.data.materials.new("other")
    bpy.context.object.active_material = other
    r = run_operator(bpy.ops.script.execute_preset, filepath=str(files[0]), menu_idname="NLM_MT_presets")
    assert r.finished, r.error
    from addon.blender import stack_io

    assert stack_io.stack_from_material(other) == saved != PRESETS["red_car_paint"]
    # The menu's Remove Preset removes the user's preset applied last, and none once a bundled one came after it.
    assert bpy.types.NLM_MT_presets.bl_label == "My Paint"
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    assert bpy.types.NLM_MT_presets.bl_label == "Layer Presets"
    assert not run_operator(bpy.ops.neural_layers.preset_add, remove_active=True).finished
    assert files[0].exists()
    r = run_operator(bpy.ops.script.execute_preset, filepath=str(files[0]), menu_idname="NLM_MT_presets")
    assert r.finished, r.error
    from addon.blender import ui

    assert ui.removable_preset() == "My Paint"
    assert run_operator(bpy.ops.neural_layers.preset_add, remove_active=True).finished
    assert not files[0].exists()
    assert ui.removable_preset() is None  # the menu offers no Remove Preset 'Presets'
    r = run_operator(bpy.ops.neural_layers.stack_apply, stack="{not json")
    assert not r.finished and "not a layer stack" in r.error


def test_undo_after_a_preset_of_ones_own_returns_to_the_stack_before_it(bpy_addon, material, tmp_path, monkeypatch):
    """Blender's preset menu runs the file with no undo step of its own: the file asks for one, else Ctrl+Z after
    the preset undid the edit before it too (red car paint lost, back to coated gold)."""
    import os

    from addon.blender import stack_io
    from addon.blender.operators import PRESET_SUBDIR
    from addon.core.stack import PRESETS

    bpy = bpy_addon
    monkeypatch.setitem(os.environ, "BLENDER_USER_SCRIPTS", str(tmp_path / "scripts"))
    bpy.ops.ed.undo_push(message="start")
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="varnished_wood").finished
    assert run_operator(bpy.ops.neural_layers.preset_add, name="Mine").finished
    (preset,) = (tmp_path / "scripts" / "presets" / PRESET_SUBDIR).glob("*.py")
    assert run_operator(bpy.ops.neural_layers.preset_apply, "EXEC_DEFAULT", True, preset="coated_gold").finished
    assert run_operator(bpy.ops.neural_layers.preset_apply, "EXEC_DEFAULT", True, preset="red_car_paint").finished
    before = stack_io.stack_from_material(bpy.data.materials["Material"])
    # as the menu calls its entries: its preset operator, as Blender's UI calls an operator (an undo step when the
    # operator asks for one)
    op = getattr(bpy.ops.neural_layers, bpy.types.NLM_MT_presets.preset_operator.split(".")[1])
    r = run_operator(op, "EXEC_DEFAULT", True, filepath=str(preset), menu_idname="NLM_MT_presets")
    assert r.finished, r.error
    assert len(stack_io.stack_from_material(bpy.data.materials["Material"]).coatings) == len(
        PRESETS["varnished_wood"].coatings
    )
    bpy.ops.ed.undo()
    assert stack_io.stack_from_material(bpy.data.materials["Material"]) == before  # red car paint, not coated gold


def test_every_stack_edit_reaches_the_evaluated_material(bpy_addon, material):
    """What the viewport and the render operators export is the evaluated copy of a material, made again only
    when the material is tagged. An operator that removes a layer or a map from Python tags nothing by itself:
    the viewport kept showing the removed layer until another edit."""
    bpy = bpy_addon
    ops = bpy.ops.neural_layers

    def stack(s):
        return [(l.layer_type, round(l.roughness, 4), len(l.maps)) for l in s.layers]

    def evaluated():
        bpy.context.view_layer.update()
        return material.evaluated_get(bpy.context.evaluated_depsgraph_get()).neural_layers

    edits = [
        (ops.preset_apply, {"preset": "coated_gold"}),
        (ops.layer_add, {}),
        (ops.layer_duplicate, {}),
        (ops.layer_move, {"direction": "DOWN"}),
        (ops.layer_remove, {}),
        (ops.map_add, {"parameter": "ROUGHNESS"}),
        (ops.map_remove, {}),
    ]
    for op, kwargs in edits:
        assert run_operator(op, **kwargs).finished, op
        assert stack(evaluated()) == stack(material.neural_layers), op
    material.neural_layers.bake_refine = 3.0  # part of a baked texture's key
    assert evaluated().bake_refine == 3.0


def test_a_linked_material_is_read_but_never_edited_and_its_texture_found_beside_its_library(
    bpy_addon, fresh_scene, tmp_path, monkeypatch
):
    """A material linked from another file is read-only: an edit would be lost when the file is saved, so the
    editing buttons grey out and scripts get the reason; what only reads it still runs. Its baked texture's
    "//" path is relative to its library, not to the open file."""
    import types

    from addon.blender import bake_state, operator_base, operators

    bpy = bpy_addon
    (tmp_path / "lib" / "textures").mkdir(parents=True)
    (tmp_path / "shot").mkdir()
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    bpy.data.materials["Material"].neural_layers.texture_path = "//textures/Material.exr"
    (tmp_path / "lib" / "textures" / "Material.exr").write_bytes(b"")
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "lib" / "lib.blend"))
    bpy.ops.wm.read_homefile(app_template="")
    with bpy.data.libraries.load(str(tmp_path / "lib" / "lib.blend"), link=True) as (_, linked):
        linked.materials = ["Material"]
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot" / "shot.blend"))
    ob = fresh_scene.view_layer.objects.active
    ob.material_slots[0].link = "OBJECT"
    ob.material_slots[0].material = linked.materials[0]
    mat = ob.active_material
    assert mat.library is not None and len(mat.neural_layers.layers) == 2
    monkeypatch.setattr(operator_base, "scripted", lambda: False)
    ctx = types.SimpleNamespace(object=ob)
    assert not operators.NLM_OT_layer_add.poll(ctx) and not operators.NLM_OT_preset_apply.poll(ctx)
    assert "linked" in operator_base.poll_problem(ctx, "stack", edits=True)
    assert operators.NLM_OT_preview_lobe.poll(ctx) and operators.NLM_OT_preset_add.poll(ctx)
    monkeypatch.setattr(operator_base, "scripted", lambda: True)
    r = run_operator(bpy.ops.neural_layers.layer_add, layer_type="COATING")
    assert not r.finished and "linked" in r.error and "Make Local" in r.error
    assert len(mat.neural_layers.layers) == 2
    # the texture is found beside the library (the empty file is then refused for its content, not as missing)
    state = bake_state.current_texture(mat)[1]
    assert "missing" not in state, state
    # a library override of it: Blender does not override its layer stack, so an edit there crashed (Add Layer:
    # "not supported for this collection") or was lost at the next save (a rename, a slider)
    override = mat.override_create(remap_local_usages=True)
    ob.material_slots[0].material = override
    assert override.override_library is not None and override.library is None
    r = run_operator(bpy.ops.neural_layers.layer_add, layer_type="COATING")
    assert not r.finished and "library override" in r.error and "lib.blend" in r.error
    monkeypatch.setattr(operator_base, "scripted", lambda: False)
    assert not operators.NLM_OT_layer_add.poll(ctx) and operators.NLM_OT_preview_lobe.poll(ctx)


def test_values_at_the_ends_of_their_ranges_make_a_valid_stack(material, bpy_addon):
    """Blender holds the fields in float32: Eta's minimum 0.01 is 0.0099999998 there and g's end 0.99 is
    0.9900000095, just outside the core's ranges, so dragging a field to its end made the whole stack invalid (a
    red error in the panel, and F12 rendered the material as a Lambertian)."""
    from addon.blender import stack_io

    assert run_operator(bpy_addon.ops.neural_layers.preset_apply, preset="coated_gold").finished
    s = material.neural_layers
    s.layers[0].conductor_mode = "ETA_K"
    s.layers[0].eta = (0.01, 10.0, 0.01)
    s.layers[1].g = 0.99
    stack = stack_io.stack_from_material(material)
    assert stack.base.eta == (0.01, 10.0, 0.01) and stack.coatings[0].g == 0.99
    s.layers[1].g = -0.99
    assert stack_io.stack_from_material(material).coatings[0].g == -0.99


def test_a_layer_of_an_unknown_type_is_not_duplicated_into_a_half_made_one(material, bpy_addon):
    """A file from a newer version holds a layer type this one does not know: Duplicate refuses it by name, where
    it added a nameless Diffuse layer and failed (cancelled, so no undo step took it back)."""
    assert run_operator(bpy_addon.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    s = material.neural_layers
    s.layers[1]["layer_type"] = 99  # an enum value this version has no item for: it reads as ''
    assert s.layers[1].layer_type == ""
    before = _names(material)
    s.active_index = 1
    r = run_operator(bpy_addon.ops.neural_layers.layer_duplicate)
    assert r.error and "does not know" in r.error
    assert _names(material) == before


def test_an_edit_that_leaves_the_stack_as_it_was_keeps_a_refined_latent(material, bpy_addon):
    """Ticking Auto Update Latent, adding a parameter map or editing one (none changes the stack) encoded the stack
    again over a refined latent, which F12 then stopped rendering."""
    from addon.blender import stack_io

    ops = bpy_addon.ops.neural_layers
    assert run_operator(ops.preset_apply, preset="coated_gold").finished
    s = material.neural_layers
    refined = np.asarray(stack_io.latent_of(material)) + 0.25  # as Refine stores one, for the same stack and size
    s.latent = refined.tolist()
    material.neural_refine.kept = "yes"
    s.auto_latent = False
    s.auto_latent = True
    s.active_index = 1
    assert run_operator(ops.map_add, parameter="ROUGHNESS").finished
    assert material.neural_refine.kept == "yes"
    np.testing.assert_allclose(stack_io.latent_of(material), refined.reshape(3, 32), rtol=1e-6)
    s.layers[1].roughness = 0.5  # an edit of the stack itself: encoded again
    assert material.neural_refine.kept == "replaced"


def test_the_shader_editors_pinned_material_is_the_one_edited(bpy_addon, fresh_scene, material):
    """The Layers tab of a Shader Editor that pins another material showed and edited the active object's."""
    import types

    from addon.blender import operator_base

    bpy = bpy_addon
    pinned = bpy.data.materials.new("Pinned")
    ob = fresh_scene.view_layer.objects.active
    shader_editor = types.SimpleNamespace(
        object=ob, space_data=types.SimpleNamespace(type="NODE_EDITOR", id=pinned, pin=True)
    )
    viewport = types.SimpleNamespace(object=ob, space_data=types.SimpleNamespace(type="VIEW_3D"))
    assert operator_base.context_material(shader_editor) == pinned
    assert operator_base.context_material(viewport) == material
    assert "'Pinned'" in operator_base.poll_problem(shader_editor, "stack")  # its stack, not the active one's


def _printed(capfd, kind):
    """The reports of ``kind`` ("Warning", "Info") printed since the last call (background Blender prints them)."""
    out = capfd.readouterr().out
    return [line.removeprefix(f"{kind}: ") for line in out.splitlines() if line.startswith(f"{kind}: ")]


def _assert_same_stack(got, expected):
    """The same layers with the same values, up to Blender's float32."""
    assert [type(l) for l in got.layers] == [type(l) for l in expected.layers]
    for a, b in zip(got.layers, expected.layers, strict=True):
        for key, value in vars(a).items():
            assert value == pytest.approx(getattr(b, key), rel=1e-5, abs=1e-6), key


def _green_metal_under_a_clear_coat(bpy, mat):
    """A conductor given by its colour (Specify: Colour) under a coat, both renamed: what a bundled preset is not."""
    ops = bpy.ops.neural_layers
    assert run_operator(ops.layer_add, material=mat.name, layer_type="CONDUCTOR").finished
    assert run_operator(ops.layer_add, material=mat.name, layer_type="COATING").finished
    layers = mat.neural_layers.layers
    layers[0].f0 = (0.2, 0.9, 0.3)
    layers[0].name, layers[1].name = "Green metal", "Clear Coat"
    layers[1].roughness = 0.25
    return [(l.name, l.layer_type, l.conductor_mode if l.layer_type == "CONDUCTOR" else "") for l in layers]


def test_copy_and_paste_layer_stack_carry_it_to_another_material(bpy_addon, material, monkeypatch):
    """Blender's Copy Material / Paste Material leave the layer stack behind: Copy Layer Stack and Paste Layer Stack
    carry it (names and a conductor's colour too) through the clipboard, as a layer preset's JSON."""
    from addon.blender import operators, stack_io

    bpy = bpy_addon
    ops = bpy.ops.neural_layers
    monkeypatch.setattr(operators, "_copied_stack", "")  # headless Blender has no system clipboard: the session's copy
    bpy.context.window_manager.clipboard = ""
    r = run_operator(ops.stack_copy)
    assert r.error and "empty layer stack" in r.error
    shown = _green_metal_under_a_clear_coat(bpy, material)
    assert run_operator(ops.stack_copy).finished
    copied = stack_io.stack_from_material(material)

    target = bpy.data.materials.new("Target")
    assert run_operator(ops.preset_apply, material="Target", preset="red_car_paint").finished
    bpy.ops.ed.undo_push(message="before paste")
    assert run_operator(ops.stack_paste, "EXEC_DEFAULT", True, material="Target").finished
    target = bpy.data.materials["Target"]
    got = [
        (l.name, l.layer_type, l.conductor_mode if l.layer_type == "CONDUCTOR" else "")
        for l in target.neural_layers.layers
    ]
    assert got == shown
    assert tuple(target.neural_layers.layers[0].f0) == pytest.approx((0.2, 0.9, 0.3))
    assert stack_io.stack_from_material(target) == copied
    bpy.ops.ed.undo()  # the paste is one undo step
    assert len(bpy.data.materials["Target"].neural_layers.layers) == len(PRESETS["red_car_paint"].layers)

    before = _names(bpy.data.materials["Target"])
    for text, expected in (
        ("Hello from another application", "the clipboard holds no layer stack: the text is not valid JSON"),
        ('{"colour": [1, 0, 0]}', "the clipboard holds no layer stack: the text holds no 'base' layer"),
        ("", "the clipboard is empty"),
    ):
        monkeypatch.setattr(operators, "_copied_stack", text)
        r = run_operator(ops.stack_paste, material="Target")
        assert r.error and expected in r.error, r.error
        assert "Copy Layer Stack" in r.error and "JSONDecodeError" not in r.error and "\\n" not in r.error
        assert _names(bpy.data.materials["Target"]) == before


def test_the_layer_stack_panel_has_a_menu_with_copy_and_paste(bpy_addon, fresh_scene):
    """The stack panel's side column holds the menu, and the menu the two operators (with icons Blender has)."""
    import types

    from tests.blender.test_sidebar import draw

    bpy = bpy_addon
    context = types.SimpleNamespace(object=fresh_scene.view_layer.objects.active)
    assert ("menu", "NLM_MT_stack_specials") in draw(bpy.types.NLM_PT_view3d_stack, context)
    assert ("menu", "NLM_MT_stack_specials") in draw(bpy.types.NLM_PT_shader_stack, context)
    assert draw(bpy.types.NLM_MT_stack_specials, context) == [
        ("operator", "neural_layers.stack_copy"),
        ("operator", "neural_layers.stack_paste"),
    ]


def test_a_preset_keeps_layer_names_and_a_conductor_given_by_its_colour(bpy_addon, material, tmp_path, monkeypatch):
    """A preset restored a conductor given by its colour as a complex IOR (its colour lost) and renamed every layer;
    presets saved before it held names (a bare Stack.to_json()) still apply, with default names."""
    import os

    from addon.blender import stack_io
    from addon.blender.operators import PRESET_SUBDIR, preset_file_text

    bpy = bpy_addon
    monkeypatch.setitem(os.environ, "BLENDER_USER_SCRIPTS", str(tmp_path / "scripts"))
    shown = _green_metal_under_a_clear_coat(bpy, material)
    saved = stack_io.stack_from_material(material)
    assert run_operator(bpy.ops.neural_layers.preset_add, name="Green").finished
    (preset,) = (tmp_path / "scripts" / "presets" / PRESET_SUBDIR).glob("*.py")
    other = bpy.data.materials.new("Other")
    bpy.context.object.active_material = other
    apply = bpy.ops.neural_layers.preset_file_apply
    assert run_operator(apply, filepath=str(preset), menu_idname="NLM_MT_presets").finished
    assert [
        (l.name, l.layer_type, l.conductor_mode if l.layer_type == "CONDUCTOR" else "")
        for l in other.neural_layers.layers
    ] == shown
    assert tuple(other.neural_layers.layers[0].f0) == pytest.approx((0.2, 0.9, 0.3))
    assert stack_io.stack_from_material(other) == saved

    old = tmp_path / "old.py"  # as the add-on wrote presets before: the stack alone
    old.write_text(preset_file_text(PRESETS["coated_gold"].to_json()))
    assert run_operator(apply, filepath=str(old), menu_idname="NLM_MT_presets").finished
    assert _names(other) == [("Conductor", "CONDUCTOR"), ("Coating", "COATING")]
    assert other.neural_layers.layers[0].conductor_mode == "ETA_K"
    _assert_same_stack(stack_io.stack_from_material(other), PRESETS["coated_gold"])

    import json

    data = json.loads(stack_io.stack_text(material))
    data["sidebar"][0]["f0"] = [2.0, 0.5, 0.5]
    r = run_operator(bpy.ops.neural_layers.stack_apply, stack=json.dumps(data))
    assert r.error and "f0[R] = 2" in r.error and "valid range" in r.error
    data["sidebar"] = data["sidebar"][:1]
    r = run_operator(bpy.ops.neural_layers.stack_apply, stack=json.dumps(data))
    assert r.error and "one entry per layer (2)" in r.error
    _assert_same_stack(stack_io.stack_from_material(other), PRESETS["coated_gold"])  # neither applied


def test_a_broken_preset_file_says_which_file_and_what_is_wrong_in_words(bpy_addon, material, tmp_path):
    """The reports read "Failed to execute the preset: RuntimeError('Error: not a layer stack (ValueError: ...); a
    preset holds Stack.to_json()\\n')": a Python repr, a literal \\n and developer wording, without the file."""
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    before = _names(material)
    stack_apply = "import bpy\nbpy.ops.neural_layers.stack_apply(stack={!r})\n"
    broken = {
        "syntax": (
            "import bpy\nbpy.ops.neural_layers.stack_apply(stack='{\n",
            "line 2 of the file is not valid Python",
        ),
        "not_json": (stack_apply.format("{not json"), "the text is not valid JSON (line 1, column 2"),
        "a_list": (stack_apply.format("[1, 2]"), "holds no 'base' layer"),
        "coating_base": (stack_apply.format('{"base": {"type": "Coating"}}'), "bottom layer is a Coating"),
        "out_of_range": (
            stack_apply.format('{"base": {"type": "Diffuse", "albedo": [5, 0.5, 0.5]}}'),
            "albedo[R] = 5 is outside the valid range",
        ),
        "raises": ("raise RuntimeError('boom')\n", "running it stopped with an error: boom"),
        "empty": ("", "the file is empty"),
    }
    for name, (text, reason) in broken.items():
        path = tmp_path / f"bad_{name}.py"
        path.write_text(text)
        r = run_operator(bpy.ops.neural_layers.preset_file_apply, filepath=str(path), menu_idname="NLM_MT_presets")
        assert r.error and f"Preset file 'bad_{name}.py' was not applied: " in r.error and reason in r.error, r.error
        for developer in ("RuntimeError", "ValueError", "SyntaxError", "Error(", "\\n", "Stack.to_json", "repr"):
            assert developer not in r.error, (name, r.error)
        assert r.error.count("\n") <= 1  # one line (Blender ends the message with a newline)
        assert _names(material) == before
    r = run_operator(
        bpy.ops.neural_layers.preset_file_apply, filepath=str(tmp_path / "gone.py"), menu_idname="NLM_MT_presets"
    )
    assert r.error and "'gone.py'" in r.error and "no such file" in r.error and "FileNotFoundError" not in r.error


def test_removing_the_base_under_coatings_warns_what_renders(bpy_addon, material, capfd):
    """Removing the base while coatings sit on it left an invalid stack, rendered as a Lambertian, in silence."""
    from addon.blender import stack_io

    ops = bpy_addon.ops.neural_layers
    assert run_operator(ops.preset_apply, preset="red_car_paint").finished
    material.neural_layers.active_index = 2  # a coating: no warning
    capfd.readouterr()
    assert run_operator(ops.layer_remove).finished
    assert _printed(capfd, "Warning") == []
    material.neural_layers.active_index = 0
    assert run_operator(ops.layer_remove).finished  # allowed, as Blender allows it, and said
    (warning,) = _printed(capfd, "Warning")
    assert "no base layer now" in warning and "Lambertian" in warning and "Add Layer" in warning
    with pytest.raises(ValueError, match="bottom layer must be a base"):
        stack_io.stack_from_material(material)
    assert run_operator(ops.layer_add, layer_type="DIFFUSE").finished  # the way back: a base goes under the coating
    assert _names(material)[0] == ("Diffuse", "DIFFUSE") and stack_io.stack_from_material(material) is not None

"""The sidebar drawn headless: panels draw into a recording layout (no GPU or window needed),
every property they show exists, and the list shows the base at the bottom."""

from __future__ import annotations

import types

import pytest

from tests.blender.helpers import run_operator

pytest.importorskip("bpy")


def _icons():
    bpy = __import__("bpy")
    return set(bpy.types.UILayout.bl_rna.functions["prop"].parameters["icon"].enum_items.keys())


class RecordingLayout:
    """Stands in for ``UILayout``: records what would be drawn and checks it refers to real data
    (properties, operators, menus, lists and icon names that exist)."""

    icons = None

    def __init__(self, log):
        self.log = log
        self.enabled = True
        self.alert = False
        if RecordingLayout.icons is None:
            RecordingLayout.icons = _icons()

    def __getattribute__(self, name):
        attr = object.__getattribute__(self, name)
        if callable(attr) and not name.startswith("_"):

            def checked(*args, **kwargs):
                icon = kwargs.get("icon")
                assert icon is None or icon in RecordingLayout.icons, f"unknown icon {icon!r}"
                return attr(*args, **kwargs)

            return checked
        return attr

    def _child(self, *args, **kwargs):
        return RecordingLayout(self.log)

    row = column = box = split = _child

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.log.append(("prop", name))

    def operator(self, idname, **kwargs):
        module, op = idname.split(".")
        assert hasattr(getattr(__import__("bpy").ops, module), op), idname
        self.log.append(("operator", idname))
        button = types.SimpleNamespace()  # the properties the panel sets on the button
        self.log.buttons.append((idname, button))
        return button

    def operator_menu_enum(self, idname, prop, **kwargs):
        self.log.append(("operator_menu_enum", idname, prop))

    def template_list(self, list_id, _list_name, data, prop, active_data, active_prop, **kwargs):
        assert hasattr(__import__("bpy").types, list_id), list_id
        assert prop in data.bl_rna.properties and active_prop in active_data.bl_rna.properties
        self.log.append(("template_list", list_id))

    def template_ID(self, data, prop, **kwargs):
        self.log.append(("template_ID", prop))

    def menu(self, menu_id, **kwargs):
        assert hasattr(__import__("bpy").types, menu_id), menu_id
        self.log.append(("menu", menu_id))

    def template_icon(self, icon_value=0, scale=1.0):
        self.log.append(("template_icon", icon_value))

    def label(self, text="", **kwargs):
        self.log.append(("label", text))
        self.log.icons.append((text, kwargs.get("icon", "NONE")))

    def separator(self, **kwargs):
        pass


class DrawLog(list):
    """What a ``draw`` put on the layout, a tuple a call; beside it, the buttons ``operator`` gave (idname, the
    properties the panel set on it) and each label's (text, icon)."""

    def __init__(self):
        super().__init__()
        self.buttons, self.icons = [], []


def draw(panel_cls, context):
    log = DrawLog()
    panel_cls.draw(types.SimpleNamespace(layout=RecordingLayout(log)), context)
    return log


def _ctx(fresh_scene):
    return types.SimpleNamespace(object=fresh_scene.view_layer.objects.active)


@pytest.mark.parametrize(
    "panel", ["NLM_PT_view3d_stack", "NLM_PT_shader_stack", "NLM_PT_view3d_preview", "NLM_PT_shader_preview"]
)
def test_panels_draw_in_every_state(bpy_addon, fresh_scene, panel):
    bpy = bpy_addon
    cls = getattr(bpy.types, panel)
    assert cls.bl_category == "Layers" and cls.bl_region_type == "UI"
    ob = fresh_scene.view_layer.objects.active

    log = draw(cls, _ctx(fresh_scene))  # empty stack
    if "stack" in panel:
        assert ("template_list", "NLM_UL_layers") in log and ("menu", "NLM_MT_presets") in log
        assert ("operator_menu_enum", "neural_layers.layer_add", "layer_type") in log
        assert any(e[0] == "label" and "Add a base layer" in e[1] for e in log)

    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="red_car_paint").finished
    log = draw(cls, _ctx(fresh_scene))
    if "stack" in panel:
        # the active layer is the top coating: its fields, and no base-only fields
        props = [e[1] for e in log if e[0] == "prop"]
        assert {"ior", "medium_albedo", "thickness", "g", "roughness"} <= set(props)
        assert "albedo" not in props and "eta" not in props
        ob.active_material.neural_layers.active_index = 0
        props = [e[1] for e in draw(cls, _ctx(fresh_scene)) if e[0] == "prop"]
        assert "conductor_mode" in props and "eta" in props and "thickness" not in props
    else:
        assert ("operator", "neural_layers.preview_lobe") in log and (
            "operator",
            "neural_layers.compare_reference",
        ) in log

    ob.active_material.neural_layers.layers[0].layer_type = "COATING"  # invalid: shows why
    log = draw(cls, _ctx(fresh_scene))
    if "stack" in panel:
        assert any(e[0] == "label" and "bottom" in e[1] for e in log)

    ob.data.materials.clear()
    log = draw(cls, _ctx(fresh_scene))
    assert any(e[0] == "label" and "material" in e[1].lower() for e in log)
    log = draw(cls, types.SimpleNamespace(object=None))
    assert any(e[0] == "label" for e in log)


def test_panels_poll_for_3d_view_and_shader_editor_only(bpy_addon):
    bpy = bpy_addon
    view3d = types.SimpleNamespace(space_data=types.SimpleNamespace(type="VIEW_3D"))
    shader = types.SimpleNamespace(space_data=types.SimpleNamespace(type="NODE_EDITOR", tree_type="ShaderNodeTree"))
    geo = types.SimpleNamespace(space_data=types.SimpleNamespace(type="NODE_EDITOR", tree_type="GeometryNodeTree"))
    assert bpy.types.NLM_PT_view3d_stack.poll(view3d)
    assert bpy.types.NLM_PT_shader_stack.poll(shader)
    assert not bpy.types.NLM_PT_shader_stack.poll(geo)


def test_list_shows_base_at_the_bottom(bpy_addon, fresh_scene, material):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="three_layer").finished
    ul = types.SimpleNamespace(filter_name="", bitflag_filter_item=1 << 30)
    flags, order = bpy.types.NLM_UL_layers.filter_items(ul, None, material.neural_layers, "layers")
    assert flags == [1 << 30] * 4
    assert order == [3, 2, 1, 0]  # item 0 (the base) is drawn in the last row


def test_list_rows_draw_name_and_type(bpy_addon, fresh_scene, material):
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    s = material.neural_layers
    for item in s.layers:
        log = DrawLog()
        bpy.types.NLM_UL_layers.draw_item(None, fresh_scene, RecordingLayout(log), s, item, 0, s, "active_index", 0)
        assert ("prop", "name") in log
        assert ("label", {"CONDUCTOR": "Conductor", "COATING": "Coating"}[item.layer_type]) in log


def test_previews_are_shown_in_the_sidebar_panel(bpy_addon, fresh_scene, material):
    """After Preview Lobe the panel shows the lobe (``template_icon`` of the image's preview), whose
    pixels are the preview image encoded for display, there at once (no preview rendering job)."""
    import numpy as np

    from addon.core.render.film import to_srgb

    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    s = material.neural_layers
    s.lobe_resolution, s.preview_method, s.walks = 24, "REFERENCE", 4
    log = draw(bpy.types.NLM_PT_view3d_preview, _ctx(fresh_scene))
    assert not any(e[0] == "template_icon" for e in log)  # nothing previewed yet
    assert run_operator(bpy.ops.neural_layers.preview_lobe).finished
    image = bpy.data.images[f"Lobe {material.name}"]
    log = draw(bpy.types.NLM_PT_view3d_preview, _ctx(fresh_scene))
    assert ("template_icon", image.preview.icon_id) in log
    assert any(e[0] == "label" and e[1] == "Lobe" for e in log)
    preview = image.preview
    assert tuple(preview.image_size) == (24, 24)
    shown = np.empty(24 * 24 * 4, np.float32)
    preview.image_pixels_float.foreach_get(shown)
    px = np.empty(24 * 24 * 4, np.float32)
    image.pixels.foreach_get(px)
    px, shown = px.reshape(24, 24, 4), shown.reshape(24, 24, 4)
    np.testing.assert_allclose(shown[..., :3], to_srgb(px[..., :3]), atol=1 / 255)  # previews hold 8 bits
    assert shown[..., :3].max() > 0.1


def _texture_lines(bpy, context):
    """The Latent Texture panel's lines after its Bake button: (text, icon) of each label."""
    log = draw(bpy.types.NLM_PT_view3d_bake, context)
    return list(log.icons)


def test_the_latent_texture_panel_says_whether_the_baked_texture_is_current(
    bpy_addon, fresh_scene, material, tmp_path, monkeypatch
):
    """It showed the baked file's name whatever its state: out of date or missing, the material renders without it."""
    import os

    from addon.blender import bake_ops, bake_state
    from tests.blender.test_bake_addon import stand_in_encoder

    bpy = bpy_addon
    monkeypatch.setattr(bake_ops, "neural_encoder", stand_in_encoder)
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="varnished_wood").finished
    material.neural_layers.bake_directory = str(tmp_path)
    assert run_operator(bpy.ops.neural_layers.bake_texture).finished
    path = bake_state.baked_texture_state(material)[0]
    assert path is not None
    assert _texture_lines(bpy, _ctx(fresh_scene)) == [(f"baked: {os.path.basename(path)}", "TEXTURE")]
    material.neural_layers.layers[1].thickness = 2.0
    assert _texture_lines(bpy, _ctx(fresh_scene)) == [("baked texture is out of date: bake again", "ERROR")]
    material.neural_layers.layers[1].thickness = 0.6  # undone: the bake is the material's again
    assert _texture_lines(bpy, _ctx(fresh_scene))[0][1] == "TEXTURE"
    os.remove(path)
    lines = _texture_lines(bpy, _ctx(fresh_scene))
    assert lines[0] == ("baked texture missing:", "ERROR") and path.endswith(lines[-1][0])


def test_the_latent_texture_panel_reads_the_bake_state_again_only_when_what_it_reads_changed(
    bpy_addon, fresh_scene, material, tmp_path, monkeypatch
):
    """The panel draws at every hover: the state of a material whose maps are painted images hashes their pixels
    (0.1 s for a 2048-pixel map). It is read again after an edit of the stack or the texture's file, and, for a map
    whose pixels are Blender's, which no cheap key follows, after ``PAINTED_STATE_S``."""
    import os
    from types import SimpleNamespace

    import numpy as np

    from addon.blender import bake_state, ui

    bpy = bpy_addon
    reads = []
    real = bake_state.baked_texture_state
    monkeypatch.setattr(bake_state, "baked_texture_state", lambda mat: reads.append(mat.name) or real(mat))
    clock = [1000.0]
    monkeypatch.setattr(ui, "time", SimpleNamespace(monotonic=lambda: clock[0]), raising=False)
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="varnished_wood").finished
    s = material.neural_layers
    texture = tmp_path / "Material.exr"
    s.texture_path = str(texture)  # not there
    ctx = _ctx(fresh_scene)
    for _ in range(3):
        assert _texture_lines(bpy, ctx)[0] == ("baked texture missing:", "ERROR")
    assert len(reads) == 1
    s.layers[1].roughness = 0.5
    _texture_lines(bpy, ctx)
    assert len(reads) == 2
    texture.write_bytes(b"not a texture")  # the file there now
    _texture_lines(bpy, ctx)
    _texture_lines(bpy, ctx)
    assert len(reads) == 3
    os.utime(texture, ns=(1, 1))  # written again
    _texture_lines(bpy, ctx)
    assert len(reads) == 4
    s.active_index = 1
    assert run_operator(bpy.ops.neural_layers.map_add, parameter="ROUGHNESS").finished
    painted = bpy.data.images.new("painted", width=4, height=4)
    s.layers[1].maps[0].image = painted
    _texture_lines(bpy, ctx)
    assert len(reads) == 5
    painted.pixels.foreach_set(np.zeros(4 * 4 * 4, np.float32))  # a stroke of paint: no key follows it
    _texture_lines(bpy, ctx)
    assert len(reads) == 5
    clock[0] += ui.PAINTED_STATE_S
    _texture_lines(bpy, ctx)
    assert len(reads) == 6


def test_the_refine_button_refines_for_the_materials_refine_budget(bpy_addon, fresh_scene, material):
    """Refine's budget was its operator's default, 8 s, with no way to change it in the sidebar: a refinement that
    budget cut short could only say so."""
    bpy = bpy_addon
    assert run_operator(bpy.ops.neural_layers.preset_apply, preset="coated_gold").finished
    material.neural_layers.refine_budget = 30.0
    log = draw(bpy.types.NLM_PT_view3d_preview, _ctx(fresh_scene))
    assert ("prop", "refine_budget") in log
    (button,) = [b for idname, b in log.buttons if idname == "neural_layers.refine_latent"]
    assert button.budget == 30.0

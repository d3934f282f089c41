"""The render settings' decoder choice: Auto (by measured error, with a tolerance) or a fixed size."""

from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from addon.core import quality  # noqa: E402
from addon.core.neural import MODEL_DIR  # noqa: E402
from addon.core.stack import PRESETS  # noqa: E402

SIZES = quality.available_sizes()
needs_layering = pytest.mark.skipif(
    not SIZES or not (MODEL_DIR / f"layering_{SIZES[0]}.onnx").exists(), reason="no layering network shipped"
)


def _layered_cube(ctx, preset="coated_gold"):
    from addon.blender import stack_io

    stack_io.stack_to_material(PRESETS[preset], ctx.scene.objects["Cube"].active_material)
    r = ctx.scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 16, 12, 100
    ctx.scene.neural_render.samples = 1
    ctx.scene.neural_render.max_bounces = 2


def _export(ctx):
    from addon.blender import scene_export

    return scene_export.export_scene(ctx.evaluated_depsgraph_get())


def test_render_settings_offer_auto_with_a_tolerance(fresh_scene):
    props = fresh_scene.scene.neural_render
    assert props.decoder_quality == "AUTO"
    items = {i.identifier for i in props.bl_rna.properties["decoder_quality"].enum_items}
    assert items == {"AUTO"} | {s.upper() for s in ("tiny", "small", "medium", "paper")}
    assert 0.0 < props.tolerance <= 1.0


@needs_layering
def test_auto_puts_each_layered_material_on_its_measured_decoder(fresh_scene):
    ctx = fresh_scene
    _layered_cube(ctx)
    props = ctx.scene.neural_render
    props.tolerance = 0.9
    core, _ = _export(ctx)
    notes = props.assign_decoders(core)
    m = core.materials[core.material_names.index("Material")]
    assert type(m).__name__ == "NeuralMaterial" and m.models.size == SIZES[0]
    assert not any("tolerance" in n for n in notes)


@needs_layering
def test_a_tolerance_no_decoder_meets_warns_and_uses_the_most_accurate(fresh_scene):
    ctx = fresh_scene
    _layered_cube(ctx, "red_car_paint")
    props = ctx.scene.neural_render
    props.tolerance = 0.01
    core, _ = _export(ctx)
    notes = props.assign_decoders(core)
    assert any("Material" in n and "tolerance" in n for n in notes)
    m = core.materials[core.material_names.index("Material")]
    assert type(m).__name__ == "NeuralMaterial"


def test_reference_mode_and_fixed_sizes(fresh_scene):
    ctx = fresh_scene
    _layered_cube(ctx)
    props = ctx.scene.neural_render
    props.mode = "reference"
    core, _ = _export(ctx)
    before = list(core.materials)
    assert props.assign_decoders(core) == [] and core.materials == before  # nothing to choose
    props.mode = "neural"
    props.decoder_quality = "PAPER" if "paper" not in SIZES else "TINY"
    core, _ = _export(ctx)
    notes = props.assign_decoders(core)
    m = core.materials[core.material_names.index("Material")]
    if props.decoder_quality == "PAPER":  # not shipped: the material keeps its stack (reference) and says so
        assert type(m).__name__ == "LayeredSpec" and any("reference" in n for n in notes)


@needs_layering
def test_f12_with_auto_renders_the_layered_material_with_a_decoder(fresh_scene, tmp_path):
    ctx = fresh_scene
    _layered_cube(ctx)
    ctx.scene.render.engine = "NEURAL_LAYERED"
    ctx.scene.neural_render.tolerance = 0.9
    ctx.scene.render.image_settings.file_format = "OPEN_EXR"
    ctx.scene.render.filepath = str(tmp_path / "auto.exr")
    bpy.ops.render.render(write_still=True)
    bpy.utils.expose_bundled_modules()
    import OpenImageIO as oiio  # noqa: N813

    px = oiio.ImageBuf(str(tmp_path / "auto.exr")).get_pixels(oiio.FLOAT)[..., :3]
    assert np.isfinite(px).all() and px.max() > 0

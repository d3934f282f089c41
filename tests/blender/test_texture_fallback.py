"""A baked latent texture damaged on disk (NaN texels, cut off) does not stop a render: the
material falls back to its constant stack with a warning naming the problem."""

import numpy as np
import pytest

from tests.blender.helpers import run_operator
from tests.faults.bake_driver import stand_in_encoder

ops = pytest.importorskip("bpy").ops.neural_layers


@pytest.fixture()
def baked(bpy_addon, material, tmp_path, monkeypatch):
    from addon.blender import bake_ops

    monkeypatch.setattr(bake_ops, "neural_encoder", lambda size, threads=2, **refine: stand_in_encoder())
    assert run_operator(ops.preset_apply, preset="varnished_wood").finished
    material.neural_layers.bake_directory = str(tmp_path)
    r = run_operator(ops.bake_texture)
    assert r.finished, r.error
    path, state = bake_ops.baked_texture_state(material)
    assert path is not None, state
    return material, path


def nan_texture(path):
    """Rewrite the texture with NaN texels but its header (bake key included) intact."""
    from addon.core.textures import LatentTexture
    from addon.core.textures.latent_texture import oiio_module

    tex = LatentTexture.read_exr(path)
    tex.levels = [np.full_like(level, np.nan) for level in tex.levels]
    out = oiio_module().ImageOutput.create(path)
    tex._write_levels(out, path, path)  # the unchecked writer: what a damaged or foreign file looks like
    out.close()


@pytest.mark.parametrize("damage", ["nan", "truncated"])
def test_a_damaged_baked_texture_falls_back_to_the_constant_stack(baked, damage):
    from addon.blender import scene_export

    material, path = baked
    if damage == "nan":
        nan_texture(path)
    else:
        with open(path, "r+b") as f:
            f.truncate(f.seek(0, 2) // 2)
    warnings = []
    spec = scene_export.export_material(material, warnings)
    assert spec.latent_texture is None
    assert any("cannot read its latent texture" in w and "constant stack" in w for w in warnings), warnings
    if damage == "nan":
        assert any("non-finite" in w for w in warnings), warnings

"""bpy fixtures: one registration of the add-on per session, a fresh scene per test.

Importing bpy is slow, so the add-on (from this checkout) is registered once; each test that
needs a clean file gets ``bpy.ops.wm.read_homefile(app_template="")``, which keeps registered
classes and properties (``read_factory_settings`` would disable add-ons).
"""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def bpy_addon():
    """The bpy module with ``addon.blender`` registered (unregistered at the end of the session)."""
    bpy = pytest.importorskip("bpy")
    from addon import blender

    blender.register()
    yield bpy
    blender.unregister()


@pytest.fixture()
def fresh_scene(bpy_addon):
    """The factory startup file (a cube with one material named "Material" and a camera, light)."""
    bpy = bpy_addon
    bpy.ops.wm.read_homefile(app_template="")
    return bpy.context


@pytest.fixture()
def material(fresh_scene):
    """The cube's active material, with an empty layer stack and automatic latent updates."""
    ob = fresh_scene.view_layer.objects.active
    assert ob is not None and ob.active_material is not None, "startup file should have a cube with a material"
    return ob.active_material

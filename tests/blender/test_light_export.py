"""What the export reads of a Blender light beyond its kind, power and colour: a point or spot light's Radius and
Soft Falloff, a sun's Angle, Normalize, the object's Camera ray visibility, Cycles' per-light Max Bounces, and a
portal (left out: it emits nothing in Cycles). The images these give are compared with Cycles' in
``test_cycles_settings.py``."""

import math

import numpy as np
import pytest

from tests.blender.test_render_engine import export

bpy = pytest.importorskip("bpy")


def _only(ctx, kind, **settings):
    """The scene with one light of ``kind`` (the startup file's other objects removed), and the light object."""
    for ob in list(ctx.scene.objects):
        if ob.type != "CAMERA":
            bpy.data.objects.remove(ob)
    light = bpy.data.lights.new("L", kind)
    for k, v in settings.items():
        setattr(light, k, v)
    ob = bpy.data.objects.new("L", light)
    ob.location = (0.5, -0.2, 2.0)
    ctx.scene.collection.objects.link(ob)
    return ob


def test_a_point_and_a_spot_lights_radius_and_soft_falloff_are_exported(fresh_scene):
    """Blender's Radius (``shadow_soft_size``) was read by nothing: every point and spot light rendered as a point."""
    from addon.core import kernels
    from addon.core.render import PointLight

    ob = _only(fresh_scene, "POINT", energy=100.0, shadow_soft_size=0.4)
    ob.scale = (3.0, 3.0, 3.0)  # Cycles does not scale the radius with the object
    ob.data.cycles.max_bounces = 2
    ob.visible_camera = True
    scene, warnings = export(fresh_scene)
    (light,) = scene.lights
    assert warnings == []
    assert light.radius == pytest.approx(0.4) and light.soft_falloff and light.normalize
    assert light.camera_visible and light.max_bounces == 2
    assert light.table_row()[0] == kernels.FACING_DISK
    ob.data.use_soft_falloff, ob.data.normalize, ob.visible_camera = False, False, False
    (light,) = export(fresh_scene)[0].lights
    assert light.table_row()[0] == kernels.SPHERE and not light.normalize and not light.camera_visible
    spot = _only(fresh_scene, "SPOT", energy=100.0, shadow_soft_size=0.25, spot_size=math.radians(40.0))
    (light,) = export(fresh_scene)[0].lights
    assert light.radius == pytest.approx(0.25) and light.table_row()[0] == kernels.FACING_DISK
    spot.data.shadow_soft_size = 0.0
    (light,) = export(fresh_scene)[0].lights
    assert light.table_row()[0] == kernels.SPOT
    # radius 0: the point light it was, the same kind and table row as the light of that place, power and colour
    ob = _only(fresh_scene, "POINT", energy=100.0, shadow_soft_size=0.0, color=(1.0, 0.5, 0.2))
    (light,) = export(fresh_scene)[0].lights
    kind, row = light.table_row()
    want_kind, want = PointLight(np.array(ob.matrix_world)[:3, 3], 100.0, (1.0, 0.5, 0.2)).table_row()
    assert kind == want_kind == kernels.POINT
    np.testing.assert_allclose(row[:6], want[:6], rtol=1e-7)


def test_a_suns_angle_is_exported(fresh_scene):
    """Blender's Angle of a sun (0.526 degrees for a new one) was read by nothing: one direction. An angle of 0 is
    the sun it was (the same kind and table row)."""
    from addon.core import kernels
    from addon.core.render import SunLight

    ob = _only(fresh_scene, "SUN", energy=3.0, angle=math.radians(10.0))
    ob.rotation_euler = (0.4, 0.2, 0.0)
    scene, warnings = export(fresh_scene)
    (light,) = scene.lights
    assert warnings == []
    assert light.angle == pytest.approx(math.radians(10.0)) and light.table_row()[0] == kernels.SUN_DISK
    ob.data.angle = 0.0
    (light,) = export(fresh_scene)[0].lights
    kind, row = light.table_row()
    want_kind, want = SunLight(-np.array(ob.matrix_world)[:3, 2], 3.0).table_row()
    assert kind == want_kind == kernels.SUN
    np.testing.assert_allclose(row[:6], want[:6], rtol=1e-6, atol=1e-7)


def test_a_portal_is_left_out_with_a_line_not_a_warning(fresh_scene):
    """An area light marked a Cycles Portal emits nothing in Cycles (it guides the world's sampling): it lit the
    scene with its power here. The export leaves it out and says so among its information lines; another area
    light beside it is exported."""
    portal = _only(fresh_scene, "AREA", energy=500.0, size=2.0)
    portal.data.cycles.is_portal = True
    info = []
    scene, warnings = export(fresh_scene, info=info)
    assert scene.lights == [] and warnings == []
    assert len([line for line in info if "portal" in line]) == 1
    portal.data.cycles.is_portal = False
    portal.data.update_tag()  # a Python property group's edit from a script: the depsgraph is told
    scene, _ = export(fresh_scene)
    assert len(scene.lights) == 1

"""Blender Cycles' Principled coat at BRDF level, measured with Cycles itself.

    python benchmarks/cycles_brdf.py --preset lacquered_plastic     # prints albedo and lobe figures

A huge plane (normal +z) carries the Principled approximation of a stack
(``addon.core.render.principled.principled_inputs``, the mapping the Cycles baseline uses) and is
seen by a 180-degree equidistant fisheye camera just above it, looking down: every pixel sees
the plane from another direction, so one render covers the whole outgoing hemisphere.

- Directions: one render with an emission shader showing the Geometry node's *Incoming* vector
  gives ``wo`` per pixel (no assumption about the camera's mapping).
- Lobes: the world is black and a sun (angle 0, strength E) shines from ``wi`` at each incident
  elevation; a pixel's radiance is f(wi, wo) E cos(theta_i), calibrated by the same render of a
  white Diffuse BSDF (f = 1/pi). The lobe image f cos(theta_o) on the regular grid of
  ``addon.core.lobe`` is interpolated from the pixels (linear, in the projected disk).
- Directional albedo: no sun, a white world of radiance 1: a pixel's radiance is the albedo seen
  from its ``wo`` (Cycles traces its own multiple bounces inside the BSDF).

Cycles' own time per shading evaluation is taken as the lobe renders' wall time over pixels x
samples (scene sync and ray casting included: an upper bound).
"""

from __future__ import annotations

import math
import shutil
import sys
import tempfile
import time
import weakref
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core import lobe  # noqa: E402
from addon.core.render.principled import principled_inputs  # noqa: E402

HEIGHT = 0.01
PLANE = 4000.0


def _bpy():
    import bpy

    return bpy


class CyclesBRDF:
    """One Blender scene reused for every stack: plane, fisheye camera, sun, world."""

    def __init__(self, res: int = 128, samples: int = 64, threads: int = 2):
        bpy = _bpy()
        self.bpy, self.res, self.samples = bpy, int(res), int(samples)
        bpy.ops.wm.read_homefile(app_template="")
        bs = bpy.context.scene
        for ob in list(bs.objects):
            bpy.data.objects.remove(ob)
        me = bpy.data.meshes.new("plane")
        h = PLANE / 2
        me.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
        me.update()
        self.plane = bpy.data.objects.new("plane", me)
        bs.collection.objects.link(self.plane)
        cd = bpy.data.cameras.new("fisheye")
        cd.type = "PANO"
        cd.panorama_type = "FISHEYE_EQUIDISTANT"
        cd.fisheye_fov = math.pi
        cd.clip_start = HEIGHT * 1e-3
        cd.clip_end = PLANE * 10
        cam = bpy.data.objects.new("fisheye", cd)
        cam.location = (0.0, 0.0, HEIGHT)
        bs.collection.objects.link(cam)
        bs.camera = cam
        ld = bpy.data.lights.new("sun", "SUN")
        ld.angle = 0.0
        ld.energy = 1.0
        self.sun = bpy.data.objects.new("sun", ld)
        bs.collection.objects.link(self.sun)
        world = bpy.data.worlds.new("world")
        if world.node_tree is None:
            world.use_nodes = True
        self.background = world.node_tree.nodes["Background"]
        bs.world = world
        bs.render.engine = "CYCLES"
        c = bs.cycles
        c.device = "CPU"
        c.use_adaptive_sampling = False
        c.use_denoising = False
        c.max_bounces = 4
        c.seed = 0
        c.pixel_filter_type = "BOX"
        c.filter_width = 0.01  # each pixel is its centre direction
        bs.render.threads_mode = "FIXED"
        bs.render.threads = int(threads)
        bs.render.resolution_x = bs.render.resolution_y = self.res
        bs.render.resolution_percentage = 100
        bs.view_settings.view_transform = "Standard"
        bs.render.image_settings.file_format = "OPEN_EXR"
        bs.render.image_settings.color_depth = "32"
        self.scene = bs
        self.tmp = Path(tempfile.mkdtemp(prefix="cycles_brdf_"))
        weakref.finalize(self, shutil.rmtree, self.tmp, ignore_errors=True)  # the renders' folder goes with it
        self.wo, self.on_plane = self._directions()
        self.calibration = self._calibration()

    # ---------------------------------------------------------------- rendering

    def _material(self, kind: str, stack=None):
        bpy = self.bpy
        mat = bpy.data.materials.new(kind)
        if mat.node_tree is None:
            mat.use_nodes = True
        nt = mat.node_tree
        for n in list(nt.nodes):
            nt.nodes.remove(n)  # removing nodes can invalidate references to the others: start empty
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        if kind == "incoming":
            geo = nt.nodes.new("ShaderNodeNewGeometry")
            scale = nt.nodes.new("ShaderNodeVectorMath")
            scale.operation = "MULTIPLY_ADD"
            scale.inputs[1].default_value = (0.5, 0.5, 0.5)
            scale.inputs[2].default_value = (0.5, 0.5, 0.5)
            em = nt.nodes.new("ShaderNodeEmission")
            nt.links.new(geo.outputs["Incoming"], scale.inputs[0])
            nt.links.new(scale.outputs["Vector"], em.inputs["Color"])
            nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
        elif kind == "diffuse":
            d = nt.nodes.new("ShaderNodeBsdfDiffuse")
            d.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
            d.inputs["Roughness"].default_value = 0.0
            nt.links.new(d.outputs["BSDF"], out.inputs["Surface"])
        else:
            p = nt.nodes.new("ShaderNodeBsdfPrincipled")
            for key, value in principled_inputs(stack).items():
                p.inputs[key].default_value = value
            nt.links.new(p.outputs["BSDF"], out.inputs["Surface"])
        self.plane.data.materials.clear()
        self.plane.data.materials.append(mat)
        return mat

    def _render(self, samples: int) -> tuple[np.ndarray, float]:
        bpy = self.bpy
        self.scene.cycles.samples = int(samples)
        path = self.tmp / "render.exr"
        self.scene.render.filepath = str(path)
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        seconds = time.perf_counter() - t0
        bpy.utils.expose_bundled_modules()
        import OpenImageIO as oiio  # noqa: N813

        px = oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT)[:, :, :3]
        return px.reshape(-1, 3).astype(np.float64), seconds

    def _lighting(self, theta_i: float | None, world: float) -> None:
        self.background.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        self.background.inputs["Strength"].default_value = float(world)
        if theta_i is None:
            self.sun.hide_render = True
        else:
            self.sun.hide_render = False
            self.sun.rotation_euler = (0.0, -math.radians(theta_i), 0.0)  # light travels along -wi

    def _directions(self):
        self._material("incoming")
        self._lighting(None, 0.0)
        px, _ = self._render(4)
        wo = px * 2.0 - 1.0
        norm = np.linalg.norm(wo, axis=1, keepdims=True)
        on = (norm[:, 0] > 0.5) & (wo[:, 2] > 0.0)
        wo = np.where(on[:, None], wo / np.maximum(norm, 1e-9), 0.0)
        return wo, on

    def _calibration(self) -> float:
        """Irradiance factor: radiance of a white Lambertian (f = 1/pi) under the sun at normal incidence."""
        self._material("diffuse")
        self._lighting(0.0, 0.0)
        px, _ = self._render(4)
        mid = self.on_plane & (self.wo[:, 2] > 0.5)
        return float(np.median(px[mid].mean(axis=1)) * math.pi)

    # ---------------------------------------------------------------- measurements

    def _to_grid(self, values: np.ndarray, res: int) -> np.ndarray:
        from scipy.interpolate import LinearNDInterpolator
        from scipy.spatial import Delaunay

        if getattr(self, "_tri", None) is None:  # one triangulation of the pixels' directions, reused
            self._tri = Delaunay(self.wo[self.on_plane][:, :2])
        wo, mask = lobe.lobe_grid(res)
        out = np.zeros((res * res, 3))
        out[mask] = LinearNDInterpolator(self._tri, values[self.on_plane])(wo[mask][:, :2])
        return np.nan_to_num(out).reshape(res, res, 3)

    def lobes(self, stack, res: int = 32, angles=lobe.INCIDENT_ANGLES_DEG):
        """Lobe images (A, res, res, 3) f cos(theta_o) of the stack's Principled approximation, and
        seconds per shading evaluation (render wall time / (pixels x samples))."""
        self._material("principled", stack)
        imgs, seconds, evals = [], 0.0, 0
        for theta in angles:
            self._lighting(theta, 0.0)
            px, s = self._render(self.samples)
            seconds += s
            evals += int(self.on_plane.sum()) * self.samples
            f = px / (self.calibration * math.cos(math.radians(theta)))
            imgs.append(self._to_grid(f * self.wo[:, 2:3], res))
        return np.stack(imgs), seconds / evals

    def albedo(self, stack, cos_theta: np.ndarray) -> np.ndarray:
        """Directional albedo (N, 3) of the Principled approximation seen from elevations ``cos_theta``."""
        self._material("principled", stack)
        self._lighting(None, 1.0)
        px, _ = self._render(self.samples)
        on = self.on_plane
        order = np.argsort(self.wo[on, 2])
        c = self.wo[on, 2][order]
        vals = px[on][order]
        return np.stack([np.interp(cos_theta, c, vals[:, k]) for k in range(3)], axis=1)


def main(argv=None) -> int:
    import argparse

    from addon.core import reference
    from addon.core.stack import PRESETS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="lacquered_plastic")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--samples", type=int, default=64)
    a = ap.parse_args(argv)
    cy = CyclesBRDF(a.res, a.samples)
    stack = PRESETS[a.preset]
    thetas = np.array([0.0, 30.0, 60.0, 75.0])
    al = cy.albedo(stack, np.cos(np.radians(thetas)))
    views = np.array([lobe.incident_direction(t) for t in thetas])
    ref, se = reference.albedo(stack, views, samples=20000, seed=1)
    print(f"calibration {cy.calibration:.4f} (1 for a sun of strength 1)")
    for t, c, r in zip(thetas, al, ref, strict=True):
        print(f"theta {t:4.0f}: Cycles albedo {np.round(c, 3)}  reference {np.round(r, 3)}")
    imgs, spe = cy.lobes(stack, 32)
    print(
        f"lobe albedo (Cycles) {[np.round(lobe.albedo_from_lobe(i), 3).tolist() for i in imgs]}; "
        f"{spe * 1e6:.2f} us/eval"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

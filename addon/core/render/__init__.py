"""The path tracer: scene arrays, lights, materials, wavefront integrator (embreex), film.

Data comes in as plain arrays (:class:`Scene`), so the core renders without Blender::

    film, stats = render(scene, RenderSettings(samples=64))
    image = film.mean()          # (H, W, 3) linear RGB, row 0 at the top
"""

from .film import Film, write_exr, write_png
from .integrator import Cancelled, RenderSettings, RenderStats, render
from .lights import AreaLight, Environment, PointLight, SpotLight, SunLight
from .materials import (
    BSDFMaterial,
    ImageTexture,
    LambertMaterial,
    LayeredSpec,
    PrincipledMaterial,
    ReferenceLayered,
    SurfaceHits,
)
from .scene import Camera, Mesh, Scene

__all__ = [
    "AreaLight",
    "BSDFMaterial",
    "Camera",
    "Cancelled",
    "Environment",
    "Film",
    "ImageTexture",
    "LambertMaterial",
    "LayeredSpec",
    "Mesh",
    "PointLight",
    "PrincipledMaterial",
    "ReferenceLayered",
    "RenderSettings",
    "RenderStats",
    "Scene",
    "SpotLight",
    "SunLight",
    "SurfaceHits",
    "render",
    "write_exr",
    "write_png",
]

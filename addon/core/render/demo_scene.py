"""The bundled demo scene: layered presets and a textured material on simple geometry, lit by a
procedural sky (environment map with a sun-like hot spot) and an area light.

Everything is generated here (no asset files), so the scene is the same for the main job
(``bake/demo.py``), the benchmarks (``benchmarks/bench_render.py``, which also rebuilds it in
Blender for Cycles) and the tests.
"""

from __future__ import annotations

import math

import numpy as np

from ..stack import PRESETS, Coating, Diffuse, Stack
from ..textures.spatial import SpatialStack
from . import shapes
from .lights import AreaLight, Environment, PointLight
from .materials import ImageTexture, LambertMaterial, LayeredSpec
from .scene import Camera, Mesh, Scene

DEMO_PRESETS = ("coated_gold", "red_car_paint", "lacquered_plastic", "varnished_wood", "frosted_copper")
SPHERE_RADIUS = 0.45


def sky_image(width: int = 128, height: int = 64) -> np.ndarray:
    """Equirectangular sky (H, W, 3), row 0 = zenith: blue gradient, warm sun, grey-brown ground."""
    el = (0.5 - (np.arange(height) + 0.5) / height) * math.pi  # elevation per row
    az = ((np.arange(width) + 0.5) / width - 0.5) * 2 * math.pi
    el, az = np.meshgrid(el, az, indexing="ij")
    up = np.clip(np.sin(el), 0.0, 1.0)[..., None]
    sky = (1 - up) * np.array([0.9, 0.95, 1.0]) + up * np.array([0.25, 0.45, 0.9])
    ground = np.array([0.25, 0.22, 0.2])
    img = np.where((el > 0)[..., None], sky, ground) * 0.8
    # A sun 35 degrees up, to the left behind the camera's right shoulder.
    sun_el, sun_az = math.radians(35.0), math.radians(-120.0)
    cos_d = np.sin(el) * math.sin(sun_el) + np.cos(el) * math.cos(sun_el) * np.cos(az - sun_az)
    img = img + np.where(cos_d > math.cos(math.radians(6.0)), 1.0, 0.0)[..., None] * np.array([22.0, 19.0, 15.0])
    return img.astype(np.float32)


def checker_texture(size: int = 512, squares: int = 16) -> np.ndarray:
    """A two-tone tile texture (H, W, 3) with thin grout lines: the textured floor's base colour."""
    i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    cell = size // squares
    parity = ((i // cell) + (j // cell)) % 2
    img = np.where(parity[..., None] == 0, np.array([0.62, 0.58, 0.5]), np.array([0.25, 0.3, 0.36]))
    grout = ((i % cell) < 2) | ((j % cell) < 2)
    img = np.where(grout[..., None], np.array([0.8, 0.8, 0.78]), img)
    return img.astype(np.float32)


FLOOR_STACK = Stack(
    Diffuse((0.6, 0.6, 0.6)), (Coating(roughness=0.05, ior=1.5, albedo=(0.9, 0.75, 0.4), thickness=0.3),)
)


def floor_maps(size: int = 256, squares: int = 16) -> dict[str, np.ndarray]:
    """Driving images of the varnished tile floor (``FLOOR_STACK``): the tile colours as the base
    albedo, and a varnish that is glossy on the light tiles and worn (rougher, thinner) on the dark."""
    colour = checker_texture(size, squares)
    light = colour[..., 0] > 0.5
    return {
        "base.albedo": colour,
        "coatings[0].roughness": np.where(light, 0.03, 0.25),
        "coatings[0].thickness": np.where(light, 0.4, 0.1),
    }


def bake_floor(encode=None, size: int = 256, squares: int = 16, **options):
    """The varnished tile floor (``FLOOR_STACK`` driven by ``floor_maps(size, squares)``) baked into a latent
    texture by ``encode`` (default: ``textures.bake.neural_encoder()``), with ``bake_stack``'s ``options``: its
    (texture, stats). The floor of the main job's scene, as the main job, the benchmarks and the tests bake it."""
    from ..textures.bake import bake_stack, neural_encoder

    return bake_stack(SpatialStack(FLOOR_STACK, floor_maps(size, squares)), encode or neural_encoder(), **options)


def demo_scene(width: int = 320, height: int = 180, presets=DEMO_PRESETS, floor_texture=None) -> Scene:
    """Spheres of the given presets (names, or Stack objects) in a row on a tiled floor, a sky and
    a soft area light. With ``floor_texture`` (a latent texture baked from ``FLOOR_STACK`` and
    :func:`floor_maps`) the floor is a varnished, spatially varying layered material (in reference mode
    its stacks texel by texel, from the same maps); without it a Lambertian with the tile texture."""
    presets = list(presets)
    stacks = [PRESETS[p] if isinstance(p, str) else p for p in presets]
    names = [p if isinstance(p, str) else f"stack{i}" for i, p in enumerate(presets)]
    n = len(presets)
    spacing = 1.1
    meshes = []
    for i in range(n):
        x = (i - (n - 1) / 2) * spacing
        meshes.append(shapes.uv_sphere((x, 0.0, SPHERE_RADIUS), SPHERE_RADIUS, 48, 24, material=i + 1))
    floor = shapes.quad((0, 30.0, 0), (40.0, 0, 0), (0, 40.0, 0), material=0)
    floor.uvs = floor.uvs * 10.0  # the tile texture repeats (0.5 m squares)
    meshes.append(floor)
    mesh = Mesh.concatenate(meshes)
    if floor_texture is None:
        tiles = LambertMaterial((1.0, 1.0, 1.0), ImageTexture(checker_texture()))
    else:
        tiles = LayeredSpec(
            FLOOR_STACK, floor_texture, "varnished_tiles", spatial=SpatialStack(FLOOR_STACK, floor_maps())
        )
    materials = [tiles] + [LayeredSpec(st, None, name) for st, name in zip(stacks, names, strict=True)]
    light = np.eye(4)
    light[:3, 3] = (1.5, -1.5, 3.0)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    light[:3, :3] = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])  # tilted toward the spheres
    lights = [AreaLight(light, power=250.0, size=1.5, color=(1.0, 0.92, 0.85))]
    cam = Camera.look_at((0.0, -5.6, 1.5), (0.0, 0.0, 0.6), fov_deg=50.0, width=width, height=height)
    return Scene(cam, mesh, materials, lights, Environment(image=sky_image()), ["tiles"] + names)


TERMINATOR_PRESETS = ("coated_gold", "red_car_paint")
TERMINATOR_LIGHT = (
    6.0,
    -0.8,
    0.5,
)  # nearly level with the spheres' centres, to their right, a little towards the camera


def terminator_scene(width: int = 160, height: int = 90, presets=TERMINATOR_PRESETS) -> Scene:
    """Spheres of the given presets on a grey floor under one point light from the side, no sky: the
    scene in which a decoder that reflects too much at grazing light draws a bright line along each
    sphere's terminator (``benchmarks/bench_terminator.py``). The light is nearly level with the spheres
    and a little in front of them, so the terminator runs down each sphere just left of its middle as the
    camera sees it, where the viewer is near the normal."""
    stacks = [PRESETS[p] if isinstance(p, str) else p for p in presets]
    names = [p if isinstance(p, str) else f"stack{i}" for i, p in enumerate(presets)]
    n = len(stacks)
    spacing = 1.2
    meshes = [
        shapes.uv_sphere(((i - (n - 1) / 2) * spacing, 0.0, SPHERE_RADIUS), SPHERE_RADIUS, 96, 48, material=i + 1)
        for i in range(n)
    ]
    meshes.append(shapes.quad((0, 10.0, 0), (20.0, 0, 0), (0, 20.0, 0), material=0))
    materials = [LambertMaterial((0.18, 0.18, 0.18))] + [
        LayeredSpec(st, None, name) for st, name in zip(stacks, names, strict=True)
    ]
    cam = Camera.look_at((0.0, -3.2, 0.9), (0.0, 0.0, SPHERE_RADIUS), fov_deg=40.0, width=width, height=height)
    lights = [PointLight(TERMINATOR_LIGHT, power=600.0)]
    return Scene(cam, Mesh.concatenate(meshes), materials, lights, Environment(), ["floor"] + names)


def sphere_centres(scene: Scene, names) -> dict[str, np.ndarray]:
    """Centres of the spheres of :func:`terminator_scene` (or :func:`demo_scene`), by material name: the
    middle of their triangles' bounding box."""
    mesh = scene.mesh
    out = {}
    for name in names:
        p = mesh.positions[mesh.material_index == scene.material_names.index(name)].reshape(-1, 3)
        out[name] = 0.5 * (p.min(axis=0) + p.max(axis=0)).astype(np.float64)
    return out

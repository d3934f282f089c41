"""Compile (or load from numba's disk cache) every loop of ``addon.core.kernels`` before a user waits
on it, by rendering a tiny scene that holds every light kind, an image texture and both kinds of
environment.

The first render after installing would otherwise spend about twenty seconds compiling (the loops are
then cached on disk, and a later process loads them in a fraction of a second). The Blender add-on
calls :func:`warm_up_in_background` when it registers; the compile runs on a daemon thread while the
user works, and a render that starts meanwhile waits only for what is still compiling.
"""

from __future__ import annotations

import math
import threading

import numpy as np

_finished = threading.Event()  # every loop compiled (or loaded) in this process
_stop = threading.Event()  # set by ``wait_for_background``: the warm-up ends at its next step
_thread: threading.Thread | None = None


def warm_scene(environment_image: bool):
    """A 4 x 4 pixel scene with a textured quad, a sphere, every light kind, and a sky (an image or
    a constant colour)."""
    from . import shapes
    from .lights import AreaLight, Environment, PointLight, SpotLight, SunLight
    from .materials import ImageTexture, LambertMaterial, PrincipledMaterial
    from .scene import Camera, Mesh, Scene

    floor = shapes.quad((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 2.0, 0.0), material=0)
    ball = shapes.uv_sphere((0.0, 0.0, 0.5), 0.5, 8, 4, material=1)
    texture = ImageTexture(np.random.default_rng(0).random((4, 4, 3)))
    # the ball a Principled BSDF (a specular layer and half a metal): an ordinary Blender material's loop
    materials = [LambertMaterial((0.8, 0.8, 0.8), texture), PrincipledMaterial((0.5, 0.5, 0.5), metallic=0.5)]
    rect, disk = np.eye(4), np.eye(4)
    rect[:3, 3], disk[:3, 3] = (0.0, 0.0, 3.0), (1.0, 0.0, 3.0)
    lights = [
        PointLight((0.0, 1.0, 2.0), 10.0),
        SpotLight((0.0, -1.0, 2.0), 10.0, direction=(0.0, 0.0, -1.0), spot_size=math.radians(60.0)),
        SunLight((0.3, 0.2, -1.0), 1.0),
        PointLight((1.0, 1.0, 2.0), 10.0, radius=0.2),  # a sphere's and a facing disk's loops, and a sun's disk's
        PointLight((-1.0, 1.0, 2.0), 10.0, radius=0.2, soft_falloff=False),
        SunLight((-0.3, 0.2, -1.0), 1.0, angle=math.radians(5.0)),
        AreaLight(rect, 10.0, size=0.5),
        AreaLight(disk, 10.0, size=0.5, ellipse=True),
    ]
    sky = np.full((4, 8, 3), 0.2) if environment_image else None
    env = Environment(color=(0.1, 0.1, 0.1), image=sky)
    cam = Camera.look_at((0.0, -3.0, 1.5), (0.0, 0.0, 0.3), fov_deg=60.0, width=4, height=4)
    return Scene(cam, Mesh.concatenate([floor, ball]), materials, lights, env, ["floor", "ball"])


def warm_up(stop: threading.Event | None = None) -> None:
    """Render the warm-up scenes once each (one thread, one sample, analytic materials), and run the
    neural materials' loops (the sampling proxy, the albedo calibration and a latent texture's choice of
    table and its half-float taps, the exact top coat) on a few rows, and the half-float conversions and
    range checks of a bake, a texture's file and its projection, with the argument types a render and a bake
    pass. ``stop`` (set from another thread) ends it at its next step: a loop being compiled finishes first."""
    from .integrator import Cancelled, RenderSettings, render

    def stopped() -> bool:
        return stop is not None and stop.is_set()

    for image in (True, False):
        if stopped():  # before the scene: its environment's tables compile loops of their own
            return
        try:
            render(warm_scene(image), RenderSettings(samples=1, max_bounces=3, rr_depth=1, threads=1), stop=stop)
        except Cancelled:
            return
    for _ in _warm_the_other_loops():  # a loop over its steps, each compiling a loop or two
        if stopped():
            return


def _warm_the_other_loops():
    """The loops no render of the warm-up scenes runs (``warm_up``'s docstring), each on a few rows: a generator that
    yields after each step, where ``warm_up`` may stop."""
    from .. import kernels
    from ..neural import proxy, top_lobe
    from ..textures.mip import MipChain, build_mip_chain, first_row_beyond_half, store_texels, trilinear_lookup

    wo = np.array([[0.0, 0.6, 0.8], [0.6, 0.0, 0.8]])
    proxy.sample(wo, np.array([0.2, 0.3]), 0.5, np.full((2, 3), 0.5))
    yield
    grid, table = np.array([0.0, 1.0]), np.ones((2, 2, 3))
    kernels.scale_by_table(np.ones((2, 3)), wo[:, 2].copy(), wo[:, 2].copy(), grid, table[None], np.zeros(0, np.int64))
    yield
    top, half = np.array([[0.1, 1.5]]), np.full(2, 0.5)  # a remainder decoder's exact top coat
    wi, share, missed = kernels.propose_with_top(wo, half, np.full((2, 2), 0.5), half, half, top)
    _f, p_top = kernels.top_lobe_eval_pdf(wi, wo, top)
    pdf = kernels.mixture_pdf(wo, wi, half, half, share, p_top)
    kernels.finish_proposals(wi, pdf, np.ones((2, 3)))
    yield
    f32, rows = np.ones((2, 3), dtype=np.float32), np.arange(2)
    kernels.neural_shading(f32, p_top, wi, wo, rows, 1, half, half, share, missed, True)
    yield
    grids = top_lobe.transmittance_grids()
    calibration = (grid, table[None], np.zeros(0, np.int64))
    for coat in (top, np.repeat(top, 2, axis=0), top_lobe.NO_TOP_ROWS):  # shared, per row, none
        f32 = np.ones((2, 3), dtype=np.float32)
        kernels.decoded_brdf(f32, wi, wo, calibration, coat, grids, True, True, kernels.EVERY_ROW)
        yield
    kernels.transmission_rows(top, wo[:, 2].copy(), *grids)
    yield
    kernels.nearest_rows(np.zeros((2, 96), np.float32), np.ones((3, 96), np.float32))  # a latent texture's tables
    yield
    # a latent texture read from its file: half floats (the image texture above took the float32 loop)
    trilinear_lookup(MipChain([np.zeros((1, 1, 100))], dtype=np.float16), np.zeros((2, 2)), 0.0)
    yield
    kernels.take_half_channels(np.zeros((1, 3), np.uint16), np.arange(2, dtype=np.int64), np.zeros((1, 2), np.uint16))
    yield
    # the half-float conversions: a baked texture's chain, and the projected texture's columns a render makes
    build_mip_chain(np.zeros((2, 2, 3), np.float32), dtype=np.float16)
    yield
    store_texels(np.zeros((2, 2), np.float32), np.zeros((2, 3), np.float16)[:, :2], "the warm-up's texels")
    yield
    for dtype in (np.float16, np.float32):  # the range checks: a texture's file write, a bake's texels
        first_row_beyond_half(np.zeros((2, 2), dtype))
        yield


def warm_up_in_background() -> threading.Thread | None:
    """Start :func:`warm_up` on a daemon thread, unless it is running or has finished in this process (None then);
    one that ``wait_for_background`` stopped starts again."""
    global _thread
    if _finished.is_set() or (_thread is not None and _thread.is_alive()):
        return None
    _stop.clear()

    def run():
        warm_up(_stop)
        if not _stop.is_set():
            _finished.set()

    _thread = threading.Thread(target=run, name="compile-render-kernels", daemon=True)
    _thread.start()
    return _thread


def wait_for_background(timeout: float | None = None) -> None:
    """Stop the background warm-up (if any) at its next step and wait for it. The add-on calls it when it is
    disabled: the thread imports the extension's modules, and a thread still running would put them
    back after disabling forgot them. It waited for the whole compile (about ten seconds after an install, 31 s on
    a loaded machine) with Blender frozen; now for the loop being compiled at most."""
    if _thread is not None:
        _stop.set()
        _thread.join(timeout)

"""The renderer's compiled loops (addon/core/kernels.py): compiled before a user waits on them."""

import numba

from addon.core import kernels
from addon.core.render import RenderSettings, render
from addon.core.render.demo_scene import demo_scene
from addon.core.render.warm_up import warm_up


def _signatures() -> dict[str, int]:
    return {
        name: len(obj.signatures)
        for name, obj in vars(kernels).items()
        if isinstance(obj, numba.core.registry.CPUDispatcher)
    }


def test_the_warm_up_compiles_every_loop_a_render_of_the_demo_scene_runs():
    """After the warm-up, rendering the demo scene (neural materials, an image texture, the sky, an
    area light, every strategy) compiles nothing more: the types the warm-up scene passes are the
    ones a real render passes."""
    warm_up()
    before = _signatures()
    assert before["surface_hits"] and before["sample_lights"] and before["trilinear"]
    scene = demo_scene(16, 9)
    for strategy in ("mis", "light", "bsdf"):
        render(scene, RenderSettings(samples=1, max_bounces=3, threads=2, strategy=strategy, calibrate=False))
    assert _signatures() == before

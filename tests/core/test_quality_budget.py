"""Auto decoder choice within a time budget: predicted decoder time per size, sizes left out."""

import math

import pytest

from addon.core import quality
from addon.core.render.demo_scene import demo_scene
from addon.core.stack import PRESETS


def test_predicted_time_follows_the_measured_speed_of_each_size():
    sizes = quality.available_sizes()
    assert len(sizes) >= 2
    t = {s: quality.predicted_decoder_seconds(s, 1e6) for s in sizes}
    assert all(math.isfinite(v) and v > 0 for v in t.values())
    assert t[sizes[0]] < t[sizes[-1]]  # more parameters, slower
    assert quality.predicted_decoder_seconds(sizes[0], 2e6) == pytest.approx(2 * t[sizes[0]])
    assert quality.frame_decoder_queries(480 * 270, 64, 4) == 2 * 480 * 270 * 64 * 5  # the first hit and 4 bounces
    assert quality.frame_decoder_queries(480 * 270, 64, 4, 0.5) == 480 * 270 * 64


def _layered_box(inside: bool, bounces: int = 4):
    """A camera in or before a closed box of a coated material, seen whole: a camera inside meets it at every
    bounce, one outside at its first hit and, from the box's outside, never again."""
    from addon.core.render import Camera, Mesh, Scene, shapes

    box = shapes.box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    eye = (0.0, 0.0, 0.0) if inside else (0.0, -3.0, 0.0)
    cam = Camera.look_at(eye, (0.0, 1.0, 0.0) if inside else (0.0, 0.0, 0.0), fov_deg=30, width=16, height=12)
    scene = Scene(cam, Mesh.concatenate([box]), [PRESETS["coated_gold"]], [])
    return scene, quality.scene_decoder_hits(scene, bounces)


@pytest.mark.parametrize("inside", [True, False])
def test_the_budget_predicts_from_the_paths_hits_on_layered_materials(inside):
    """The pilot's hits a path: a camera inside a closed box of the material meets it at the first hit and each of
    4 bounces (5, the bound); one before the box sees it fill the view once (1). The default cube filling a tenth
    of the view was predicted the bound, 7 at 6 bounces: 10 times its decoder time."""
    scene, hits = _layered_box(inside)
    assert hits == pytest.approx(5.0 if inside else 1.0, rel=0.02)
    scene.materials = [PRESETS["coated_gold"].base]  # a single layer: no decoder to choose
    assert quality.scene_decoder_hits(scene, 4) == 0.0


def test_sizes_over_the_budget_are_left_out_with_their_prediction():
    sizes = quality.available_sizes()
    queries = quality.frame_decoder_queries(480 * 270, 64, 4)
    budget = 2 * quality.predicted_decoder_seconds(sizes[0], queries)
    keep, notes = quality.sizes_within_budget(queries, budget, sizes)
    assert sizes[0] in keep and sizes[-1] not in keep
    assert any(sizes[-1] in n and "time budget" in n for n in notes)
    assert quality.sizes_within_budget(queries, None, sizes) == (sizes, [])
    # Nothing fits: the fastest, said so.
    keep, notes = quality.sizes_within_budget(queries, 1e-9, sizes)
    assert keep == [sizes[0]] and "no decoder" in notes[0]


def test_auto_never_takes_a_size_over_the_budget_even_when_none_meets_the_tolerance():
    sizes = quality.available_sizes()
    scene = demo_scene(8, 6, [PRESETS["coated_gold"]])
    queries = quality.frame_decoder_queries(1920 * 1080, 64, 6)
    budget = 1.01 * quality.predicted_decoder_seconds(sizes[1], queries)
    _, choices, notes = quality.assign_decoders(
        scene, "auto", 1e-4, res=8, walks=256, cache=quality.ErrorCache(), budget_seconds=budget, evaluations=queries
    )
    (choice,) = [c for c in choices.values()]
    assert choice.size in sizes[:2] and not choice.met
    assert set(choice.errors) <= set(sizes[:2])
    assert any(sizes[-1] in n and "left out" in n for n in notes)
    reason = quality.choice_reason("gold", choice)
    assert choice.size in reason and "measured error" in reason
    # The reason and the warning say the budget limited the choice, and name what it left out: they said "the most
    # accurate" and told to raise the tolerance, where a size the budget left out may meet it.
    assert "within the time budget" in reason and choice.left_out == tuple(sizes[2:])
    (warned,) = [n for n in notes if "meets the tolerance" in n]
    assert "within the time budget" in warned and all(s in warned for s in sizes[2:]) and "Time Budget" in warned


def test_a_scene_without_layered_materials_gets_no_budget_notes():
    """The budget's notes come with a material that goes through Auto: a scene of Lambertian and single-layer
    materials at the factory 1920x1080, 64 spp, 6 bounces (no size fits the default 120 s) warned at every F12."""
    from addon.core.stack import Conductor, Stack

    queries = quality.frame_decoder_queries(1920 * 1080, 64, 6)
    assert quality.sizes_within_budget(queries, 120.0)[1] != []  # the budget does leave sizes out here
    scene = demo_scene(8, 6, [Stack(Conductor(0.3))])  # a floor (Lambertian) and a single-layer sphere
    _, choices, notes = quality.assign_decoders(scene, "auto", budget_seconds=120.0, evaluations=queries)
    assert choices == {} and notes == []

"""Material thumbnails: the settings Blender's material previews render with."""

import numpy as np
import pytest

from addon.core.neural.models import SIZES
from addon.core.render import LayeredSpec, render
from addon.core.render.demo_scene import demo_scene
from addon.core.render.thumbnail import (
    THUMBNAIL_DECODER,
    THUMBNAIL_MAX_SIDE,
    prepare_thumbnail,
    thumbnail_settings,
)


def test_thumbnail_settings_are_few_samples_few_bounces_neural():
    s = thumbnail_settings(128, 128, threads=2)
    assert s.samples <= 8 and s.max_bounces <= 3 and s.mode == "neural" and s.reference_walks == 1
    assert s.threads == 2
    assert THUMBNAIL_DECODER == SIZES[0]  # the fastest decoder


@pytest.mark.parametrize("size", [(0, 128), (128, THUMBNAIL_MAX_SIDE + 1), (1920, 1080)])
def test_a_frame_is_not_rendered_as_a_thumbnail(size):
    with pytest.raises(ValueError, match="thumbnail"):
        thumbnail_settings(*size)


def test_prepare_thumbnail_puts_layered_materials_on_the_fastest_decoder_without_measuring(monkeypatch):
    from addon.core import quality

    def no_measurement(*a, **k):
        raise AssertionError("a thumbnail must not measure decoder errors (reference walks)")

    monkeypatch.setattr(quality, "choose_decoder", no_measurement)
    scene = demo_scene(24, 16)
    settings, notes = prepare_thumbnail(scene)
    layered = [m for m in scene.materials if hasattr(m, "size")]
    assert layered and all(m.size == THUMBNAIL_DECODER for m in layered), [type(m) for m in scene.materials]
    assert not any(isinstance(m, LayeredSpec) for m in scene.materials)
    film, stats = render(scene, settings)
    assert np.isfinite(film.mean()).all() and film.mean().max() > 0
    assert stats.seconds["reference"] == 0.0

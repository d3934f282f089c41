"""The arrays a render's chunks write their bounces into again (``render.scratch``): views of kept buffers,
never shared by two chunks at once, and images the same as with new arrays each bounce."""

import numpy as np
import pytest

from addon.core import kernels
from addon.core.render import RenderSettings, RenderStats, integrator, render
from addon.core.render.demo_scene import demo_scene
from addon.core.render.scratch import Scratch, ScratchPool

LAYOUT = ((3, np.float64), (0, np.int64), (2, np.bool_))


def test_arrays_are_contiguous_views_of_buffers_kept_for_the_next_call():
    s = Scratch()
    a, b, c = s.arrays("x", 10, LAYOUT)
    assert (a.shape, b.shape, c.shape) == ((10, 3), (10,), (10, 2))
    assert (a.dtype, b.dtype, c.dtype) == (np.float64, np.int64, np.bool_)
    assert all(v.flags.c_contiguous for v in (a, b, c))
    a[:] = 7.0
    a2, b2, _ = s.arrays("x", 4, LAYOUT)  # fewer rows: the same memory, not a new buffer
    assert a2.shape == (4, 3) and np.shares_memory(a2, a) and a2.base is a.base and b2.base is b.base
    assert s.arrays("y", 4, LAYOUT)[0].base is not a.base  # each name its own buffers
    assert s.nbytes == 10 * (24 + 8 + 2) + 4 * (24 + 8 + 2)


def test_arrays_grow_when_asked_for_more_rows_and_start_at_the_scratchs_rows():
    s = Scratch(rows=100)
    a = s.arrays("x", 10, LAYOUT)[0]
    assert len(a.base) == 100  # made for a chunk's rows at once: no regrowth as the bounces' counts move
    assert s.arrays("x", 100, LAYOUT)[0].base is a.base
    grown = s.arrays("x", 101, LAYOUT)[0]
    assert grown.shape == (101, 3) and grown.base is not a.base
    assert s.arrays("x", 0, LAYOUT)[0].shape == (0, 3)


def test_a_name_asked_for_with_another_layout_gets_buffers_of_that_layout():
    s = Scratch()
    s.arrays("x", 10, LAYOUT)
    other = ((2, np.float32), (0, np.int64), (2, np.bool_))  # as many arrays, not the same ones
    a, _, _ = s.arrays("x", 10, other)
    assert a.shape == (10, 2) and a.dtype == np.float32


def test_a_negative_row_count_is_refused():
    with pytest.raises(ValueError, match=">= 0"):
        Scratch().arrays("x", -1, LAYOUT)


def test_the_pool_hands_back_what_was_given_and_makes_one_only_when_none_is_free():
    pool = ScratchPool(rows=8)
    a, b = pool.take(), pool.take()
    assert a is not b and pool.made == 2 and a.rows == b.rows == 8
    pool.give(a)
    assert pool.take() is a and pool.made == 2


class NewArrays(Scratch):
    """A scratch that gives new arrays at every call, as the renderer's bounces had before they kept them."""

    def arrays(self, name, n, layout):
        self._groups.pop(name, None)
        return super().arrays(name, n, layout)


@pytest.fixture(scope="module")
def baked_floor():
    """The main job's floor: the varnished tiles baked into a latent texture (3 distinct texels, with the bake's
    albedo calibration), 64 x 64 texels."""
    from addon.core.render.demo_scene import bake_floor

    texture, _ = bake_floor(size=64, squares=4)
    return texture


@pytest.mark.parametrize("floor", ["lambertian", "baked"])
def test_a_chunk_traced_in_kept_arrays_is_the_chunk_traced_in_new_arrays_at_every_bounce(floor, request):
    """No array a bounce reads is overwritten before it reads it (the paths alternate between two groups), and
    a scratch left by other chunks (other pixels, passes and bounce counts) changes nothing: to the bit. The
    baked floor is a latent texture (per-hit latents, coatings, proxies and calibration tables, the main job's
    floor) beside the spheres' single-latent materials."""
    texture = request.getfixturevalue("baked_floor") if floor == "baked" else None
    scene = demo_scene(48, 27, floor_texture=texture)
    settings = RenderSettings(samples=1, max_bounces=4, threads=1)
    ctx = integrator._Context(scene, settings, RenderStats())
    if texture is not None:  # the floor renders as its latent texture, not the reference
        assert any(getattr(m, "texture", None) is texture for m in ctx.materials)
    pixels = np.arange(48 * 27)
    used = Scratch(400)
    for k, pix in enumerate((pixels[:400], pixels[-300:], pixels[500:900])):
        L, features, _ = integrator._trace_paths(ctx, pix, k, k, None, used, Scratch())
        L_new, features_new, _ = integrator._trace_paths(ctx, pix, k, k, None, NewArrays(), NewArrays())
        np.testing.assert_array_equal(L, L_new)
        np.testing.assert_array_equal(features, features_new)
        assert np.abs(L).sum() > 0


def test_a_render_makes_each_chunks_buffers_once_and_its_image_does_not_depend_on_the_threads(monkeypatch):
    """Two threads, 4 chunks a pass, 6 passes: two Scratch objects (one per chunk traced at once), each name's
    buffers made once, so that no bounce after the first chunk's faults new memory in; and the image equals the
    one-thread render's (a chunk's radiance is not overwritten before the film adds it)."""
    scene = demo_scene(64, 36)
    made, bases = [], {}
    take, arrays = ScratchPool.take, Scratch.arrays

    def counting_take(self, *rows):
        s = take(self, *rows)
        if s not in made:
            made.append(s)
        return s

    def recording_arrays(self, name, n, layout):
        views = arrays(self, name, n, layout)
        bases.setdefault((id(self), name), set()).add(id(views[0].base))
        return views

    monkeypatch.setattr(ScratchPool, "take", counting_take)
    monkeypatch.setattr(Scratch, "arrays", recording_arrays)
    chunk = 64 * 36 // 4
    film2, _ = render(scene, RenderSettings(samples=6, max_bounces=4, threads=2, chunk_paths=chunk))
    monkeypatch.undo()
    film1, _ = render(scene, RenderSettings(samples=6, max_bounces=4, threads=1, chunk_paths=chunk))
    np.testing.assert_array_equal(film2.mean(), film1.mean())
    np.testing.assert_array_equal(film2.features()["normal"], film1.features()["normal"])
    bounce_scratches = [s for s in made if "hits" in s._groups]
    assert len(bounce_scratches) == 2
    for s in bounce_scratches:
        for name in ("hits", "lights", "paths.taken", "paths.next", "scatter", "closest"):
            assert len(bases[(id(s), name)]) == 1, f"{name} was made again"
            assert len(s._groups[name][0]) == chunk  # made for the chunk's paths at once


def test_the_loops_write_the_arrays_they_are_given():
    """The outputs a kernel returns are the arrays passed in (or their first rows), not copies."""
    rows = kernels.rows_of(kernels.HIT_PATHS_OUT, 5)
    fields = kernels.rows_of(kernels.HIT_PATHS_OUT, 8)
    for f in fields:
        f[...] = 1
    got = kernels.take_paths(rows, np.arange(5), *fields)
    assert all(g is r for g, r in zip(got, rows, strict=True))


def test_renders_given_one_pool_keep_its_scratches_and_buffers_from_one_render_to_the_next():
    """A viewport session's renders share its pool: the second render takes the first one's Scratch objects and
    buffers (no new memory to fault in after a view change), and renders the image it renders alone."""
    scene = demo_scene(64, 36)
    settings = RenderSettings(samples=2, max_bounces=4, threads=2, chunk_paths=64 * 36 // 4)
    pool = ScratchPool()
    render(scene, settings, scratches=pool)
    assert pool.made == 2
    kept = {id(s): {k: g[0] for k, g in s._groups.items()} for s in pool._free}
    film, _ = render(scene, settings, scratches=pool)
    assert pool.made == 2
    for s in pool._free:
        assert all(s._groups[k][0] is buffer for k, buffer in kept[id(s)].items())
    np.testing.assert_array_equal(film.mean(), render(scene, settings)[0].mean())


def test_a_viewport_session_renders_in_its_own_pool_and_frees_it_when_closed():
    from addon.core.render.progressive import ProgressiveSession

    session = ProgressiveSession(RenderSettings(samples=2, max_bounces=2, threads=2), preview_divisor=1)
    try:
        session.restart(demo_scene(48, 27))
        assert session.wait(timeout=120) is not None
        pool = session.scratches
        assert 1 <= pool.made <= 2 and pool._free  # the renders' chunks took their arrays from it, and gave them back
        session.move_camera(demo_scene(48, 27).camera)
        assert session.wait(timeout=120) is not None
        assert session.scratches is pool and pool.made <= 2
    finally:
        session.close()
    assert session.scratches is not pool and session.scratches.made == 0

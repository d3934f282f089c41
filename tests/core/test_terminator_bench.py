"""benchmarks/bench_terminator.py: the bands of the angle to the light, and a small run end to end."""

import json

import numpy as np

from addon.core.render.demo_scene import TERMINATOR_LIGHT, TERMINATOR_PRESETS, sphere_centres, terminator_scene
from benchmarks import bench_terminator as bt


def test_light_angles_are_those_of_the_spheres_normals_and_every_band_is_seen():
    scene = terminator_scene(96, 54)
    angles = bt.light_angles(scene, TERMINATOR_PRESETS)
    assert set(angles) == set(TERMINATOR_PRESETS)
    seen = [np.isfinite(a) for a in angles.values()]
    assert not np.logical_and(*seen).any()  # a pixel sees one sphere at most
    for a in angles.values():
        ok = a[np.isfinite(a)]
        assert ok.size > 500 and ok.min() >= 0.0 and ok.max() <= 180.0
    # the light is level with the spheres' centres, to the right: the angle grows leftwards on the image
    gold = angles["coated_gold"].reshape(54, 96)
    row = gold[np.isfinite(gold).sum(axis=1).argmax()]
    cols = np.flatnonzero(np.isfinite(row))
    assert row[cols[0]] > 90.0 > row[cols[-1]]
    masks, lows = bt.band_masks(angles)
    assert set(lows) == set(masks)
    for name in TERMINATOR_PRESETS:  # every band of the measurement holds pixels at the documented resolution
        for lo, hi in zip(bt.BAND_EDGES[:-1], bt.BAND_EDGES[1:], strict=True):
            assert masks[f"{name}, {lo:.0f}-{hi:.0f} deg"].sum() >= 10
    centres = sphere_centres(scene, TERMINATOR_PRESETS)
    assert abs(centres["coated_gold"][2] - centres["red_car_paint"][2]) < 1e-6
    assert np.linalg.norm(np.asarray(TERMINATOR_LIGHT) - centres["red_car_paint"]) > 4.0


def test_a_small_run_writes_its_tables_and_image_and_reuses_the_cached_reference(tmp_path, monkeypatch):
    cache = tmp_path / "ref.npz"
    args = ["--width", "40", "--height", "24", "--samples", "2", "--lobe-walks", "64", "--reference-cache", str(cache)]
    bt.main([*args, "--out", str(tmp_path / "a.md")])
    text = (tmp_path / "a.md").read_text()
    assert "`python benchmarks/bench_terminator.py --width 40" in text and "80-84 deg" in text
    assert "## Coated gold's lobe at 83 degrees" in text
    data = json.loads((tmp_path / "a.json").read_text())
    assert [r["label"] for r in data["results"]] == ["default size, calibrated"]
    assert np.isfinite([b["ratio"] for b in data["results"][0]["bands"].values()]).all()
    assert len(data["results"][0]["lobe"]) == len(bt.LOBE_VIEWS) and np.isfinite(data["results"][0]["lobe"]).all()
    assert (tmp_path / "a.png").stat().st_size > 0 and cache.exists()
    modes = []
    real = bt.render_film
    monkeypatch.setattr(
        bt, "render_film", lambda scene, mode, *a, **k: modes.append(mode) or real(scene, mode, *a, **k)
    )
    bt.main([*args, "--out", str(tmp_path / "b.md"), "--sizes", "tiny", "small", "--uncalibrated-too"])
    assert modes == ["neural"] * 4  # the reference came from the cache
    again = json.loads((tmp_path / "b.json").read_text())
    assert again["reference"] == data["reference"]
    labels = ["tiny, calibrated", "tiny, decoder alone", "small, calibrated", "small, decoder alone"]
    assert [r["label"] for r in again["results"]] == labels
    assert all(f"| {label} |" in (tmp_path / "b.md").read_text() for label in labels)

"""benchmarks/bench_stack_sweep.py: its stacks are the ranges it says, and a small run end to end."""

import json

import numpy as np

from addon.core.stack import TRAINED_RANGES, VALID_RANGES, validate
from benchmarks import bench_stack_sweep as bs


def test_the_trained_group_stays_in_the_trained_ranges_and_the_valid_group_leaves_them():
    trained, valid = bs.trained_stacks(12, 1), bs.valid_stacks(40, 2)
    assert [len(s.coatings) for s in trained] == [1] * 4 + [2] * 4 + [3] * 4
    lo, hi = TRAINED_RANGES["ior"]
    assert all(lo <= c.ior <= hi and c.roughness >= TRAINED_RANGES["roughness"][0] for s in trained for c in s.coatings)
    iors = [c.ior for s in valid for c in s.coatings]
    assert (
        min(iors) < lo and max(iors) > hi and all(VALID_RANGES["ior"][0] <= x <= VALID_RANGES["ior"][1] for x in iors)
    )
    assert any(c.roughness == 0.0 for s in valid for c in s.coatings)
    for s in trained + valid:
        validate(s)
    assert bs.describe(valid[0]).count("/") == len(valid[0].coatings)


def test_a_small_run_writes_its_report_and_json(tmp_path):
    out = tmp_path / "sweep.md"
    bs.main(["--trained", "1", "--valid", "1", "--checks", "2", "--samples", "4", "--walks", "500", "--directions",
             "500", "--out", str(out)])  # fmt: skip
    text = out.read_text()
    assert "python benchmarks/bench_stack_sweep.py --trained 1" in text
    assert "| trained ranges | 3 |" in text and "| valid ranges | 3 |" in text and "| 2 |" in text
    data = json.loads(out.with_suffix(".json").read_text())
    assert len(data["trained ranges"]) == 3 and len(data["checks"]) == 2
    assert all(np.isfinite(r["neural"]).all() and np.isfinite(r["reference"]).all() for r in data["valid ranges"])

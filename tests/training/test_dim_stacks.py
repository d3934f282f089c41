"""benchmarks/dim_stacks.py: the fit of a model set on layered data, per stack."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from addon.core.neural import load_models
from addon.core.stack import StackArrays
from onnx_export.layered_data import make_chunk

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "dim_stacks.py"


def _module():
    spec = importlib.util.spec_from_file_location("dim_stacks", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_stack_ratios_compare_the_decoded_remainder_with_the_data_stack_by_stack():
    chunk = make_chunk(seed=3, coatings=1, chunk=0, stacks=6, n_wo=4, n_wi=16, walks=8)
    chunk["arrays"] = StackArrays(**{f: chunk.pop(f"p_{f}") for f in StackArrays.FIELDS})
    ratio, level = _module().stack_ratios(load_models("tiny", threads=1), chunk)
    assert ratio.shape == level.shape == (6,)
    assert np.isfinite(ratio).all() and (ratio > 0).all()
    assert np.median(level) == pytest.approx(1.0)  # levels are over the set's median
    # a model that decodes the data's own mean remainder would read 1: the shipped one is within 2x on most stacks
    assert np.mean((ratio > 0.5) & (ratio < 2.0)) >= 0.5

"""The stability harness on its quick configuration, and the detection behaviours it relies on."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from addon.core import quality, reference
from addon.core.neural import ClampWarning, encode_stack, load_models
from addon.core.render import materials
from addon.core.stack import PRESETS, Coating, Dielectric, Diffuse, Stack

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import stability  # noqa: E402

SIZES = quality.available_sizes()


@pytest.fixture(scope="module")
def cells():
    return stability.run(quick=True)


def test_matrix_covers_every_method_and_case(cells):
    methods = {c.method for c in cells}
    assert methods == {"reference", "principled mapping"} | {f"neural {s}" for s in SIZES}
    names = [c.name for c in stability.cases()]
    for required in (
        "alpha_to_0",
        "grazing",
        "thick_absorbing",
        "thick_scattering",
        "ior_near_1",
        "ior_high",
        "total_internal_reflection",
        "three_coatings",
        "four_coatings",
        "out_of_range",
        "nan_direction",
        "nan_parameter",
    ):
        assert required in names
    assert {(c.method, c.case) for c in cells} == {(m, n) for m in methods for n in names}


def test_no_cell_fails_silently(cells):
    """Every check either passes or the product detected the problem (rejected, warned, fell back)."""
    bad = [(c.method, c.case, c.notes) for c in cells if c.status == "FAIL"]
    assert not bad
    for c in cells:
        if c.status == "ok" and c.finite is not None:
            assert c.finite and c.nonnegative
            if c.albedo_ok is not None:
                assert c.albedo_ok, (c.method, c.case, c.albedo_max)


def test_auto_setting_flags_decoder_cells_clearly_over_the_tolerance(cells):
    """The auto setting measures at the incident angles 0/30/60/75 degrees: every decoder cell at
    ordinary angles that is clearly over the tolerance is caught. Errors only at grazing angles are
    not part of its measure (a documented limit)."""
    tol = quality.DEFAULT_TOLERANCE
    grazing = {c.name for c in stability.cases() if max(c.angles) > 80}
    checked = 0
    for c in cells:
        # an error of 0 is one the quick matrix's few reference walks cannot resolve (its noise is larger)
        if c.method.startswith("neural") and c.error and c.case not in grazing:
            if c.error > 2 * tol:
                assert c.auto == "flagged", (c.case, c.error)
                checked += 1
            elif c.error < tol / 2:
                assert c.auto == "within tolerance", (c.case, c.error)
    assert checked > 0


def test_reference_is_finite_nonnegative_and_energy_conserving_in_every_stress_case(cells):
    for c in cells:
        if c.method != "reference" or c.case.startswith("nan"):
            continue
        assert c.status == "ok", (c.case, c.notes)
        assert c.finite and c.nonnegative and c.albedo_ok, c.case
        assert c.albedo_max <= 1.05 and c.seconds_per_eval > 0


def test_nan_inputs_are_rejected_naming_the_value(cells):
    for c in cells:
        if c.case.startswith("nan") and c.method != "principled mapping" or c.case == "nan_parameter":
            assert c.status == "rejected", (c.method, c.case)
    wi = np.array([[np.nan, 0.0, 1.0]])
    wo = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="finite"):
        reference.eval_brdf(PRESETS["lacquered_plastic"], wi, wo, walks=2)
    m = load_models(SIZES[0])
    with pytest.raises(ValueError, match="finite"):
        m.eval_brdf(encode_stack(Stack(Diffuse((0.5, 0.5, 0.5))), m), wi, wo)
    with pytest.raises(ValueError, match="roughness"):
        Coating(roughness=float("nan"))


def test_untrained_parameters_warn_and_stay_finite():
    m = load_models(SIZES[0])
    with pytest.warns(ClampWarning, match="ior"):
        z = encode_stack(Stack(Dielectric(roughness=0.1, ior=4.0)), m)
    wi = np.array([[-np.sin(1.55), 0.0, np.cos(1.55)]] * 3)  # 88.8 degrees: grazing
    wo = np.array([[np.sin(1.55), 0.0, np.cos(1.55)], [0.0, 0.0, 1.0], [0.0, np.sin(1.55), np.cos(1.55)]])
    f = m.eval_brdf(z, wi, wo)
    assert np.isfinite(f).all() and (f >= 0).all()


def test_near_delta_lobe_is_detected_by_the_auto_setting(cells):
    """alpha 2e-3 is clamped by the decoders (trained from 0.01) and its lobe error is large: the auto
    setting measures that and does not pretend the tolerance is met."""
    cell = next(c for c in cells if c.method == f"neural {SIZES[0]}" and c.case == "alpha_to_0_conductor")
    assert cell.status == "warned" and any("clamped" in n for n in cell.notes)
    stack = next(c.stack for c in stability.cases() if c.name == "alpha_to_0_conductor")
    with pytest.warns(quality.QualityWarning):
        choice = quality.choose_decoder(stack, 0.5, sizes=SIZES[:1], cache=quality.ErrorCache(), fallback="reference")
    assert choice.size is None and choice.errors[SIZES[0]] > 0.5


def test_renderer_materials_stay_finite_for_every_stress_stack():
    """Whatever serves a stress stack in the renderer (decoder, reference or exact BSDF) gives finite,
    non-negative values at normal and grazing directions."""
    t = np.radians([0.0, 60.0, 89.5])
    wi = np.stack([-np.sin(t), np.zeros(3), np.cos(t)], axis=1)
    wo = np.stack([np.sin(t), np.zeros(3), np.cos(t)], axis=1)
    hits = materials.SurfaceHits(np.zeros((3, 2)), np.full(3, 0.01), 0)
    for case in stability.cases():
        if case.stack is None or case.nan_directions:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            bound = materials.resolve(case.stack, "neural", reference_walks=4).bind(hits)
            f = bound.eval(wi, wo)
        assert f.shape == (3, 3) and np.isfinite(f).all() and (f >= 0).all(), case.name


def test_markdown_lists_every_cell_and_the_command(cells):
    text = stability.markdown(cells, "python benchmarks/stability.py --quick")
    assert "`python benchmarks/stability.py --quick`" in text
    for c in stability.cases():
        assert f"| {c.name} |" in text
    rows = [line for line in text.splitlines() if line.startswith("| ") and line.count("|") == 12]
    assert len(rows) == len(cells) + 1  # header + one row per cell

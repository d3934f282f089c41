"""Stability matrix: every BRDF method under every stress case (docs/architecture.md, Measurement).

    python benchmarks/stability.py            # writes docs/stability.md
    python benchmarks/stability.py --quick    # smaller lobes and fewer walks (the test's configuration)

Methods: the position-free reference (``addon.core.reference``, ``eval_brdf`` + analog-walk
albedo), every shipped neural decoder size (encoded as the renderer encodes it: encoder +
layering network, clamped to the trained range), the Principled coat mapping used for the
Cycles baseline (``addon.core.render.principled``: whether it maps the stack to finite socket
values) and, when run by ``benchmarks/bench_all.py`` (which has bpy), Cycles' Principled coat
itself: its directional albedo rendered in Cycles (``benchmarks/cycles_brdf.py``).

Stress cases: alpha -> 0, grazing incidence and exitance (89.5 degrees), very thick absorbing
and very thick highly scattering media, ior near 1 and at the top of the valid range, total
internal reflection inside the stack, three and four coatings, out-of-range (valid but
untrained) parameters, NaN directions and NaN parameters.

Each cell records: finite (no NaN/Inf), non-negative, albedo <= 1 (the reference's analog-walk
albedo within 3 standard errors; a decoder's albedo from its lobe images, within 2%), the lobe
error against the reference (noise-corrected, as ``addon.core.quality``), the time per
evaluation, and what the product did: ``ok``, ``warned`` (a ClampWarning or QualityWarning),
``rejected`` (ValueError naming the bad value), ``fallback: reference`` (the decoder cannot
encode the stack, so the renderer uses the reference) or ``FAIL`` (a check failed and nothing
said so). Tests (``tests/core/test_stability.py``) run the quick configuration and pin the
detection behaviours.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from addon.core import lobe, quality, reference  # noqa: E402
from addon.core.stack import PRESETS, Coating, Conductor, Dielectric, Diffuse, Stack  # noqa: E402

GRAZING_DEG = 89.5


@dataclass
class Case:
    name: str
    what: str
    stack: Stack | None  # None: the stack itself cannot be built (NaN parameter)
    angles: tuple = (0.0, 60.0)
    nan_directions: bool = False


def cases() -> list[Case]:
    white = Diffuse((0.8, 0.8, 0.8))
    three = PRESETS["three_layer"]
    return [
        Case("alpha_to_0", "coat alpha 1e-4 over a white base", Stack(white, (Coating(roughness=1e-4, ior=1.5),))),
        Case(
            "alpha_to_0_conductor",
            "bare conductor, alpha 2e-3 (just above the delta threshold)",
            Stack(Conductor(roughness=2e-3)),
        ),
        Case(
            "grazing_single",
            f"bare rough conductor (alpha 0.2) at {GRAZING_DEG} degrees incidence and exitance",
            Stack(Conductor(roughness=0.2)),
            angles=(GRAZING_DEG,),
        ),
        Case(
            "grazing",
            f"lacquered plastic at {GRAZING_DEG} degrees incidence and exitance",
            PRESETS["lacquered_plastic"],
            angles=(GRAZING_DEG,),
        ),
        Case(
            "thick_absorbing",
            "medium albedo 0, optical thickness 100 over a white base",
            Stack(white, (Coating(roughness=0.1, ior=1.5, albedo=(0.0, 0.0, 0.0), thickness=100.0),)),
        ),
        Case(
            "thick_scattering",
            "medium albedo 0.999, optical thickness 100 over a black base",
            Stack(Diffuse((0.0, 0.0, 0.0)), (Coating(roughness=0.1, ior=1.5, albedo=(0.999,) * 3, thickness=100.0),)),
        ),
        Case(
            "ior_near_1",
            "coat ior 1.001 (index-matched limit) over a white base",
            Stack(white, (Coating(roughness=0.1, ior=1.001),)),
        ),
        Case(
            "ior_near_1_base", "bare dielectric base, ior 1.001, alpha 0.1", Stack(Dielectric(roughness=0.1, ior=1.001))
        ),
        Case(
            "ior_high_base",
            "bare dielectric base, ior 4.0 (top of the valid range), alpha 0.1",
            Stack(Dielectric(roughness=0.1, ior=4.0)),
        ),
        Case(
            "ior_high",
            "coat ior 4.0 (top of the valid range) over a white base",
            Stack(white, (Coating(roughness=0.1, ior=4.0),)),
        ),
        Case(
            "total_internal_reflection",
            "ior 2.0 coating under an ior 1.1 top: TIR at the inner interface",
            Stack(
                white,
                (
                    Coating(roughness=0.1, ior=2.0, albedo=(0.9, 0.9, 0.9), thickness=0.5),
                    Coating(roughness=0.05, ior=1.1),
                ),
            ),
        ),
        Case("three_coatings", "the three_layer preset", three),
        Case(
            "four_coatings",
            "three_layer plus a rough tinted coat on top",
            Stack(
                three.base, three.coatings + (Coating(roughness=0.4, ior=1.3, albedo=(0.5, 0.9, 0.5), thickness=0.8),)
            ),
        ),
        Case(
            "out_of_range",
            "alpha 0 (trained from 0.01), ior 3 (trained to 2), thickness 50 (trained to 5)",
            Stack(
                white,
                (
                    Coating(roughness=0.3, ior=3.0, albedo=(0.5, 0.5, 0.5), thickness=50.0),
                    Coating(roughness=0.0, ior=1.5),
                ),
            ),
        ),
        Case("nan_direction", "a NaN component in wi", PRESETS["lacquered_plastic"], nan_directions=True),
        Case("nan_parameter", "a NaN coat roughness", None),
    ]


@dataclass
class Cell:
    method: str
    case: str
    status: str = "ok"
    finite: bool | None = None
    nonnegative: bool | None = None
    albedo_max: float | None = None
    albedo_ok: bool | None = None
    error: float | None = None
    seconds_per_eval: float | None = None
    auto: str | None = None  # neural cells: what the auto setting picks at the default tolerance
    notes: list = field(default_factory=list)


def _grid(res: int, theta: float):
    wo, mask = lobe.lobe_grid(res)
    wo = wo[mask]
    return np.broadcast_to(lobe.incident_direction(theta), wo.shape).copy(), wo


def _caught(fn):
    """Run fn(), returning (result, warnings, exception)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            return fn(), list(caught), None
        except (ValueError, FloatingPointError) as e:
            return None, list(caught), e


def _nan_cell(method: str, case: Case, evaluate) -> Cell:
    """A NaN input must be rejected with a ValueError that says what was wrong."""
    cell = Cell(method, case.name)
    if case.stack is None:
        try:
            Stack(Diffuse((0.8, 0.8, 0.8)), (Coating(roughness=float("nan")),))
        except ValueError as e:
            cell.status, cell.notes = "rejected", [str(e)]
        else:
            cell.status = "FAIL"
            cell.notes = ["a NaN roughness was accepted"]
        return cell
    wi, wo = _grid(4, 30.0)
    wi[0, 0] = np.nan
    _, _, exc = _caught(lambda: evaluate(wi, wo))
    if exc is not None and ("finite" in str(exc).lower() or "nan" in str(exc).lower()):
        cell.status, cell.notes = "rejected", [str(exc)]
    else:
        cell.status = "FAIL"
        cell.notes = [f"a NaN direction was not rejected ({exc!r})"]
    return cell


def reference_cell(case: Case, res: int, walks: int, albedo_samples: int) -> Cell:
    if case.nan_directions or case.stack is None:
        return _nan_cell(
            "reference", case, lambda wi, wo: reference.eval_brdf(PRESETS["lacquered_plastic"], wi, wo, walks=2)
        )
    cell = Cell("reference", case.name)
    fs, ses, n, t = [], [], 0, 0.0
    for theta in case.angles:
        wi, wo = _grid(res, theta)
        t0 = time.perf_counter()
        out, _, exc = _caught(lambda: reference.eval_brdf(case.stack, wi, wo, walks=walks, seed=1))
        t += time.perf_counter() - t0
        if exc is not None:
            cell.status, cell.notes = "FAIL", [f"raised {exc!r}"]
            return cell
        f, se = out
        fs.append(f * wo[:, 2:3])
        ses.append(se * wo[:, 2:3])
        n += len(wi)
    f = np.concatenate(fs)
    se = np.concatenate(ses)
    cell.finite = bool(np.isfinite(f).all() and np.isfinite(se).all())
    cell.nonnegative = bool((f >= 0).all())
    cell.seconds_per_eval = t / n
    den = math.sqrt(float(np.sum(f * f)))
    cell.error = math.sqrt(float(np.sum(se * se))) / den if den > 0 else 0.0  # its own relative noise
    views = np.array([lobe.incident_direction(th) for th in case.angles])
    a, a_se = reference.albedo(case.stack, views, samples=albedo_samples, seed=2)
    cell.albedo_max = float(a.max())
    cell.albedo_ok = bool(np.all(a <= 1.0 + 3.0 * a_se + 1e-9))
    if not (cell.finite and cell.nonnegative and cell.albedo_ok):
        cell.status = "FAIL"
    cell.notes.append("error = its own relative noise at this walk count")
    return cell


def neural_cell(size: str, case: Case, res: int, walks: int) -> Cell:
    from addon.core.neural import encode_stack, load_models

    method = f"neural {size}"
    if case.nan_directions or case.stack is None:
        m = load_models(size)
        z = encode_stack(Stack(Diffuse((0.5, 0.5, 0.5))), m)
        return _nan_cell(method, case, lambda wi, wo: m.eval_brdf(z, wi, wo))
    cell = Cell(method, case.name)
    imgs, caught, exc = _caught(lambda: _decoder_lobes(case.stack, size, res, case.angles))
    if exc is not None:
        cell.status, cell.notes = "rejected", [str(exc)]
        return cell
    if imgs is None:
        cell.status = "fallback: reference"
        cell.notes = [
            "the shipped models cannot encode this stack (no layering network for this size); the "
            "renderer shades it with the reference estimator"
        ]
        return cell
    pred, seconds_per_eval = imgs
    cell.seconds_per_eval = seconds_per_eval
    cell.finite = bool(np.isfinite(pred).all())
    cell.nonnegative = bool((pred >= 0).all())
    alb = np.array([lobe.albedo_from_lobe(p) for p in pred])
    cell.albedo_max = float(alb.max())
    cell.albedo_ok = bool(cell.albedo_max <= 1.02)  # lobe-grid quadrature at this resolution is within ~2%
    ref, se = _reference_lobes(case.stack, res, walks, case.angles)
    cell.error = quality.noise_corrected_error(pred, ref, se)
    notes = sorted({str(w.message) for w in caught})
    cell.notes += notes
    if notes:
        cell.status = "warned"
    # What the auto quality setting does with this stack and size at the default tolerance.
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        auto = quality.choose_decoder(
            case.stack,
            quality.DEFAULT_TOLERANCE,
            sizes=[size],
            fallback="reference",
            res=res,
            walks=walks,
            cache=quality.ErrorCache(),
        )
    cell.auto = "within tolerance" if auto.size == size else "flagged"
    if not (cell.finite and cell.nonnegative and cell.albedo_ok):
        cell.status = "FAIL" if not notes else "warned"
        cell.notes.append("a check failed" + (" (after a warning)" if notes else ""))
    return cell


def _decoder_lobes(stack: Stack, size: str, res: int, angles):
    from addon.core.neural import encode_stack, load_models, top_coat

    m = load_models(size)
    try:
        z = encode_stack(stack, m)
    except (FileNotFoundError, NotImplementedError):
        return None
    top = top_coat(stack)
    t0 = time.perf_counter()
    imgs = np.stack([lobe.lobe_image(lambda wi, wo: m.eval_brdf(z, wi, wo, top), th, res) for th in angles])
    n = len(angles) * int(lobe.lobe_grid(res)[1].sum())
    return imgs, (time.perf_counter() - t0) / n


_REFERENCE_LOBES: dict = {}


def _reference_lobes(stack: Stack, res: int, walks: int, angles):
    """Reference lobe images and their standard errors, computed once per stack and grid: every decoder
    size is scored against the same (seeded) images, and thick coats make them the matrix's main cost."""
    key = (stack.to_json(), res, walks, tuple(float(a) for a in angles))
    if key not in _REFERENCE_LOBES:
        _REFERENCE_LOBES[key] = _compute_reference_lobes(stack, res, walks, angles)
    imgs, errs = _REFERENCE_LOBES[key]
    return imgs.copy(), errs.copy()


def _compute_reference_lobes(stack: Stack, res: int, walks: int, angles):
    wo, mask = lobe.lobe_grid(res)
    grid = wo[mask]
    imgs = np.zeros((len(angles), res * res, 3))
    errs = np.zeros_like(imgs)
    for a, th in enumerate(angles):
        f, se = reference.eval_brdf_many(stack, grid[None], lobe.incident_direction(th)[None], walks=walks, seed=3 + a)
        imgs[a, mask] = f[0] * grid[:, 2:3]
        errs[a, mask] = se[0] * grid[:, 2:3]
    return imgs.reshape(len(angles), res, res, 3), errs.reshape(len(angles), res, res, 3)


def principled_cell(case: Case) -> Cell:
    from addon.core.render.principled import principled_inputs

    cell = Cell("principled mapping", case.name)
    if case.nan_directions:
        cell.status, cell.notes = "n/a", ["Cycles traces its own rays"]
        return cell
    if case.stack is None:
        return _nan_cell(cell.method, case, None)
    t0 = time.perf_counter()
    inputs, caught, exc = _caught(lambda: principled_inputs(case.stack))
    cell.seconds_per_eval = time.perf_counter() - t0
    if exc is not None:
        cell.status, cell.notes = "FAIL", [repr(exc)]
        return cell
    vals = np.concatenate([np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in inputs.values()])
    cell.finite = bool(np.isfinite(vals).all())
    cell.nonnegative = bool((vals >= 0).all())
    if not (cell.finite and cell.nonnegative):
        cell.status = "FAIL"
    cell.notes.append("socket values only; the BRDF is measured in Cycles by bench_all.py")
    return cell


def cycles_cell(cy, case: Case, albedo_samples: int) -> Cell:
    """Cycles' Principled coat (``cycles_brdf.CyclesBRDF``): its directional albedo at the case's angles,
    rendered in Cycles, against the reference's; the error is the largest relative albedo difference."""
    cell = Cell("Cycles Principled", case.name)
    if case.nan_directions:
        cell.status, cell.notes = "n/a", ["Cycles traces its own rays"]
        return cell
    if case.stack is None:
        return _nan_cell(cell.method, case, None)
    cos = np.cos(np.radians(np.asarray(case.angles, dtype=np.float64)))
    t0 = time.perf_counter()
    a = cy.albedo(case.stack, cos)
    cell.seconds_per_eval = (time.perf_counter() - t0) / max(1, int(cy.on_plane.sum()) * cy.samples)
    cell.finite = bool(np.isfinite(a).all())
    cell.nonnegative = bool((a >= 0).all())
    cell.albedo_max = float(a.max())
    cell.albedo_ok = bool(cell.albedo_max <= 1.02)  # Monte Carlo noise of the render
    views = np.array([lobe.incident_direction(th) for th in case.angles])
    ref, _ = reference.albedo(case.stack, views, samples=albedo_samples, seed=2)
    cell.error = float(np.max(np.abs(a - ref) / np.maximum(ref, 1e-3)))
    cell.notes.append("albedo only (world of radiance 1); error = largest relative albedo difference")
    if not (cell.finite and cell.nonnegative and cell.albedo_ok):
        cell.status = "FAIL"
    return cell


def run(quick: bool = False, sizes=None, case_names=None, cycles=None) -> list[Cell]:
    """The matrix; ``cycles`` is an optional ``cycles_brdf.CyclesBRDF`` (needs bpy) adding Cycles' column."""
    res = 8 if quick else 16
    walks = 32 if quick else 256
    albedo_samples = 2000 if quick else 20000
    sizes = quality.available_sizes() if sizes is None else list(sizes)
    chosen = [c for c in cases() if case_names is None or c.name in case_names]
    cells = []
    for case in chosen:
        cells.append(reference_cell(case, res, walks, albedo_samples))
        for s in sizes:
            cells.append(neural_cell(s, case, res, walks))
        cells.append(principled_cell(case))
        if cycles is not None:
            cells.append(cycles_cell(cycles, case, albedo_samples))
        print(" | ".join(f"{c.method}: {c.status}" for c in cells if c.case == case.name), file=sys.stderr, flush=True)
    return cells


def _fmt(v, kind):
    if v is None:
        return "-"
    if kind == "bool":
        return "yes" if v else "**no**"
    if kind == "pct":
        return f"{100 * v:.1f}%" if math.isfinite(v) else "inf"
    if kind == "us":
        return f"{1e6 * v:.1f}"
    return f"{v:.3f}"


def markdown(cells: list[Cell], command: str) -> str:
    names = {c.name: c for c in cases()}
    methods = list(dict.fromkeys(c.method for c in cells))
    case_names = list(dict.fromkeys(c.case for c in cells))
    lines = [
        "# Stability matrix",
        "",
        f"Produced by `{command}` on a shared 2-core CPU (times are noisy).",
        "",
        "Per cell: the product's behaviour, then finite / non-negative / albedo <= 1 (max albedo) / error "
        "against the reference / microseconds per RGB evaluation. The reference's error is its own relative "
        "noise at the walk count used; a decoder's is the noise-corrected lobe error "
        "(`addon.core.quality.noise_corrected_error`). `warned` = the product clamped or flagged the input "
        "and said so; `rejected` = ValueError naming the bad value; `fallback: reference` = the decoder "
        "cannot encode the stack and the renderer uses the reference. `auto:` what the auto quality setting "
        f"(`addon.core.quality.choose_decoder`, tolerance {quality.DEFAULT_TOLERANCE:g}, this size only) "
        "measures for the stack: `flagged` means its measured error is over the tolerance, so it warns "
        "(QualityWarning) and uses a more accurate decoder or, if asked to, the reference. It measures at "
        "0/30/60/75 degrees incidence, so errors only at grazing angles pass it.",
        "",
        "## Summary",
        "",
        "| case | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    by = {(c.method, c.case): c for c in cells}
    for cn in case_names:
        row = []
        for m in methods:
            c = by.get((m, cn))
            if c is None:
                row.append("-")
                continue
            err = f", err {_fmt(c.error, 'pct')}" if c.error is not None else ""
            auto = f", auto: {c.auto}" if c.auto else ""
            row.append(f"{c.status}{err}{auto}")
        lines.append(f"| {cn} | " + " | ".join(row) + " |")
    lines += ["", "## Cases", "", "| case | what |", "|---|---|"]
    lines += [f"| {cn} | {names[cn].what} |" for cn in case_names]
    lines += [
        "",
        "## All cells",
        "",
        "| case | method | status | finite | non-negative | albedo max | albedo <= 1 | error | us/eval | auto "
        "| notes |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        notes = "; ".join(n.replace("|", "/") for n in c.notes)[:300]
        lines.append(
            f"| {c.case} | {c.method} | {c.status} | {_fmt(c.finite, 'bool')} | {_fmt(c.nonnegative, 'bool')} "
            f"| {_fmt(c.albedo_max, 'f')} | {_fmt(c.albedo_ok, 'bool')} | {_fmt(c.error, 'pct')} | "
            f"{_fmt(c.seconds_per_eval, 'us')} | {c.auto or '-'} | {notes} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    a = ap.parse_args(argv)
    command = "python benchmarks/stability.py" + (" --quick" if a.quick else "")
    cells = run(a.quick)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "stability.md").write_text(markdown(cells, command))
    print(f"wrote {a.out / 'stability.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

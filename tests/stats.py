"""The one chi-square harness of the sampling tests: a direction sampler against its own density.

``chi2_sphere(wi, valid, pdf_fn)`` bins samples over the whole sphere in equal-area
(cos theta, phi) cells, integrates the density over each cell with a midpoint rule, counts the
rejected samples against the density's missing mass ("no sample" cell), pools the cells of
small expectation into one, and returns the statistic, the p-value and the integral of the
density; a sample at which the density is zero fails outright.
``chi2_direction_test(sample_fn, pdf_fn, n)`` draws the samples first.
The power checks in ``tests/core/test_bsdf_sampling.py`` show that it rejects a slightly wrong
density.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

# Axis orders that put the binning grid's pole on +z (the local normal) or on +y (off the x-z
# plane of incidence, so that peaks at the normal or in that plane, common for BRDF samplers,
# are not squeezed into the grid's polar cells). ``TO_GRID[pole]`` maps a direction to the grid's
# frame, ``FROM_GRID[pole]`` maps it back.
TO_GRID = {"z": [0, 1, 2], "y": [2, 0, 1]}
FROM_GRID = {"z": [0, 1, 2], "y": [1, 2, 0]}


@dataclass
class Chi2:
    statistic: float
    pvalue: float
    dof: int
    pdf_integral: float  # the density's integral over the sphere (quadrature): the expected valid fraction


def sphere_grid(theta_bins: int, phi_bins: int, sub: tuple[int, int], pole: str = "z"):
    """Midpoints of ``sub`` x ``sub`` quadrature points per cell, (theta_bins*sub0, phi_bins*sub1, 3) in
    the sampler's frame, and the solid angle of each."""
    nz, nphi = theta_bins * sub[0], phi_bins * sub[1]
    z = -1.0 + (np.arange(nz) + 0.5) * (2.0 / nz)
    phi = (np.arange(nphi) + 0.5) * (2.0 * np.pi / nphi)
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(np.maximum(1.0 - zz * zz, 0.0))
    dirs = np.stack([r * np.cos(pp), r * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    return dirs[:, FROM_GRID[pole]], 4.0 * np.pi / dirs.shape[0]


def _cell(w_grid: np.ndarray, theta_bins: int, phi_bins: int) -> np.ndarray:
    iz = np.clip(((w_grid[:, 2] + 1.0) * 0.5 * theta_bins).astype(int), 0, theta_bins - 1)
    phi = np.mod(np.arctan2(w_grid[:, 1], w_grid[:, 0]), 2.0 * np.pi)
    ip = np.clip((phi / (2.0 * np.pi) * phi_bins).astype(int), 0, phi_bins - 1)
    return iz * phi_bins + ip


def _pool(observed: np.ndarray, expected: np.ndarray, min_expected: float):
    """Cells expecting fewer than ``min_expected`` samples are merged into one."""
    low = expected < min_expected
    if not np.any(low):
        return observed, expected
    return np.append(observed[~low], observed[low].sum()), np.append(expected[~low], expected[low].sum())


def chi2_sphere(
    wi,
    valid,
    pdf_fn,
    theta_bins: int = 40,
    phi_bins: int = 80,
    sub=(24, 12),
    pole: str = "z",
    min_expected: float = 5.0,
) -> Chi2:
    """Chi-square test that the samples ``wi[valid]`` (``wi`` (n, 3); the other rows are rejected
    samples) are distributed as ``pdf_fn(directions (m, 3)) -> (m,)``, a solid-angle density whose
    integral is the probability of a valid sample.

    Fails (AssertionError) when a valid sample has density zero.
    The expected counts are rescaled to the sample count: the quadrature integral is 1 only to
    about 1e-4 for steep densities.
    """
    sub = (sub, sub) if isinstance(sub, int) else tuple(sub)
    wi = np.asarray(wi, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.all(np.isfinite(wi), axis=1)
    n = wi.shape[0]
    cells = theta_bins * phi_bins
    observed = np.bincount(_cell(wi[valid][:, TO_GRID[pole]], theta_bins, phi_bins), minlength=cells)
    grid, dw = sphere_grid(theta_bins, phi_bins, sub, pole)
    dens = np.asarray(pdf_fn(grid), dtype=np.float64).reshape(theta_bins, sub[0], phi_bins, sub[1])
    mass = dens.sum(axis=(1, 3)).reshape(-1) * dw
    total = float(mass.sum())
    expected = np.append(mass * n, max(n * (1.0 - total), 0.0))
    observed = np.append(observed, n - valid.sum()).astype(np.float64)
    inside = np.asarray(pdf_fn(wi[valid]), dtype=np.float64)
    assert np.all(inside > 0.0), f"{int(np.sum(~(inside > 0.0)))} samples fall where the density is zero"
    o, e = _pool(observed, expected, min_expected)
    assert np.all(o[e == 0.0] == 0), "samples fall in cells the quadrature sees no density in: refine sub"
    o, e = o[e > 0.0], e[e > 0.0]
    e = e * (o.sum() / e.sum())
    stat = float(np.sum((o - e) ** 2 / e))
    dof = max(len(e) - 1, 1)
    return Chi2(stat, float(stats.chi2.sf(stat, dof)), dof, total)


def chi2_direction_test(
    sample_fn,
    pdf_fn,
    n: int = 200_000,
    theta_bins: int = 16,
    phi_bins: int = 32,
    seed: int = 0,
    min_expected: float = 5.0,
    sub: int = 16,
) -> tuple[float, float]:
    """:func:`chi2_sphere` of ``sample_fn(n, rng) -> wi (n, 3)`` (rejected samples as rows that are
    not finite) against ``pdf_fn``, binned with the pole on +y. Returns (statistic, p-value)."""
    wi = np.asarray(sample_fn(n, np.random.default_rng(seed)), dtype=np.float64)
    res = chi2_sphere(wi, np.all(np.isfinite(wi), axis=1), pdf_fn, theta_bins, phi_bins, sub, "y", min_expected)
    return res.statistic, res.pvalue

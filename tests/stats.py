"""Statistical checks shared by the tests: a chi-square test of a direction sampler against its pdf."""

from __future__ import annotations

import numpy as np
from scipy import stats


def chi2_direction_test(sample_fn, pdf_fn, n: int = 200_000, theta_bins: int = 16, phi_bins: int = 32,
                        seed: int = 0, min_expected: float = 5.0, sub: int = 16) -> tuple[float, float]:
    """Chi-square test of ``sample_fn(n, rng) -> wi (n, 3) (invalid rows NaN or with valid False)``
    against ``pdf_fn(wi) -> (m,)`` over a (cos theta, phi) grid of the whole sphere (rows of
    ``wi`` that are not finite are rejected samples).

    Expected counts integrate the pdf over each cell with a sub x sub midpoint rule per cell. Cells
    with few expected counts are pooled, as in Mitsuba's chi2 test. Returns (statistic, p-value).
    """
    rng = np.random.default_rng(seed)
    wi = np.asarray(sample_fn(n, rng), dtype=np.float64)
    ok = np.isfinite(wi).all(axis=1)
    # Bin in a frame whose pole lies along +y (off the x-z plane of incidence), so that peaks at the
    # normal or in the plane of incidence, common for BRDF samplers, are not squeezed into the grid's polar cells.
    wi = wi[ok][:, [2, 0, 1]]
    ct = np.clip(wi[:, 2], -1.0, 1.0)
    ph = np.mod(np.arctan2(wi[:, 1], wi[:, 0]), 2 * np.pi)
    ti = np.minimum(((ct + 1.0) * 0.5 * theta_bins).astype(int), theta_bins - 1)
    pi_ = np.minimum((ph / (2 * np.pi) * phi_bins).astype(int), phi_bins - 1)
    observed = np.bincount(ti * phi_bins + pi_, minlength=theta_bins * phi_bins).astype(np.float64)


    cu = (np.arange(theta_bins * sub) + 0.5) / (theta_bins * sub) * 2.0 - 1.0
    pu = (np.arange(phi_bins * sub) + 0.5) / (phi_bins * sub) * 2 * np.pi
    C, P = np.meshgrid(cu, pu, indexing="ij")
    S = np.sqrt(np.maximum(1.0 - C * C, 0.0))
    dirs = np.stack([S * np.cos(P), S * np.sin(P), C], axis=-1).reshape(-1, 3)
    dA = (2.0 / (theta_bins * sub)) * (2 * np.pi / (phi_bins * sub))
    dens = np.asarray(pdf_fn(dirs[:, [1, 2, 0]]), dtype=np.float64).reshape(theta_bins, sub, phi_bins, sub)
    expected = dens.sum(axis=(1, 3)).reshape(-1) * dA * n

    order = np.argsort(expected)
    obs, exp = observed[order], expected[order]
    pooled_o, pooled_e, acc_o, acc_e = [], [], 0.0, 0.0
    for o, e in zip(obs, exp):  # pooling over a few hundred cells, not samples
        acc_o += o
        acc_e += e
        if acc_e >= min_expected:
            pooled_o.append(acc_o)
            pooled_e.append(acc_e)
            acc_o = acc_e = 0.0
    if acc_e > 0 and pooled_e:
        pooled_o[-1] += acc_o
        pooled_e[-1] += acc_e
    o = np.array(pooled_o)
    e = np.array(pooled_e)
    stat = float(np.sum((o - e) ** 2 / e))
    dof = max(len(e) - 1, 1)
    return stat, float(stats.chi2.sf(stat, dof))

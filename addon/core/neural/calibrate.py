"""Albedo calibration: a decoded material made as bright as the reference, angle by angle.

    cal = calibrate(stack, models, z, proxy)      # about a second per material, cached
    f = cal.apply(models.eval_brdf(z, wi, wo), wi, wo)

The decoders hold layered lobes only approximately, and what an artist sees first is the error of
the lobe's integral: the directional albedo. Measured on the presets with the tiny decoder
(``benchmarks/bench_fidelity.py``, docs/fidelity.md): varnished wood 10-20% too bright at every
angle, lacquered plastic 12-34% too bright towards grazing, red car paint twice as bright at 87
degrees. That is a colour or brightness shift on every object, and a bright rim at the terminator
under small lights.

The calibration multiplies the decoded f of one material by a reciprocal, per-channel factor

    f_cal(wi, wo) = S(cos theta_i, cos theta_o, phi) * f(wi, wo)

with ``S`` a table on the grid :data:`COSINES` x :data:`COSINES` x :data:`AZIMUTHS` nodes of the relative azimuth
phi, symmetric in the cosines, bilinear between their nodes (constant beyond the grid's ends), linear in phi.
It is found in three steps, from the same reference walks
(the position-free estimator's analog walks, ``reference.albedo_parts``, with their standard errors)
and the same decoded samples (the decoder itself, integrated by importance sampling with the
material's own sampling proxy mixed half and half with a cosine lobe: exact pdfs, one-sample MIS):

1. A separable start, S = c(cos theta_i) c(cos theta_o), that makes the decoded directional albedo
   equal to the reference's at every grid angle. Writing the decoded albedo at grid angle k as
   ``c_k * sum_l M_kl c_l`` (``M`` integrates the lobe against the grid's hat functions), ``c`` is
   the fixed point of ``c <- sqrt(c * A_ref / (M c))``, the symmetric form of matrix scaling.
2. The table itself (:func:`solve_table`): the walks of each grid angle, binned by the cosine they
   leave at, say where that angle's light goes; S = c c (1 + D) with the symmetric D that brings the
   decoded energy of every (angle, exit bin) to the reference's, in least squares weighted by the noise
   of both, plus sum D^2, so that a bin the reference does not pin keeps the separable factor. A
   separable factor matches each angle's albedo by scaling all of its light alike: where the decoder
   holds too little of a lobe's grazing forward light and too much towards the normal, it brightened
   the terminator of coated gold under a level light (docs/terminator.md). A material whose lobe is
   narrower than the grid resolves (:data:`SEPARABLE_SIGMA`, or whose table comes out far from
   separable along its diagonal, :data:`DIAGONAL_MISMATCH`) keeps the separable factors where the grid
   is coarse (:data:`COARSE_COS`).

3. The relative azimuth (:func:`solve_azimuth`): the table gets :data:`AZIMUTHS` nodes in phi = |phi_i - phi_o|,
   S[m, k, q] = table[m, k] (1 + D[m, k, q]), D found as in step 2 from the same walks and samples binned by exit
   cosine and relative azimuth, with each angle's albedo as one more row of the least squares (the bins' targets
   are shrunk one by one, and the fit to them alone drifted off the albedo); a bin the reference does not pin
   keeps the elevation table's factor, and the elevation table stands where the azimuth table would miss the albedo
   by more. It tells backscatter (light and view on the same side of the normal) from forward light, which an
   elevation-only table cannot.

What it does not change: the lobe's shape within a bin (where exactly the light goes between two cosines or two
azimuth nodes). It keeps f >= 0 and reciprocity (the table is symmetric in the two cosines) and adds no network
evaluation. It needs one latent per material; a latent texture is
calibrated per cluster of its texels (``textures.calibration``, with :func:`calibrate_texels`).

With a remainder decoder (``ModelSet.remainder``) the factors scale only the decoded remainder: the exact
top lobe (``top_lobe``) stays as it is, and the target of the decoded part is the albedo of the light
that entered the top interface, from the same walks with the top interface's first reflections left out
(``reference.albedo_parts``: ``below_top``, ``below_top_by_exit``). The reference albedo less the top
lobe's would be the same in expectation, but carries the noise of the walks the coat reflects: at
grazing on a near-black remainder under a bright clear coat, the difference of 0.1-0.7 and 0.1-0.7 with
a standard error of 0.005-0.008, as large as the remainder itself (docs/calibration.md).

The factors follow the reference only where it is clear of its own noise: each target (an angle's
albedo, a bin's energy) is shrunk towards the decoded one where the two are within two standard errors
(:func:`shrink_target`).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import kernels
from ..bsdf.lambert import sample_cosine_hemisphere
from ..reference import AlbedoParts
from ..stack import Stack, StackArrays
from . import proxy, top_lobe
from .calibration_formulas import azimuth_cell

# Incident cosines of the grid: normal incidence to 88.9 degrees, denser towards grazing, where the
# decoders' albedo is furthest off and the reference changes fastest (the coat's Fresnel).
COSINES = (1.0, 0.85, 0.7, 0.5, 0.35, 0.25, 0.17, 0.11, 0.07, 0.04, 0.02)
# Analog walks per grid angle: the reference's relative noise is largest near normal incidence (a few
# percent of the walks carry the coat's specular reflection), so those angles get more walks. Half of
# these counts gave the same render-level fidelity as the full ones (docs/fidelity.md).
WALKS = (16384, 12288, 8192, 8192, 4096, 4096, 4096, 4096, 4096, 4096, 4096)
DECODED_SAMPLES = 8192  # importance samples of the decoded lobe per grid angle
# Nodes of the tables in the relative azimuth phi = |phi_i - phi_o|, evenly spaced on [0, pi] (0, 90, 180 degrees;
# linear between them): light and view on the same side of the normal (phi = 0, backscatter) apart from
# the forward light towards the mirror direction (phi = pi). An elevation-only table (one node) rendered a rough coat
# over copper 1.65-1.89x too bright on a sphere's shadow side under a light near the camera (docs/calibration.md).
AZIMUTHS = 3
EXIT_BINS = len(COSINES) * (AZIMUTHS + 1)  # the reference's exit bins: elevation, then elevation and azimuth
FACTOR_RANGE = (0.1, 10.0)  # c is kept in this range: a factor outside it means the decoder failed the stack
ITERATIONS = 60
# A calibration target moves the factors only by as much as it differs from the decoded albedo beyond this
# many of the reference's standard errors (:func:`shrink_target`).
NOISE_THRESHOLD = 2.0
# A material whose lobe is narrower than the grid resolves keeps the separable factors where the grid is coarse
# (:data:`COARSE_COS`): the table's exit bins split a near-mirror lobe between two nodes, a slight offset between the
# decoded lobe and the reference's drives the entries off the diagonal towards their bounds, and the view
# directions between nodes, interpolated through those entries, lose their light. Measured as the decoded albedo
# against the reference's between the nodes (10 and 20 degrees), tiny: a conductor of alpha 0.01 under a coat of
# 0.01, 17% and 39% dark with the table, 3.3% and 1.7% with this rule; alpha 0.03 under 0.02 (proxy sigma 0.078)
# 14% / 0.9%; alpha 0.05 (0.109) 7% / 0.3%; alpha 0.08 (0.134) 4.1% with the table; alpha 0.12 (0.160) the same
# either way. The limit is the proxy's spread (``proxy.material_params``), below every preset's (0.135 and up,
# whose calibrations stay as they were).
SEPARABLE_SIGMA = 0.12
# The same for a solved table whose coarse part is far from separable along its diagonal (``diagonal_mismatch``):
# a narrow lobe the sampling network does not see as narrow (it sees a coat's ior clamped to 2: a conductor of alpha
# 0.04 under a coat of 0.05 and ior 3 read 1.24 of the reference at 20 degrees, its table's mismatch 1.23; under a
# coat of 0.03, 0.75). The presets' tables: 0.03-0.16. Held-out stacks of two coatings with wide lobes reach 0.3-0.6,
# where the table's lobe is the better one (at 0.3 their calibrated lobe error's 90th percentile rose from 0.16 to
# 0.22: tests/core/test_layering.py).
DIAGONAL_MISMATCH = 0.6
# Where a narrow lobe's table is the separable factors': every pair of grid cosines at or above this (within 70
# degrees of the normal, where the grid's nodes are 8-15 degrees apart). Towards grazing the nodes are close enough
# for the table, which keeps the held-out grazing set's largest albedo ratio at 80-89.5 degrees (tiny: 1.10; the
# separable factors everywhere gave 1.22).
COARSE_COS = 0.35
# What the key of such a calibration adds (``cache_key``).
SEPARABLE_RULE = "-separable"
# A solved table misses its own target where, at some cosine and channel, its calibrated albedo is off the target by
# more than MISS_SIGMA of the target's standard errors and MISS_RELATIVE of it (``_target_miss``): its entries
# held at their bounds. The separable factors then take its place where they come nearer (a smooth clear coat over a
# smooth metal: 1.32 of the reference at 80 degrees with the table). The presets' tables meet their targets.
MISS_SIGMA = 4.0
MISS_RELATIVE = 0.03
# What every calibration's key adds for that rule (``cache_key``): those made before it are not current. Not in
# ``settings_key``, which latent textures' bake keys hold: a texture keeps the tables it was baked with.
MISS_RULE = "-miss-separable"
# Decoded rows per network call while a calibration integrates its lobe, with ``step`` called between calls:
# the granularity at which a calibration can be stopped (0.17 s of paper's 1.8 s of decoding, 2 threads).
STEP_ROWS = 8192


@dataclass(frozen=True)
class AlbedoCalibration:
    """The factor ``table`` (K, K, P, 3) on incident x outgoing cosines ``cosines`` (K,), decreasing, symmetric
    in its first two axes, x the P relative azimuth nodes (:data:`AZIMUTHS`; a table (K, K, 3) is one node, elevation
    only); ``scale`` (K, 3), the separable factors it starts from (``table`` is their
    outer product where the reference says nothing more); and the albedos that set them: ``reference``
    (K, 3) with its standard error ``reference_stderr``, and the decoded albedo before (``decoded``) and
    after (``calibrated``) the factors."""

    cosines: np.ndarray
    scale: np.ndarray
    table: np.ndarray
    reference: np.ndarray
    reference_stderr: np.ndarray
    decoded: np.ndarray
    calibrated: np.ndarray
    top: np.ndarray | None = None  # (K, 3) albedo of the exact top lobe (remainder decoders), in both of the above

    def factor(self, cos_i: np.ndarray, cos_o: np.ndarray, cos_phi: np.ndarray | None = None) -> np.ndarray:
        """The factor (N, 3) at pairs of cosines (N,) and cosines of their relative azimuth (N,; may be left out for
        an elevation-only table): bilinear between the grid's cosines, constant beyond them, linear in the azimuth
        between its nodes."""
        return self.rows().factor(cos_i, cos_o, cos_phi)

    def apply(self, f: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """f (N, 3) at local unit directions wi, wo (N, 3) times the factor at (cos theta_i, cos theta_o, their
        relative azimuth) (f: the decoded part)."""
        return self.rows().apply(f, wi, wo)

    def rows(self) -> "RowCalibration":
        """This table for every row."""
        return RowCalibration(self.cosines, self.table[None], np.zeros(0, dtype=np.int64))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`RowCalibration.arrays` of this table for every row."""
        return self.rows().arrays()


@dataclass(frozen=True)
class RowCalibration:
    """Factor tables (T, K, K, P, 3) (or (T, K, K, 3): one azimuth node) on decreasing ``cosines`` (K,) and
    :data:`AZIMUTHS`-like relative azimuth nodes, and, per row, the one that applies
    (``which`` (N,); empty: table 0 for every row): a latent texture's calibration at a bounce's hits
    (``textures.calibration``), or one material's (:meth:`AlbedoCalibration.rows`)."""

    cosines: np.ndarray
    tables: np.ndarray
    which: np.ndarray

    def take(self, index) -> "RowCalibration":
        """The calibration of the rows ``index``."""
        return self if len(self.which) == 0 else RowCalibration(self.cosines, self.tables, self.which[index])

    def factor(self, cos_i: np.ndarray, cos_o: np.ndarray, cos_phi: np.ndarray | None = None) -> np.ndarray:
        """The factor (N, 3) at pairs of cosines (N,) and the cosines of their relative azimuth (N,; may be left
        out for elevation-only tables): :meth:`AlbedoCalibration.factor`."""
        x = np.clip(np.asarray(cos_i, dtype=np.float64).reshape(-1), 0.0, 1.0)
        y = np.clip(np.asarray(cos_o, dtype=np.float64).reshape(-1), 0.0, 1.0)
        out = np.ones((len(x), 3))
        if cos_phi is None:
            kernels.scale_by_table(out, x, y, *self.arrays())
        else:
            c = np.ascontiguousarray(np.asarray(cos_phi, dtype=np.float64).reshape(-1))
            kernels.scale_by_table(out, x, y, *self.arrays(), c)
        return out

    def check_rows(self, n: int) -> None:
        """ValueError unless this calibration can scale ``n`` rows (one table for all, or a choice per row)."""
        if len(self.which) not in (0, n):
            raise ValueError(f"the calibration has {len(self.which)} rows, f has {n}")

    def apply(self, f: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """f (N, 3) at local unit directions wi, wo (N, 3) times each row's factor at (cos theta_i, cos theta_o)."""
        out = np.array(f, dtype=np.float64)
        self.check_rows(len(out))
        ui, uo = kernels.float64_rows(np.asarray(wi)), kernels.float64_rows(np.asarray(wo))
        cos_i = np.clip(np.ascontiguousarray(ui[:, 2]), 0.0, 1.0)
        cos_o = np.clip(np.ascontiguousarray(uo[:, 2]), 0.0, 1.0)
        cos_phi = kernels.relative_azimuth_cosines(ui, uo)
        kernels.scale_by_table(out, cos_i, cos_o, *self.arrays(), cos_phi)
        return out.astype(np.asarray(f).dtype, copy=False)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The calibration as the compiled loops take it (``kernels.scale_by_table``, ``kernels.decoded_brdf``):
        the grid's cosines increasing, the tables in the same order as (T, K, K * P, 3) (each outgoing cosine's
        P azimuth nodes side by side), and ``which``."""
        grid = np.ascontiguousarray(self.cosines[::-1], dtype=np.float64)
        t = with_azimuth(self.tables)
        tables = np.ascontiguousarray(t[:, ::-1, ::-1], dtype=np.float64).reshape(t.shape[0], t.shape[1], -1, 3)
        return grid, tables, np.ascontiguousarray(self.which, dtype=np.int64)


def with_azimuth(tables: np.ndarray, stacked: bool = True) -> np.ndarray:
    """Factor tables ((T,) K, K, P, 3), ``stacked``: with the leading T axis; those of the elevations only ((T,) K,
    K, 3) as one azimuth node (a view)."""
    t = np.asarray(tables)
    lead = 1 if stacked else 0
    if t.ndim == 3 + lead and t.shape[-1] == 3:
        return t[..., None, :]
    if t.ndim == 4 + lead and t.shape[-1] == 3:
        return t
    raise ValueError(f"factor tables must be ({'T, ' if stacked else ''}K, K, [P,] 3), got {t.shape}")


# ``RowCalibration.arrays`` of no calibration (no table), for ``kernels.decoded_brdf``
NO_CALIBRATION = (np.zeros(2), np.zeros((0, 2, 2, 3)), np.zeros(0, dtype=np.int64))


def grid_directions(cosines=COSINES) -> np.ndarray:
    """(K, 3) unit directions in the xz-plane at the given cosines to the normal."""
    c = np.asarray(cosines, dtype=np.float64)
    return np.stack([np.sqrt(np.maximum(1.0 - c * c, 0.0)), np.zeros_like(c), c], axis=1)


@dataclass(frozen=True)
class ReferenceParts(AlbedoParts):
    """``reference.AlbedoParts`` at the grid's angles with the parts by exit direction split by relative azimuth
    too: ``by_azimuth`` and ``below_top_by_azimuth`` (K, K, P, 3) (outgoing angle, exit cosine, azimuth node: the
    exit bins :func:`exit_cells` weighs), with their standard errors; ``by_exit`` and ``below_top_by_exit`` (K, K,
    3) are their sums over the azimuth (with their own standard errors, from the same walks)."""

    by_azimuth: np.ndarray | None = None
    by_azimuth_stderr: np.ndarray | None = None
    below_top_by_azimuth: np.ndarray | None = None
    below_top_by_azimuth_stderr: np.ndarray | None = None


def reference_parts(stacks, walks=WALKS, seed: int = 0, step=None) -> ReferenceParts:
    """:class:`ReferenceParts` at the grid's angles (K rows), the parts by exit direction split over the
    grid's hat functions of the exit cosine ((K, K, 3): outgoing angle, exit cosine) and of the exit cosine and the
    relative azimuth ((K, K, P, 3)), from analog walks.

    ``stacks``: one ``Stack``, or ``StackArrays`` of R rows (a sample of a latent texture's texels): then
    the parts of their mean, each row walked with 1/R of ``walks``, so the mean is about as noisy as one
    stack's parts. One estimator call for all angles and rows (each angle's direction repeated
    ``walks[k] / q`` times per row with q / R walks each, q the counts' greatest common divisor): the walks
    advance in the same vectorised loop, about twice as fast as one call per angle, and faster than threads
    (the walks' many small numpy steps hold the GIL). ``step``: see :func:`calibrate`."""
    from .. import reference

    arrays = stacks if isinstance(stacks, StackArrays) else StackArrays.from_stacks([stacks])
    if len(arrays) < 1:
        raise ValueError("reference_parts needs at least one stack")
    dirs = grid_directions()
    walks = np.asarray(walks, dtype=np.int64)
    if walks.shape != (len(dirs),) or (walks < 1).any():
        raise ValueError(f"walks must give one positive count per grid angle ({len(dirs)}), got {walks.tolist()}")
    r = len(arrays)
    q = int(np.gcd.reduce(walks))
    reps = walks // q
    per_row = np.repeat(dirs, reps, axis=0)
    rows = arrays if r == 1 else arrays.take(np.repeat(np.arange(r), len(per_row)))
    parts = reference.albedo_parts(
        rows,
        np.tile(per_row, (r, 1)),
        samples=max(1, q // r),
        seed=seed,
        exit_bins=exit_bin_cells,
        step=step,
        bins=EXIT_BINS,
    )
    angle = np.tile(np.repeat(np.arange(len(dirs)), reps), r)
    count = reps * r

    def per_angle(mean, stderr):
        m, v = np.zeros((len(dirs),) + mean.shape[1:]), np.zeros((len(dirs),) + mean.shape[1:])
        np.add.at(m, angle, mean)
        np.add.at(v, angle, stderr**2)
        c = count.reshape((-1,) + (1,) * (mean.ndim - 1))
        return m / c, np.sqrt(v) / c

    fields = ("albedo", "below_top", "by_exit", "below_top_by_exit")
    out = {}
    for name in fields:
        out[name], out[f"{name}_stderr"] = per_angle(getattr(parts, name), getattr(parts, f"{name}_stderr"))
    for name in ("by_exit", "below_top_by_exit"):  # the exit bins' two parts: elevation; elevation and azimuth
        both = name.replace("exit", "azimuth")
        out[name], out[both] = split_exit_bins(out[name])
        out[name + "_stderr"], out[both + "_stderr"] = split_exit_bins(out[name + "_stderr"])
    return ReferenceParts(**out)


def _hat_cells(cos: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two nodes (N, 2) of the decreasing ``grid`` around each of ``cos`` (N,) and their weights of linear
    interpolation (N, 2), constant beyond the grid's ends."""
    x = np.clip(cos, grid[-1], grid[0])
    inc = grid[::-1]
    j = np.clip(np.searchsorted(inc, x, side="right") - 1, 0, len(inc) - 2)
    t = (x - inc[j]) / (inc[j + 1] - inc[j])
    k = len(grid) - 1 - j  # index in the decreasing grid
    return np.stack([k, k - 1], axis=1), np.stack([1.0 - t, t], axis=1)


def _hats(cos: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """(N, K) weights of linear interpolation on the decreasing ``grid`` at ``cos`` (rows sum to 1)."""
    nodes, weights = _hat_cells(cos, grid)
    w = np.zeros((len(nodes), len(grid)))
    np.put_along_axis(w, nodes, weights, axis=1)
    return w


def _azimuth_cells(cos_phi: np.ndarray, nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """The two azimuth nodes (N, 2) around each relative azimuth acos(``cos_phi``) (N,) of ``nodes`` evenly spaced on
    [0, pi], and their weights (N, 2): ``calibration_formulas.azimuth_cell``, which the renderer's loops run too."""
    if nodes < 2:
        return np.zeros((len(cos_phi), 2), dtype=np.int64), np.column_stack(
            [np.ones(len(cos_phi)), np.zeros(len(cos_phi))]
        )
    q, w = azimuth_cell(np.asarray(cos_phi, dtype=np.float64), nodes)
    return np.stack([q, q + 1], axis=1), np.stack([1.0 - w, w], axis=1)


def azimuth_hats(cos_phi: np.ndarray, nodes: int | None = None) -> np.ndarray:
    """(N, P) weights of linear interpolation in the relative azimuth between ``nodes`` evenly spaced on [0, pi]."""
    nodes = AZIMUTHS if nodes is None else nodes
    q, w = _azimuth_cells(np.asarray(cos_phi, dtype=np.float64).reshape(-1), nodes)
    out = np.zeros((len(q), nodes))
    np.add.at(out, (np.arange(len(q))[:, None], q), w)
    return out


def grid_azimuth(w: np.ndarray) -> np.ndarray:
    """(N,) the cosine of the relative azimuth between directions ``w`` (N, 3) and the grid's (in the xz-plane,
    towards +x: :func:`grid_directions`), as ``kernels._cos_relative_azimuth`` takes it (1 along the normal)."""
    r = np.hypot(w[:, 0], w[:, 1])
    return np.where(r > 1e-15, w[:, 0] / np.maximum(r, 1e-300), 1.0)


def exit_cells(cos: np.ndarray, cos_phi: np.ndarray, grid=COSINES) -> tuple[np.ndarray, np.ndarray]:
    """The four exit bins (N, 4) of directions at cosines ``cos`` and relative azimuth cosines ``cos_phi`` (N,),
    bin l * P + p for exit cosine node l and azimuth node p, and their weights (N, 4): the products of the hat
    functions of the two."""
    (l, wl), (q, wq) = _hat_cells(cos, np.asarray(grid)), _azimuth_cells(cos_phi, AZIMUTHS)
    return (l[:, :, None] * AZIMUTHS + q[:, None, :]).reshape(-1, 4), (wl[:, :, None] * wq[:, None, :]).reshape(-1, 4)


def exit_bins(wi: np.ndarray) -> np.ndarray:
    """(N, K + K * P) the weights of exit directions ``wi`` (N, 3), seen from a grid direction: in the elevation bins
    (K: the exit cosine's hat functions), then in the elevation and azimuth bins (:func:`exit_cells`); the dense
    form of :func:`exit_bin_cells` (:func:`split_exit_bins` splits the two kinds)."""
    cells, weights = exit_bin_cells(wi)
    out = np.zeros((len(wi), EXIT_BINS))
    np.put_along_axis(out, cells, weights, axis=1)
    return out


def exit_bin_cells(wi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bins of :func:`exit_bins` (of :data:`EXIT_BINS`) that exit directions ``wi`` (N, 3) fall in, (N, 6),
    distinct in each row, and their weights (N, 6): two elevation bins, then four elevation and azimuth bins. The
    reference's ``exit_bins`` in its sparse form (``reference.albedo_parts``' ``bins``): both kinds from the same
    walks, each with its own standard errors (the parts of one walk's weight in neighbouring bins are correlated),
    at the cost of six columns a walk, not K (P + 1)."""
    grid = np.asarray(COSINES)
    cos = np.clip(wi[:, 2], 0.0, 1.0)
    nodes, hats = _hat_cells(cos, grid)
    cells, weights = exit_cells(cos, grid_azimuth(wi))
    return np.concatenate([nodes, len(grid) + cells], axis=1), np.concatenate([hats, weights], axis=1)


def split_exit_bins(binned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The elevation bins (K, K, C) and the elevation and azimuth bins (K, K, P, C) of parts binned by
    :func:`exit_bins` (K, K (P + 1), C), or of their standard errors."""
    k = binned.shape[0]
    return binned[:, :k], binned[:, k:].reshape(k, k, AZIMUTHS, -1)


def _lobe_samples(models, z, sigma: float, w: float, cosines, samples: int, seed: int, top=None, step=None):
    """Importance samples of the decoded lobe seen from each of ``cosines`` (outgoing): cos(theta_i)
    (A, S), the cosine of the relative azimuth (A, S) and f cos(theta_i) / pdf (A, S, 3), incident directions drawn
    from the material's proxy
    and a cosine lobe half and half (one-sample MIS, balance heuristic: exact pdfs). ``step()`` (optional)
    is called before each :data:`STEP_ROWS` rows are decoded; it stops the work by raising."""
    rng = np.random.default_rng(seed)
    wo = np.repeat(grid_directions(cosines), samples, axis=0)
    n = len(wo)
    u = rng.random((n, 3))
    wi_proxy, _ = proxy.sample(wo, sigma, w, u)
    wi_cos = sample_cosine_hemisphere(u[:, 1:])
    wi = np.where((rng.random(n) < 0.5)[:, None], wi_proxy, wi_cos)
    cos_i = np.maximum(wi[:, 2], 0.0)
    pdf = 0.5 * proxy.pdf(wo, wi, sigma, w) + 0.5 * cos_i / np.pi
    # the decoded part as the renderer scales it (a top_transmission decoder's remainder), without the top lobe
    f = np.empty((n, 3))
    per_call = STEP_ROWS if step is not None else max(n, 1)  # without ``step``, one call
    for r0 in range(0, n, per_call):
        if step is not None:
            step()
        rows = slice(r0, r0 + per_call)
        f[rows] = models.eval_brdf(z, wi[rows], wo[rows], top, with_top_lobe=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where((pdf > 0)[:, None], f * (cos_i / pdf)[:, None], 0.0)
    a = len(np.atleast_1d(cosines))
    return cos_i.reshape(a, samples), grid_azimuth(wi).reshape(a, samples), v.reshape(a, samples, 3)


def decoded_albedo(
    models, z, sigma: float, w: float, cosines, calibration=None, samples=DECODED_SAMPLES, seed=0, top=None
):
    """Directional albedo (A, 3) of the decoded lobe at ``cosines`` (outgoing), with ``calibration``'s
    factors when given, plus the exact top lobe's of a remainder decoder when ``top`` (alpha, ior) is given."""
    cos_i, cos_phi, v = _lobe_samples(models, z, sigma, w, cosines, samples, seed, top)
    if calibration is not None:
        a = len(cos_i)
        cos_o = np.repeat(np.asarray(cosines, dtype=np.float64), samples)
        v = v * calibration.factor(cos_i.reshape(-1), cos_o, cos_phi.reshape(-1)).reshape(a, samples, 3)
    out = v.mean(axis=1)
    if top is not None and models.remainder:
        out = out + top_lobe.top_albedo(top, cosines, samples, seed)[:, None]
    return out


@dataclass(frozen=True)
class DecodedMoments:
    """The decoded lobe at each grid angle k (outgoing) integrated over incident directions against the
    grid's hat functions of cos(theta_i): ``pairs`` (K, K, K, 3), [k, l, m] against hat l times hat m,
    so that with a factor table S the decoded energy in bin l is ``sum_m S[m, k] pairs[k, l, m]``;
    ``m`` (K, K, 3), its sum over l (the separable form: albedo ``c_k (m c)_k``); ``bins_stderr``
    (K, K, 3), the standard error of its sum over m (the energy in each bin of cos theta_i). The same resolved in
    the relative azimuth too (P nodes, :data:`AZIMUTHS`): ``azimuth_pairs`` (K, K, P, K, P, 3), [k, l, p, m, q]
    against exit bin (l, p) (:func:`exit_cells`) times table node (m, q), so that with a table S (K, K, P, 3) the
    energy in exit bin (l, p) is ``sum_mq S[m, k, q] azimuth_pairs[k, l, p, m, q]`` (``pairs`` is its sum over p
    and q); ``azimuth_stderr`` (K, K, P, 3), the standard error of each exit bin's energy."""

    pairs: np.ndarray
    bins_stderr: np.ndarray
    azimuth_pairs: np.ndarray | None = None
    azimuth_stderr: np.ndarray | None = None

    @property
    def m(self) -> np.ndarray:
        return self.pairs.sum(axis=1)


def decoded_moments(
    models, z, sigma: float, w: float, samples: int = DECODED_SAMPLES, seed: int = 0, top=None, step=None
) -> DecodedMoments:
    """:class:`DecodedMoments` from ``samples`` importance samples per grid angle (``step``: see
    :func:`_lobe_samples`)."""
    grid = np.asarray(COSINES)
    k, p = len(grid), AZIMUTHS
    cos_i, cos_phi, v = _lobe_samples(models, z, sigma, w, grid, samples, seed, top, step)
    v = v.reshape(-1, 3)
    angle = np.repeat(np.arange(k), samples)
    # each sample in its four exit bins (cosine x azimuth) and, for the table, the same four nodes: sixteen
    # products a sample, summed by bin (sparse: the dense hat functions' products cost 16x more)
    cells, weights = exit_cells(cos_i.reshape(-1), cos_phi.reshape(-1), grid)
    b = k * p
    flat = ((angle[:, None, None] * b + cells[:, :, None]) * b + cells[:, None, :]).reshape(-1)
    both = (weights[:, :, None] * weights[:, None, :]).reshape(len(v), -1)
    azimuth_pairs = _binned(flat, both, v, k * b * b).reshape(k, k, p, k, p, 3) / samples
    second = _binned((angle[:, None] * b + cells).reshape(-1), weights**2, v * v, k * b).reshape(k, k, p, 3)
    var = np.maximum(second / samples - azimuth_pairs.sum(axis=(3, 4)) ** 2, 0.0) / samples
    nodes, hats = _hat_cells(cos_i.reshape(-1), grid)
    second = _binned((angle[:, None] * k + nodes).reshape(-1), hats**2, v * v, k * k).reshape(k, k, 3)
    pairs = azimuth_pairs.sum(axis=(2, 4))
    var_bins = np.maximum(second / samples - pairs.sum(axis=2) ** 2, 0.0) / samples
    return DecodedMoments(pairs, np.sqrt(var_bins), azimuth_pairs, np.sqrt(var))


def _binned(index: np.ndarray, weights: np.ndarray, v: np.ndarray, size: int) -> np.ndarray:
    """(size, 3): per channel, the sum of ``weights`` (N, B) times the samples' values ``v`` (N, 3) by bin
    ``index`` (N * B,)."""
    return np.stack([np.bincount(index, (weights * v[:, c, None]).reshape(-1), size) for c in range(3)], axis=-1)


def solve_factors(m: np.ndarray, target: np.ndarray, iterations: int = ITERATIONS) -> np.ndarray:
    """Per channel, c (K, 3) with c_k (M c)_k = target_k, by the iteration c <- sqrt(c target / (M c)),
    kept in :data:`FACTOR_RANGE`."""
    lo, hi = FACTOR_RANGE
    c = np.ones_like(target)
    tiny = 1e-12
    for _ in range(iterations):
        mc = np.einsum("klc,lc->kc", m, c)
        c = np.clip(np.sqrt(c * np.maximum(target, tiny) / np.maximum(mc, tiny)), lo, hi)
    return c


def shrink_target(target: np.ndarray, decoded: np.ndarray, stderr: np.ndarray, k: float = NOISE_THRESHOLD):
    """``target`` shrunk towards ``decoded`` (same shape) by ``k`` standard errors ``stderr`` (the
    non-negative garrote): where the two differ by less than k sigma the decoded value stands, beyond it
    the gap g keeps g (1 - (k sigma / g)^2), nearly all of it once it is clear of the noise (a soft
    threshold would keep g - k sigma, a bias of k sigma on every clear gap). So a factor moves where the
    reference says it should, not with the walks' noise on a near-black material."""
    if k < 0:
        raise ValueError(f"the noise threshold must be >= 0 standard errors, got {k}")
    gap = np.asarray(target, dtype=np.float64) - decoded
    noise = k * np.asarray(stderr, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = np.where(np.abs(gap) > noise, 1.0 - (noise / gap) ** 2, 0.0)
    return decoded + gap * keep


def table_energy(pairs, table: np.ndarray) -> np.ndarray:
    """(K, K, 3): the decoded energy at each grid angle k in each bin l of cos theta_i with the factor
    ``table`` (K, K, 3): ``sum_m table[m, k] pairs[k, l, m]``. ``pairs`` may be the :class:`DecodedMoments`, then
    ``table`` may be one with azimuth nodes (K, K, P, 3) too (its energy summed over the azimuth bins)."""
    if isinstance(pairs, DecodedMoments):
        if np.ndim(table) == 4:
            return azimuth_energy(pairs.azimuth_pairs, table).sum(axis=2)
        pairs = pairs.pairs
    if np.ndim(table) != 3:
        raise ValueError("a table with azimuth nodes needs the DecodedMoments (their azimuth_pairs), not pairs")
    return np.einsum("mkc,klmc->klc", table, pairs)


def azimuth_energy(azimuth_pairs: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(K, K, P, 3): the decoded energy at each grid angle k in each exit bin (l, p) with the factor ``table``
    (K, K, P, 3) (:class:`DecodedMoments`' ``azimuth_pairs``)."""
    return np.einsum("mkqc,klpmqc->klpc", table, azimuth_pairs)


def solve_azimuth(
    moments: DecodedMoments,
    table: np.ndarray,
    target: np.ndarray,
    target_stderr: np.ndarray,
    stderr_floor=0.0,
    fixed: np.ndarray | None = None,
    k: float = NOISE_THRESHOLD,
    albedo: np.ndarray | None = None,
    albedo_stderr: np.ndarray | None = None,
) -> np.ndarray:
    """The factor table (K, K, P, 3) that brings the decoded energy of each (outgoing angle, exit bin of cosine and
    relative azimuth) to ``target`` (K, K, P, 3), the reference's, starting from the elevation-only ``table`` (K, K,
    3): S[m, k, q] = table[m, k] (1 + D[m, k, q]), D symmetric in m and k, found as :func:`solve_table` finds its
    own (each target shrunk towards the start's energy by ``k`` standard errors, at least ``stderr_floor``; least
    squares weighted by the noise, plus ``sum D^2``): an azimuth bin the reference does not pin keeps the elevation
    table's factor. Where either cosine is the normal's (the grid's first node) the azimuth is undefined: one D for
    all of its nodes, so that the factor is continuous there. ``fixed`` (K, K) bool: pairs of cosines kept at
    ``table`` (the separable factors of a narrow lobe, :func:`_solve`).

    ``albedo`` (K, 3), each angle's directional albedo (the target's sum over its bins), with ``albedo_stderr``: one
    more row per angle, its energy summed over every bin, towards that albedo shrunk the same way. The bins' targets
    are shrunk one by one, so a clear gap in a few bins moves the fit while the opposite gap spread over many bins,
    each within its noise, does not: without these rows the fit drifted off the albedo the elevation table meets
    (coated gold: 3-4% dark at grazing, where :func:`_solve` then kept the elevation table)."""
    kk, p = len(table), moments.azimuth_pairs.shape[2]
    base = np.repeat(table[:, :, None, :], p, axis=2)
    e0 = azimuth_energy(moments.azimuth_pairs, base)
    sigma2 = np.maximum(target_stderr**2 + moments.azimuth_stderr**2, np.square(stderr_floor) + 1e-30)
    goal = shrink_target(target, e0, np.sqrt(sigma2), k)
    rows_albedo = 0 if albedo is None else kk
    if albedo is not None:  # each angle's albedo: the same walks' total, as clear as its own standard error
        a0 = e0.sum(axis=(1, 2))
        floor = np.broadcast_to(np.square(stderr_floor), target.shape).max(axis=(1, 2))
        albedo_sigma2 = np.maximum(np.square(albedo_stderr), floor + 1e-30)
        albedo_goal = shrink_target(albedo, a0, np.sqrt(albedo_sigma2), k)
    # the unknowns: D[m, k, q] for m <= k, one for every q where m is the normal's node, none where fixed
    iu, ju = np.triu_indices(kk)
    count = np.where(iu == 0, 1, p)
    if fixed is not None:
        count = np.where(fixed[iu, ju], 0, count)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    index = np.full((kk, kk, p), -1, dtype=np.int64)
    node = np.arange(p)[None, :]
    index[iu, ju] = np.where(count[:, None] == 0, -1, start[:, None] + np.where(count[:, None] == p, node, 0))
    index[ju, iu] = index[iu, ju]
    unknowns = int(count.sum())
    if unknowns == 0:
        return base.copy()
    # row (k, l, p) of the energy, column index[m, k, q]: d energy[k, l, p] / d D[m, k, q] = base[m, k, q] pairs[...]
    column = np.broadcast_to(index.transpose(1, 0, 2)[:, None, None, :, :], moments.azimuth_pairs.shape[:5])
    row = np.broadcast_to(np.arange(kk * kk * p).reshape(kk, kk, p)[:, :, :, None, None], column.shape)
    used = column >= 0
    out = np.empty_like(base)
    for c in range(3):  # one solve per channel (three of them)
        grad = base[:, :, :, c].transpose(1, 0, 2)[:, None, None, :, :] * moments.azimuth_pairs[..., c]
        a = np.zeros((kk * kk * p + rows_albedo, unknowns))
        np.add.at(a, (row[used], column[used]), grad[used])
        wsqrt = 1.0 / np.sqrt(sigma2[..., c]).reshape(-1)
        r = (goal[..., c] - e0[..., c]).reshape(-1)
        if albedo is not None:  # an angle's albedo row: the sum of its bins' rows
            a[kk * kk * p :] = a[: kk * kk * p].reshape(kk, kk * p, unknowns).sum(axis=1)
            wsqrt = np.concatenate([wsqrt, 1.0 / np.sqrt(albedo_sigma2[:, c])])
            r = np.concatenate([r, albedo_goal[:, c] - a0[:, c]])
        aw = a * wsqrt[:, None]
        d = np.linalg.solve(aw.T @ aw + np.eye(unknowns), aw.T @ (r * wsqrt))
        out[..., c] = base[..., c] * (1.0 + np.where(index >= 0, d[np.maximum(index, 0)], 0.0))
    return np.clip(out, *FACTOR_RANGE)


def solve_table(
    moments: DecodedMoments,
    scale: np.ndarray,
    target: np.ndarray,
    target_stderr: np.ndarray,
    stderr_floor=0.0,
    k: float = NOISE_THRESHOLD,
) -> np.ndarray:
    """The symmetric factor table (K, K, 3) that brings the decoded energy of each (outgoing angle, bin of
    cos theta_i) to ``target`` (K, K, 3), the reference's, where the reference says so: each target is
    first shrunk (:func:`shrink_target`) towards the separable factors' energy by ``k`` standard errors
    (the walks' and the decoded samples', at least ``stderr_floor``: a bin no walk left through has a
    standard error of 0 but is known only to about one walk's weight), then the table is
    S = outer(scale, scale) (1 + D) with D the least-squares solution of the noise-weighted misfit plus
    ``sum D^2`` (a bin the reference does not pin keeps the separable factor). The energy is linear in
    S, so one solve per channel is exact."""
    kk = len(scale)
    base = scale[:, None, :] * scale[None, :, :]
    e0 = table_energy(moments.pairs, base)
    sigma2 = np.maximum(target_stderr**2 + moments.bins_stderr**2, np.square(stderr_floor) + 1e-30)
    goal = shrink_target(target, e0, np.sqrt(sigma2), k)
    iu, ju = np.triu_indices(kk)
    index = np.zeros((kk, kk), dtype=np.int64)
    index[iu, ju] = np.arange(len(iu))
    index[ju, iu] = index[iu, ju]
    table = np.empty_like(base)
    for c in range(3):
        # row (k, l), column D[m, k] (= D[k, m]): d energy[k, l] / d D[m, k] = base[m, k] pairs[k, l, m]
        grad = base[:, :, c].T[:, None, :] * moments.pairs[:, :, :, c]  # [k, l, m]
        a = np.zeros((kk * kk, len(iu)))
        rows = np.arange(kk * kk)
        for m in range(kk):
            np.add.at(a, (rows, np.repeat(index[:, m], kk)), grad[:, :, m].reshape(-1))
        wsqrt = 1.0 / np.sqrt(sigma2[:, :, c]).reshape(-1)
        r = (goal[:, :, c] - e0[:, :, c]).reshape(-1)
        aw = a * wsqrt[:, None]
        d = np.linalg.solve(aw.T @ aw + np.eye(len(iu)), aw.T @ (r * wsqrt))
        table[:, :, c] = base[:, :, c] * (1.0 + d[index])
    return np.clip(table, *FACTOR_RANGE)


MODES = (True, False, "cached")


def check_mode(calibrate) -> bool | str:
    """``calibrate`` if it is one of :data:`MODES` (True: calibrate, False: not, "cached": only reuse
    a calibration already made: this session's, or one kept on disk), else ValueError."""
    if calibrate is True or calibrate is False or (isinstance(calibrate, str) and calibrate == "cached"):
        return calibrate
    raise ValueError(f"calibrate must be True, False or 'cached', got {calibrate!r}")


_CACHE: dict[str, AlbedoCalibration] = {}
_DISK_FOLDER: Path | None = None  # see ``use_disk_cache``
# Calibrations kept on disk at most (the most recently used; 6.6 kB each, 27 MB in all).
MAX_DISK_ENTRIES = 4096
_FIELDS = ("cosines", "scale", "table", "reference", "reference_stderr", "decoded", "calibrated")


def use_disk_cache(folder) -> None:
    """Keep every calibration in ``folder`` too (one small file each, the :data:`MAX_DISK_ENTRIES` most recently
    used), where a later session finds it instead of walking the reference again: the add-on gives its
    extension's user folder, so a scene's first render in a new Blender session, its viewport and its thumbnails
    have their calibrations at once. None: this session's memory only (the default)."""
    global _DISK_FOLDER
    _DISK_FOLDER = None if folder is None else Path(folder)
    if _DISK_FOLDER is not None:
        from ..textures import files

        files.remove_stale_temps(_DISK_FOLDER)  # what a killed session's writes left there


def _disk_path(key: str) -> Path | None:
    return None if _DISK_FOLDER is None else _DISK_FOLDER / f"calibration_{key}.npz"


def _from_disk(key: str) -> AlbedoCalibration | None:
    """The calibration stored under ``key``, or None (none stored, or a file that is damaged or of another
    layout: a miss, made again)."""
    from ..textures import files

    path = _disk_path(key)
    arrays = None if path is None else files.load_arrays(path)
    if arrays is None or any(name not in arrays for name in _FIELDS):
        return None
    k = len(COSINES)
    shapes = {"cosines": (k,), "table": (k, k, AZIMUTHS, 3)}
    if any(arrays[n].shape != shapes.get(n, (k, 3)) for n in _FIELDS) or not np.array_equal(
        arrays["cosines"], np.asarray(COSINES, dtype=np.float64)
    ):
        return None
    if "top" in arrays and arrays["top"].shape != (k, 3):
        return None
    try:
        os.utime(path)  # most recently used: kept when the folder is pruned
    except OSError:
        pass
    return AlbedoCalibration(**{n: arrays[n] for n in _FIELDS}, top=arrays.get("top"))


def _to_disk(key: str, calibration: AlbedoCalibration) -> None:
    """Store ``calibration`` under ``key`` and prune the folder to :data:`MAX_DISK_ENTRIES`; a folder that cannot be
    written only loses the entry (the calibration itself is made and used)."""
    from ..textures import files

    path = _disk_path(key)
    if path is None:
        return
    arrays = {n: np.asarray(getattr(calibration, n), dtype=np.float64) for n in _FIELDS}
    if calibration.top is not None:
        arrays["top"] = np.asarray(calibration.top, dtype=np.float64)
    try:
        files.save_arrays(path, **arrays)
        entries = list(path.parent.glob("calibration_*.npz"))
        if len(entries) > MAX_DISK_ENTRIES:
            entries.sort(key=lambda p: p.stat().st_mtime)
            for old in entries[: len(entries) - MAX_DISK_ENTRIES]:
                old.unlink(missing_ok=True)
    except OSError:
        pass


def settings_key() -> str:
    """What a calibration depends on besides the stack, the model files and the latent: part of every key
    under which calibrated figures are kept (here, and ``quality``'s measured errors on disk)."""
    # DECODED_SAMPLES, ITERATIONS and FACTOR_RANGE change a calibration too but are not in this key: adding them
    # now would mark every texture baked with a calibration out of date (their keys hold this one). Whoever changes
    # one of them adds it here.
    key = f"walks{list(WALKS)}-cosines{list(COSINES)}-target-below-top-shrink{NOISE_THRESHOLD:g}-table"
    # tables made before the azimuth nodes, or before their fit kept each angle's albedo (``solve_azimuth``), are not
    # current (textures: rebake)
    return key + f"-azimuths{AZIMUTHS}-albedo"


# What the key of a calibration of a clamped top coating adds (``_as_rendered``): the calibrations made before that
# rule lacked it, and are not current for such stacks.
TOP_RULE = "-top-as-rendered-albedo"  # the difference of the two first reflections taken by albedo, not bin by bin


def stack_settings_key(stack: Stack) -> str:
    """:func:`settings_key`, and for a stack whose top coating the decoders see clamped (``top_clamped``) the
    rule that calibrates it (:data:`TOP_RULE`); for one whose top lobe takes an ior outside the trained range,
    ``top_lobe.OWN_TOP_IOR`` (calibrations on disk made with the lobe at the trained bound are not found)."""
    arrays = StackArrays.from_stacks([stack])
    key = settings_key() + (TOP_RULE if top_clamped(arrays).any() else "")
    return key + (top_lobe.OWN_TOP_IOR if top_lobe.ior_outside_trained(arrays).any() else "")


def narrow_lobe(sigma) -> bool:
    """Whether a material whose sampling proxy has spread ``sigma`` keeps the separable factors where the grid is
    coarse (:data:`SEPARABLE_SIGMA`)."""
    return float(sigma) < SEPARABLE_SIGMA


def cache_key(stack: Stack, models, z, narrow: bool | None = None) -> str:
    """The key of a calibration of ``stack``'s latent ``z`` on ``models``; ``narrow`` (:func:`narrow_lobe` of the
    material's proxy, found from ``models`` and ``z`` when None) marks one made by the rule for narrow lobes."""
    z = np.ascontiguousarray(np.asarray(z, dtype=np.float32))
    if narrow is None:
        narrow = narrow_lobe(proxy.material_params(models, z, stack)[0])
    parts = (stack.to_json(), models.size, models.digest, hashlib.sha256(z.tobytes()).hexdigest())
    settings = stack_settings_key(stack) + (SEPARABLE_RULE if narrow else "") + MISS_RULE
    return hashlib.sha256(repr((*parts, settings)).encode()).hexdigest()


def cached(stack: Stack, models, z, proxy_params=None) -> AlbedoCalibration | None:
    """The calibration of this stack and latent if it was made in this session or is on disk
    (:func:`use_disk_cache`), else None (no walks). ``proxy_params``: the material's (sigma, w) when the caller
    has them (else the sampling network is asked again)."""
    narrow = None if proxy_params is None else narrow_lobe(proxy_params[0])
    return _lookup(cache_key(stack, models, z, narrow))


def _lookup(key: str) -> AlbedoCalibration | None:
    """The calibration under ``key``: this session's, else the disk's (then kept for the session), else None."""
    hit = _CACHE.get(key)
    if hit is None:
        hit = _from_disk(key)
        if hit is not None:
            _CACHE[key] = hit
    return hit


def calibrate(stack: Stack, models, z, proxy_params, seed: int = 0, step=None) -> AlbedoCalibration:
    """The albedo calibration of latent ``z`` (3, 32) of ``stack`` on ``models`` (see the module
    docstring); ``proxy_params`` (sigma, w) are the material's sampling proxy. Cached per stack,
    model files and latent for the session, and on disk with :func:`use_disk_cache`. A remainder decoder's
    factors scale the decoded part only, towards the reference less the stack's exact top lobe.

    ``step()`` (optional) is called between parts of the work (every :data:`STEP_ROWS` decoded rows, and
    before each event of the reference walks): raising there stops the calibration, which then caches nothing. The
    viewport stops a calibration so when an edit makes its stack stale."""
    if not isinstance(stack, Stack):
        raise ValueError(f"calibrate needs a Stack, got {type(stack).__name__}")
    sigma, w = (float(v) for v in proxy_params)
    key = cache_key(stack, models, z, narrow_lobe(sigma))
    hit = _lookup(key)
    if hit is not None:
        return hit
    coat = top_lobe.top_coat(stack)
    moments = decoded_moments(models, z, sigma, w, seed=seed, top=coat, step=step)
    top = top_lobe.top_albedo(coat, COSINES, DECODED_SAMPLES, seed)
    ref = _as_rendered(reference_parts(stack, seed=seed, step=step), StackArrays.from_stacks([stack]), seed)
    out = _solve(ref, moments, top, bool(getattr(models, "remainder", False)), separable=narrow_lobe(sigma))
    _CACHE[key] = out
    _to_disk(key, out)
    return out


def calibrate_texels(arrays: StackArrays, models, z, proxy_params, tops, seed: int = 0, step=None) -> AlbedoCalibration:
    """One calibration for a sample of a latent texture's texels: their stacks ``arrays`` (R rows), baked
    latents ``z`` (R, 3, 32), proxies (R, 2) and top coatings ``tops`` (R, 2). The factor table brings the
    *mean* of the R decoded lobes to the mean of their references, energy by energy (every target and
    decoded sum below is a mean over the rows, each row with 1/R of the walks and of the decoded samples,
    so it costs about what one material's calibration costs). A texture whose texels share their decoder's
    error (the same coats over a varying base colour, say) is corrected like one material; what differs from
    texel to texel is corrected on average only (``benchmarks/bench_texture_calibration.py``). ``step``: as
    :func:`calibrate`'s."""
    z = np.asarray(z, dtype=np.float32).reshape(-1, 3, 32)
    prox = np.asarray(proxy_params, dtype=np.float64).reshape(-1, 2)
    tops = top_lobe.as_top(tops, len(z))
    if not (len(arrays) == len(z) == len(prox) == len(tops)) or len(z) == 0:
        raise ValueError(
            f"calibrate_texels needs as many stacks, latents, proxies and top coatings (at least one); got "
            f"{len(arrays)}, {len(z)}, {len(prox)}, {len(tops)}"
        )
    r = len(z)
    per = max(1, DECODED_SAMPLES // r)
    each = [
        decoded_moments(models, z[j], *prox[j], samples=per, seed=seed + j, top=tops[j], step=step) for j in range(r)
    ]
    moments = DecodedMoments(
        np.mean([m.pairs for m in each], axis=0),
        np.sqrt(np.sum([m.bins_stderr**2 for m in each], axis=0)) / r,
        np.mean([m.azimuth_pairs for m in each], axis=0),
        np.sqrt(np.sum([m.azimuth_stderr**2 for m in each], axis=0)) / r,
    )  # a loop over the R sampled materials, not over texels
    top = np.mean([top_lobe.top_albedo(t, COSINES, per, seed) for t in tops], axis=0)
    ref = _as_rendered(reference_parts(arrays, seed=seed, step=step), arrays, seed)
    narrow = narrow_lobe(np.median(prox[:, 0]))
    return _solve(ref, moments, top, bool(getattr(models, "remainder", False)), separable=narrow)


def top_clamped(arrays: StackArrays) -> np.ndarray:
    """(N,) bool: the stacks whose top coating the renderer's top lobe takes other than it is (``top_lobe.top_coats``:
    clamped to the trained alpha): a smooth one (alpha below the trained 0.01). The lobe keeps the coating's own
    ior."""
    return np.any(top_lobe.top_coats(arrays) != top_lobe.own_tops(arrays), axis=1)


def _as_rendered(ref, arrays: StackArrays, seed: int):
    """The reference's parts ``ref`` (of the mean of ``arrays``' R stacks) with the remainder's target as the
    renderer needs it. A remainder decoder's material is the exact top lobe *at the clamped top coating* plus the
    calibrated remainder; the reference's ``below_top`` leaves out the first reflection at the stack's own top
    interface. Where the two interfaces differ, ``below_top`` takes the difference of their first reflections'
    albedos, so the material's albedo is the reference's (the two differ in alpha only: the lobe keeps the
    coating's own ior, since a difference taken from the remainder cannot take away light the exact lobe adds, nor
    add light where the remainder is dark). Its split by exit takes that difference in proportion to where the
    clamped lobe sends its light, never below 0: bin by bin, the difference of a mirror reflection (one exit bin)
    and the clamped lobe's (its neighbours too near grazing) asked the remainder for negative light beside the
    mirror bin and more in it, which the table's bounds could not give back: a smooth clear coat over white
    rendered 1.10 at 80 degrees, its calibration's own albedo 1.115 for 1.000."""
    clamped = np.flatnonzero(top_clamped(arrays))
    if len(clamped) == 0:
        return ref
    grid = np.asarray(COSINES)
    k = len(grid)
    used, own = top_lobe.top_coats(arrays), top_lobe.own_tops(arrays)
    samples = max(256, DECODED_SAMPLES // len(arrays))
    d_albedo, d_bins = np.zeros(k), np.zeros((k, k, AZIMUTHS))
    for j in clamped:  # a loop over the stacks sampled (one, or a texture's few), each vectorised over the grid
        a_own, b_own = top_lobe.interface_reflection(own[j], grid, exit_bins, samples, seed + int(j))
        a_used, b_used = top_lobe.interface_reflection(used[j], grid, exit_bins, samples, seed + int(j))
        d = a_own - a_used  # the same samples for both: their noise mostly cancels
        d_albedo += d / len(arrays)
        b_used = split_exit_bins(b_used[:, :, None])[1][..., 0]  # (K, K, P)
        d_bins += d[:, None, None] * b_used / np.maximum(b_used.sum(axis=(1, 2), keepdims=True), 1e-300) / len(arrays)
    return replace(
        ref,
        below_top=np.maximum(ref.below_top + d_albedo[:, None], 0.0),
        below_top_by_exit=np.maximum(ref.below_top_by_exit + d_bins.sum(axis=2)[..., None], 0.0),
        below_top_by_azimuth=np.maximum(ref.below_top_by_azimuth + d_bins[..., None], 0.0),
    )


def diagonal_mismatch(table: np.ndarray, nodes: np.ndarray) -> float:
    """How far a factor table (K, K, 3) is from separable along its diagonal at the grid nodes ``nodes`` (ascending
    indices): the largest |log(S[k, k+1] / sqrt(S[k, k] S[k+1, k+1]))| over neighbouring nodes and channels (0 for a
    separable table). A narrow lobe seen between two nodes takes its factor from those four entries."""
    k = nodes[:-1]
    return float(np.max(np.abs(np.log(table[k, k + 1] / np.sqrt(table[k, k] * table[k + 1, k + 1])))))


def _solve(
    ref, moments: DecodedMoments, top_albedo: np.ndarray, remainder: bool, separable: bool = False
) -> AlbedoCalibration:
    """The calibration from the reference's parts ``ref`` and the decoded ``moments`` (both at the grid's
    angles); ``top_albedo`` (K,), the exact top lobe's albedo, counts only for a remainder decoder.
    ``separable``: the table is the separable factors' where the grid is coarse (:data:`SEPARABLE_SIGMA`); so is
    a solved table's there that is far from separable along its diagonal (:data:`DIAGONAL_MISMATCH`)."""
    top = np.zeros_like(ref.albedo)
    if remainder:  # the decoded part's target: the light that entered the top interface
        top[:] = top_albedo[:, None]
        target, target_se = ref.below_top, ref.below_top_stderr
        bins, bins_se = ref.below_top_by_exit, ref.below_top_by_exit_stderr
    else:
        target, target_se = ref.albedo, ref.albedo_stderr
        bins, bins_se = ref.by_exit, ref.by_exit_stderr
    m = moments.m
    scale = solve_factors(m, np.maximum(shrink_target(target, m.sum(axis=1), target_se), 0.0))
    one_walk = target / np.asarray(WALKS, dtype=np.float64)[:, None]  # (K, 3): one walk's share of the albedo
    table = solve_table(moments, scale, bins, bins_se, stderr_floor=one_walk[:, None, :])
    coarse = np.flatnonzero(np.asarray(COSINES) >= COARSE_COS)
    sep = np.clip(scale[:, None, :] * scale[None, :, :], *FACTOR_RANGE)
    fixed = np.zeros(table.shape[:2], dtype=bool)
    if separable or diagonal_mismatch(table, coarse) > DIAGONAL_MISMATCH:
        table[np.ix_(coarse, coarse)] = sep[np.ix_(coarse, coarse)]
        fixed[np.ix_(coarse, coarse)] = True  # nor does the azimuth change them there
    # A table that misses its own target at some cosine (its entries held at their bounds) against the separable
    # factors, which meet the albedo by construction: the one nearer the target at its worst cosine.
    miss_table = _target_miss(table_energy(moments.pairs, table).sum(axis=1), target, target_se)
    if miss_table > 0.0 and _target_miss(table_energy(moments.pairs, sep).sum(axis=1), target, target_se) < miss_table:
        table, fixed = sep, np.ones_like(fixed)
        miss_table = _target_miss(table_energy(moments.pairs, table).sum(axis=1), target, target_se)
    # The relative azimuth (:func:`solve_azimuth`), kept where it would miss the target by more than the elevation
    # table does.
    bins_az, bins_az_se = (
        (ref.below_top_by_azimuth, ref.below_top_by_azimuth_stderr)
        if remainder
        else (
            ref.by_azimuth,
            ref.by_azimuth_stderr,
        )
    )
    full = solve_azimuth(
        moments, table, bins_az, bins_az_se, one_walk[:, None, None, :], fixed, albedo=target, albedo_stderr=target_se
    )
    energy = azimuth_energy(moments.azimuth_pairs, full).sum(axis=(1, 2))
    if _target_miss(energy, target, target_se) > miss_table:
        full = np.repeat(table[:, :, None, :], AZIMUTHS, axis=2)
        energy = azimuth_energy(moments.azimuth_pairs, full).sum(axis=(1, 2))
    return AlbedoCalibration(
        cosines=np.asarray(COSINES, dtype=np.float64),
        scale=scale,
        table=full,
        reference=ref.albedo,
        reference_stderr=ref.albedo_stderr,
        decoded=top + m.sum(axis=1),
        calibrated=top + energy,
        top=top,
    )


def _target_miss(got: np.ndarray, target: np.ndarray, target_se: np.ndarray) -> float:
    """How far calibrated albedos ``got`` (K, 3) miss ``target`` at the worst cosine and channel, beyond what the
    target's noise allows (:data:`MISS_SIGMA` standard errors, and :data:`MISS_RELATIVE` of it): 0 within that."""
    allowed = np.maximum(MISS_SIGMA * target_se, MISS_RELATIVE * np.abs(target)) + 1e-4
    return float(np.max(np.maximum(np.abs(got - target) - allowed, 0.0) / np.maximum(np.abs(target), 1e-3)))


def clear_cache() -> None:
    """Forget this session's calibrations (those on disk stay: :func:`use_disk_cache`)."""
    _CACHE.clear()

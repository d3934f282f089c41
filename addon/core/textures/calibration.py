"""The albedo calibration of a latent texture: its texels clustered by latent, one factor table per cluster.

A single material is calibrated against the reference once (``neural.calibrate``: a factor table over
incident and outgoing elevations, about a second of reference walks). A latent texture holds a latent
per texel, and the decoder errs differently on different texels: one table for the whole texture corrects
only their average, and a table per texel costs a second per distinct texel.

So the bake (``bake.bake_stack``) clusters the distinct texels by latent (:func:`cluster_latents`:
k-means, weighted by how many texels share a row, at most :data:`MAX_CLUSTERS`), calibrates each
cluster once on a sample of its texels (``calibrate.calibrate_texels``: the table that brings the
cluster's mean lobe to the mean of their references) and stores the centroids and the tables in the
texture's metadata (:meth:`TextureCalibration.to_text`). The renderer gives each hit the table of the
centroid nearest its looked-up latent (:meth:`TextureCalibration.at`): filtered texels between two
clusters take the nearer one's. A texture the tiny decoder reads through its first layer
(``LatentTexture.projected``) is chosen among the centroids put through that layer too. Measured against the
reference texel by texel, the clusters' tables do about as well as each texel's own
(``benchmarks/bench_texture_calibration.py``, docs/texture_calibration.md).
"""

from __future__ import annotations

import base64
import json
import threading
from dataclasses import dataclass

import numpy as np

from .. import kernels
from ..neural import calibrate as cal
from ..stack import LATENT, StackArrays
from ..threads import map_on_threads, thread_count
from .mip import float32_texels

MAX_CLUSTERS = 8  # tables per texture: calibrations cost about a second each
SAMPLES_PER_CLUSTER = 8  # texels of a cluster walked for its table (each with 1/8 of one calibration's walks)
KMEANS_ITERATIONS = 30
# distinct texels the clustering sees at most: a larger texture is sampled by texel count (a 2048 x 2048 bake of
# smooth maps has millions of distinct texels, and its latents in float64 would take gigabytes)
MAX_ROWS = 65536
SEED = 0


def cluster_latents(z: np.ndarray, weights: np.ndarray, k: int = MAX_CLUSTERS, seed: int = SEED):
    """k-means of latents ``z`` (M, D) weighted by ``weights`` (M,): ``(centroids (k', D), labels (M,))``
    with k' = min(k, M); seeded k-means++ start, then Lloyd's iterations (all rows at once per step)."""
    x = np.asarray(z, dtype=np.float64).reshape(len(z), -1)
    wt = np.asarray(weights, dtype=np.float64)
    if len(x) == 0 or wt.shape != (len(x),) or (wt < 0).any() or wt.sum() <= 0:
        raise ValueError(f"cluster_latents needs rows and as many non-negative weights, got {x.shape}, {wt.shape}")
    k = max(1, min(int(k), len(x)))
    rng = np.random.default_rng(seed)
    sq = np.einsum("md,md->m", x, x)
    centres = [x[rng.choice(len(x), p=wt / wt.sum())]]
    d2 = np.maximum(sq - 2.0 * x @ centres[0] + centres[0] @ centres[0], 0.0)
    for _ in range(1, k):  # k-means++: a loop over the k centres, each a pass over all rows
        p = wt * d2
        if p.sum() <= 0:  # fewer distinct latents than k
            break
        c = x[rng.choice(len(x), p=p / p.sum())]
        centres.append(c)
        d2 = np.minimum(d2, np.maximum(sq - 2.0 * x @ c + c @ c, 0.0))
    c = np.array(centres)
    labels = np.zeros(len(x), dtype=np.int64)
    for _ in range(KMEANS_ITERATIONS):
        labels = _nearest(x, sq, c)
        member = np.zeros((len(x), len(c)))
        member[np.arange(len(x)), labels] = wt  # each row's weight in its cluster's column
        mass = member.sum(axis=0)
        sums = member.T @ x
        moved = np.where(mass[:, None] > 0, sums / np.maximum(mass, 1e-300)[:, None], c)
        if np.allclose(moved, c, rtol=0.0, atol=1e-7):
            break
        c = moved
    keep = np.bincount(labels, minlength=len(c)) > 0
    c = c[keep]
    return c, _nearest(x, sq, c)


def _nearest(x: np.ndarray, sq: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest of ``centres`` (k, D) for each row of ``x`` (M, D) with norms ``sq`` (M,)."""
    d2 = sq[:, None] - 2.0 * x @ centres.T + np.einsum("kd,kd->k", centres, centres)[None, :]
    return np.argmin(d2, axis=1)


@dataclass(frozen=True)
class TextureCalibration:
    """Factor tables (T, K, K, P, 3) on ``cosines`` (K,) and P relative azimuth nodes (``calibrate.AZIMUTHS``; a
    texture baked before them holds (T, K, K, 3), not current: :meth:`is_current`) and the latent centroids
    (T, 3 * LATENT) that choose them; ``settings``: ``calibrate.settings_key()`` of the calibrations."""

    cosines: np.ndarray
    centroids: np.ndarray
    tables: np.ndarray
    settings: str

    def at(self, z: np.ndarray, centroids: np.ndarray | None = None) -> cal.RowCalibration:
        """The calibration of rows with latents ``z`` (N, 3, LATENT): each row the table of its nearest centroid
        (once per bounce and material, in float32: ``kernels.nearest_rows``). With ``centroids`` (T, D), rows ``z``
        (N, D) are chosen by those instead: a projected texture's rows, its latents through the decoder's first
        layer, with the centroids projected the same way (``render.neural_material``)."""
        if len(self.centroids) == 1:
            return cal.RowCalibration(self.cosines, self.tables, np.zeros(len(z), np.int64))
        x = np.ascontiguousarray(z, dtype=np.float32).reshape(len(z), -1)
        c = np.ascontiguousarray(self.centroids if centroids is None else centroids, dtype=np.float32)
        return cal.RowCalibration(self.cosines, self.tables, kernels.nearest_rows(x, c))

    def to_text(self) -> str:
        """The calibration as one line of JSON (the arrays as base64 float32), for the texture's metadata."""

        def packed(a):
            return base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode("ascii")

        return json.dumps(
            {
                "settings": self.settings,
                "shape": list(self.tables.shape),
                "cosines": [float(v) for v in self.cosines],
                "centroids": packed(self.centroids),
                "tables": packed(self.tables),
            },
            separators=(",", ":"),
        )

    @classmethod
    def from_text(cls, text: str) -> "TextureCalibration":
        """The calibration :meth:`to_text` wrote; ValueError for anything else."""
        try:
            d = json.loads(text)
            shape = [int(v) for v in d["shape"]]
            if len(shape) not in (4, 5):
                raise ValueError(f"tables of shape {shape}")
            t, k, k2, c = shape[0], shape[1], shape[2], shape[-1]
            cosines = np.asarray(d["cosines"], dtype=np.float64)
            centroids = np.frombuffer(base64.b64decode(d["centroids"]), dtype="<f4").reshape(t, 3 * LATENT)
            tables = np.frombuffer(base64.b64decode(d["tables"]), dtype="<f4").reshape(shape)
            settings = str(d["settings"])
        except (ValueError, KeyError, TypeError) as e:
            raise ValueError(f"not a latent texture's calibration: {e}") from None
        if k != k2 or c != 3 or cosines.shape != (k,) or t < 1:
            raise ValueError(f"not a latent texture's calibration: tables {d['shape']}, {len(cosines)} cosines")
        if not (np.isfinite(tables).all() and np.isfinite(centroids).all()) or (tables < 0).any():
            raise ValueError("not a latent texture's calibration: non-finite or negative values")
        return cls(cosines, centroids.astype(np.float64), tables.astype(np.float64), settings)

    def is_current(self, top_at_bounds: bool = False) -> bool:
        """Whether it was made with this version's calibration settings (else a renderer ignores it). A texture
        some of whose texels' top coatings sit at a bound of the trained ranges (``top_at_trained_bounds``: clamped
        there, as far as its channels tell) needs the rule for clamped tops (``calibrate.TOP_RULE``), which its
        bake records when it applied it; those made before it are not current."""
        if self.settings == cal.settings_key() + cal.TOP_RULE:
            return True
        return self.settings == cal.settings_key() and not top_at_bounds


def top_at_trained_bounds(levels) -> bool:
    """Whether some texel of a latent texture's base level (``levels[0]``, (H, W, 100): its last two channels the top
    coating's alpha and ior, clamped to the trained ranges by the bake) sits at a bound of those ranges: alpha at
    its least, ior at its least or greatest, in the half floats the texture holds (a texel exactly there unclamped
    counts too: the bake records the rule for it, :func:`calibrate_texture`, where it changes nothing)."""
    base = levels[0]
    return tops_at_trained_bounds(base[..., -2], base[..., -1])


def tops_at_trained_bounds(alpha, ior) -> bool:
    """Whether some of these top coatings (a texture's alpha and ior channels, any shape) sit at a bound of the
    trained ranges, as :func:`top_at_trained_bounds` tells it from a texture's base level."""
    from ..stack import TRAINED_RANGES

    alpha, ior = np.asarray(alpha), np.asarray(ior)
    if alpha.size == 0:
        return False
    half = np.float16
    return bool(
        np.min(alpha) <= half(TRAINED_RANGES["roughness"][0])
        or np.min(ior) <= half(TRAINED_RANGES["ior"][0])
        or np.max(ior) >= half(TRAINED_RANGES["ior"][1])
    )


def calibrate_texture(
    arrays: StackArrays,
    texels: np.ndarray,
    counts: np.ndarray,
    models,
    progress=None,
    seed: int = SEED,
    threads: int = 1,
) -> TextureCalibration:
    """The calibration of a texture's distinct texels: their stacks ``arrays`` (M rows), baked channels
    ``texels`` (M, 100: latents, proxy, top coating; ``latent_texture.CHANNEL_NAMES``) and how many texels
    each stands for (``counts``). ``progress(fraction)`` after each cluster, and between the parts of one
    (``calibrate.calibrate``'s ``step``: a bake's cancel raises there). The clusters are calibrated on up to
    ``threads`` threads, each with its own seed, so the tables do not depend on the thread count."""
    texels = np.asarray(texels)
    counts = np.asarray(counts, dtype=np.float64)
    if len(arrays) != len(texels) or counts.shape != (len(texels),) or len(texels) == 0:
        raise ValueError(
            f"calibrate_texture needs as many stacks, texels and counts (at least one); got {len(arrays)}, "
            f"{len(texels)}, {counts.shape}"
        )
    k = 3 * LATENT
    # The rule for clamped tops, recorded where the renderer will ask for it: where a top coating was clamped, or
    # where one sits at a bound as the texture's channels tell (``top_at_trained_bounds``; unclamped there, the rule
    # changes nothing). Recorded only for clamped ones, a texture of red car paint (top alpha 0.01, the trained
    # least) was always rendered uncalibrated, and a rebake did not help.
    rule = cal.top_clamped(arrays).any() or tops_at_trained_bounds(texels[:, k + 2], texels[:, k + 3])
    if len(texels) > MAX_ROWS:  # a systematic sample by texel count; a row drawn m times weighs m
        pick, weight = np.unique(_stratified(counts, MAX_ROWS), return_counts=True)
        arrays, texels, counts = arrays.take(pick), texels[pick], weight.astype(np.float64)
    texels = float32_texels(texels)  # a bake's are half floats: converted once sampled
    z = texels[:, :k]
    centroids, labels = cluster_latents(z, counts, MAX_CLUSTERS, seed)
    n = len(centroids)
    done = [0]  # clusters calibrated so far: what the progress reports, from any thread
    counting = threading.Lock()

    def table_of(j: int) -> np.ndarray:  # one calibration per cluster (at most MAX_CLUSTERS), not per texel
        members = np.flatnonzero(labels == j)
        pick = members[_stratified(counts[members], SAMPLES_PER_CLUSTER)]
        table = cal.calibrate_texels(
            arrays.take(pick),
            models,
            z[pick].reshape(-1, 3, LATENT),
            texels[pick, k : k + 2],
            texels[pick, k + 2 : k + 4],
            seed=seed + j,
            step=None if progress is None else (lambda: progress(done[0] / n)),
        ).table
        with counting:
            done[0] += 1
            fraction = done[0] / n
        if progress is not None:
            progress(fraction)
        return table

    tables = map_on_threads(table_of, range(n), threads, "calibrate")  # a cancel (a step raising) stops the others
    cosines = np.asarray(cal.COSINES, dtype=np.float64)
    settings = cal.settings_key() + (cal.TOP_RULE if rule else "")
    return TextureCalibration(cosines, centroids, np.array(tables), settings)


def _stratified(weights: np.ndarray, n: int) -> np.ndarray:
    """``n`` indices into ``weights`` at evenly spaced points of their cumulative sum (systematic
    sampling: a row holding a share s of the weight is drawn about n s times)."""
    cum = np.cumsum(weights)
    points = (np.arange(n) + 0.5) * cum[-1] / n
    return np.minimum(np.searchsorted(cum, points, side="right"), len(weights) - 1)


def calibrate_baked(
    arrays: StackArrays, texels: np.ndarray, models, progress=None, threads: int = 0
) -> TextureCalibration:
    """:func:`calibrate_texture` of baked texels (N, 100) and their stacks (N rows, repeats allowed: the
    distinct rows are found first, as the bake finds them), its clusters on ``threads`` threads (0: every
    core, as a bake's)."""
    from ..rows import distinct_rows

    first, inverse = distinct_rows(arrays.to_matrix(np.float32))
    counts = np.bincount(inverse, minlength=len(first)).astype(np.float64)
    distinct = np.asarray(texels).reshape(len(arrays), -1)[first]  # half floats, converted where sampled
    return calibrate_texture(arrays.take(first), distinct, counts, models, progress, threads=thread_count(threads))

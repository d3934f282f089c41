"""Refine on demand: fit one material's latent (3, 32) to the reference BRDF (numpy + ONNX Runtime).

    z, report = refine_latent(stack, "small", budget_s=5.0)

The latent starts where the runtime puts it (``encode_stack``: the encoder, then the layering network
over the coatings) and is fitted with Adam to Monte Carlo values of the reference
(``addon.core.reference.eval_brdf_many``) on a fixed, seeded set of direction pairs. The report gives
the error before and after on a SEPARATE, independently seeded validation set of pairs (never fitted);
the refined latent is returned only when it is better there, otherwise the encoded one is.

Direction pairs come in groups, as lobe images do: one incident direction ``wi`` and M outgoing
directions ``wo``, drawn from the cosine distribution (uniform on the projected disk, the measure of
``addon.core.lobe``) and from lobes about the mirror direction, each pair weighted by the ratio of the
two densities: a group is an importance-sampled Monte Carlo lobe image (``refinement_pairs``).
Incident directions have cos(theta_i) uniform in [cos 80 deg, 1] (the lobe metric's elevations and
between) and a share of them grazing, 80 to 89.5 degrees. The reference walks start from ``wi`` and
connect to all M ``wo`` (reciprocity), one set of walks per group.

Loss (``lobe_loss``): per pair, the error of the cosine-weighted lobe value relative to the group's mean
lobe value, or to the value itself in a peak far above that mean (PEAK_RATIO times it; relative where
values are large, as ``l2rel`` in training: a squared error of the lobe image alone let the 1e3-high
spike of a smooth coat decide, and the fit dropped the diffuse body under it; relative from the mean
on, it neglected a clear coat's highlight that the lobe metric weighs, measured on held-out stacks).
The value in that weight is an independent estimate (other walks), not the prediction
(``l2rel``'s choice made a 3x overshoot of a peak cheap: measured on a held-out coated metal) nor the
target itself (whose noise would bias the fit low in the peaks), so for each pair the minimiser is the
MEAN of noisy targets (a squared error; an L1 or log loss would fit their median or the mean of their
log).
The validation error is the same quantity on the validation pairs; against noisy targets it includes
their noise, equally before and after (for a squared error, E|f - t|^2 = |f - E t|^2 + var t), so the
comparison is fair.

With a remainder decoder (``ModelSet.remainder``) the fitted values are the decoded remainder plus the
stack's exact top lobe (``top_lobe``), the sum the renderer evaluates; the lobe has no latent to fit.

Gradients: one closed-form backward pass of the decoder's MLP in numpy (``NumpyDecoder``), from the
weights exported beside each ONNX decoder (``decoder_<size>_weights.npz``, written by
``python -m onnx_export.decoder_weights``, which records the sha256 of the ONNX file it read: weights
of another version of the decoder are refused). A numpy pass over a few thousand pairs of a 96-float
latent is cheaper than an ONNX gradient graph would be to ship and keep in step, and the same weights
give the forward pass, tested against ONNX Runtime (tests/core) and the gradient against torch autograd
(tests/training).

Results are cached (in memory, and in ``cache_dir`` when given) by a key that hashes the stack's JSON,
the sha256 of every model file the result depends on (decoder, its weights, encoder, layering network)
and the settings that change the result (pairs, walks, seed, steps, learning rate). The time budget is
not part of the key: a cached result made with another budget is returned as it is (its report says
the budget it had), but for one its budget cut short (``stopped == "budget"``), which serves only a smaller budget:
asked again with the same budget or a larger one, it is refined again, and the better of the two on the validation
pairs is kept (the time a budget buys varies with the machine's load).

The budget is this material's time: the reference walks and the fit. What a session makes once before its first
refinement (the top lobe's compiled loops, the transmission table of a remainder decoder: 2.5 s) is made before its
clock starts: a first refinement with a budget of a few seconds spent it there and made no step of the fit.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..bsdf.frame import dot
from ..stack import LATENT, Stack
from .encode import encode_stack
from .models import MODEL_DIR, SIZES, _unit_or_up, file_digest, load_models, resolve_size
from .top_lobe import NO_TOP, eval_top, remainder_scale, top_coat

# Lobe values up to about this many times the group's mean count as absolute errors (the lobe metric), above
# it as relative ones: a highlight a few pixels wide keeps its weight, a smooth coat's spike does not
PEAK_RATIO = 30.0
# Part of the cache key: bump when the procedure changes what it returns. 6: the top lobe at the coating's own ior
# (``top_lobe.top_coats``); the key holds ``reference.ESTIMATOR_VERSION`` too, whose eval gives the targets.
REFINE_VERSION = 6
GRAZING_COS = (float(np.cos(np.radians(89.5))), float(np.cos(np.radians(80.0))))


class StaleWeightsError(RuntimeError):
    """The numpy weights were exported from another version of the decoder's ONNX file."""


# ---------------------------------------------------------------------- the decoder in numpy


def direction_features(wi: np.ndarray, wo: np.ndarray, bump_sharpness) -> np.ndarray:
    """(P, 6 + bumps) float64 direction features of unit directions (P, 3): the numpy form of
    ``onnx_export.nets.direction_features(..., "iso_bumps")`` (same terms, same cancellation-free
    1 - cos(theta_h)), tested against the ONNX graph through the decoder's output."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    dio = dot(wi, wo)
    s = wi + wo
    sxy = s[:, 0] ** 2 + s[:, 1] ** 2
    sn = np.sqrt(np.maximum(sxy + s[:, 2] ** 2, 1e-12))
    one_minus = sxy / np.maximum(sn * (sn + s[:, 2]), 1e-12)
    cols = [wi[:, 2], wo[:, 2], dio, s[:, 2] / sn, np.sqrt(np.maximum(0.5 * (1.0 + dio), 0.0)), np.sqrt(sxy) / sn]
    cols += [np.exp(-float(k) * one_minus) for k in bump_sharpness]
    return np.stack(cols, axis=1)


@dataclass
class _Pass:
    """What the backward pass needs from a forward pass."""

    pre: list  # pre-activations of the hidden layers, (3 P, W) each (rows: pair-major, then channel)
    hidden: list  # their ReLU outputs
    y: np.ndarray  # (P, 3) network output before exp
    f: np.ndarray  # (P, 3) f, 0 below the horizon
    above: np.ndarray  # (P,) both directions above the horizon


class NumpyDecoder:
    """The decoder MLP of one size in numpy: f(z (3, 32), wi, wo) for the three channels, and the
    gradient of a scalar loss with respect to z (one backward pass)."""

    def __init__(self, arrays: dict, size: str, dtype=np.float32):
        self.size = size
        self.dtype = np.dtype(dtype)  # float32 as the ONNX graphs; float64 for finite-difference checks
        self.depth = int(arrays["depth"])
        self.width = int(arrays["width"])
        self.w_latent = np.asarray(arrays["w0_latent"], dtype=self.dtype)
        self.w_directions = np.asarray(arrays["w0_directions"], dtype=self.dtype)
        self.weights = [np.asarray(arrays[f"w{i}"], dtype=self.dtype) for i in range(1, self.depth + 1)]
        self.biases = [np.asarray(arrays[f"b{i}"], dtype=self.dtype) for i in range(self.depth + 1)]
        self.bump_sharpness = tuple(float(v) for v in arrays["bump_sharpness"])
        self.max_log_f = float(arrays["max_log_f"])

    @classmethod
    def load(cls, size: str, model_dir: Path | str | None = None, dtype=np.float32) -> "NumpyDecoder":
        """The weights of ``decoder_<size>.onnx``; raises FileNotFoundError when the weights file is
        missing and StaleWeightsError when it was exported from another version of the ONNX file."""
        if size not in SIZES:
            raise ValueError(f"unknown decoder size {size!r}; sizes are {list(SIZES)}")
        d = Path(model_dir) if model_dir is not None else MODEL_DIR
        path = d / f"decoder_{size}_weights.npz"
        if not path.exists():
            raise FileNotFoundError(
                f"{path.name} is missing from the models folder; export it with "
                f"python -m onnx_export.decoder_weights --sizes {size}"
            )
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        onnx_path = d / f"decoder_{size}.onnx"
        if not onnx_path.exists():
            raise FileNotFoundError(f"{onnx_path.name} is missing from the models folder")
        digest = file_digest(onnx_path)
        if str(arrays["onnx_sha256"]) != digest:
            raise StaleWeightsError(
                f"{path.name} was exported from another version of {onnx_path.name} "
                f"(sha256 {str(arrays['onnx_sha256'])[:12]}..., the file is {digest[:12]}...): "
                f"run python -m onnx_export.decoder_weights --sizes {size}"
            )
        return cls(arrays, size, dtype)

    def _features_product(self, wi, wo):
        a, ok_a = _unit_or_up(np.asarray(wi, dtype=np.float64))
        b, ok_b = _unit_or_up(np.asarray(wo, dtype=np.float64))
        feats = direction_features(a, b, self.bump_sharpness).astype(self.dtype)
        return feats @ self.w_directions.T, ok_a & ok_b

    def run(self, z, wi=None, wo=None, directions_product=None) -> _Pass:
        """Forward pass keeping what the backward pass needs. ``directions_product`` (the first
        layer's product with the direction features and the horizon mask) may be passed from
        ``directions(wi, wo)`` to skip recomputing it for fixed pairs."""
        dprod, above = directions_product if directions_product is not None else self._features_product(wi, wo)
        z = np.asarray(z, dtype=self.dtype).reshape(3, LATENT)
        n = dprod.shape[0]
        # rows (pair, channel) as one 2-D matrix: numpy runs a 3-D matmul as many small ones
        pre = [(dprod[:, None, :] + (z @ self.w_latent.T + self.biases[0])[None]).reshape(3 * n, self.width)]
        hidden = [np.maximum(pre[0], 0.0)]
        for w, b in zip(self.weights[:-1], self.biases[1:-1], strict=True):
            pre.append(hidden[-1] @ w.T + b)
            hidden.append(np.maximum(pre[-1], 0.0))
        y = (hidden[-1] @ self.weights[-1][0] + self.biases[-1][0]).reshape(n, 3)
        f = np.exp(np.minimum(y, self.max_log_f))
        f = np.where(above[:, None], f, 0.0).astype(self.dtype)
        return _Pass(pre, hidden, y, f, above)

    def directions(self, wi, wo):
        """The direction part of the first layer for fixed pairs, to pass to ``run``."""
        return self._features_product(wi, wo)

    def forward(self, z, wi, wo) -> np.ndarray:
        """f (P, 3) in 1/sr (float32 unless made with another dtype) for one latent z (3, 32); 0 where a
        direction is below the horizon."""
        return self.run(z, wi, wo).f

    def backward(self, p: _Pass, grad_f: np.ndarray) -> np.ndarray:
        """dL/dz (3, 32) float64 from dL/df (P, 3) of the forward pass ``p``."""
        gy = np.asarray(grad_f, dtype=self.dtype) * p.f * (p.y < self.max_log_f)  # d exp(y) = f; 0 if clamped
        gh = gy.reshape(-1, 1) * self.weights[-1][0]  # (3 P, W)
        for k in range(len(p.pre) - 1, 0, -1):
            gh = (gh * (p.pre[k] > 0.0)) @ self.weights[k - 1]
        g_pre0 = (gh * (p.pre[0] > 0.0)).reshape(-1, 3, self.width).sum(axis=0, dtype=np.float64)
        return g_pre0 @ self.w_latent.astype(np.float64)  # z enters the first layer of every pair alike


# ---------------------------------------------------------------------- pairs, targets, loss


def _cosine_directions(rng, n: int) -> np.ndarray:
    """Cosine-distributed unit directions (uniform on the projected disk)."""
    u = rng.random((n, 2))
    r = np.sqrt(u[:, 0])
    phi = 2.0 * np.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - r * r, 0.0))], axis=1)


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (G, 3) orthogonal to unit ``axis`` (G, 3) and to each other."""
    helper = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t = np.cross(axis, helper)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(axis, t)


def lobe_exponents(stack: Stack) -> tuple[float, ...]:
    """Exponents of the cosine-power lobes about the mirror direction that the pairs are drawn in: one
    for the top interface and one for a rough base (a lobe cos^n has a width of about sqrt(2 / n) rad,
    a GGX reflection of roughness alpha about 2 alpha: n = 1 / (2 alpha^2), in [1, 5000])."""
    alphas = [stack.coatings[-1].roughness] if stack.coatings else []
    if hasattr(stack.base, "roughness"):
        alphas.append(stack.base.roughness)
    return tuple(float(np.clip(0.5 / max(a, 1e-3) ** 2, 1.0, 5000.0)) for a in alphas)


def refinement_pairs(stack: Stack, groups: int, per_group: int, seed: int, grazing_share: float = 0.2):
    """Seeded direction pairs in groups, each a Monte Carlo lobe image: ``wi`` (G, 3) incident
    directions (cos theta_i uniform in [cos 80 deg, 1], a share ``grazing_share`` between 80 and 89.5
    degrees), ``wo`` (G, M, 3) outgoing directions drawn from an equal mixture of the cosine
    distribution and cosine-power lobes about the mirror direction (``lobe_exponents``: the peaks a
    cosine draw of 32 directions would miss), and ``weight`` (G, M) = p_cosine / p_mixture, so a
    weighted mean over a group estimates the lobe image's mean over the projected disk."""
    if groups < 1 or per_group < 1:
        raise ValueError(f"pairs need at least one group and one direction per group, got {groups} x {per_group}")
    if not 0.0 <= grazing_share <= 1.0:
        raise ValueError(f"grazing_share must be in [0, 1], got {grazing_share}")
    rng = np.random.default_rng([int(seed), 0x5EF1])
    n_grazing = int(round(grazing_share * groups))
    ct = np.concatenate(
        [rng.uniform(GRAZING_COS[1], 1.0, groups - n_grazing), rng.uniform(GRAZING_COS[0], GRAZING_COS[1], n_grazing)]
    )
    phi = rng.uniform(0.0, 2.0 * np.pi, groups)
    st = np.sqrt(1.0 - ct * ct)
    wi = np.stack([st * np.cos(phi), st * np.sin(phi), ct], axis=1)
    mirror = wi * [-1.0, -1.0, 1.0]
    exps = lobe_exponents(stack)
    comp = rng.integers(0, 1 + len(exps), (groups, per_group))  # 0: cosine, k: lobe k
    wo = _cosine_directions(rng, groups * per_group).reshape(groups, per_group, 3)
    t, b = _frame(mirror)
    for k, n in enumerate(exps, start=1):
        u = rng.random((groups, per_group, 2))
        c = u[..., 0] ** (1.0 / (n + 1.0))
        s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
        p = 2.0 * np.pi * u[..., 1]
        d = (
            (s * np.cos(p))[..., None] * t[:, None]
            + (s * np.sin(p))[..., None] * b[:, None]
            + c[..., None] * mirror[:, None]
        )
        wo = np.where((comp == k)[..., None], d, wo)
    cos_o = np.maximum(wo[..., 2], 0.0)
    p_cos = cos_o / np.pi
    p_mix = p_cos.copy()
    cm = np.einsum("gmk,gk->gm", wo, mirror)
    for n in exps:
        p_mix += (n + 1.0) / (2.0 * np.pi) * np.maximum(cm, 0.0) ** n
    p_mix /= 1 + len(exps)
    weight = np.where(cos_o > 0.0, p_cos / np.maximum(p_mix, 1e-300), 0.0)
    wo[..., 2] = np.where(cos_o > 0.0, wo[..., 2], 1e-6)  # below the horizon: weight 0, kept as a valid row
    return wi, wo / np.linalg.norm(wo, axis=-1, keepdims=True), weight


@dataclass
class PairSet:
    """Fixed pairs of one material with reference values: rows ``wi``, ``wo`` (P, 3), targets (P, 3)."""

    wi: np.ndarray
    wo: np.ndarray
    target: np.ndarray
    stderr: np.ndarray
    weight: np.ndarray  # (P,) p_cosine / p_mixture of wo
    groups: int
    level: np.ndarray | None = None  # (P, 3) an independent estimate of the targets, for the loss's weights

    @classmethod
    def measure(cls, stack: Stack, groups: int, per_group: int, walks: int, seed: int) -> "PairSet":
        from .. import reference

        wi, wo, weight = refinement_pairs(stack, groups, per_group, seed)
        # walks start from wi and connect to every wo of the group: f(wo[g, j], wi[g]) = f(wi[g], wo[g, j])
        f, se = reference.eval_brdf_many(stack, wo, wi, walks=walks, seed=int(seed))
        # the loss's weights come from other walks (a quarter as many): independent of the targets' noise
        level, _ = reference.eval_brdf_many(
            stack, wo, wi, walks=max(4, walks // 4), seed=np.random.default_rng([int(seed), 0x1E7E1])
        )
        rows_wi = np.repeat(wi, per_group, axis=0)
        return cls(
            rows_wi,
            wo.reshape(-1, 3),
            f.reshape(-1, 3),
            se.reshape(-1, 3),
            weight.reshape(-1),
            groups,
            level.reshape(-1, 3),
        )


def lobe_loss(f: np.ndarray, pairs: PairSet) -> tuple[float, np.ndarray, np.ndarray]:
    """(loss, dloss/df (P, 3), per-group error (G,)) of the cosine-weighted lobe values ``cos_o f``.

    Per pair and channel ``d = cos_o (f - t) / (s + cos_o l / PEAK_RATIO)``: ``s`` the group's mean lobe
    value (weighted by ``pairs.weight``, RGB together) and ``l`` an independent estimate of the target
    (``pairs.level``, other walks; the targets themselves where it is not given). Up to about PEAK_RATIO
    times the lobe's mean, ``d`` is the error relative to that mean (the lobe metric, which a highlight
    a few pixels wide dominates); far above it, the error relative to the peak, so the spike of a smooth
    coat cannot outweigh the rest of the lobe, and an overshoot is not cheaper than an undershoot.
    The group's loss is the weighted mean of ``d^2``, the loss the mean
    over groups. No weight depends on the prediction or on the targets' own noise, so each pair's
    minimiser is the mean of its noisy targets."""
    g = pairs.groups
    m = pairs.wo.shape[0] // g
    cos_o = np.maximum(pairs.wo[:, 2], 0.0)[:, None]
    level = np.maximum(pairs.target if pairs.level is None else pairs.level, 0.0)
    w = pairs.weight[:, None]
    wsum = np.maximum(pairs.weight.reshape(g, m).sum(axis=1), 1e-30)  # (G,)
    scale = (w * cos_o * level).reshape(g, -1).sum(axis=1) / (3.0 * wsum)
    den = np.repeat(np.maximum(scale, 1e-12), m)[:, None] + cos_o * level / PEAK_RATIO
    d = cos_o * (f.astype(np.float64) - pairs.target) / den
    per_group = (w * d**2).reshape(g, -1).sum(axis=1) / (3.0 * wsum)
    grad = 2.0 * w * d * cos_o / den / (3.0 * np.repeat(wsum, m)[:, None] * g)
    return float(per_group.mean()), grad, np.sqrt(per_group)


# ---------------------------------------------------------------------- refinement


@dataclass
class RefineReport:
    size: str
    key: str
    kept: bool  # the refined latent was better on the validation pairs and is the one returned
    validation_error_before: float  # median over validation groups of the relative RMSE of f cos_o
    validation_error_after: float
    validation_loss_before: float  # mean squared relative error over validation groups (the keep criterion)
    validation_loss_after: float
    fit_loss_before: float
    fit_loss_after: float
    steps: int  # Adam updates of the latent made
    stopped: str  # "converged", "steps" or "budget"
    budget_s: float
    reference_s: float
    optimise_s: float
    total_s: float
    settings: dict = field(default_factory=dict)
    cached: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class RefineSettings:
    fit_groups: int = 32
    validation_groups: int = 16
    per_group: int = 32
    walks: int = 32
    steps: int = 300
    lr: float = 0.02
    seed: int = 0
    patience: int = 40  # steps without a 0.1% improvement of the fit loss before stopping

    def __post_init__(self):
        for name in ("fit_groups", "validation_groups", "per_group", "walks", "steps", "patience"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"RefineSettings.{name} must be an integer >= 1, got {v!r}")
        if not (np.isfinite(self.lr) and self.lr > 0.0):
            raise ValueError(f"RefineSettings.lr must be a finite number > 0, got {self.lr!r}")


_MEMORY: dict[str, tuple[np.ndarray, RefineReport]] = {}


def clear_memory() -> None:
    """Forget this session's refinements (those on disk stay)."""
    _MEMORY.clear()


def model_files(stack: Stack, size: str, model_dir: Path | str | None = None) -> list[Path]:
    """The model files a refined latent of ``stack`` depends on."""
    d = Path(model_dir) if model_dir is not None else MODEL_DIR
    files = [d / f"decoder_{size}.onnx", d / f"decoder_{size}_weights.npz", d / f"encoder_{size}.onnx"]
    if stack.coatings:
        files.append(d / f"layering_{size}.onnx")
    return files


def refine_key(stack: Stack, size: str, settings: RefineSettings, model_dir=None) -> str:
    """sha256 of what the refined latent depends on: the stack's JSON, every model file, the settings, the version
    of this procedure and of the reference estimator that gives its targets."""
    from ..reference import ESTIMATOR_VERSION

    h = hashlib.sha256()
    h.update(
        json.dumps(
            {
                "version": REFINE_VERSION,
                "estimator": ESTIMATOR_VERSION,
                "size": size,
                "stack": stack.to_json(),
                "settings": asdict(settings),
            },
            sort_keys=True,
        ).encode()
    )
    for p in model_files(stack, size, model_dir):
        if not p.exists():
            raise FileNotFoundError(f"{p.name} is missing from the models folder (needed to refine a {size} latent)")
        h.update(p.name.encode())
        stat = p.stat()
        h.update(_file_digest(str(p), stat.st_mtime_ns, stat.st_size).encode())
    return h.hexdigest()


@functools.lru_cache(maxsize=64)
def _file_digest(path: str, mtime_ns: int, size: int) -> str:
    """``file_digest`` of a file as it is at that modification time and size: an export asks for a refined
    material's key at every edit, and a paper decoder takes 4 MB to hash."""
    return file_digest(path)


def _adam(
    decoder: NumpyDecoder,
    z0: np.ndarray,
    fit: PairSet,
    s: RefineSettings,
    deadline: float,
    top_f=0.0,
    scale=1.0,
    step_done=None,
):
    """Adam on the latent; a remainder decoder's value is ``scale * f + top_f`` (the top coat's transmission
    (P, 1) and its exact top lobe (P, 1)); ``step_done()`` (optional) after each step, which may raise to stop."""
    dprod = decoder.directions(fit.wi, fit.wo)
    z = z0.astype(np.float64).copy()
    m = np.zeros_like(z)
    v = np.zeros_like(z)
    best_z, best = z.copy(), np.inf
    first = None
    since = 0
    stopped, step = "steps", 0
    for step in range(1, s.steps + 1):
        p = decoder.run(z, directions_product=dprod)
        loss, grad_f, _ = lobe_loss(scale * p.f + top_f, fit)
        first = loss if first is None else first
        if loss < best * (1.0 - 1e-3):
            since = 0
        else:
            since += 1
        if loss < best:
            best, best_z = loss, z.copy()
        if since >= s.patience:
            stopped = "converged"
            break
        if time.perf_counter() > deadline:
            stopped = "budget"
            break
        if step_done is not None:
            step_done()
        g = decoder.backward(p, scale * grad_f)
        m = 0.9 * m + 0.1 * g
        v = 0.999 * v + 0.001 * g * g
        z -= s.lr * (m / (1 - 0.9**step)) / (np.sqrt(v / (1 - 0.999**step)) + 1e-8)
    updates = step if stopped == "steps" else step - 1  # a stop comes after a step's loss, before its update
    return best_z.astype(np.float32), first, best, updates, stopped


def refine_latent(
    stack: Stack,
    size: str = "auto",
    budget_s: float = 5.0,
    settings: RefineSettings | None = None,
    threads: int = 2,
    model_dir=None,
    cache_dir: Path | str | None = None,
    use_cache: bool = True,
    progress=None,
):
    """``(z (3, 32) float32, RefineReport)``: the latent of ``stack`` for decoder ``size`` fitted to the
    reference (see the module docstring). ``budget_s`` bounds the refinement (reference walks and
    optimisation; the walks of the two pair sets are always made; what a session makes once, before it, is not
    counted); the latent returned is the refined
    one only where it is better on the validation pairs, else the encoded one. ``progress(fraction)``
    (optional: the share of the budget spent) between the reference walks and after each optimisation step; it
    may raise to stop the refinement, which then caches nothing."""
    if not isinstance(stack, Stack):
        raise ValueError(f"refine_latent needs a Stack, got {type(stack).__name__}")
    size = resolve_size(size, model_dir)
    if isinstance(budget_s, bool) or not np.isfinite(budget_s) or budget_s <= 0:
        raise ValueError(f"budget_s must be a finite number of seconds > 0, got {budget_s!r}")
    s = settings or RefineSettings()
    key = refine_key(stack, size, s, model_dir)
    cached = _cache_get(key, cache_dir) if use_cache else None
    # a refinement its budget cut short is no answer for the same budget or a larger one: refined again (the same
    # budget answered from the cache "did not improve" again and again, where the first had made no step)
    if cached is not None and not (cached[1].stopped == "budget" and float(budget_s) >= cached[1].budget_s):
        return cached
    started = time.perf_counter()
    decoder = NumpyDecoder.load(size, model_dir)
    models = load_models(size, threads, model_dir)
    # a remainder decoder holds the BRDF less the exact top lobe: the fit is of their sum
    top = top_coat(stack) if models.remainder else NO_TOP
    one = models.top_transmission
    _made_once(top, one)
    t0 = time.perf_counter()  # the budget's clock

    def spent() -> None:
        if progress is not None:
            progress(min(1.0, (time.perf_counter() - t0) / float(budget_s)))

    z0 = np.asarray(encode_stack(stack, models), dtype=np.float32)
    spent()
    fit = PairSet.measure(stack, s.fit_groups, s.per_group, s.walks, seed=2 * s.seed)
    spent()
    val = PairSet.measure(stack, s.validation_groups, s.per_group, s.walks, seed=2 * s.seed + 1)
    spent()
    t1 = time.perf_counter()
    top_fit = eval_top(top, fit.wi, fit.wo)[:, None]
    top_val = eval_top(top, val.wi, val.wo)[:, None]
    sc_fit = remainder_scale(top, fit.wi, fit.wo)[:, None] if one else 1.0
    sc_val = remainder_scale(top, val.wi, val.wo)[:, None] if one else 1.0
    z1, fit0, fit1, steps, stopped = _adam(decoder, z0, fit, s, t0 + float(budget_s), top_fit, sc_fit, spent)
    t2 = time.perf_counter()
    v0, _, e0 = lobe_loss(sc_val * decoder.forward(z0, val.wi, val.wo) + top_val, val)
    v1, _, e1 = lobe_loss(sc_val * decoder.forward(z1, val.wi, val.wo) + top_val, val)
    kept = bool(v1 < v0)
    report = RefineReport(
        size=size,
        key=key,
        kept=kept,
        validation_error_before=float(np.median(e0)),
        validation_error_after=float(np.median(e1)),
        validation_loss_before=v0,
        validation_loss_after=v1,
        fit_loss_before=float(fit0),
        fit_loss_after=float(fit1),
        steps=steps,
        stopped=stopped,
        budget_s=float(budget_s),
        reference_s=t1 - t0,
        optimise_s=t2 - t1,
        total_s=time.perf_counter() - started,
        settings=asdict(s),
    )
    z = z1 if kept else z0
    if cached is not None and _loss_of_returned(cached[1]) < _loss_of_returned(report):
        return cached  # the try its budget cut short before went further (a less busy machine): it stays the answer
    if use_cache:
        _cache_put(key, z, report, cache_dir)
    return z.copy(), report


def _loss_of_returned(report: RefineReport) -> float:
    """The validation loss of the latent a refinement returned: the refined one where it was kept, else the encoded."""
    return report.validation_loss_after if report.kept else report.validation_loss_before


def _made_once(top, transmission: bool) -> None:
    """What a session makes once and every refinement needs, made on one pair before a refinement's budget counts:
    the top lobe's compiled loops (``eval_top``) and, for a decoder of the light through the top coat
    (``transmission``), its transmission table (``remainder_scale``). Measured: 2.5 s in a new session, 0.3 ms after."""
    up = np.array([[0.0, 0.0, 1.0]])
    eval_top(top, up, up)
    if transmission:
        remainder_scale(top, up, up)


def _cache_get(key: str, cache_dir):
    from ..textures import files

    hit = _MEMORY.get(key)
    if hit is None and cache_dir is not None:
        npz = files.load_arrays(Path(cache_dir) / f"refine_{key}.npz")
        if npz is not None and "z" in npz and "report" in npz:
            hit = (npz["z"].astype(np.float32), RefineReport(**json.loads(str(npz["report"]))))
            _MEMORY[key] = hit
    if hit is None:
        return None
    z, report = hit
    return z.copy(), RefineReport(**{**report.to_dict(), "cached": True})


def _cache_put(key: str, z: np.ndarray, report: RefineReport, cache_dir) -> None:
    from ..textures import files

    _MEMORY[key] = (z.copy(), report)
    if cache_dir is not None:  # published atomically: concurrent bakes never read half a file
        files.save_arrays(Path(cache_dir) / f"refine_{key}.npz", z=z, report=np.array(json.dumps(report.to_dict())))

"""The "auto" quality setting: no bigger decoder, no finer texture than the scene needs.

    choice = choose_decoder(stack, tolerance=0.15)        # smallest size shown to meet the tolerance
    choice.size, choice.errors, choice.met                # e.g. "tiny", {"tiny": 0.06}, True
    choice.bounds                                         # e.g. {"tiny": (0.05, 0.07)}: what the noise allows
    res = texture_resolution_for_footprint(fp, (2048, 2048))   # e.g. (256, 256)
    fps = primary_footprints(scene)                       # smallest on-screen footprint per material

**Decoder choice.** For one stack, the *measured error* of a decoder size is the relative RMSE of
its lobe images (``addon.core.lobe``: f cos(theta_o) on the projected hemisphere) at the four
incident elevations of docs/architecture.md, Measurement, all four images together, against the reference
(``addon.core.reference``): exact for single-layer stacks, the amortised estimator
(``eval_brdf_many``, by reciprocity) for layered ones, with the estimator's own noise taken out
(error^2 = max(||pred - ref||^2 - ||stderr||^2, 0) / max(||ref||^2, N ERROR_FLOOR^2), as independent noise adds
its variance; the floor, over the N values of the images, keeps a black or nearly black stack's error finite and
absolute: a reference of 0 makes every relative error infinite). The stack is encoded as the renderer encodes it
(encoder + layering network, values clamped to the trained range), so clamping costs show up in the error; with
``calibrate`` the material carries the albedo calibration a render gives it (``addon.core.neural.calibrate``).

That estimate is unbiased but, under a glossy coat, far from sure: the walks that find the coat's peak are few, so
one set of 256 walks sees much less or much more than the average noise, and a lacquered plastic's tiny decoder
measured 0.011-0.042 over ten seeds where 8192 walks give 0.032. So the walks run in independent batches
(:data:`REFERENCE_BATCHES` a round) and the error comes with bounds, :data:`CONFIDENCE` standard errors of the
estimate either side (a jackknife over the batches, :func:`error_bounds`): a size *meets* the tolerance when its
upper bound does. Where the bounds hold the tolerance (the noise leaves it open), the stack is measured again with
:data:`MORE_ROUNDS` rounds of walks, the first among them, and its later sizes with as many.
Sizes are tried from the fewest parameters up and the first one shown within the tolerance is chosen; when none
is, the choice falls back (``fallback``) to the most accurate size (the lowest upper bound) or to the reference,
and a :class:`QualityWarning` says so. Errors are cached per (stack, size, model files, settings) in memory and,
given ``cache_dir``, in a JSON file there.

**Texture resolution.** A latent texture needs one texel per footprint of the finest ray that
sees it: ``texture_resolution_for_footprint`` turns a footprint in uv units into a resolution
(the next power of two above 1 / footprint texels along the longer side, never above the
source's). ``primary_footprints`` measures, with one camera ray per pixel, the smallest
footprint of every material as the renderer computes it (ray cone width over the square root of
the cosine, times the triangle's uv scale); materials no camera ray hits get ``inf``.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import lobe
from .reference.walk import stopping
from .stack import ClampWarning, Stack, clamp_to_trained

DEFAULT_TOLERANCE = 0.2
LOBE_RES = 16
# The smallest lobe value (f cos) an error is relative to, as if the reference were this everywhere: a Lambertian
# of about 3% albedo (0.01 pi). Below it an error is absolute: a black stack under a clear coat (a reference of 0)
# measured infinite for every size, and Auto said no decoder could encode it.
ERROR_FLOOR = 0.01
REFERENCE_WALKS = 256  # walks a round of the reference lobes (``reference_batches``) from each incident direction
REFERENCE_BATCHES = 16  # independent batches a round's walks run in: their spread is the estimate's uncertainty
CONFIDENCE = 2.0  # standard errors of the estimated squared error between it and its bounds (about 95% each side)
MORE_ROUNDS = 4  # rounds of walks a stack is measured with where one round's bounds hold the tolerance
FALLBACKS = ("best", "reference")


class QualityWarning(UserWarning):
    """No decoder meets the tolerance for a stack (or none can encode it): the choice fell back."""


@dataclass(frozen=True)
class DecoderChoice:
    """The decoder size chosen for one stack.

    ``size`` is a decoder size, or None when the stack should be rendered by the reference
    estimator (no decoder can encode it, or none meets the tolerance with ``fallback="reference"``).
    ``errors`` holds the measured error of every size tried (smallest first; ``inf`` for sizes
    that cannot encode the stack), ``bounds`` their ``(low, high)`` bounds (module docstring; a size without one was
    measured exactly, its bounds its error), ``met`` whether ``size`` is shown within ``tolerance`` (its upper bound
    is); ``left_out`` the sizes a time budget kept from the choice (``assign_decoders``), never measured.
    """

    size: str | None
    tolerance: float
    errors: dict = field(default_factory=dict)
    met: bool = False
    notes: tuple = ()
    left_out: tuple = ()
    bounds: dict = field(default_factory=dict)

    def bound(self, size: str) -> tuple[float, float]:
        """``(low, high)`` of ``size``'s measured error: its error both, when it has no bounds (exact, or unknown)."""
        err = self.errors.get(size, math.nan)
        return self.bounds.get(size, (err, err))


def available_sizes(model_dir=None) -> list[str]:
    """Shipped decoder sizes, fewest parameters first (from the checked model cards, ``neural.read_card``;
    unknown counts last). A size whose decoder or encoder is damaged or does not match its card is
    left out with a :class:`QualityWarning` naming the file."""
    from .neural.models import MODEL_DIR, SIZES, ModelFileError, read_card

    d = Path(model_dir) if model_dir is not None else MODEL_DIR
    found = []
    for s in SIZES:
        if not ((d / f"decoder_{s}.onnx").exists() and (d / f"encoder_{s}.onnx").exists()):
            continue
        try:
            params = read_card("decoder", s, d).get("parameters", math.inf)
            read_card("encoder", s, d)
        except (FileNotFoundError, ModelFileError) as e:
            warnings.warn(f"decoder size {s} is not available: {e}", QualityWarning, stacklevel=2)
            continue
        found.append((params, SIZES.index(s), s))
    return [s for _, _, s in sorted(found)]


def _fingerprint(size: str, model_dir=None) -> str:
    """Identity of what decodes a size's stacks: the sha256 of each of its networks' files as their cards record
    them (the runtime refuses a file that does not match its card), and the decoder card's flags that change how
    its output is used (``remainder``, ``top_transmission``). A retrained model is new; the same files installed
    again (a reinstalled extension: new modification times) are not, and keep their measured errors."""
    from .neural.models import MODEL_DIR

    d = Path(model_dir) if model_dir is not None else MODEL_DIR
    parts = []
    for role in ("decoder", "encoder", "layering"):
        try:
            card = json.loads((d / f"{role}_{size}.json").read_text())
        except (OSError, ValueError):
            continue  # a missing or damaged card: the size cannot be loaded, nothing is measured with it
        if not isinstance(card, dict):
            continue
        files = card.get("files")
        parts.append(f"{role}:{json.dumps(files, sort_keys=True) if isinstance(files, dict) else None}")
        if role == "decoder":
            parts.append(f"remainder={card.get('remainder')}:top_transmission={card.get('top_transmission')}")
    return ";".join(parts)


def _key(*parts) -> str:
    return hashlib.sha256("|".join(str(p) for p in parts).encode()).hexdigest()[:24]


_MEMO: dict[str, object] = {}


def clear_memo() -> None:
    """Forget the reference lobe images measured this session (``reference_lobes``)."""
    _MEMO.clear()


def reference_batches(
    stack: Stack, res: int = LOBE_RES, walks: int = REFERENCE_WALKS, seed: int = 0, rounds: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Reference lobe images at ``lobe.INCIDENT_ANGLES_DEG`` in independent batches: ``(refs, stderrs)``, each
    (B, 4, res, res, 3), the batches' means and their standard errors. Their mean is the reference
    (:func:`reference_lobes`), their spread its uncertainty (:func:`error_bounds`).

    Layered stacks use ``reference.eval_brdf_many`` (every walk serves every pixel, by reciprocity): ``rounds``
    rounds of ``walks`` walks from each incident direction, each round :data:`REFERENCE_BATCHES` batches (fewer for
    fewer than two walks a batch) seeded by (``seed``, round, direction); a round is walked once a session, so
    asking more rounds walks only the new ones. Single-layer stacks are exact: one batch, zero error.
    """
    if not stack.coatings:
        rounds, batches = 1, 1
    else:
        batches = max(1, min(REFERENCE_BATCHES, int(walks) // 2))
    parts = [_reference_round(stack, res, walks, seed, r, batches) for r in range(int(rounds))]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _reference_round(stack: Stack, res: int, walks: int, seed: int, r: int, batches: int):
    """One round of :func:`reference_batches`, kept for the session (``_MEMO``)."""
    from . import reference

    key = _key("ref-batches", stack.to_json(), res, walks, seed, r, batches)
    if key in _MEMO:
        return _MEMO[key]
    wo, mask = lobe.lobe_grid(res)
    grid = wo[mask]
    imgs = np.zeros((batches, len(lobe.INCIDENT_ANGLES_DEG), res * res, 3))
    errs = np.zeros_like(imgs)
    for a, theta in enumerate(lobe.INCIDENT_ANGLES_DEG):  # four calls, each vectorised over the batches and the grid
        wi = lobe.incident_direction(theta)
        f, se = reference.eval_brdf_many(
            stack,
            np.broadcast_to(grid, (batches, *grid.shape)),
            np.broadcast_to(wi, (batches, 3)),
            walks=max(1, int(walks) // batches),
            seed=np.random.default_rng([int(seed), r, a]),
        )
        imgs[:, a, mask] = f * grid[None, :, 2:3]
        errs[:, a, mask] = se * grid[None, :, 2:3]
    out = (imgs.reshape(batches, -1, res, res, 3), errs.reshape(batches, -1, res, res, 3))
    _MEMO[key] = out
    return out


def reference_lobes(stack: Stack, res: int = LOBE_RES, walks: int = REFERENCE_WALKS, seed: int = 0, rounds: int = 1):
    """Reference lobe images (4, res, res, 3) at ``lobe.INCIDENT_ANGLES_DEG`` and their standard error: the mean of
    :func:`reference_batches` (exact for single-layer stacks, zero error)."""
    refs, ses = reference_batches(stack, res, walks, seed, rounds)
    return refs.mean(axis=0), np.sqrt(np.sum(ses * ses, axis=0)) / len(refs)


def decoder_lobes(stack: Stack, size: str, res: int = LOBE_RES, threads: int = 2, calibrate=False) -> np.ndarray:
    """Lobe images (4, res, res, 3) of ``stack`` encoded and decoded by one decoder size, with the
    material's albedo calibration when ``calibrate`` asks for it (True, or "cached": only one a render
    has made), as the renderer shades it.

    Raises FileNotFoundError when a model the stack needs is not shipped (e.g. no layering
    network for this size); ClampWarnings of the encoding are passed on.
    """
    from .neural import encode_stack, load_models, top_coat

    models = load_models(size, threads=threads)
    if calibrate:
        bound = neural_material(stack, size, calibrate).bind(None)
        f = bound.eval
    else:
        z = encode_stack(stack, models)

        top = top_coat(stack)

        def f(wi, wo):
            return models.eval_brdf(z, wi, wo, top)

    return np.stack([lobe.lobe_image(f, t, res) for t in lobe.INCIDENT_ANGLES_DEG])


def noise_corrected_error(pred: np.ndarray, ref: np.ndarray, ref_stderr: np.ndarray | None = None) -> float:
    """Relative RMSE of ``pred`` against a noisy ``ref``, the reference's own noise variance removed; relative to
    at least :data:`ERROR_FLOOR` a value (module docstring), so finite for a black reference."""
    pred = np.asarray(pred, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    den = max(float(np.sum(ref * ref)), ref.size * ERROR_FLOOR**2)
    num = float(np.sum((pred - ref) ** 2))
    if ref_stderr is not None:
        num = max(num - float(np.sum(np.asarray(ref_stderr, dtype=np.float64) ** 2)), 0.0)
    if den == 0.0:  # empty images
        return 0.0 if num == 0.0 else math.inf
    return math.sqrt(num / den)


def error_bounds(pred: np.ndarray, refs: np.ndarray, ref_stderrs: np.ndarray) -> tuple[float, float, float]:
    """``(error, low, high)`` of ``pred`` against a reference measured in B independent batches (``refs`` and
    ``ref_stderrs``, (B, ...) each, as :func:`reference_batches` gives them): the :func:`noise_corrected_error`
    against their mean, and bounds :data:`CONFIDENCE` standard errors either side of its square (the numerator,
    error^2 x the denominator), by a jackknife over the batches (the estimate with each batch left out in turn).

    The jackknife sees the noise as it is: the walks serve every pixel, so a lobe's pixels err together, mostly
    along the decoder's own error, and the ``stderr`` of each pixel says nothing of that. With fewer than two
    batches (an exact reference) the bounds are the error."""
    pred = np.asarray(pred, dtype=np.float64).reshape(-1)
    refs = np.asarray(refs, dtype=np.float64).reshape(len(refs), -1)
    var = np.sum(np.asarray(ref_stderrs, dtype=np.float64).reshape(len(refs), -1) ** 2, axis=1)  # (B,)
    b = len(refs)
    ref = refs.mean(axis=0)
    error = noise_corrected_error(pred, ref, np.sqrt(var.sum()) / b)
    if b < 2 or not math.isfinite(error):
        return error, error, error
    den = max(float(np.sum(ref * ref)), ref.size * ERROR_FLOOR**2)
    d = pred - ref  # the difference from the whole mean, and from each batch's
    d_b = pred[None] - refs
    # ||pred - mean of the others||^2 = ||b d - d_b||^2 / (b - 1)^2, less their noise, for each batch left out
    left_out = (b * b * float(d @ d) - 2 * b * (d_b @ d) + np.sum(d_b * d_b, axis=1)) / (b - 1) ** 2
    left_out = left_out - (var.sum() - var) / (b - 1) ** 2
    spread = math.sqrt((b - 1) / b * float(np.sum((left_out - left_out.mean()) ** 2)))
    num = float(d @ d) - var.sum() / (b * b)  # error^2 x den before its clamp at 0: the noise may exceed it
    low = math.sqrt(max(num - CONFIDENCE * spread, 0.0) / den)
    high = math.sqrt(max(num + CONFIDENCE * spread, 0.0) / den)
    return error, low, high


# Measured errors kept at most (the most recently measured): about 200 bytes each in decoder_errors.json, which is
# written whole at every new entry.
MAX_ERROR_ENTRIES = 20000


def _cache_entry(value) -> float | tuple[float, float, float]:
    """An :class:`ErrorCache` value as it is kept: a number (an error measured exactly: its bounds are itself) or
    ``(error, low, high)`` (:func:`error_bounds`); ValueError or TypeError for anything else (a damaged file)."""
    if isinstance(value, (list, tuple)):
        if len(value) != 3:
            raise ValueError(f"an error entry is a number or (error, low, high), got {value!r}")
        error, low, high = (float(v) for v in value)
        return error if error == low == high else (error, low, high)
    return float(value)


class ErrorCache:
    """Measured errors keyed by (stack, size, model files, settings): in memory, and in
    ``<cache_dir>/decoder_errors.json`` when a folder is given (written after every new entry). A value is a number,
    or ``(error, low, high)`` where the reference's noise leaves the error uncertain (:func:`error_bounds`)."""

    def __init__(self, cache_dir=None):
        self.path = Path(cache_dir) / "decoder_errors.json" if cache_dir is not None else None
        self.data: dict[str, float | tuple] = {}
        self._lock = threading.Lock()  # the viewport and an F12 render may measure at once
        if self.path is not None:
            from .textures import files

            files.remove_stale_temps(self.path.parent)  # what a killed session's writes left there
        self.data = self._read()

    def _read(self) -> dict[str, float | tuple]:
        """The file's entries; none when there is no file or it is damaged (rebuilt, never trusted)."""
        if self.path is None or not self.path.exists():
            return {}
        try:
            return {k: _cache_entry(v) for k, v in json.loads(self.path.read_text()).items()}
        except (OSError, ValueError, AttributeError, TypeError):  # TypeError: a null or a list as a value
            return {}

    def get(self, key: str):
        return self.data.get(key)

    def put(self, key: str, value) -> None:
        from .textures import files

        with self._lock:
            # What other sessions wrote since this one read the file is kept: each wrote its whole dictionary, and
            # the last one to write lost the others' new entries (measured again by every later session).
            on_disk = self._read()
            if on_disk:
                self.data = {**{k: v for k, v in on_disk.items() if k not in self.data}, **self.data}
            self.data.pop(key, None)
            self.data[key] = _cache_entry(value)  # last: the dict keeps insertion order, oldest first
            while len(self.data) > MAX_ERROR_ENTRIES:
                del self.data[next(iter(self.data))]
            if self.path is None:
                return
            text = json.dumps(self.data, indent=0)  # in the order measured: the oldest go first when it is full
            try:  # published atomically: another session never reads half a file
                self.path.parent.mkdir(parents=True, exist_ok=True)
                files.write_bytes(self.path, text.encode())
            except OSError:
                pass  # a folder that cannot be written loses the entry on disk, not the measurement


_DEFAULT_CACHE = ErrorCache()


def use_disk_cache(folder) -> None:
    """Keep the measured errors that ``choose_decoder`` and ``assign_decoders`` make without a cache of their own
    in ``folder`` too (``decoder_errors.json``), where a later session finds them: the add-on gives its extension's
    user folder, so *Auto* chooses at once for the stacks a session before measured. None: memory only."""
    global _DEFAULT_CACHE
    _DEFAULT_CACHE = ErrorCache(folder)


def error_key(
    stack: Stack,
    size: str,
    res: int = LOBE_RES,
    walks: int = REFERENCE_WALKS,
    seed: int = 0,
    calibrated=False,
    rounds: int = 1,
) -> str:
    """The error cache's key of ``stack`` measured on ``size`` (its model files' :func:`_fingerprint`), with these
    measurement settings (``rounds`` of ``walks`` walks, :func:`reference_batches`), against the reference of
    ``reference.ESTIMATOR_VERSION`` (an error measured against an estimator since corrected is measured again),
    calibrated or not (then with the calibration's settings, ``calibrate.settings_key``). Errors measured before
    they had bounds (one batch of walks, seeded otherwise) have keys of their own, never read as exact."""
    from .neural.calibrate import stack_settings_key
    from .reference import ESTIMATOR_VERSION

    key = _key("err-bounded", stack.to_json(), size, _fingerprint(size), res, walks, seed, rounds, ESTIMATOR_VERSION)
    return key + (f"-calibrated-{stack_settings_key(stack)}" if calibrated else "")


def measure(
    stack: Stack,
    size: str,
    res: int = LOBE_RES,
    walks: int = REFERENCE_WALKS,
    seed: int = 0,
    cache: ErrorCache | None = None,
    threads: int = 2,
    calibrate=False,
    only_cached: bool = False,
    rounds: int = 1,
) -> tuple[float, float, float]:
    """``(error, low, high)``: the measured lobe error of ``size`` on ``stack`` and its bounds (see the module
    docstring; :func:`error_bounds`), against ``rounds`` rounds of ``walks`` reference walks; ``inf`` (all three)
    when the size cannot encode the stack (a model it needs is missing). ``calibrate`` measures the
    material as the renderer shades it with that setting (:func:`decoder_lobes`). ``only_cached``: nan where
    it was not measured yet (no measurement: a second or two of reference walks and decodes)."""
    if not isinstance(stack, Stack):
        raise ValueError(f"measured_error needs a Stack, got {type(stack).__name__}")
    from .neural import ModelFileError
    from .neural.calibrate import cached, check_mode

    calibrate = check_mode(calibrate)
    cache = _DEFAULT_CACHE if cache is None else cache
    if calibrate == "cached":  # measured calibrated only once a render has made the calibration
        from .neural import encode_stack, load_models

        try:
            models = load_models(size, threads=threads)
            calibrate = cached(stack, models, encode_stack(stack, models)) is not None
        except (FileNotFoundError, ModelFileError):
            return math.inf, math.inf, math.inf
    key = error_key(stack, size, res, walks, seed, calibrated=bool(calibrate), rounds=rounds)
    hit = cache.get(key)
    if hit is not None:
        return hit if isinstance(hit, tuple) else (hit, hit, hit)
    if only_cached:
        return math.nan, math.nan, math.nan
    try:
        pred = decoder_lobes(stack, size, res, threads, calibrate)
    except (FileNotFoundError, ModelFileError):
        return math.inf, math.inf, math.inf  # not cached: the missing or damaged model may be shipped (repaired) later
    measured = error_bounds(pred, *reference_batches(stack, res, walks, seed, rounds))
    cache.put(key, measured)
    return measured


def measured_error(stack: Stack, size: str, *args, **kwargs) -> float:
    """The measured lobe error of :func:`measure` (its arguments), without its bounds."""
    return measure(stack, size, *args, **kwargs)[0]


def _checked_tolerance(tolerance, fallback: str) -> float:
    """``choose_decoder``'s tolerance as a float, after its and ``fallback``'s checks (ValueError)."""
    try:
        tol = float(tolerance)
    except (TypeError, ValueError):
        raise ValueError(f"tolerance must be a number (relative lobe error, e.g. 0.2), got {tolerance!r}") from None
    if not (tol > 0.0) or math.isnan(tol):
        raise ValueError(f"tolerance must be a positive relative error (e.g. 0.2 for 20%), got {tolerance!r}")
    if fallback not in FALLBACKS:
        raise ValueError(f"fallback must be one of {FALLBACKS}, got {fallback!r}")
    return tol


def choose_decoder(
    stack: Stack,
    tolerance: float = DEFAULT_TOLERANCE,
    sizes=None,
    fallback: str = "best",
    res: int = LOBE_RES,
    walks: int = REFERENCE_WALKS,
    seed: int = 0,
    cache: ErrorCache | None = None,
    cache_dir=None,
    threads: int = 2,
    calibrate=False,
    only_cached: bool = False,
    stop=None,
    left_out=(),
) -> DecoderChoice:
    """The smallest decoder size shown to meet ``tolerance`` on ``stack`` (the upper bound of its measured error is
    at most ``tolerance``: module docstring), measured as the renderer shades the material with ``calibrate``
    (:func:`measure`).

    ``only_cached`` (the viewport, which must not stop for a measurement at every edit): only errors measured
    before are read; where a size was not measured before the choice is made, the default size
    (``neural.resolve_size``) with a note saying so, ``met`` False and the sizes' errors as known (nan: not
    measured). ``stop()`` (optional: F12's Esc) before each size's measurement (a second or two each), and between
    the reference walks' events within it: True raises ``render.Cancelled``. ``left_out``: the sizes a time budget
    kept out of ``sizes`` (``assign_decoders``), named in the choice and its warning when none of ``sizes`` fits.

    ``tolerance`` is a relative lobe RMSE (0.2 = 20%). Sizes default to the shipped ones, fewest
    parameters first; they are measured in that order and the search stops at the first fit. A size whose bounds
    hold the tolerance is measured again with :data:`MORE_ROUNDS` rounds of ``walks`` walks, and so are the sizes
    after it. When none fits, ``fallback="best"`` returns the size with the lowest upper bound and
    ``fallback="reference"`` returns ``size=None`` (render the stack with the reference); both
    warn with a :class:`QualityWarning`, as does a stack no size can encode (``size=None``).
    """
    if not isinstance(stack, Stack):
        raise ValueError(f"choose_decoder needs a Stack, got {type(stack).__name__}")
    tol = _checked_tolerance(tolerance, fallback)
    sizes = available_sizes() if sizes is None else list(sizes)
    if cache is None:
        cache = ErrorCache(cache_dir) if cache_dir is not None else _DEFAULT_CACHE
    errors: dict[str, float] = {}
    bounds: dict[str, tuple[float, float]] = {}
    notes: list[str] = []
    rounds = 1
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for s in sizes:
            _check_stop(stop)
            # heard inside the measurement too, between the reference walks' events: a thick scattering coat's
            # walks took minutes between two sizes' checks
            with stopping(None if stop is None else (lambda: _check_stop(stop))):
                m = measure(stack, s, res, walks, seed, cache, threads, calibrate, only_cached, rounds)
                if m[1] <= tol < m[2] and rounds < MORE_ROUNDS:  # the noise leaves it open: more walks decide
                    rounds = MORE_ROUNDS
                    m = measure(stack, s, res, walks, seed, cache, threads, calibrate, only_cached, rounds)
            errors[s], bounds[s] = m[0], (m[1], m[2])
            if m[2] <= tol or math.isnan(m[0]):
                break
    left_out = tuple(left_out)
    if any(math.isnan(e) for e in errors.values()):
        from .neural.models import resolve_size

        msg = "not measured yet: the default decoder until a render (F12) measures this stack"
        return DecoderChoice(resolve_size(), tol, errors, False, tuple(notes + [msg]), left_out, bounds)
    for w in caught:
        if issubclass(w.category, QualityWarning):
            continue
        text = str(w.message)
        if text not in notes:
            notes.append(text)
    fits = [s for s in errors if bounds[s][1] <= tol]
    if fits:
        return DecoderChoice(fits[0], tol, errors, True, tuple(notes), left_out, bounds)
    finite = {s: bounds[s][1] for s, e in errors.items() if math.isfinite(e)}
    if not finite:
        msg = (
            f"no shipped decoder can encode this stack ({len(stack.coatings)} coating(s); sizes tried: "
            f"{list(errors) or 'none'}): it renders with the reference estimator"
        )
        warnings.warn(msg, QualityWarning, stacklevel=2)
        return DecoderChoice(None, tol, errors, False, tuple(notes + [msg]), left_out, bounds)
    best = min(finite, key=finite.get)
    measured = error_text(errors[best], *bounds[best])
    # With sizes the time budget left out, what was measured is not every decoder: they were never tried.
    within = " within the time budget" if left_out else ""
    budget = f"; {', '.join(left_out)} left out by the time budget (raise Time Budget to try them)" if left_out else ""
    # "shown": a size whose error may be under the tolerance, by the reference's noise, is not said to meet it
    shown = "" if all(bounds[s][0] == bounds[s][1] for s in finite) else ", as far as the reference's noise shows"
    if fallback == "reference":
        msg = (
            f"no decoder{within} meets the tolerance {tol:.2g} for this stack{shown} (best: {best}, {measured})"
            f"{budget}: it renders with the reference estimator"
        )
        warnings.warn(msg, QualityWarning, stacklevel=2)
        return DecoderChoice(None, tol, errors, False, tuple(notes + [msg]), left_out, bounds)
    msg = (
        f"no decoder{within} meets the tolerance {tol:.2g} for this stack{shown}; using the most accurate one, {best} "
        f"({measured}){budget}; raise the tolerance or use the reference for this material"
    )
    warnings.warn(msg, QualityWarning, stacklevel=2)
    return DecoderChoice(best, tol, errors, False, tuple(notes + [msg]), left_out, bounds)


def error_text(error: float, low: float, high: float) -> str:
    """A measured error as the user reads it, with the precision it has: two significant digits, and its upper
    bound where the reference's noise leaves it uncertain ("measured error 0.017, at most 0.034"); an error within
    the noise (0 less the noise's own share) is said as such, not as "0", which reads as exact."""
    bound = f", at most {high:.2g}" if high > error else ""
    if error > 0:
        return f"measured error {error:.2g}{bound}"
    return f"its error within the reference's own noise{bound}"


def _check_stop(stop) -> None:
    """Raise ``render.Cancelled`` when ``stop()`` (None: never) says stop."""
    if stop is not None and stop():
        from .render.integrator import Cancelled

        raise Cancelled("the decoder choice was stopped")


def choice_reason(name: str, choice: DecoderChoice) -> str:
    """One line for the user: the size a material got, and why."""
    if choice.size is None:
        return f"material {name!r}: the reference estimator (no decoder fits: {', '.join(choice.notes) or 'none'})"
    err = choice.errors.get(choice.size, math.nan)
    if math.isnan(err) and any(math.isnan(e) for e in choice.errors.values()):
        return f"material {name!r}: decoder {choice.size}, {choice.notes[-1]}"
    if math.isnan(err):
        return f"material {name!r}: decoder {choice.size} (as set)"
    within = " within the time budget" if choice.left_out else ""
    why = "the smallest shown within" if choice.met else f"the most accurate{within}, none shown within"
    # the error less the reference's own noise (the module docstring), with the bound the noise leaves it
    return (
        f"material {name!r}: decoder {choice.size}, {error_text(err, *choice.bound(choice.size))} ({why} "
        f"{choice.tolerance:.2g})"
    )


# A decoder batch's fixed cost in a render, beside its queries at the card's speed: each chunk of paths sends one
# batch a material and bounce (``frame_decoder_batches``), of a few hundred rows in a small frame, where the card's
# speed is that of 65,536-row batches. Fitted to the network seconds of renders of three coated materials (64 x 64
# and 256 x 256 pixels, 4 samples, 3 bounces, 48 batches each, every size; docs/render.md, Time Budget): 0.15-0.5 ms
# a batch; without it a 64 x 64 frame's decoder time was predicted 2.4 times too short on tiny, 2 times on small.
BATCH_SECONDS = 2e-4


def predicted_decoder_seconds(size: str, evaluations: float, model_dir=None, batches: float = 0.0) -> float:
    """Seconds ``evaluations`` RGB decoder queries, sent in ``batches`` batches, take on this machine class at
    ``size``'s measured speed (``speed_cpu.rgb_evals_per_s`` of its card, written by
    ``benchmarks/bench_decoders.py``), and :data:`BATCH_SECONDS` a batch; ``inf`` when the card holds no speed."""
    from .neural.models import read_card

    rate = float(read_card("decoder", size, model_dir).get("speed_cpu", {}).get("rgb_evals_per_s", 0.0))
    return float(evaluations) / rate + float(batches) * BATCH_SECONDS if rate > 0 else math.inf


def frame_decoder_queries(pixels: int, samples: int, max_bounces: int, hits_per_path: float | None = None) -> float:
    """A frame's decoder queries: one next-event and one sampled direction at each of a path's ``hits_per_path``
    hits on the materials in question (``scene_decoder_hits``); without it, the bound of every path on them at its
    first hit and each of its ``max_bounces`` bounces."""
    hits = int(max_bounces) + 1 if hits_per_path is None else float(hits_per_path)
    return 2.0 * int(pixels) * int(samples) * hits


def frame_decoder_batches(pixels: int, samples: int, max_bounces: int, materials: int) -> float:
    """A frame's decoder batches, at most: the renderer cuts each pass into chunks of at most
    ``RenderSettings.chunk_paths`` pixels, and a chunk sends one batch for each of ``materials`` at its first hit
    and each of its ``max_bounces`` bounces (``render.integrator``)."""
    from .render.integrator import RenderSettings

    chunks = -(-int(pixels) // int(RenderSettings().chunk_paths))
    return float(int(samples) * chunks * (int(max_bounces) + 1) * int(materials))


def auto_spec(material):
    """The ``LayeredSpec`` of a scene material whose decoder :func:`assign_decoders` chooses (a coated stack
    without a latent texture or a latent of its own, which fix the size), else None."""
    from .render.materials import LayeredSpec

    spec = material if isinstance(material, LayeredSpec) else None
    if spec is None and isinstance(material, Stack):
        spec = LayeredSpec(material)
    if spec is None or not spec.stack.coatings or spec.latent_texture is not None or spec.latent is not None:
        return None
    return spec


def scene_decoder_hits(scene, max_bounces: int) -> float:
    """How often a path of ``scene`` meets a layered material whose decoder *Auto* chooses (coated stacks without
    a latent texture or a latent of their own), on average, from a pilot of camera rays and a bounce
    (``render.integrator.material_hits_per_path``): what the time budget predicts from. A cube filling a tenth of
    the image was predicted 7 hits a path (the bound), 10 times its decoder time."""
    from .render.integrator import material_hits_per_path

    chosen = np.array([auto_spec(m) is not None for m in scene.materials], dtype=bool)
    if not chosen.any():
        return 0.0
    return material_hits_per_path(scene, chosen, max_bounces)


def sizes_within_budget(
    evaluations: float, budget_seconds: float | None, sizes=None, batches: float = 0.0
) -> tuple[list[str], list[str]]:
    """The sizes whose predicted decoder time for ``evaluations`` queries in ``batches`` batches
    (:func:`predicted_decoder_seconds`) fits ``budget_seconds`` (all of them when the budget is None), and a note
    per size left out, with its prediction."""
    sizes = available_sizes() if sizes is None else list(sizes)
    if budget_seconds is None:
        return sizes, []
    predicted = {s: predicted_decoder_seconds(s, evaluations, batches=batches) for s in sizes}
    keep = [s for s in sizes if predicted[s] <= budget_seconds]
    if not keep and sizes:
        fastest = min(sizes, key=predicted.get)
        note = (
            f"no decoder's predicted time for this frame fits the time budget of {budget_seconds:,.0f} s "
            f"(fastest: {fastest}, {predicted[fastest]:,.0f} s); using {fastest}"
        )
        return [fastest], [note]
    return keep, [
        f"decoder {s} left out: its predicted decoder time for this frame, {predicted[s]:,.0f} s, is over "
        f"the time budget of {budget_seconds:,.0f} s"
        for s in sizes
        if s not in keep
    ]


# --------------------------------------------------------------------------- textures


def texture_resolution_for_footprint(footprint_uv, source: tuple[int, int], min_size: int = 1) -> tuple[int, int]:
    """(height, width) of a latent texture fine enough for a footprint of ``footprint_uv`` (uv units).

    One texel per footprint along the longer side: ``2^ceil(log2(1 / footprint))`` texels, never
    more than the ``source`` (height, width) has and never fewer than ``min_size``; the shorter
    side keeps the source's aspect ratio (rounded up). A footprint of ``inf`` or larger than the
    whole texture (a material seen from afar, or not at all) gives ``min_size``.
    """
    try:
        h, w = (int(v) for v in source)
    except (TypeError, ValueError):
        raise ValueError(f"source must be (height, width), got {source!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"source resolution must be at least 1 x 1, got {w} x {h}")
    fp = float(footprint_uv)
    if math.isnan(fp) or fp <= 0.0:
        raise ValueError(f"footprint must be a positive size in uv units (or inf), got {footprint_uv!r}")
    big = max(h, w)
    if math.isinf(fp):
        need = 1
    else:
        need = 2 ** max(0, math.ceil(math.log2(max(1.0 / fp, 1.0)) - 1e-9))
    side = int(min(big, max(int(min_size), need)))
    scale = side / big
    return max(1, min(h, math.ceil(h * scale - 1e-9))), max(1, min(w, math.ceil(w * scale - 1e-9)))


def primary_footprints(scene, stride: int = 1) -> np.ndarray:
    """Smallest footprint (uv units) of a camera ray on each material of ``scene`` (``inf`` if unseen).

    One ray through the centre of every ``stride``-th pixel in x and y (one embreex call); the
    footprint is the renderer's: pixel spread x distance / sqrt(cos) x the triangle's uv scale.
    """
    from .render.integrator import camera_hits

    if int(stride) < 1:
        raise ValueError(f"stride must be >= 1, got {stride!r}")
    cam = scene.camera
    out = np.full(len(scene.materials), np.inf)
    ys, xs = np.meshgrid(np.arange(0, cam.height, int(stride)), np.arange(0, cam.width, int(stride)), indexing="ij")
    prim, fp = camera_hits(scene, xs.reshape(-1), ys.reshape(-1))
    hit = prim >= 0
    if not hit.any():
        return out
    mats = scene.mesh.material_index[prim[hit]].astype(np.int64)
    ok = (mats >= 0) & (mats < len(out))
    np.minimum.at(out, mats[ok], fp[hit][ok])
    return out


# --------------------------------------------------------------------------- renderer materials


def neural_material(stack: Stack, size: str, calibrate=False, step=None):
    """The renderer's NeuralMaterial of ``stack`` on decoder ``size`` (``render.neural_material.make``,
    with its ``calibrate`` and ``step``: called between the calibration's parts, raising there stops it); raises
    FileNotFoundError when that size cannot encode the stack (a model it needs is missing)."""
    from .render import neural_material as nm

    made = nm.make(stack, size=size, calibrate=calibrate, step=step)
    if made is None:
        raise FileNotFoundError(
            f"the shipped models of decoder size {size!r} cannot encode this stack "
            f"({len(stack.coatings)} coating(s)): a model it needs is missing"
        )
    return made


def _fixed_size_line(name: str, material, quality: str) -> str | None:
    """The line for a layered material whose own latent fixes its decoder size (a refined latent, a baked latent
    texture: each belongs to its size's latent space): its size and why, with the Decoder setting where that
    differs (a refined tiny latent rendered on tiny under Decoder: Paper, without a word); None for the others."""
    from .render.materials import LayeredSpec
    from .render.neural_material import texture_size

    if not isinstance(material, LayeredSpec) or not material.stack.coatings:
        return None
    if material.latent is not None:
        size, what = str(material.latent[1]), "its refined latent"
    elif material.latent_texture is not None:
        try:
            size, what = texture_size(material.latent_texture)[0], "its baked latent texture"
        except ValueError:
            return None  # the render says what is wrong with the texture
    else:
        return None
    differs = "" if size == quality else f"; Decoder: {'Auto' if quality == 'auto' else quality.capitalize()}"
    return f"material {name!r}: decoder {size} ({what}{differs})"


def assign_decoders(
    scene,
    quality: str = "auto",
    tolerance: float = DEFAULT_TOLERANCE,
    fallback: str = "best",
    threads: int = 2,
    budget_seconds: float | None = None,
    evaluations: float = 0.0,
    calibrate=False,
    stop=None,
    batches: float = 0.0,
    info: list | None = None,
    **measure,
) -> tuple[list, dict, list[str]]:
    """Renderer materials for the layered materials of a core ``Scene``, each on its decoder size.

    ``quality`` is "auto" (per material, :func:`choose_decoder` with ``tolerance`` and ``fallback``)
    or a decoder size (every layered material on it). Returns ``(materials, choices, notes)``:
    a new material list for ``scene.materials`` (entries the decoders do not take stay as they were:
    materials without coatings, which render exactly; latent-textured ones and ones given a latent
    (refined), whose latent fixes the size, a line in ``info`` saying so; and stacks no shipped model can encode,
    which the renderer shades with the reference),
    the choice per material name (its size and the measured errors that decided it), and the
    warnings to show the user.
    ``measure`` passes ``res``, ``walks``, ``cache`` or ``only_cached`` on to :func:`choose_decoder`.
    ``stop()`` (optional: F12's Esc) is heard before each material, in Auto's measurements and between the parts
    of each calibration (a second or two a new stack, on a fixed size as on Auto): True raises ``render.Cancelled``.

    With ``budget_seconds``, "auto" only considers the sizes whose predicted decoder time for
    ``evaluations`` queries (:func:`frame_decoder_queries`) in ``batches`` batches (:func:`frame_decoder_batches`)
    fits the budget (:func:`sizes_within_budget`), so no frame meets the paper-sized decoder unless its cost fits;
    when no size fits, the fastest one is used. What the budget left out is one line in ``info`` (a list of lines
    for the user, when given), with the predictions; a warning only where it changed a material's choice (that
    material's own: no size within the budget met its tolerance). Fixed sizes are never changed.
    ``calibrate`` (True, False or "cached") gives each material its albedo calibration
    (``neural_material.make``), and "auto" measures the errors of the materials so calibrated.
    """

    if quality != "auto":
        from .neural.models import SIZES

        if quality not in SIZES:
            raise ValueError(f"quality must be 'auto' or a decoder size {list(SIZES)}, got {quality!r}")
    names = list(scene.material_names) + [
        f"material {i}" for i in range(len(scene.material_names), len(scene.materials))
    ]
    step = None if stop is None else (lambda: _check_stop(stop))
    out, choices, notes = [], {}, []
    sizes, left_out = None, ()
    budgeted = False  # the budget's sizes worked out, once a material goes through Auto: no notes without one
    for name, m in zip(names, scene.materials, strict=True):
        spec = auto_spec(m)
        if spec is None:
            fixed = _fixed_size_line(name, m, quality)
            if fixed is not None and info is not None:
                info.append(fixed)
            out.append(m)
            continue
        _check_stop(stop)
        if quality == "auto" and budget_seconds is not None and not budgeted:
            budgeted = True
            sizes, _ = sizes_within_budget(evaluations, budget_seconds, batches=batches)
            left_out = tuple(s for s in available_sizes() if s not in sizes)
        if quality == "auto":
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                choice = choose_decoder(
                    spec.stack,
                    tolerance,
                    sizes=sizes,
                    fallback=fallback,
                    threads=threads,
                    calibrate=calibrate,
                    left_out=left_out,
                    stop=stop,
                    **measure,
                )
            size = choice.size
            choices[name] = choice
            notes += [f"material {name!r}: {w.message}" for w in caught if issubclass(w.category, QualityWarning)]
        else:
            size = quality
            choices[name] = DecoderChoice(size, math.nan)
        if size is None:  # no size serves it, or none fits and the fallback is the reference: rendered so
            out.append(replace(spec, reference=True))
            continue
        # What the networks see clamped to their trained ranges, said wherever the stack renders (its encoding is
        # cached, so the encoder's own ClampWarning came once a session, to the console)
        notes += [f"material {name!r}: {n}; rendered clamped" for n in clamp_to_trained(spec.stack)[1]]
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                # a new stack's calibration (a second or two of reference walks) hears the stop between its parts
                out.append(neural_material(spec.stack, size, calibrate, step))
            notes += [f"material {name!r}: {w.message}" for w in caught if not issubclass(w.category, ClampWarning)]
        except FileNotFoundError as e:
            notes.append(f"material {name!r}: decoder {size} cannot encode it ({e}); rendering it with the reference")
            out.append(m)
    if left_out and info is not None:
        # once, for the frame: each material whose choice the budget changed has its own warning
        info.append(_budget_line(sizes, left_out, budget_seconds, evaluations, batches))
    return out, choices, list(dict.fromkeys(notes))


def _budget_line(kept, left_out, budget_seconds: float, evaluations: float, batches: float) -> str:
    """The line that says what the time budget left out of Auto's choice for a frame, with the predictions."""
    predicted = {s: predicted_decoder_seconds(s, evaluations, batches=batches) for s in (*kept, *left_out)}
    line = (
        f"Time Budget {budget_seconds:,.0f} s: Auto left out decoder "
        f"{', '.join(f'{s} ({predicted[s]:,.0f} s)' for s in left_out)}, whose predicted decoder time for this frame "
        "is over it"
    )
    if all(predicted[s] > budget_seconds for s in kept):
        line += f"; none fits it, so the fastest, {', '.join(f'{s} ({predicted[s]:,.0f} s)' for s in kept)}"
    return line

"""Previews of a layer stack: which BRDF to use, lobe and shaded-sphere images, reference comparison.

Everything here is plain numpy on top of a ``brdf(wi, wo) -> (N, 3)`` callable (local frame,
normal +z, no cosine, docs/architecture.md, Conventions), so the same functions serve the Blender operators, scripts
and tests. The BRDF is either the neural runtime (``addon.core.neural``) or the position-free Monte
Carlo reference (``addon.core.reference``); this module holds no BRDF maths of its own.

Long evaluations take a ``progress(fraction)`` callback, called between chunks; it may raise
:class:`Cancelled` to stop the work (the Blender operators do so when the user presses Esc).
Images are ``(H, W, 4)`` float32, linear RGB + alpha, rows top to bottom.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from . import lobe
from .stack import LATENT, Stack, clamp_to_trained

BrdfFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
ProgressFn = Optional[Callable[[float], None]]

DEFAULT_CHUNK = 32768
METHODS = ("AUTO", "NEURAL", "REFERENCE")


class Cancelled(Exception):
    """Raised by a progress callback to stop a long evaluation."""


class NeuralUnavailable(RuntimeError):
    """The neural runtime cannot serve this stack (not importable, models missing, unsupported)."""


def stack_hash(stack: Stack) -> str:
    """Stable hash of a stack's parameters: a stored latent is current when the hashes match."""
    return hashlib.sha1(stack.to_json().encode("utf-8")).hexdigest()


def chunked(brdf: BrdfFn, chunk: int = DEFAULT_CHUNK, progress: ProgressFn = None) -> BrdfFn:
    """Wrap ``brdf`` so that one call evaluates its rows in chunks and reports progress.

    Chunks keep memory bounded (the reference holds per-walk state for every row) and give the
    caller a place to cancel.
    """
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1 rows, got {chunk}")

    def evaluate(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        n = len(wi)
        out = np.zeros((n, 3), dtype=np.float32)
        for start in range(0, n, chunk):
            stop = min(start + chunk, n)
            out[start:stop] = np.asarray(brdf(wi[start:stop], wo[start:stop]), dtype=np.float32)
            if progress is not None:
                progress(stop / n)
        return out

    return evaluate


def _scaled(progress: ProgressFn, lo: float, hi: float) -> ProgressFn:
    if progress is None:
        return None
    return lambda f: progress(lo + (hi - lo) * f)


# --------------------------------------------------------------------------------------------
# Which BRDF: neural runtime or reference


def _neural_module():
    try:
        from . import neural
    except Exception as e:  # an import error anywhere inside the runtime
        raise NeuralUnavailable(f"the neural runtime cannot be imported ({type(e).__name__}: {e})") from None
    for name in ("load_models", "encode_stack", "eval_brdf"):
        if not hasattr(neural, name):
            raise NeuralUnavailable(f"the neural runtime has no {name}() yet")
    return neural


def resolve_size(size: str = "auto") -> str:
    """The decoder size to use: ``size`` itself, or for "auto" the neural runtime's choice
    (``neural.resolve_size``, the one rule for every consumer), once its models load. Raises
    :class:`NeuralUnavailable` naming what is missing."""
    neural = _neural_module()
    from .neural.models import resolve_size as runtime_resolve_size

    try:
        candidate = runtime_resolve_size(size)
    except (ValueError, FileNotFoundError) as e:
        raise NeuralUnavailable(str(e)) from None
    try:
        neural.load_models(size=candidate)
    except Exception as e:
        raise NeuralUnavailable(f"models of size {candidate!r} cannot be loaded ({e})") from None
    return candidate


def encode_latent(stack: Stack, size: str = "auto") -> tuple[np.ndarray, str, list[str]]:
    """The stack's latent code ``(3, 32)`` float32, the decoder size it belongs to, and notes.

    Parameters outside the trained range are clamped first (the notes say which). Raises
    :class:`NeuralUnavailable` naming the reason when the runtime, its models or support for
    this kind of stack are missing.
    """
    neural = _neural_module()
    size = resolve_size(size)
    clamped, notes = clamp_to_trained(stack)
    try:
        z = np.asarray(neural.encode_stack(clamped, size), dtype=np.float32)
    except Exception as e:
        raise NeuralUnavailable(f"the {size} encoder cannot encode this stack ({e})") from None
    if z.shape != (3, LATENT):
        raise NeuralUnavailable(f"the encoder returned a latent of shape {z.shape}, expected (3, {LATENT})")
    if not np.all(np.isfinite(z)):
        raise NeuralUnavailable("the encoder returned a latent with non-finite values")
    return z, size, notes


def neural_brdf_from_latent(z: np.ndarray, size: str = "auto", top=None, calibration=None) -> BrdfFn:
    """``brdf(wi, wo)`` of the neural decoder of ``size`` for a latent ``(3, 32)`` of that size, with
    the stack's top coating ``top`` (alpha, ior: a remainder decoder adds its exact lobe) and an albedo
    calibration of the decoded part, as the renderer evaluates it (``ModelSet.eval_brdf``)."""
    neural = _neural_module()
    z = np.asarray(z, dtype=np.float32).reshape(3, LATENT)
    return lambda wi, wo: neural.eval_brdf(z, wi, wo, size=size, top=top, calibration=calibration)


def neural_proxy(z: np.ndarray, size: str) -> tuple[Optional[tuple[float, float]], list[str]]:
    """(sigma, w) of the shipped sampling network for latent ``z`` of decoder ``size``, and notes;
    (None, [why]) when that network cannot be loaded (previews then sample a cosine lobe)."""
    try:
        z = np.asarray(z, dtype=np.float32).reshape(3, LATENT)
        sigma, w = _neural_module().load_models(size).proxy_params(z)[0]
    except Exception as e:  # a missing or unloadable sampling model: the preview still works, noisier
        return None, [
            f"no sampling proxy for the {size} decoder ({type(e).__name__}: {e}); "
            "the sphere preview samples a cosine lobe (noisier on glossy stacks)"
        ]
    return (float(sigma), float(w)), []


def reference_brdf(stack: Stack, walks: int = 64, seed: int = 0) -> BrdfFn:
    """``brdf(wi, wo)`` of the position-free Monte Carlo reference (estimate only).

    Every row (pixel) gets ``walks`` walks of its own, so the noise of neighbouring pixels is
    independent. (The reference's amortised estimator, one set of walks connected to every
    pixel of a chunk, is 2x faster on a lobe but shares each chunk's noise among its pixels,
    which a lobe image shows as horizontal bands.) Each call uses the next seed so that chunks
    are independent yet the whole preview is deterministic for a given ``seed``.
    """
    if walks < 1:
        raise ValueError(f"walks must be >= 1, got {walks}")
    from . import reference

    calls = [0]

    def evaluate(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        f, _stderr = reference.eval_brdf(stack, wi, wo, walks=walks, seed=seed + calls[0])
        calls[0] += 1
        return f

    return evaluate


def _latent_for(stack, latent, size):
    """(z, size, notes): the stored ``latent`` when it belongs to ``size``, else the stack encoded; the notes say
    what the networks see clamped to their trained ranges either way (a stored latent said nothing of it)."""
    if latent is not None and latent[1] == (resolve_size(size) if size == "auto" else size):
        from .stack import clamp_to_trained

        return latent[0], latent[1], clamp_to_trained(stack)[1]
    return encode_latent(stack, size)


def _cached_calibration(stack: Stack, z: np.ndarray, size: str, calibrated: bool, notes: list[str]):
    """The albedo calibration a render or the viewport made for this stack and latent (this session, or kept on
    disk: ``calibrate.use_disk_cache``), or None (also when ``calibrated`` is off: the scene's *Calibrate Albedo*,
    so that a preview shows what F12 renders); ``notes`` is told when one is applied."""
    from .neural import calibrate, load_models

    found = calibrate.cached(stack, load_models(size), z) if calibrated else None
    if found is not None:  # as thumbnails: the calibration a render or the viewport made, no walks here
        notes.append("albedo calibration of the last render applied")
    return found


def _top_coat(stack: Stack) -> np.ndarray:
    """The stack's top coating (alpha, ior) for a remainder decoder's exact top lobe."""
    from .neural.top_lobe import top_coat

    return top_coat(stack)


def reference_sampler(stack: Stack, seed: int = 0):
    """``sampler(wo) -> (wi, weight)``: one analog walk of the reference per row (weight = f cos / pdf,
    delta reflections included); successive calls continue one seeded random stream."""
    from . import reference

    rng = np.random.default_rng(seed)
    return lambda wo: reference.sample(stack, wo, rng)


@dataclass
class BrdfChoice:
    brdf: BrdfFn
    method: str  # "NEURAL" or "REFERENCE"
    notes: list[str] = field(default_factory=list)
    chunk: int = DEFAULT_CHUNK  # rows per call: small enough for prompt progress and cancel
    sampler: Optional[Callable] = None  # importance sampling of f cos, where the method has one
    sample_chunk: int = 16384  # rows per sampler call (one walk each)
    proxy: Optional[tuple[float, float]] = None  # (sigma, w) of the sampling proxy, where the method has one
    # the renderer's sampler of the material (``sample_direction``, ``pdf``): the proxy, mixed with exact
    # samples of the top lobe for a remainder decoder
    proposal: Optional[object] = None


def reference_chunk(walks: int) -> int:
    """Rows per reference call: about 16 k walks, a fraction of a second on one core."""
    return max(64, 16384 // max(int(walks), 1))


def _reference_choice(stack: Stack, walks: int, seed: int, notes: list[str]) -> "BrdfChoice":
    return BrdfChoice(
        reference_brdf(stack, walks, seed),
        "REFERENCE",
        notes,
        reference_chunk(walks),
        sampler=reference_sampler(stack, seed),
    )


def choose_brdf(
    stack: Stack,
    method: str = "AUTO",
    latent: Optional[tuple[np.ndarray, str]] = None,
    size: str = "auto",
    walks: int = 64,
    seed: int = 0,
    calibrated: bool = True,
) -> BrdfChoice:
    """The BRDF a preview uses.

    ``method``: "NEURAL" (fail with :class:`NeuralUnavailable` if it cannot), "REFERENCE", or
    "AUTO" (neural when available, else the reference, with a note saying why). ``latent``, when
    given, is ``(z, size)``: a current latent of ``stack`` and the decoder size it belongs to; it
    saves an encoder call when that size is the one ``size`` resolves to. ``calibrated``: apply the albedo
    calibration a render made, as F12 does with *Calibrate Albedo* on.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "REFERENCE":
        return _reference_choice(stack, walks, seed, [])
    try:
        z, used, notes = _latent_for(stack, latent, size)
        proxy, proxy_note = neural_proxy(z, used)
        notes = list(notes)
        calibration = _cached_calibration(stack, z, used, calibrated, notes)
        brdf = neural_brdf_from_latent(z, used, _top_coat(stack), calibration)
        proposal = None
        if proxy is not None:
            from .render.neural_material import NeuralMaterial

            models = _neural_module().load_models(used)
            proposal = NeuralMaterial(models, z, proxy, top=_top_coat(stack)).bind(None)
        return BrdfChoice(brdf, "NEURAL", notes + proxy_note, proxy=proxy, proposal=proposal)
    except NeuralUnavailable as e:
        if method == "NEURAL":
            raise
        note = f"neural models not available: {e}; showing the position-free Monte Carlo reference"
        return _reference_choice(stack, walks, seed, [note])


# --------------------------------------------------------------------------------------------
# Images


def sanitize(img: np.ndarray) -> tuple[np.ndarray, int]:
    """Replace non-finite and negative values by 0; return the image and how many were replaced."""
    bad = ~np.isfinite(img) | (img < 0)
    n = int(bad.sum())
    if n:
        img = np.where(bad, 0.0, img)
    return img, n


def _rgba(rgb: np.ndarray, alpha: np.ndarray | float = 1.0) -> np.ndarray:
    h, w = rgb.shape[:2]
    out = np.empty((h, w, 4), dtype=np.float32)
    out[..., :3] = rgb
    out[..., 3] = alpha
    return out


def lobe_preview(
    brdf: BrdfFn, theta_i_deg: float, res: int = 128, progress: ProgressFn = None, chunk: int = DEFAULT_CHUNK
) -> np.ndarray:
    """(res, res, 4) image of f cos(theta_o) over the projected outgoing hemisphere (see ``lobe``).

    Alpha is 1 on the disk and 0 outside it.
    """
    if not (0.0 <= theta_i_deg < 90.0):
        raise ValueError(f"incident angle must be in [0, 90) degrees, got {theta_i_deg}")
    img = lobe.lobe_image(chunked(brdf, chunk, progress), theta_i_deg, res)
    _, mask = lobe.lobe_grid(res)
    return _rgba(img, mask.reshape(res, res).astype(np.float32))


@dataclass(frozen=True)
class Environment:
    """A deterministic preview environment: sky gradient over a flat ground colour plus a sun.

    World frame of the sphere preview: x right, y up, z toward the (orthographic) viewer.
    Radiances are linear RGB; ``sun_irradiance`` is the irradiance on a surface facing the sun.
    """

    zenith: tuple[float, float, float] = (0.25, 0.40, 0.80)
    horizon: tuple[float, float, float] = (0.80, 0.85, 0.90)
    ground: tuple[float, float, float] = (0.18, 0.16, 0.14)
    sun_direction: tuple[float, float, float] = (-0.45, 0.70, 0.55)
    sun_irradiance: tuple[float, float, float] = (3.0, 2.85, 2.6)

    def radiance(self, d: np.ndarray) -> np.ndarray:
        """Sky/ground radiance (N, 3) toward world directions ``d`` (N, 3), sun excluded."""
        up = d[:, 1:2]
        t = np.clip(up, 0.0, 1.0)
        sky = np.asarray(self.horizon) * (1.0 - t) + np.asarray(self.zenith) * t
        return np.where(up > 0.0, sky, np.asarray(self.ground))

    def sun(self) -> np.ndarray:
        d = np.asarray(self.sun_direction, dtype=np.float64)
        return d / np.linalg.norm(d)

    # The sky's own distribution: its radiance depends on the height y = d_y alone, and on the
    # sphere d(omega) = dy dphi, so directions are drawn with y from a piecewise-constant density
    # proportional to the mean radiance of SKY_BINS slabs and phi uniform.
    SKY_BINS = 256

    def _sky_table(self) -> tuple[np.ndarray, np.ndarray]:
        """(per-bin density in y, cumulative probability at the bin edges)."""
        n = self.SKY_BINS
        y = (np.arange(n) + 0.5) / n * 2.0 - 1.0
        d = np.stack([np.sqrt(1.0 - y * y), y, np.zeros(n)], axis=1)
        weight = self.radiance(d).mean(axis=1) + 1e-3  # every direction can be drawn
        dy = 2.0 / n
        density = weight / (weight.sum() * dy)
        cdf = np.concatenate([[0.0], np.cumsum(density * dy)])
        cdf[-1] = 1.0
        return density, cdf

    def sample_sky(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World directions (N, 3) from the sky's own distribution, with their solid-angle density;
        ``u`` (N, 2) uniform in [0, 1)."""
        density, cdf = self._sky_table()
        n = self.SKY_BINS
        b = np.clip(np.searchsorted(cdf, u[:, 0], side="right") - 1, 0, n - 1)
        frac = (u[:, 0] - cdf[b]) / np.maximum(cdf[b + 1] - cdf[b], 1e-300)
        y = np.clip(-1.0 + (b + frac) * (2.0 / n), -1.0, 1.0)
        phi = 2.0 * math.pi * u[:, 1]
        r = np.sqrt(np.maximum(1.0 - y * y, 0.0))
        d = np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)
        return d, density[b] / (2.0 * math.pi)

    def sky_pdf(self, d: np.ndarray) -> np.ndarray:
        """Solid-angle density (N,) of :meth:`sample_sky` at world directions ``d``."""
        density, _ = self._sky_table()
        b = np.clip(((d[:, 1] + 1.0) * 0.5 * self.SKY_BINS).astype(int), 0, self.SKY_BINS - 1)
        return density[b] / (2.0 * math.pi)


DEFAULT_ENVIRONMENT = Environment()


SamplerFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def _mis_sky_samples(brdf, env, proxy, wo, s, t, n, k, rng, chunk, progress, proposal=None):
    """Sky directions (local frame) and their weights f cos / (balance-heuristic density) for the
    rows of ``wo`` (pixel-major, ``k`` rows per pixel): the first ceil(k / 2) rows of each pixel
    from the material's ``proposal`` (its ``sample_direction`` and ``pdf``) or else the proxy, the
    others from the sky's distribution."""
    from .bsdf.frame import to_local, to_world
    from .neural import proxy as proxy_pdf

    sigma, w = proxy if proxy is not None else (1.0, 1.0)
    rows = len(wo)
    k_brdf = (k + 1) // 2
    k_sky = k - k_brdf
    j = np.arange(rows) % k
    from_brdf = j < k_brdf
    # stratified per pixel: sample j of a strategy's m takes the j-th slice of [0, 1) in one
    # dimension and a golden-ratio step in the other, both shifted by the pixel's random offsets
    index = np.where(from_brdf, j, j - k_brdf)
    count = np.where(from_brdf, k_brdf, max(k_sky, 1))
    shift = np.repeat(rng.random((rows // k, 2)), k, axis=0)
    u1 = (index + shift[:, 0]) / count
    u2 = np.mod(index * 0.6180339887498949 + shift[:, 1], 1.0)
    if proposal is not None:
        wi_brdf, _ = proposal.sample_direction(wo, rng.random(rows), np.stack([u1, u2], axis=1))
    else:
        wi_brdf, _ = proxy_pdf.sample(wo, sigma, w, np.stack([rng.random(rows), u1, u2], axis=1))
    d_sky, _ = env.sample_sky(np.stack([u1, u2], axis=1))
    wi = np.where(from_brdf[:, None], wi_brdf, to_local(d_sky, s, t, n))
    p_brdf = proposal.pdf(wi, wo) if proposal is not None else proxy_pdf.pdf(wo, wi, sigma, w)
    p_sky = env.sky_pdf(to_world(wi, s, t, n))
    # balance heuristic over both strategies' sample counts; each pixel's k rows are averaged
    # later, so the weight is scaled by k
    denominator = (k_brdf * p_brdf + k_sky * p_sky) / k
    above = wi[:, 2] > 0.0
    f = chunked(brdf, chunk, progress)(wi.astype(np.float32), wo.astype(np.float32)).astype(np.float64)
    weight = np.where(
        above[:, None], f * np.clip(wi[:, 2:3], 0.0, None) / np.maximum(denominator, 1e-300)[:, None], 0.0
    )
    return wi, weight


def choice_sphere(choice: BrdfChoice, res: int = 128, **kwargs) -> np.ndarray:
    """:func:`sphere_preview` of a :class:`BrdfChoice`, with everything the choice carries for it (its row
    chunk, sampler, proxy and proposal); ``kwargs``: the other arguments of ``sphere_preview``."""
    return sphere_preview(
        choice.brdf,
        res,
        chunk=choice.chunk,
        sampler=choice.sampler,
        sample_chunk=choice.sample_chunk,
        proxy=choice.proxy,
        proposal=choice.proposal,
        **kwargs,
    )


SPHERE_BLOCK_ROWS = 1 << 18  # directions of the sphere preview's sky term held at once (about 90 MB)


def sphere_preview(
    brdf: BrdfFn,
    res: int = 128,
    env: Environment = DEFAULT_ENVIRONMENT,
    env_samples: int = 16,
    progress: ProgressFn = None,
    chunk: int = DEFAULT_CHUNK,
    sampler: Optional[SamplerFn] = None,
    seed: int = 0,
    sample_chunk: int = 16384,
    proxy: Optional[tuple[float, float]] = None,
    proposal: Optional[object] = None,
) -> np.ndarray:
    """(res, res, 4) image of a unit sphere seen orthographically, shaded with ``brdf``.

    Radiance per pixel = f(sun, wo) E_sun cos(sun) + the sky/ground term, estimated with
    ``env_samples`` directions per pixel:

    - with ``sampler(wo) -> (wi, weight)`` (weight = f cos / pdf, e.g. the reference's analog
      walks, which include the mirror reflection of smooth coats): mean of weight L(wi);
    - otherwise: multiple importance sampling (balance heuristic) of two strategies, half of
      the directions each: the BRDF's sampling proxy ``proxy = (sigma, w)`` (the shipped
      sampling network's parameters of the material; a cosine lobe when None) and the sky's own
      distribution (:meth:`Environment.sample_sky`). The proxy puts directions into a glossy
      lobe that a cosine pattern would miss with all but a few pixels' samples (the fireflies
      of a neural car-paint sphere at 8 samples), the sky strategy covers what the proxy does not.
      ``proposal`` (``BrdfChoice.proposal``, the renderer's sampler of the material: for a remainder
      decoder the proxy mixed with exact samples of the top lobe) takes the proxy's place when given.

    Deterministic for a given ``seed``. Alpha is 1 on the sphere, 0 elsewhere (RGB 0 there).
    """
    from .bsdf.frame import coordinate_system, to_local, to_world

    if res < 2:
        raise ValueError(f"sphere resolution must be >= 2, got {res}")
    if env_samples < 1:
        raise ValueError(f"need at least 1 environment sample per pixel, got {env_samples}")
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)  # rows top to bottom
    r2 = (x * x + y * y).reshape(-1)
    mask = r2 < 1.0
    n = np.stack([x.reshape(-1)[mask], y.reshape(-1)[mask], np.sqrt(1.0 - r2[mask])], axis=-1)
    m, k = len(n), env_samples
    s, t = coordinate_system(n)
    rng = np.random.default_rng(seed)

    wo = to_local(np.broadcast_to(np.array([0.0, 0.0, 1.0]), n.shape), s, t, n)
    wi_sun = to_local(np.broadcast_to(env.sun(), n.shape), s, t, n)
    sun_share = 1.0 / (1.0 + k)  # of the progress bar

    # directions below the shading horizon give f = 0: the sun may be behind a pixel
    f_sun = chunked(brdf, chunk, _scaled(progress, 0.0, sun_share))(wi_sun.astype(np.float32), wo.astype(np.float32))
    radiance = f_sun.astype(np.float64) * np.clip(wi_sun[:, 2:3], 0.0, None) * np.asarray(env.sun_irradiance)

    # The sky term a block of pixels at a time (at most SPHERE_BLOCK_ROWS directions): all at once, a 512-pixel
    # sphere of 64 samples held 4.6 GB and heard no Esc for 12 s, and the largest sizes the panel offers would not fit.
    rep = lambda a: np.repeat(a, k, axis=0)  # noqa: E731  pixel-major: rows p*k ... p*k + k - 1 belong to pixel p
    block = max(1, SPHERE_BLOCK_ROWS // k)
    blocks = range(0, m, block)
    for b, first in enumerate(blocks):  # a loop over blocks of pixels, each vectorised over its rows
        px = slice(first, min(first + block, m))
        env_progress = _scaled(progress, sun_share + (1.0 - sun_share) * b / len(blocks),
                               sun_share + (1.0 - sun_share) * (b + 1) / len(blocks))  # fmt: skip
        wo_env = rep(wo[px])
        if sampler is not None:
            wi_env = np.zeros_like(wo_env)
            weight = np.zeros_like(wo_env)
            rows = len(wo_env)
            for start in range(0, rows, sample_chunk):
                stop = min(start + sample_chunk, rows)
                wi_env[start:stop], weight[start:stop] = sampler(wo_env[start:stop])
                if env_progress is not None:
                    env_progress(stop / rows)
        else:
            wi_env, weight = _mis_sky_samples(
                brdf, env, proxy, wo_env, rep(s[px]), rep(t[px]), rep(n[px]), k, rng, chunk, env_progress, proposal
            )
        world = to_world(np.asarray(wi_env, dtype=np.float64), rep(s[px]), rep(t[px]), rep(n[px]))
        sky = (np.asarray(weight, dtype=np.float64) * env.radiance(world)).reshape(-1, k, 3).mean(axis=1)
        radiance[px] += sky

    img = np.zeros((res * res, 3))
    img[mask] = radiance
    return _rgba(img.reshape(res, res, 3), mask.reshape(res, res).astype(np.float32))


@dataclass
class Comparison:
    neural: np.ndarray  # (res, res, 4) lobe image
    reference: np.ndarray  # (res, res, 4)
    error: np.ndarray  # (res, res, 4): |neural - reference| per channel
    seconds_neural: float
    seconds_reference: float
    relative_rmse: float
    size: str = ""
    notes: list[str] = field(default_factory=list)

    def side_by_side(self, gap: int = 2) -> np.ndarray:
        """One (res, 3 res + 2 gap, 4) image: neural | reference | error."""
        h = self.neural.shape[0]
        sep = np.zeros((h, gap, 4), dtype=np.float32)
        return np.concatenate([self.neural, sep, self.reference, sep, self.error], axis=1)

    def summary(self) -> str:
        return (
            f"neural ({self.size}) {self.seconds_neural * 1e3:.1f} ms, "
            f"reference {self.seconds_reference * 1e3:.1f} ms, "
            f"relative RMSE {self.relative_rmse:.3f}"
        )


def compare_with_reference(
    stack: Stack,
    theta_i_deg: float = 30.0,
    res: int = 64,
    walks: int = 64,
    seed: int = 0,
    latent: Optional[tuple[np.ndarray, str]] = None,
    size: str = "auto",
    progress: ProgressFn = None,
    calibrated: bool = True,
) -> Comparison:
    """Neural and reference lobe images of ``stack`` with their timings and the error between them.

    Raises :class:`NeuralUnavailable` when the neural runtime cannot serve the stack. Timings
    are wall-clock seconds of each method's evaluation alone (encoding excluded). The neural lobe is the one
    the other previews show (``calibrated`` as :func:`choose_brdf`'s), so its error is that of what F12 renders.
    """
    from .stack import clamp_to_trained

    z, used, notes = _latent_for(stack, latent, size)
    notes = list(notes)
    calibration = _cached_calibration(stack, z, used, calibrated, notes)
    neural = neural_brdf_from_latent(z, used, _top_coat(stack), calibration)
    # The reference of the stack the networks see: a smooth coat (roughness 0) is clamped to the trained 0.01, whose
    # sharp lobe the neural image shows and the reference's delta reflection never does (relative RMSE 4.95 of a
    # network within 0.03 of its clamped stack).
    seen = clamp_to_trained(stack)[0]
    if seen != stack:
        notes.append("compared with the reference of the stack the networks see (clamped to their trained ranges)")
    truth = reference_brdf(seen, walks, seed)
    one = np.array([[0.0, 0.0, 1.0]])
    neural(one, one)  # once before the clock: the first evaluation loads and tabulates (0.45 s against 3 ms)
    t0 = time.perf_counter()
    img_n = lobe_preview(neural, theta_i_deg, res, _scaled(progress, 0.0, 0.1))
    t1 = time.perf_counter()
    img_r = lobe_preview(truth, theta_i_deg, res, _scaled(progress, 0.1, 1.0), reference_chunk(walks))
    t2 = time.perf_counter()
    img_n, bad_n = sanitize(img_n)
    img_r, bad_r = sanitize(img_r)
    for label, bad in (("neural", bad_n), ("reference", bad_r)):
        if bad:
            notes.append(f"{label}: {bad} negative or non-finite values set to 0")
    err = img_n.copy()
    err[..., :3] = np.abs(img_n[..., :3] - img_r[..., :3])
    rmse = lobe.relative_rmse(img_n[..., :3], img_r[..., :3])
    return Comparison(img_n, img_r, err, t1 - t0, t2 - t1, rmse, used, notes)

"""Neural layered materials in the renderer: decoder evaluation and proxy sampling.

A :class:`NeuralMaterial` holds one latent (3, 32) or a latent texture (per-hit latents and proxy
parameters looked up at the hit's uv with its ray footprint). ``eval`` runs the ONNX decoder
(``addon.core.neural``); sampling uses the paper's proxy (``addon.core.neural.proxy``: a Gaussian
over the projected half vector plus a cosine lobe) whose pdf is exact, so MIS with next-event
estimation stays unbiased whatever the proxy's parameters are.

Such a material only proposes directions (``sample_direction``) and evaluates the decoder for
those directions together with the next-event directions (``shade``, from
``addon.core.render.shading.ShadeByProposal``), so each neural material costs one ONNX batch per
bounce.
"""

from __future__ import annotations

import copy
import warnings

import numpy as np

from .. import kernels
from ..bsdf.base import BSDFSample
from ..neural import proxy, top_lobe
from ..neural.proxy import guess as proxy_guess  # noqa: F401 (this module's name for it, as callers import it)
from ..stack import LATENT, Stack
from .shading import ShadeByProposal, Shading, finish_sample


class _BoundNeural(ShadeByProposal):
    """A neural material at the hits of one bounce. ``top`` (the top coating's (alpha, ior), shared
    (2,) or per hit (N, 2)) is None for a whole-BRDF decoder; for a remainder decoder the sampler mixes
    exact samples of the top lobe (share ``top_lobe.top_share`` of wo) with the proxy's."""

    def __init__(self, models, z, sigma, w, calibration=None, top=None, zc=None):
        self.models, self.z, self.sigma, self.w = models, z, sigma, w
        self.zc = zc  # per-hit latents already through the decoder's first layer (a projected texture), z None
        self.calibration = calibration
        self.top = top if getattr(models, "remainder", False) else None
        if self.top is not None:  # checked once, as the compiled loops take them: (1, ...) shared, else per hit
            self._top_table = top_lobe.top_table(self.top, len(self.top) if np.ndim(self.top) == 2 else 1)
            self._sigma_rows, self._w_rows = proxy.params(sigma, w, np.size(sigma))

    @staticmethod
    def _rows(a, index):
        """Shared parameters (0-d sigma/w, (3, 32) z) as they are; per-hit ones restricted to index."""
        shared = np.ndim(a) == 0 or (np.ndim(a) == 2)
        return a if index is None or shared else a[index]

    def _decoder_inputs(self, index) -> dict:
        """``eval_brdf``'s arguments of the material for the rows ``index`` (all when None): the material's one
        latent, coating and calibration; or a latent texture's per-hit latents, coatings and choice of tables
        with the rows to read them at (``z_rows``: gathered a chunk at a time by the runtime, or read through
        the rows by its loop, not copied here first)."""
        inputs = {"z": self.z, "top": self.top, "calibration": self.calibration}
        if self.zc is not None:
            inputs["zc"] = self.zc
        if index is not None and (np.ndim(self.z) == 3 or self.zc is not None):
            inputs["z_rows"] = index
        return inputs

    def _top_rows(self, index, n):
        """The top coatings of the rows ``index`` (all when None): the material's one pair (2,) or per hit
        (n, 2); None without a top lobe."""
        if self.top is None:
            return None
        shared = np.ndim(self.top) == 1
        return self.top if index is None or shared else self.top[index]

    def eval(self, wi, wo, index=None):
        return self.models.eval_brdf(wi=wi, wo=wo, **self._decoder_inputs(index)).astype(np.float64)

    def _mixture(self, wi, wo, index, share, p_top):
        """The sampler's density: the proxy's, mixed with the top lobe's ``p_top`` by ``share``."""
        sigma, w = self._rows(self.sigma, index), self._rows(self.w, index)
        if share is None:
            return proxy.pdf(wo, wi, sigma, w)
        sigma, w = proxy.params(sigma, w, len(wi))
        wo, wi, share, p_top = (kernels.float64_rows(a) for a in (wo, wi, share, p_top))
        return kernels.mixture_pdf(wo, wi, sigma, w, share, p_top)

    def pdf(self, wi, wo, index=None):
        top = self._top_rows(index, len(wi))
        if top is None:
            return self._mixture(wi, wo, index, None, None)
        return self._mixture(wi, wo, index, top_lobe.top_share(top, wo), top_lobe.pdf_top(top, wi, wo))

    def _propose(self, wo, u_lobe, u):
        """Directions of the mixture sampler (the top lobe with probability ``share``, else the proxy),
        ``share`` (None without a top lobe) and the rows whose top-lobe sample failed (below the horizon:
        zero-weight samples): one compiled pass (``kernels.propose_with_top``)."""
        if self.top is None:
            u3 = np.concatenate([u_lobe[:, None], u], axis=1)
            return proxy.sample_directions(wo, self.sigma, self.w, u3), None, None
        if len(self._sigma_rows) not in (1, len(wo)) or len(self._top_table) not in (1, len(wo)):
            raise ValueError(f"the material's per-hit parameters do not match its {len(wo)} hits")
        return kernels.propose_with_top(
            *(kernels.float64_rows(a) for a in (wo, u_lobe, u)), self._sigma_rows, self._w_rows, self._top_table
        )

    def sample_direction(self, wo, u_lobe, u):
        wi, share, missed = self._propose(wo, u_lobe, u)
        if share is None:
            return wi, self._mixture(wi, wo, None, None, None)
        pdf = self._mixture(wi, wo, None, share, top_lobe.pdf_top(self._top_rows(None, len(wo)), wi, wo))
        return wi, np.where(missed, 0.0, pdf)

    def shade(self, wo, light_wi, light_rows, u_lobe, u, need_pdf):
        """The bounce's query in one pass: proposals and next-event directions through one decoder batch,
        and, with a top lobe, its f and density at all of them from one evaluation of the lobe."""
        if self.top is None:
            return super().shade(wo, light_wi, light_rows, u_lobe, u, need_pdf)
        prop_wi, share, missed = self._propose(wo, u_lobe, u)
        v, n = len(light_rows), len(wo)
        index = np.concatenate([light_rows, np.arange(n)])
        # np.take: 72 us for 28,000 rows of (N, 3), where numpy's fancy indexing took 260
        wi_all, wo_all = np.concatenate([light_wi, prop_wi]), np.take(wo, index, axis=0)
        f, p_top = self.models.eval_brdf(wi=wi_all, wo=wo_all, top_pdf=True, unit=True, **self._decoder_inputs(index))
        need_pdf = bool(need_pdf and v)  # the lights' density only when asked
        f_light, pdf_light, *sample = kernels.neural_shading(
            f, p_top, wi_all, wo_all, index, v, self._sigma_rows, self._w_rows, share, missed, need_pdf
        )
        false = np.zeros(n, dtype=bool)
        return Shading(
            f_light, pdf_light if need_pdf else None, BSDFSample(*sample[:3], false, false.copy(), sample[3])
        )

    def sample(self, wo, u_lobe, u):
        """Self-contained sampling (one decoder batch of its own); the integrator uses ``shade``."""
        wi, pdf = self.sample_direction(wo, u_lobe, u)
        return finish_sample(wi, pdf, self.eval(wi, wo))


class NeuralMaterial:
    """A stack's latent (or a latent texture) decoded by the neural runtime, with its albedo calibration
    when it has one, applied to every evaluation: a single latent's ``calibrate.AlbedoCalibration``, a
    latent texture's ``textures.calibration.TextureCalibration`` (a table per cluster of its texels)."""

    kind = "neural"
    has_pdf = True

    def __init__(self, models, z=None, proxy=(0.2, 0.5), latent_texture=None, calibration=None, top=None):
        self.models = models
        self.z = None if z is None else np.asarray(z, dtype=np.float32).reshape(3, LATENT)
        # the stack's top coating (alpha, ior) for a remainder decoder's exact top lobe (top_lobe.top_coat)
        self.top = None if top is None else top_lobe.as_top(top, 1)[0]
        self.sigma, self.w = float(proxy[0]), float(proxy[1])
        self.texture = latent_texture
        self.calibration = calibration
        self._projected_centroids = None  # the calibration's centroids as a projected texture's rows (``bind``)
        self.uncalibrated_stack = None  # set by ``make`` for "cached" without a calibration: see ``calibrated``
        if self.z is None and self.texture is None:
            raise ValueError("a NeuralMaterial needs a latent z (3, 32) or a latent texture")
        if calibration is not None and (self.texture is not None) != hasattr(calibration, "centroids"):
            raise ValueError(
                "a latent texture takes a TextureCalibration and a single latent an AlbedoCalibration, got "
                f"{type(calibration).__name__} for a {'latent texture' if self.texture is not None else 'latent'}"
            )

    def calibrated(self, step=None) -> "NeuralMaterial":
        """This material with the calibration ``make`` left out when asked for "cached" only and none was made
        yet (``uncalibrated_stack``): made now (about a second of reference walks, then cached, in memory and on
        disk with ``calibrate.use_disk_cache``), in a copy; the material itself when nothing is left out. The
        viewport's session calls it after its first full-resolution pass (``progressive``), with a ``step`` that
        stops it on an edit (``calibrate.calibrate``)."""
        if self.uncalibrated_stack is None:
            return self
        from ..neural import calibrate as cal

        out = copy.copy(self)
        out.calibration = cal.calibrate(self.uncalibrated_stack, self.models, self.z, (self.sigma, self.w), step=step)
        out._projected_centroids = None
        out.uncalibrated_stack = None
        return out

    def bind(self, hits):
        if self.texture is None:
            return _BoundNeural(
                self.models, self.z, np.float64(self.sigma), np.float64(self.w), self.calibration, self.top
            )
        projected = self._projected_texture()
        # one texel a hit, picked by its filter weight: the pixel's samples average what each texel renders
        # (``kernels.trilinear``), where a blend of latents decoded is not the blend of their BRDFs; hits with no
        # ``seed`` attribute at all (a caller's own object, not ``SurfaceHits``) are looked up blended
        seed = getattr(hits, "seed", None)
        if projected is None:
            z, prox, top = self.texture.lookup(hits.uv, hits.footprint, pick_seed=seed)
            calibration = None if self.calibration is None else self.calibration.at(z)
            zc = None
        else:
            (zc, prox, top), z = projected.lookup(hits.uv, hits.footprint, pick_seed=seed), None
            calibration = None if self.calibration is None else self.calibration.at(zc, self._projected_centroids)
        sigma = np.asarray(prox[:, 0], dtype=np.float64)
        w = np.asarray(prox[:, 1], dtype=np.float64)
        return _BoundNeural(self.models, z, sigma, w, calibration, top, zc)

    def _projected_texture(self):
        """The latent texture as the decoder's fused graph reads it (``LatentTexture.projected``), when its
        projected latents are no wider than the latents (the tiny decoder's 32 channels: the same taps, in a second
        chain as large as the texture's, and each query row skips the latents' layer); None otherwise, and the
        runtime projects each hit's looked-up latents once a bounce instead. A calibration then chooses each hit's
        table by the centroid nearest its projected latents (its centroids projected the same way): the distance
        the decoder sees. The latents' own distance also counts directions the tiny decoder all but ignores (its
        first layer's latent columns have a condition number of about 1,200), and keeping the latents beside the
        products for it doubled the taps, which cost what the products saved."""
        models = self.models
        if not hasattr(self.texture, "projected") or not models.projects_latents or models.width > LATENT:
            return None
        if self.calibration is not None and self._projected_centroids is None:
            self._projected_centroids = models.project_latents(self.calibration.centroids.reshape(-1, 3, LATENT))
        key = (models.size, str(models.model_dir))
        return self.texture.projected(key, models.project_latents, models.width)


class NeuralFallbackWarning(UserWarning):
    """A layered material renders with the reference instead of its neural models; the message says why."""


def texture_size(latent_texture) -> tuple[str, str | None]:
    """The decoder size a latent texture was baked for and the decoder digest it records (or None): what ``make``
    decodes it with, and what the decoder choice says fixes its size (``quality.assign_decoders``)."""
    from ..neural import SIZES

    meta = getattr(latent_texture, "metadata", None)
    if not isinstance(meta, dict) or "model" not in meta:
        raise ValueError(
            "the latent texture records no decoder size (metadata 'model'): its latent space is "
            "unknown; bake it with textures.bake.neural_encoder, which records it"
        )
    size = meta["model"]
    if size not in SIZES:
        raise ValueError(
            f"the latent texture was baked for decoder size {size!r}, which is not one of {list(SIZES)}; rebake it"
        )
    return size, meta.get("model_digest")


def make(stack: Stack, latent_texture=None, size: str | None = None, latent=None, calibrate=False, step=None):
    """A NeuralMaterial for ``stack`` (or for its latent texture), or None in the documented cases below.

    ``calibrate``: True gives the material its albedo calibration against the reference
    (``neural.calibrate``: about a second of reference walks per stack, cached in memory and, with
    ``calibrate.use_disk_cache``, on disk), "cached" only one already made (no work: for the viewport and
    thumbnails), False none. A latent texture brings the calibration its bake made (``textures.calibration``;
    none when it was baked without one or with other calibration settings, with a warning to rebake), for True
    and "cached". ``step`` (optional) is passed to the calibration (``calibrate.calibrate``): raising there stops it.

    ``size`` picks the decoder ("auto" or None: ``neural.resolve_size``, the default size). A latent
    texture is decoded by the size it was baked for (its ``model`` metadata, checked against ``size``
    when one is given). ``latent``, when given, is ``(z (3, 32), size)``: a latent of ``stack`` for
    that decoder size (a refined one), decoded as it is instead of encoding the stack.
    Proxy parameters come from the size's sampling network when it is shipped,
    else from :func:`proxy_guess`.

    Returns None, with a :class:`NeuralFallbackWarning` naming the reason (the renderer then shades
    the stack with the reference), only when
    - a model file the material needs is missing or damaged (``FileNotFoundError``,
      ``neural.ModelFileError``: a layered stack needs the size's layering network), or
    - the latent texture was baked with another decoder file than the shipped one (its
      ``model_digest``): its latents belong to another latent space.
    Everything else raises: ValueError for an unknown size, a texture that records no or an unknown
    decoder size, or one baked for another size than ``size``.
    """
    from ..neural import AUTO, ModelFileError, load_models, resolve_size

    if not isinstance(stack, Stack):
        raise ValueError(f"make needs a Stack, got {type(stack).__name__}")
    from ..neural.calibrate import check_mode

    check_mode(calibrate)
    requested = None if size is None or size == AUTO else resolve_size(size)
    z = None
    if latent is not None:
        if latent_texture is not None:
            raise ValueError("give make a latent texture or a latent (z, size), not both")
        z, latent_size = latent
        size = resolve_size(latent_size)
        z = np.asarray(z, dtype=np.float32)
        if z.size != 3 * LATENT or not np.all(np.isfinite(z)):
            raise ValueError(
                f"a given latent must be 3 x {LATENT} finite numbers; got shape {z.shape}"
                f"{'' if np.all(np.isfinite(z)) else ' with non-finite values'}"
            )
        z = z.reshape(3, LATENT)
        if requested is not None and requested != size:
            raise ValueError(f"the given latent belongs to decoder size {size!r}, not {requested!r}")
        digest = None
    elif latent_texture is not None:
        size, digest = texture_size(latent_texture)
        if requested is not None and requested != size:
            raise ValueError(
                f"the latent texture was baked for decoder size {size!r}, not {requested!r}: a latent "
                f"belongs to the latent space of its size; rebake it or pass size={size!r}"
            )
    else:
        size, digest = requested or resolve_size(AUTO), None
    try:
        models = load_models(size)
        if digest is not None and digest != models.digest:
            warnings.warn(
                f"the latent texture was baked with another decoder_{size}.onnx (sha256 {digest[:12]}...) "
                f"than the shipped one ({models.digest[:12]}...): rebake it; rendering the stack with the "
                f"reference",
                NeuralFallbackWarning,
                stacklevel=2,
            )
            return None
        if latent_texture is not None:
            calibration = _texture_calibration(latent_texture) if calibrate else None
            material = NeuralMaterial(models, None, proxy_guess(stack), latent_texture, calibration)
        else:
            z, proxy, top = _encoded(stack, models, z)
            material = NeuralMaterial(
                models,
                z,
                tuple(float(v) for v in proxy),
                calibration=_calibration(stack, models, z, proxy, calibrate, step),
                top=top,
            )
            if calibrate == "cached" and material.calibration is None:
                material.uncalibrated_stack = stack
    except (FileNotFoundError, ModelFileError) as e:
        warnings.warn(
            f"decoder size {size}: {e}; rendering the stack with the reference", NeuralFallbackWarning, stacklevel=2
        )
        return None
    material.size = size
    return material


ENCODINGS_KEPT = 256  # stacks whose encoding each model set keeps (``_encoded``)


def _encoded(stack: Stack, models, z=None):
    """``stack``'s latent on ``models`` (``z`` when given: a refined one), its proxy parameters (sigma, w) and its
    top coating, what ``make`` gives a material. An encoded stack is kept, read-only, by the model set
    (``ModelSet.encodings``, the last :data:`ENCODINGS_KEPT`) for the renders that follow: every render resolves
    its scene's materials again, the viewport's after each edit, where usually one stack changed (encoding the
    demo scene's five stacks took 30-35 ms of the viewport's 50-80 ms first image)."""
    cache = getattr(models, "encodings", None) if z is None else None
    if cache is not None:
        with models.encodings_lock:
            hit = cache.get(stack)
            if hit is not None:
                cache.move_to_end(stack)
                return hit
    from ..neural import encode_stack

    z = encode_stack(stack, models) if z is None else z
    made = (np.array(z, dtype=np.float32), np.array(proxy.material_params(models, z, stack)), top_lobe.top_coat(stack))
    for a in made:
        a.setflags(write=False)
    if cache is not None:
        with models.encodings_lock:
            cache[stack] = made
            while len(cache) > ENCODINGS_KEPT:
                cache.popitem(last=False)
    return made


def _calibration(stack: Stack, models, z, proxy, calibrate, step=None):
    """The albedo calibration ``make`` gives a single latent (see its ``calibrate`` and ``step``)."""
    from ..neural import calibrate as cal

    if calibrate is True:
        return cal.calibrate(stack, models, z, proxy, step=step)
    return cal.cached(stack, models, z, proxy) if calibrate == "cached" else None


class StaleCalibrationWarning(UserWarning):
    """A latent texture's stored calibration is not used: made with other calibration settings, or unreadable."""


def _texture_calibration(latent_texture):
    """The calibration a latent texture's bake stored in its metadata (``calibration``), or None."""
    from ..textures.calibration import TextureCalibration, top_at_trained_bounds

    text = (getattr(latent_texture, "metadata", None) or {}).get("calibration")
    if not text:
        return None
    try:
        calibration = TextureCalibration.from_text(text)
    except ValueError as e:
        why = f"cannot be read ({e})"
    else:
        if calibration.is_current(top_at_trained_bounds(latent_texture.levels)):
            return calibration
        why = "was made with other calibration settings than this version's"
    warnings.warn(
        f"the latent texture's albedo calibration {why}; rendering it uncalibrated: rebake it",
        StaleCalibrationWarning,
        stacklevel=3,
    )
    return None

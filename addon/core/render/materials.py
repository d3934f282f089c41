"""Renderer materials: what the integrator asks of a surface, in one declared interface.

A :class:`Material` is bound to a batch of hits (``bind(hits)``, once per bounce and material);
the :class:`BoundMaterial` it returns answers one query per bounce on local-frame directions
(normal +z, ``wi`` toward the light, ``wo`` toward the viewer, docs/architecture.md):

    shade(wo, light_wi, light_rows, u_lobe, u, need_pdf) -> Shading

``wo`` (N, 3) are the bound hits' view directions; ``light_wi`` (V, 3) next-event directions of
the rows ``light_rows`` (V,) of the batch (the hits whose shadow ray reached a light); ``u_lobe``
(N,) and ``u`` (N, 2) the random numbers of the BSDF sample. The answer holds f (without the
cosine) at the next-event directions, their solid-angle BSDF pdf when ``need_pdf`` (for MIS),
and a BSDF sample for every hit. Answering both in one call lets a material that is expensive to
evaluate (a neural decoder, the position-free estimator) serve shadow and sampled directions with
one evaluation.

Most materials answer from three smaller methods, and :class:`ShadeByParts` builds ``shade`` from
them:

    eval(wi, wo, index=None) -> (M, 3)   f without the cosine
    pdf(wi, wo, index=None) -> (M,)      solid-angle density of sample(); only if has_pdf
    sample(wo, u_lobe, u) -> BSDFSample  for all N bound hits (addon.core.bsdf.base)

``index`` (M,) selects rows of the bound batch; None means all rows. :class:`ShadeByProposal`
does the same for materials that only propose directions (``sample_direction``) and evaluate
proposals together with the next-event directions in one ``eval`` call.

``hits`` is a :class:`SurfaceHits` (uv, ray-cone footprint in uv units, a seed): everything a
textured, latent-textured or stochastic material needs. The integrator never looks inside.

``kind`` names the cost class for the render statistics ("analytic", "neural" or
"reference"). A material without a pdf (``has_pdf = False``, e.g. a sampler with no
closed-form density) is rendered without MIS: next-event estimation for every light,
BSDF-sampled emission only after delta (specular) events.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .. import kernels
from ..bsdf import Lambertian, RoughConductor, RoughDielectric
from ..bsdf.base import SMOOTH_ALPHA, BSDFSample
from ..bsdf.dielectric import INDEX_MATCHED_TOL, is_smooth
from ..bsdf.specular_diffuse import SpecularDiffuse, specular_ior
from ..stack import Conductor, Dielectric, Diffuse, Stack
from ..textures.mip import build_mip_chain, trilinear_lookup
from ..threads import map_on_threads
from .shading import ShadeByParts, Shading, finish_sample


@dataclass
class SurfaceHits:
    """Per-hit information a material may use: uv (N, 2), footprint (N,) in uv units (the ray
    cone's width on the surface), an integer seed for stochastic estimators, and ``front`` (N,) bool, whether
    each ray came from the side the surface's face normal points to (None: all of them). The local frame is
    turned toward the viewer either way; a material that lets light through tells entering from leaving by
    ``front``."""

    uv: np.ndarray
    footprint: np.ndarray
    seed: int = 0
    front: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.uv)


class BoundMaterial(Protocol):
    """A material bound to a batch of hits (see the module docstring)."""

    def shade(
        self,
        wo: np.ndarray,
        light_wi: np.ndarray,
        light_rows: np.ndarray,
        u_lobe: np.ndarray,
        u: np.ndarray,
        need_pdf: bool,
    ) -> Shading: ...


class Material(Protocol):
    """What the integrator asks of a scene material."""

    kind: str  # "analytic", "neural" or "reference": the cost class in the render statistics
    has_pdf: bool  # sample() has a closed-form pdf (MIS with next-event estimation)

    def bind(self, hits: SurfaceHits) -> BoundMaterial: ...


class _BoundBSDF(ShadeByParts):
    """An analytic BSDF (addon.core.bsdf) seen through the material interface."""

    def __init__(self, bsdf):
        self.bsdf = bsdf

    def _rows(self, index):
        if index is None or self.bsdf.batch_rows is None:
            return self.bsdf
        return self.bsdf.take(index)

    def eval(self, wi, wo, index=None):
        return self._rows(index).eval(wi, wo, check=False)

    def pdf(self, wi, wo, index=None):
        return self._rows(index).pdf(wi, wo, check=False)

    def sample(self, wo, u_lobe, u):
        return self.bsdf.sample(wo, u_lobe, u, check=False)

    def shade(self, wo, light_wi, light_rows, u_lobe, u, need_pdf) -> Shading:
        """One compiled pass for a Lambertian (``kernels.lambert_shade``) or a Principled BSDF whose lobes are shared
        by its rows (``kernels.principled_shade``); any other BSDF answers from eval, pdf and sample."""
        principled = isinstance(self.bsdf, SpecularDiffuse) and (arrays := self.bsdf.shading_arrays()) is not None
        if not (principled or isinstance(self.bsdf, Lambertian)):
            return super().shade(wo, light_wi, light_rows, u_lobe, u, need_pdf)
        rows = np.ascontiguousarray(light_rows, dtype=np.int64)
        wo, light_wi, u = kernels.float64_rows(wo), kernels.float64_rows(light_wi), kernels.float64_rows(u)
        if principled:
            f, pdf, wi, weight, p, delta, valid = kernels.principled_shade(
                *arrays, wo, light_wi, rows, kernels.float64_rows(u_lobe), u
            )
        else:
            albedo = np.require(self.bsdf.albedo, np.float64, ["C", "W"])  # kernels.lambert_shade
            f, pdf, wi, weight, p, valid = kernels.lambert_shade(albedo, wo, light_wi, rows, u)
            delta = np.zeros(len(wo), dtype=bool)
        false = np.zeros(len(wo), dtype=bool)
        sample = BSDFSample(wi, weight, p, delta, false, valid)
        return Shading(f, pdf if need_pdf and len(light_rows) else None, sample)


class ImageTexture:
    """An RGB image (H, W, 3), row 0 at the top, looked up trilinearly with the ray footprint.

    Uses the same mip chain and lookup as latent textures (``addon.core.textures.mip``).
    """

    EXTENSIONS = ("REPEAT", "EXTEND", "CLIP", "MIRROR")  # Blender's Image Texture node's Extension

    def __init__(self, image: np.ndarray, uv_transform=None, extension: str = "REPEAT"):
        """``uv_transform``: a (2, 3) affine map applied to the uv before the lookup (a Mapping node's), None for
        none. ``extension``: what lies outside the uv square, as Blender's Image Texture node says: the image
        repeated, its edge texels extended, black (Clip) or the image mirrored."""
        img = np.asarray(image, dtype=np.float32)
        if img.ndim != 3 or img.shape[2] < 3 or img.shape[0] < 1 or img.shape[1] < 1:
            raise ValueError(f"an image texture must be (H, W, 3 or 4), got shape {img.shape}")
        if extension not in self.EXTENSIONS:
            raise ValueError(f"extension must be one of {self.EXTENSIONS}, got {extension!r}")
        self.extension = extension
        img = np.nan_to_num(img[:, :, :3], nan=0.0, posinf=0.0, neginf=0.0)
        self.levels = build_mip_chain(img)
        self.uv_transform = None
        if uv_transform is not None:
            a = np.asarray(uv_transform, dtype=np.float64).reshape(2, 3)
            if not np.isfinite(a).all():
                raise ValueError(f"uv_transform must be finite, got {a.tolist()}")
            self.uv_transform = a

    def lookup(self, uv: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """The texture at ``uv`` (N, 2) with ``footprint`` (N,) in uv units, both through ``uv_transform``: the
        footprint scaled by the square root of the map's area scale (the geometric mean of its two scales)."""
        if self.uv_transform is not None:
            a = self.uv_transform
            uv = np.asarray(uv, dtype=np.float64) @ a[:, :2].T + a[:, 2]
            footprint = np.asarray(footprint, dtype=np.float64) * np.sqrt(abs(np.linalg.det(a[:, :2])))
        if self.extension == "REPEAT":
            return trilinear_lookup(self.levels, uv, footprint)
        uv = np.asarray(uv, dtype=np.float64)
        if self.extension == "MIRROR":  # a triangle wave of period 2: the image, then its mirror image
            uv = 1.0 - np.abs(np.mod(uv, 2.0) - 1.0)
        h, w = self.levels[0].shape[:2]
        half = 0.5 / np.array([w, h])  # the edge texels' centres: a tap never reaches round to the other side
        # on the base level only, as Cycles looks an image up (no mip levels by default): a coarser level's taps
        # wrap round to the far edge, which these modes never show (a minified decal took 47% of the other edge)
        out = trilinear_lookup(self.levels, np.clip(uv, half, 1.0 - half), footprint, n_levels=1)
        if self.extension == "CLIP":  # black outside the uv square, blended over half a texel each side as a
            # bilinear tap between the edge texel and a black one beyond it blends them
            texels = np.minimum(uv, 1.0 - uv) * np.array([w, h]) + 0.5
            out *= np.prod(np.clip(texels, 0.0, 1.0), axis=1)[:, None].astype(out.dtype)
        return out


class LambertMaterial:
    """Lambertian with a constant colour or an image texture (what unmanaged materials become).

    A colour above 1 reflects more light than it receives, as Cycles renders it (a Diffuse BSDF of colour 1.5 was
    clipped to 1, 0.667 of Cycles' image); the integrator needs no bound on it (Russian roulette's survival
    probability is clipped to 1). A negative or non-finite channel is 0."""

    kind = "analytic"
    has_pdf = True

    def __init__(self, color=(0.8, 0.8, 0.8), texture: ImageTexture | None = None):
        color = np.broadcast_to(np.asarray(color, dtype=np.float64), (3,))
        self.color = np.maximum(np.nan_to_num(color, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
        self.texture = texture
        # of_valid_rows: Lambertian's own check holds an albedo to [0, 1], a physical surface's range
        self._const = _BoundBSDF(Lambertian.of_valid_rows(self.color[None, :].copy()))

    def bind(self, hits: SurfaceHits):
        if self.texture is None:
            return self._const
        # the texels clipped to [0, 1], times the colour
        albedo = kernels.tinted_albedo(self.texture.lookup(hits.uv, hits.footprint), self.color)
        return _BoundBSDF(Lambertian.of_valid_rows(albedo))


class PrincipledMaterial:
    """Cycles' Principled BSDF without transmission, coat, sheen, subsurface, emission or tints: a GGX dielectric
    reflection over a Lambertian of the base colour, mixed with a GGX metal of that colour by ``metallic``
    (``bsdf.SpecularDiffuse``). ``roughness`` is artist roughness (GGX alpha = roughness^2), ``ior`` and
    ``specular_level`` Blender's IOR and Specular IOR Level (``bsdf.specular_diffuse.specular_ior``; an IOR below 1
    is read as 1 / IOR, the same interface seen from the other side). The base colour is textured as
    :class:`LambertMaterial`'s is (the texels times ``base_color``); a channel above 1 is kept, as Cycles keeps it.
    A bounce shades in one compiled pass (``kernels.principled_shade``, the formulas SpecularDiffuse runs on arrays),
    at about a Lambertian's cost: a cube on a plane of Blender's default material renders in 1.3x the time of the
    same scene of Lambertians (240 x 160, 16 spp: 0.42 s against 0.32 s), where numpy's eval, pdf and sample took
    3.3x (1.04 s)."""

    kind = "analytic"
    has_pdf = True

    def __init__(self, base_color, metallic=0.0, roughness=0.5, ior=1.5, specular_level=0.5, texture=None):
        color = np.broadcast_to(np.asarray(base_color, dtype=np.float64), (3,))
        self.color = np.maximum(np.nan_to_num(color, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
        self.metallic = float(np.clip(metallic, 0.0, 1.0))
        self.roughness = float(np.clip(roughness, 0.0, 1.0))
        eta = specular_ior(ior, specular_level)
        self.ior = max(eta, 1.0 / eta)
        self.texture = texture
        self._const = _BoundBSDF(self._bsdf(self.color[None, :].copy()))

    def _bsdf(self, base: np.ndarray) -> SpecularDiffuse:
        return SpecularDiffuse(base, self.roughness**2, self.ior, self.metallic)

    def bind(self, hits: SurfaceHits):
        if self.texture is None:
            return self._const
        # the texels times the colour, as a Lambertian's: float64, finite, >= 0 (SpecularDiffuse's checks skipped)
        texels = self.texture.lookup(hits.uv, hits.footprint)
        return _BoundBSDF(self._const.bsdf.with_base(kernels.tinted_albedo(texels, self.color)))


class BSDFMaterial:
    """Any analytic BSDF from addon.core.bsdf with shared (not per-hit) parameters."""

    kind = "analytic"
    has_pdf = True

    def __init__(self, bsdf):
        self.bsdf = bsdf
        self._bound = _BoundBSDF(bsdf)

    def bind(self, hits: SurfaceHits):
        bsdf = self.bsdf
        if (
            isinstance(bsdf, RoughDielectric)
            and not bsdf.reflection_only
            and hits.front is not None
            and not np.all(hits.front)
        ):
            # A ray leaving through the surface (from the back of its faces) meets the interface from inside: the
            # frame faces the viewer, so the relative index is turned (else every crossing entered, and light
            # never met total internal reflection on its way out).
            ior = np.where(hits.front, bsdf.ior, 1.0 / np.asarray(bsdf.ior, dtype=np.float64))
            return _BoundBSDF(RoughDielectric(np.broadcast_to(bsdf.alpha, ior.shape), ior))
        return self._bound


def conductor(alpha: float, eta, k) -> BSDFMaterial:
    return BSDFMaterial(RoughConductor(alpha, eta, k))


def analytic_for_stack(stack: Stack):
    """The exact analytic material of a single-layer stack, or None if it has coatings."""
    if stack.coatings:
        return None
    b = stack.base
    if isinstance(b, Diffuse):
        return LambertMaterial(b.albedo)
    if isinstance(b, Conductor):
        return conductor(b.roughness, b.eta, b.k)
    if isinstance(b, Dielectric):
        return BSDFMaterial(RoughDielectric(b.roughness, b.ior, reflection_only=True))
    raise ValueError(f"unknown base layer {type(b).__name__}")


def _top_is_smooth(stack: Stack) -> bool:
    """True when the top interface is a delta one (the walk's ``is_smooth``): smooth, or index-matched whatever its
    roughness (light passes straight through it, and a mirror below reflects a delta lobe; a rough ior-1 coat over a
    mirror rendered 0.21 of its 0.93 albedo, its delta part never sampled)."""
    top = stack.coatings[-1] if stack.coatings else stack.base
    if isinstance(top, Diffuse):
        return False
    ior = getattr(top, "ior", None)
    return bool(is_smooth(top.roughness, ior)) if ior is not None else top.roughness < SMOOTH_ALPHA


class _BoundReference(ShadeByParts):
    """The position-free estimator behind the material interface.

    Directions are proposed by the sampling proxy (``addon.core.neural.proxy``, exact pdf) and
    weighted by an ``eval_brdf`` estimate, so MIS with next-event estimation works as for any
    material. When the top interface is smooth, part of f is a delta component that eval_brdf
    cannot represent: then a fraction ``1 - q`` of the samples runs the analog walk and keeps
    only its delta-only (specular) paths, which carry that component exactly.
    """

    def __init__(self, stack, walks: int, seed: int, sigma: float, w: float, q: float):
        # ``stack``: one Stack, or StackArrays with a row per hit (a spatially varying stack's texels)
        self.stack, self.walks, self.seed = stack, walks, seed
        self.sigma, self.w, self.q = sigma, w, q

    def _stacks(self, index):
        """The stack of the rows ``index`` (all when None): the material's one, or those hits' own."""
        return self.stack if index is None or isinstance(self.stack, Stack) else self.stack.take(index)

    def eval(self, wi, wo, index=None):
        from .. import reference

        if len(wi) == 0:
            return np.zeros((0, 3))
        f, _ = reference.eval_brdf(self._stacks(index), wi, wo, walks=self.walks, seed=self.seed)
        return np.nan_to_num(np.maximum(f, 0.0))

    def shade(self, wo, light_wi, light_rows, u_lobe, u, need_pdf) -> Shading:
        if self.q < 1.0:  # a delta component: the analog walk samples part of the time
            return ShadeByParts.shade(self, wo, light_wi, light_rows, u_lobe, u, need_pdf)
        # Rough top: next-event and proposed directions are estimated from the same walks.
        prop_wi, prop_pdf = self.sample_direction(wo, u_lobe, u)
        wi_a = prop_wi.copy()
        wi_a[light_rows] = light_wi
        f_a, f_b = self.eval_pair(wi_a, prop_wi, wo)
        pdf = self.pdf(light_wi, wo[light_rows], light_rows) if need_pdf and len(light_rows) else None
        return Shading(f_a[light_rows], pdf, finish_sample(prop_wi, prop_pdf, f_b))

    def eval_pair(self, wi_a, wi_b, wo):
        """f at two incident directions per row from the same walks (reference.eval_brdf_many)."""
        from .. import reference

        f, _ = reference.eval_brdf_many(
            self.stack, np.stack([wi_a, wi_b], axis=1), wo, walks=self.walks, seed=self.seed + 7
        )
        f = np.nan_to_num(np.maximum(f, 0.0))
        return f[:, 0], f[:, 1]

    def pdf(self, wi, wo, index=None):
        from ..neural import proxy

        return self.q * proxy.pdf(wo, wi, self.sigma, self.w)

    def sample_direction(self, wo, u_lobe, u):
        from ..neural import proxy

        return proxy.sample(wo, self.sigma, self.w, np.concatenate([u_lobe[:, None], u], axis=1))

    def sample(self, wo, u_lobe, u):
        from .. import reference

        n = len(wo)
        rough = u_lobe < self.q
        out_wi, out_w = np.zeros((n, 3)), np.zeros((n, 3))
        out_pdf, out_delta = np.zeros(n), np.zeros(n, dtype=bool)
        r = np.nonzero(rough)[0]
        if len(r):
            wi, p = self.sample_direction(wo[r], u_lobe[r] / self.q, u[r])
            f, _ = reference.eval_brdf(self._stacks(r), wi, wo[r], walks=self.walks, seed=self.seed + 1)
            bs = finish_sample(wi, self.q * p, np.nan_to_num(np.maximum(f, 0.0)))
            out_wi[r], out_w[r], out_pdf[r] = bs.wi, bs.weight, bs.pdf
        d = np.nonzero(~rough)[0]
        if len(d):
            # The analog walk draws its own numbers from a stream keyed by the bounce's seed.
            rng = np.random.default_rng([self.seed, 1])
            wi, weight, specular = reference.sample(self._stacks(d), wo[d], rng, with_flags=True)
            keep = np.asarray(specular, dtype=bool)
            weight = np.nan_to_num(np.maximum(np.asarray(weight, dtype=np.float64), 0.0)) / (1 - self.q)
            out_wi[d] = np.where(keep[:, None], wi, 0.0)
            out_w[d] = np.where(keep[:, None], weight, 0.0)
            out_pdf[d] = np.where(keep, 1 - self.q, 0.0)
            out_delta[d] = keep
        valid = out_pdf > 0
        false = np.zeros(n, dtype=bool)
        return BSDFSample.build(out_wi, out_w, out_pdf, out_delta, false, valid)


class ReferenceLayered:
    """A layered stack shaded by the position-free Monte Carlo estimator (reference mode).

    ``eval`` is ``reference.eval_brdf`` with ``walks`` walks per query: an unbiased estimate of
    f, so next-event estimation stays unbiased. Sampling proposes directions with the proxy
    (exact pdf, hence MIS) and weights them with the same estimator; stacks with a smooth top
    interface add the analog walk's specular paths for the delta component (see
    ``_BoundReference``). With a rough top, next-event and sampled directions are evaluated
    from the same walks (``eval_pair``), one estimator call per bounce.
    """

    kind = "reference"
    has_pdf = True

    def __init__(self, stack: Stack, walks: int = 16, spatial=None):
        if walks < 1:
            raise ValueError(f"reference walks must be >= 1, got {walks}")
        if spatial is not None and spatial.stack != stack:
            raise ValueError("a reference material's spatially varying stack must vary its own stack")
        from .neural_material import proxy_guess

        self.stack, self.walks, self.spatial = stack, int(walks), spatial
        self.sigma, self.w = proxy_guess(stack)
        # a delta component wherever a texel's top is smooth or index-matched (its roughness or ior may be maps)
        if spatial is None:
            smooth = _top_is_smooth(stack)
        else:
            alpha, ior = spatial.top_range("roughness"), spatial.top_range("ior")
            smooth = (alpha is not None and alpha[0] < SMOOTH_ALPHA) or (
                ior is not None and ior[0] < 1.0 + INDEX_MATCHED_TOL
            )
        self.q = 0.5 if smooth else 1.0

    def bind(self, hits: SurfaceHits):
        stack = self.stack if self.spatial is None else self.spatial.stacks_at(hits.uv)
        return _BoundReference(stack, self.walks, hits.seed, self.sigma, self.w, self.q)


@dataclass
class LayeredSpec:
    """A managed material: its layer stack and, for spatially varying stacks, a latent texture.

    ``latent``, when given, is ``(z (3, 32), size)``: a latent of ``stack`` for decoder ``size``
    (a refined one, say) that neural mode decodes instead of encoding the stack again; like a latent
    texture it fixes the material's decoder size. ``spatial`` (``textures.spatial.SpatialStack`` of
    ``stack``): the per-texel stacks the latent texture was baked from, which reference mode shades hit
    by hit (without it, reference mode shades ``stack`` everywhere)."""

    stack: Stack
    latent_texture: object | None = None
    name: str = ""
    latent: tuple | None = None
    spatial: object | None = None
    reference: bool = False  # rendered with the reference estimator in every mode (Auto's fallback="reference")


def resolve(material, mode: str, reference_walks: int = 16, calibrate=False, step=None):
    """A renderer material for a scene entry (material object, Stack or LayeredSpec).

    ``mode`` is "neural" or "reference". Single-layer stacks render exactly with their analytic
    BSDF in both modes. Layered stacks use the neural runtime in "neural" mode when it is
    available, else the reference (see :func:`neural_available`); ``calibrate`` is passed to
    ``neural_material.make`` (the albedo calibration of each layered stack), with ``step`` (called between the
    calibration's parts: raising there stops it, and nothing is cached).
    """
    if mode not in ("neural", "reference"):
        raise ValueError(f"render mode must be 'neural' or 'reference', got {mode!r}")
    if material is None:
        return LambertMaterial()
    if hasattr(material, "bind"):
        return material
    spec = material if isinstance(material, LayeredSpec) else None
    stack = spec.stack if spec else material
    if not isinstance(stack, Stack):
        raise ValueError(
            f"a scene material must be a renderer material, a Stack or a LayeredSpec, got {type(material).__name__}"
        )
    exact = analytic_for_stack(stack)
    if exact is not None and (spec is None or spec.latent_texture is None):
        return exact
    if mode == "neural" and not (spec is not None and spec.reference):
        from . import neural_material

        made = neural_material.make(
            stack,
            spec.latent_texture if spec else None,
            latent=spec.latent if spec else None,
            calibrate=calibrate,
            step=step,
        )
        if made is not None:
            return made
    return ReferenceLayered(stack, reference_walks, spatial=spec.spatial if spec else None)


def resolve_all(
    materials, mode: str, reference_walks: int = 16, calibrate=False, threads: int = 1, step=None, check=None
) -> list:
    """:func:`resolve` of each of ``materials``, in order, on up to ``threads`` threads: a scene's layered stacks
    are encoded and calibrated side by side (``threads.map_on_threads``: their decoder batches release the GIL,
    their walks in part). On two cores the demo scene's first render, its five stacks to calibrate, spent
    1.53-1.70 s before its first path where it spent 1.94-1.97 s one stack at a time (fresh processes,
    alternating). Each material's own work is seeded, so the materials do not depend on the thread count.

    ``step`` is passed to each :func:`resolve`; ``check`` to ``map_on_threads`` (called on this thread while it
    waits: a render's stop that only this thread may poll), and also called before each material when they are
    resolved on this thread alone."""
    materials = list(materials)
    to_make = sum(1 for m in materials if m is not None and not hasattr(m, "bind"))  # the others are as they are
    workers = threads if to_make > 1 else 1

    def one(m):
        if check is not None and workers == 1:
            check()
        return resolve(m, mode, reference_walks, calibrate, step)

    return map_on_threads(one, materials, workers, "materials", check=check)

"""The exact top lobe's formulas (``addon.core.formula``), which the compiled loops (``addon.core.kernels``)
call while ``top_lobe`` calls those loops: a module of its own, so that neither imports the other.

- ``top_reflection``: f and the sampling density of the first reflection at a stack's top interface,
  ``RoughDielectric(alpha, ior, reflection_only=True)`` in radiance mode, 0 unless both directions are
  above the horizon and the interface reflects (``top_lobe.eval_pdf_top``).
- ``top_share_cos``: the share of a remainder material's samples the renderer gives the lobe
  (``top_lobe.top_share``). It is the Fresnel reflectance at the outgoing direction against a remainder taken as
TOP_SHARE_REST of the light, kept in TOP_SHARE_RANGE: about 0.14 at normal incidence for an index of
1.5, 0.5 where F = 0.2, and most samples towards grazing, where the coat reflects nearly everything. Any
share keeps a render unbiased (the mixture's pdf is exact); it only shapes noise.
"""

from __future__ import annotations

from ..bsdf.base import SMOOTH_ALPHA
from ..bsdf.dielectric import INDEX_MATCHED_TOL, rough_dielectric_eval_pdf
from ..bsdf.fresnel import fresnel_dielectric_cos
from ..formula import clip, formula, where

TOP_SHARE_REST = 0.25
TOP_SHARE_RANGE = (0.05, 0.9)


@formula
def top_share_cos(co, alpha, ior):
    """The share of samples for the top lobe at outgoing cosine ``co`` of a top coating (alpha, ior): 0
    without a rough top interface (index-matched, or smooth: its reflection is a delta, not in f)."""
    f = fresnel_dielectric_cos(clip(co, 0.0, 1.0), ior)
    share = clip(f / (f + TOP_SHARE_REST * (1.0 - f)), TOP_SHARE_RANGE[0], TOP_SHARE_RANGE[1])
    rough = (abs(ior - 1.0) >= INDEX_MATCHED_TOL) & (alpha >= SMOOTH_ALPHA)
    return where(rough, share, 0.0)


@formula
def top_reflection(ix, iy, iz, ox, oy, oz, alpha, ior):
    """(f, pdf) of the top interface's reflection at unit wi, wo (components) for the coating (alpha, ior)."""
    f, p = rough_dielectric_eval_pdf(ix, iy, iz, ox, oy, oz, alpha, ior, True, True)
    live = (iz > 0.0) & (oz > 0.0) & (abs(ior - 1.0) >= INDEX_MATCHED_TOL)
    return where(live, f, 0.0), where(live, p, 0.0)

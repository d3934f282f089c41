"""How a driving image's values become parameter values: one colour-space rule for ``bake/bake.py``.

It matches what a Blender user gets by default (the add-on itself decodes through Blender's
OpenColorIO, ``addon/blender/images.py``): an image driving a colour field (``albedo``) is decoded
from sRGB to linear when it is stored as integers (8- or 16-bit) without a linear colour-space tag
(OpenImageIO's ``oiio:ColorSpace``), as Blender's default "sRGB" for byte images; float images
(EXR, HDR) and integer images tagged linear are linear already. Every other field (roughness,
thickness, ior, eta, k, masks) reads the stored values raw, as Blender's "Non-Color". An explicit
colour space overrides the rule: ``srgb`` decodes, ``linear`` and ``non-color`` read raw.
Primaries are not converted (a linear tag of another gamut is read as linear Rec.709).
"""

from __future__ import annotations

import numpy as np

from ..render.film import from_srgb

COLOUR_FIELDS = frozenset({"albedo"})
COLOUR_SPACES = ("auto", "srgb", "linear", "non-color")


def colour_space(name: str) -> str:
    """The normalised colour-space name, or ValueError naming the valid ones."""
    key = name.strip().lower()
    if key not in COLOUR_SPACES:
        raise ValueError(f"unknown colour space {name!r}; use one of {', '.join(COLOUR_SPACES)}")
    return key


def _tag_is_linear(tag: str) -> bool:
    t = tag.strip().lower()
    return t.startswith("lin") or t in {"scene_linear", "acescg", "aces2065-1"}


def decoding(field: str, space: str, is_float: bool, tag: str) -> str:
    """'srgb' (decode to linear) or 'raw' for an image driving ``field`` (e.g. 'albedo')."""
    space = colour_space(space)
    if space != "auto":
        return "srgb" if space == "srgb" else "raw"
    if field in COLOUR_FIELDS and not is_float and not _tag_is_linear(tag):
        return "srgb"
    return "raw"


def decode(pixels: np.ndarray, how: str, alpha_channel: int = -1) -> np.ndarray:
    """``pixels`` (H, W, C) in [0, 1] decoded as ``decoding`` said; alpha is left as stored."""
    if how != "srgb":
        return pixels
    out = np.array(pixels, dtype=np.float32)
    colour = [c for c in range(min(out.shape[2], 3)) if c != alpha_channel]
    out[..., colour] = from_srgb(out[..., colour])
    return out

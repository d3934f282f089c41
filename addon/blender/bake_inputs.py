"""A material's layer stack with its image-driven parameters, as a core ``SpatialStack``.

Each layer may hold parameter maps (``NLM_ParameterMap``): an image whose pixel values, decoded
by its Color Space as Cycles decodes them (set Non-Color for data such as roughness) and read apart
from their alpha, as the bake command reads them (``map_pixels``), map linearly onto [low, high] in the
parameter's artist units (roughness as shown in the sidebar; alpha = roughness^2 for the core; F0 colour
converted to k with eta = 1). A new map spans its parameter's trained range (``map_range``); one that gives values
outside the valid range is refused in those units, naming its layer and map (``_checked``).
"""

from __future__ import annotations

import os

import numpy as np

from ..core.formula import LUMINANCE
from ..core.stack import (
    TRAINED_RANGES,
    VALID_RANGES,
    alpha_from_artist_roughness,
    artist_roughness_from_alpha,
    k_from_f0,
)
from ..core.textures.spatial import SpatialStack
from . import images, stack_io

# (map parameter, layer type) -> core field name of that layer
# The stack field each parameter map drives, per layer type: the maps a layer can have.
MAP_FIELDS = {
    ("ROUGHNESS", "CONDUCTOR"): "roughness",
    ("ROUGHNESS", "DIELECTRIC"): "roughness",
    ("ROUGHNESS", "COATING"): "roughness",
    ("ALBEDO", "DIFFUSE"): "albedo",
    ("F0", "CONDUCTOR"): "k",
    ("ETA", "CONDUCTOR"): "eta",
    ("K", "CONDUCTOR"): "k",
    ("IOR", "DIELECTRIC"): "ior",
    ("IOR", "COATING"): "ior",
    ("MEDIUM_ALBEDO", "COATING"): "albedo",
    ("THICKNESS", "COATING"): "thickness",
}
_RGB = {"ALBEDO", "F0", "ETA", "K", "MEDIUM_ALBEDO"}


def map_parameters(layer_type: str) -> list[str]:
    """The parameters a layer of ``layer_type`` can have a map of (:data:`MAP_FIELDS`), in the menu's order."""
    return [parameter for parameter, kind in MAP_FIELDS if kind == layer_type]


def map_range(parameter: str, layer_type: str, trained: bool = True) -> tuple[float, float]:
    """The range of ``parameter`` on a layer of ``layer_type`` in a map's units: its field's trained range
    (``stack.TRAINED_RANGES``: the Low and High Add Parameter Map gives a new map, so that every pixel value from 0 to 1
    is one the neural models were trained on; a new IOR map at 0 to 1 was an invalid IOR at every texel), or its valid
    range (``trained=False``: what a bake takes). Roughness in artist units (the square root of alpha); F0 a colour,
    0 to 1."""
    if parameter == "F0":  # a colour, made into k (``k_from_f0``)
        return 0.0, 1.0
    lo, hi = (TRAINED_RANGES if trained else VALID_RANGES)[MAP_FIELDS[(parameter, layer_type)]]
    if parameter == "ROUGHNESS":
        return artist_roughness_from_alpha(lo), artist_roughness_from_alpha(hi)
    return lo, hi


class MapUnreadable(ValueError):
    """A parameter map whose image has no pixels to read: its file missing, or not an image Blender can read. Its
    bake can still be rendered (``bake_state.current_texture``): a bake makes a material independent of its
    sources, as a Cycles bake does."""


def map_pixels(image) -> np.ndarray | None:
    """The (H, W, 4) scene-linear pixels a parameter map's ``image`` drives its parameter by, row 0 at the top: its
    colour apart from its alpha, as the bake command reads an image (``images.file_pixels(straight=True)``), from its
    file where its pixels are its file's (``images.pixels_file``); Blender's own buffer for a packed, generated or
    painted image (``images.linear_pixels``). None where it has no pixels."""
    path = images.pixels_file(image)
    px = images.file_pixels(image, path, straight=True) if path is not None else None
    return px if px is not None else images.linear_pixels(image)


def _unreadable(item, pmap) -> MapUnreadable:
    """Why the image of ``pmap`` (a map of layer ``item``) has no pixels: its file missing, or not an image."""
    image = pmap.image
    what = f"layer {item.name!r}: the image {image.name!r} driving {pmap.parameter.lower()}"
    path = images.file_path(image) if image.filepath else ""
    if image.packed_file is None and os.path.isdir(path):
        return MapUnreadable(f"{what}: its file {path!r} is a folder, not an image")
    if image.packed_file is None and os.path.isfile(path):
        return MapUnreadable(f"{what}: its file {path!r} is not an image Blender can read")
    if image.packed_file is None and path:
        return MapUnreadable(f"{what}: its file {path!r} is missing")
    return MapUnreadable(f"{what} has no pixels")


def _map_values(item, pmap) -> np.ndarray:
    px = map_pixels(pmap.image)
    if px is None:
        raise _unreadable(item, pmap)
    if pmap.parameter == "F0" and item.conductor_mode != "F0":
        raise ValueError(f"layer {item.name!r}: an F0 map needs the conductor specified by colour (F0)")
    if pmap.parameter in ("ETA", "K") and item.conductor_mode != "ETA_K":
        raise ValueError(
            f"layer {item.name!r}: {pmap.parameter.lower()} maps need the conductor specified by complex IOR"
        )
    # a number from a colour image as Blender makes one (its luminance), as the bake command does: a grey map is
    # its grey, a coloured one no longer its red
    pixels = px[..., :3] if pmap.parameter in _RGB else px[..., :3] @ np.array(LUMINANCE)[:, None]
    values = pmap.low + (pmap.high - pmap.low) * pixels.astype(np.float64)
    if pmap.parameter == "ROUGHNESS":
        values = np.clip(values, 0.0, None)
    values = _checked(item, pmap, pixels, values)
    if pmap.parameter == "ROUGHNESS":
        return alpha_from_artist_roughness(values)
    if pmap.parameter == "F0":
        return k_from_f0(values)
    return values


def _label(pmap) -> str:
    """The name the sidebar gives a map's parameter ("IOR", "Medium Albedo")."""
    return pmap.bl_rna.properties["parameter"].enum_items[pmap.parameter].name


def _outside(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H, W): the texels of ``values`` (H, W, C) with a channel outside [lo, hi] or not a number."""
    return (~np.isfinite(values) | (values < lo) | (values > hi)).any(axis=2)


def _checked(item, pmap, pixels: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` (H, W, C), in the map's units, where they are in its parameter's valid range (``map_range``); else
    ValueError, naming the layer and the map as the sidebar does and saying what to change: the core's refusal named
    the stack's path ("image for coatings[0].ior") and the value there. ``pixels``: the image's values the map made
    them of (0 to 1 in a byte image). A Low or High at an end of the range is a float32's, which can lie just past
    it (eta's 0.01 is 0.0099999998): values that close to an end are put on it."""
    lo, hi = map_range(pmap.parameter, item.layer_type, trained=False)
    bad = _outside(values, lo, hi)
    if not bad.any():
        return values
    for end in (lo, hi):
        values[np.abs(values - end) <= 2.0 * np.finfo(np.float32).eps * abs(end)] = end
    bad = _outside(values, lo, hi)
    if not bad.any():
        return values
    row, x = np.argwhere(bad)[0]
    y = bad.shape[0] - 1 - row  # as Blender counts an image's pixels: from the bottom
    label = _label(pmap)
    value = ", ".join(f"{v:.4g}" for v in values[row, x])
    value = value if values.shape[2] == 1 else f"({value})"
    mat = item.id_data.name
    what = (
        f"material {mat!r}, layer {item.name!r}: its {label} map (image {pmap.image.name!r}, Low {pmap.low:g}, "
        f"High {pmap.high:g}) gives {int(bad.sum())} of its {bad.size} texel(s) values outside the valid {label} "
        f"range {lo:g} to {hi:g} (the first: {value} at pixel x={x}, y={y})"
    )
    inside = pixels[bad]
    if np.isfinite(inside).all() and (inside >= 0.0).all() and (inside <= 1.0).all():
        raise ValueError(f"{what}: set the {label} map's Low and High within {lo:g} to {hi:g}")
    raise ValueError(
        f"{what}: its image holds values outside 0 to 1 there (a float image's): edit the image, or choose a Low and "
        f"High that map its values within {lo:g} to {hi:g}"
    )


def _material_maps(mat):
    """``(layer, map, parameter path)`` of each of the material's maps with an image, in the layers' order. Raises
    ``ValueError`` for a map that does not apply to its layer, or a parameter driven by two maps."""
    seen = {}
    for index, item in enumerate(mat.neural_layers.layers):
        for pmap in item.maps:
            if pmap.image is None:
                continue
            field = MAP_FIELDS.get((pmap.parameter, item.layer_type))
            if field is None:
                raise ValueError(
                    f"layer {item.name!r} ({item.layer_type.title()}) has no {pmap.parameter.lower()} "
                    f"to drive by the image {pmap.image.name!r}"
                )
            path = f"base.{field}" if index == 0 else f"coatings[{index - 1}].{field}"
            if path in seen:
                first = seen[path]
                raise ValueError(
                    f"layer {item.name!r}: two maps drive its {field} (the {_label(first)} map of image "
                    f"{first.image.name!r} and the {_label(pmap)} map of image {pmap.image.name!r}): remove one of "
                    "them (its X button)"
                )
            seen[path] = pmap
            yield item, pmap, path


def spatial_stack_from_material(mat):
    """(SpatialStack, {parameter path: image description}) or None if the material has no stack.

    Raises ``ValueError`` (naming layer, parameter and image) for a map that does not apply to
    its layer, images of different sizes or values outside the valid range, and :class:`MapUnreadable`
    for an image without pixels.
    """
    stack = stack_io.stack_from_material(mat)
    if stack is None:
        return None
    maps, sources = {}, {}
    for item, pmap, path in _material_maps(mat):
        maps[path] = _map_values(item, pmap)
        sources[path] = f"{pmap.image.name} [{pmap.low:g}, {pmap.high:g}]"
    try:
        return SpatialStack(stack, maps), sources
    except ValueError as e:
        raise ValueError(f"material {mat.name!r}: {e}") from None


def map_settings(mat) -> list:
    """What ``spatial_stack_from_material`` makes of the material's maps besides their images' pixels: for each map,
    its parameter path, layer kind and conductor mode, range, and its image's name, file, colour space and alpha
    mode (a ``ValueError`` as there for maps that do not apply). JSON-ready: a bake records it (``bake_state``)."""
    return [
        [path, item.layer_type, item.conductor_mode, pmap.parameter, float(pmap.low), float(pmap.high),
         pmap.image.name, pmap.image.filepath, pmap.image.colorspace_settings.name, pmap.image.alpha_mode]
        for item, pmap, path in _material_maps(mat)
    ]  # fmt: skip


PREVIEW_MAX_SIDE = 256  # texels a side the representative texel of a material's maps is found at


def has_maps(mat) -> bool:
    """Whether any layer of the material has a parameter map with an image."""
    return any(pmap.image is not None for item in mat.neural_layers.layers for pmap in item.maps)


def representative_stack(mat):
    """``(stack, share)``: the stack of the most common texel of the material's maps (found at most
    :data:`PREVIEW_MAX_SIDE` texels a side, the maps box-filtered down) and the share of the texels it covers; None
    for a material without maps. What the sidebar previews show of a material whose maps drive its render: its
    sliders alone are a stack F12 never renders (a coat the map makes glossy previewed 67 times too dark)."""
    found = spatial_stack_from_material(mat)
    if found is None or not found[0].maps:
        return None
    spatial = found[0]
    arrays, _ = spatial.texels(spatial.resolution_for_max_side(PREVIEW_MAX_SIDE))
    distinct, inverse = arrays.unique()
    counts = np.bincount(np.asarray(inverse).reshape(-1), minlength=len(distinct.to_matrix()))
    most = int(np.argmax(counts))
    return distinct.stack(most), float(counts[most]) / float(counts.sum())

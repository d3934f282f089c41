"""A material's layer stack with its image-driven parameters, as a core ``SpatialStack``.

Each layer may hold parameter maps (``NLM_ParameterMap``): an image whose pixel values, decoded
by its Color Space as Cycles decodes them (set Non-Color for data such as roughness) and read apart
from their alpha, as the bake command reads them (``map_pixels``), map linearly onto [low, high] in the
parameter's artist units (roughness as shown in the sidebar; alpha = roughness^2 for the core; F0 colour
converted to k with eta = 1).
"""

from __future__ import annotations

import os

import numpy as np

from ..core.formula import LUMINANCE
from ..core.stack import alpha_from_artist_roughness, k_from_f0
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
    # a number from a colour image as Blender makes one (its luminance), as the bake command does: a grey map is
    # its grey, a coloured one no longer its red
    values = px[..., :3] if pmap.parameter in _RGB else px[..., :3] @ np.array(LUMINANCE)[:, None]
    values = pmap.low + (pmap.high - pmap.low) * values.astype(np.float64)
    if pmap.parameter == "ROUGHNESS":
        values = alpha_from_artist_roughness(np.clip(values, 0.0, None))
    if pmap.parameter == "F0":
        if item.conductor_mode != "F0":
            raise ValueError(f"layer {item.name!r}: an F0 map needs the conductor specified by colour (F0)")
        values = k_from_f0(values)
    elif pmap.parameter in ("ETA", "K") and item.conductor_mode != "ETA_K":
        raise ValueError(
            f"layer {item.name!r}: {pmap.parameter.lower()} maps need the conductor specified by complex IOR"
        )
    return values


def _material_maps(mat):
    """``(layer, map, parameter path)`` of each of the material's maps with an image, in the layers' order. Raises
    ``ValueError`` for a map that does not apply to its layer, or a parameter driven by two images."""
    seen = set()
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
                raise ValueError(f"layer {item.name!r}: {pmap.parameter.lower()} is driven by two images")
            seen.add(path)
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

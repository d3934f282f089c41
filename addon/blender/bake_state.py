"""Where a material's latent texture is baked to and whether the baked one is current.

Read by the bake operator (``bake_ops``) and by the scene export (``scene_export``), which renders
a material's baked texture only while ``baked_texture_state`` says it is current.
"""

from __future__ import annotations

import os
import zlib
from collections import OrderedDict

import bpy
import numpy as np

from ..core.neural.models import ModelFileError, load_models, resolve_size
from ..core.textures.bake import bake_key, model_key
from ..core.textures.files import safe_file_name
from . import bake_inputs, images, stack_io
from .operator_base import UserError

DEFAULT_BAKE_FOLDER = "//textures/"


def texture_output_path(mat) -> str:
    """Where the bake of ``mat`` goes: its Bake Folder (relative to the .blend file by default).

    A folder relative to the .blend file ("//...") needs a saved file; without one Blender would
    resolve it against the process's working folder, so the bake refuses instead.
    """
    folder = mat.neural_layers.bake_directory or DEFAULT_BAKE_FOLDER
    if folder.startswith("//") and not bpy.data.filepath:
        raise UserError(
            f"the bake folder {folder!r} is relative to the .blend file, which is not saved: "
            "save the file first or choose an absolute Bake Folder"
        )
    # the bake CLI's file names: two different material names never share a file ("a/b", "a_b")
    return os.path.join(bpy.path.abspath(folder), f"{safe_file_name(mat.name)}.exr")


def bake_size(mat) -> str:
    """The decoder size a bake of ``mat`` uses: its model-size setting, "auto" resolved (``neural.resolve_size``)."""
    try:
        return resolve_size(stack_io.model_size(mat))
    except (ValueError, FileNotFoundError) as e:
        raise UserError(str(e)) from None


def bake_model_key(size: str, refine_s: float = 0.0) -> str:
    """The model part of the bake key of a bake with decoder ``size`` and refinement budget ``refine_s``:
    the size, the budget and the shipped decoder file's digest, as the bake CLI keys its textures
    (``textures.bake.model_key``)."""
    try:
        return model_key(size, load_models(size).digest, refine_s)
    except (ValueError, FileNotFoundError, ModelFileError) as e:
        raise UserError(str(e)) from None


def baked_texture_state(mat) -> tuple[str | None, str]:
    """(path of a current baked texture or None, a line for the user about its state)."""
    path, state, _ = current_texture(mat)
    return path, state


def current_texture(mat):
    """``baked_texture_state`` and the material's spatially varying stack the current texture was baked
    from (``textures.spatial.SpatialStack``, its maps read; None when there is no current texture)."""
    s = mat.neural_layers
    if not s.texture_path:
        return None, "not baked", None
    # "//" is relative to the file that holds the material: a linked one's library, not the open file
    path = bpy.path.abspath(s.texture_path, library=getattr(mat, "original", mat).library)
    if not os.path.isfile(path) and s.texture_file and os.path.isfile(s.texture_file):
        path = s.texture_file  # where the bake wrote it: a linked material made local has lost its library's "//"
    if not os.path.isfile(path):
        return None, f"baked texture missing: {path}", None
    res = tuple(s.texture_size)
    try:
        model = bake_model_key(bake_size(mat), s.bake_refine)
    except UserError as e:
        return None, str(e), None
    signature = _inputs_signature(mat)
    found = _INPUTS.get((signature, res, model))
    if found is None:
        try:
            spatial = bake_inputs.spatial_stack_from_material(mat)
        except ValueError as e:
            return None, str(e), None
        if spatial is None:
            return None, "no layer stack", None
        found = spatial[0], bake_key(spatial[0], res, model)
        _INPUTS[(signature, res, model)] = found
        while len(_INPUTS) > INPUTS_KEPT:
            _INPUTS.popitem(last=False)
    else:
        _INPUTS.move_to_end((signature, res, model))
    spatial, key = found
    if key != s.texture_key:
        return None, "baked texture is out of date: bake again", None
    return path, f"baked: {os.path.basename(path)}", spatial


# The bake inputs of the last few materials the export checked (``current_texture``): their maps read and the key of
# their bake, by what they are read from (``_inputs_signature``). Every export checks every baked material, and the
# viewport exports at every edit: a 4096-pixel map took 0.4-1.2 s to read into a map and hash each time.
INPUTS_KEPT = 8
_INPUTS: OrderedDict = OrderedDict()


def _image_signature(image):
    """What an image's pixels are, without turning them into a map: its identity, size, colour space (and the
    file's working space, which its bytes decode into) and alpha mode, and the CRC-32 of the pixels Blender holds
    (about 0.1-0.2 s for a 4096-pixel map, of the 0.4-1.2 s its reading into a map and hashing takes). The pixels
    themselves, not the file's time: a map file edited outside Blender and checked before Image > Reload was kept
    under the new file's time with the old pixels' key, and after the reload the stale bake still read as current. A
    checksum of every value: a sum and a sample of them missed a painted patch moved elsewhere."""
    n = int(image.size[0]) * int(image.size[1]) * int(image.channels)
    if n == 0:
        return (image.session_uid, 0)
    pixels = np.empty(n, np.float32)
    image.pixels.foreach_get(pixels)
    space = (image.colorspace_settings.name, images.working_space())  # byte pixels decode into the working space
    return (image.session_uid, tuple(image.size), *space, image.alpha_mode, zlib.crc32(pixels))


def _inputs_signature(mat):
    """What ``bake_inputs.spatial_stack_from_material`` reads on ``mat``: its stack and its maps' settings and
    images (``_image_signature``)."""
    stack = stack_io.stack_from_material(mat)
    parts = [stack.to_json() if stack is not None else None]
    for item in mat.neural_layers.layers:
        for pmap in item.maps:
            if pmap.image is None:
                continue
            image = _image_signature(pmap.image)
            parts.append((item.layer_type, item.conductor_mode, pmap.parameter, pmap.low, pmap.high, image))
    return tuple(parts)


# Save As into another folder: a texture path relative to the .blend file ("//textures/...") is made relative to the
# new file, as Blender remaps its own relative paths (images, libraries); its own do not cover this setting, so a
# bake was reported missing after a Save As. A Save Copy keeps the open file where it was: the paths written into
# the copy are remapped, and the open file's put back after the save (``_remapped``).
_remapped: list = []


def _relative_to(path: str, folder: str) -> str:
    """``path`` (absolute) relative to ``folder`` as a "//" path, or as it is where none exists (another drive)."""
    try:
        return bpy.path.relpath(path, start=folder)
    except ValueError:
        return path


@bpy.app.handlers.persistent
def remap_texture_paths(filepath, *_args) -> None:
    """``save_pre``: the materials' "//" texture paths made relative to the file being written, ``filepath``."""
    _remapped.clear()
    old = bpy.data.filepath
    if not old or not filepath or os.path.dirname(os.path.abspath(old)) == os.path.dirname(os.path.abspath(filepath)):
        return
    folder = os.path.dirname(os.path.abspath(filepath))
    for mat in bpy.data.materials:
        path = mat.neural_layers.texture_path if mat.library is None else ""
        if path.startswith("//"):
            _remapped.append((mat, path))
            mat.neural_layers.texture_path = _relative_to(bpy.path.abspath(path), folder)


@bpy.app.handlers.persistent
def restore_texture_paths(filepath, *_args) -> None:
    """``save_post``: after a Save Copy (the open file is still the old one) the texture paths as they were."""
    if _remapped and os.path.abspath(bpy.data.filepath) != os.path.abspath(filepath):
        for mat, path in _remapped:
            mat.neural_layers.texture_path = path
    _remapped.clear()


@bpy.app.handlers.persistent
def rebase_appended_texture_paths(context, *_args) -> None:
    """``blend_import_post``: a material appended from another file keeps its bake. Its "//" texture path was
    relative to that file; Blender rebases its own paths (images) as it appends, not this setting, so the bake read
    as missing when the files' folders differ."""
    for item in context.import_items:
        mat, library = item.id, item.source_library
        if item.id_type != "MATERIAL" or mat is None or mat.library is not None or library is None:
            continue  # linked, not appended: its paths stay its library's (``current_texture``)
        if item.append_action not in ("MAKE_LOCAL", "COPY_LOCAL"):
            continue  # a local material reused, not one brought in
        path = mat.neural_layers.texture_path
        if path.startswith("//"):
            absolute = bpy.path.abspath(path, library=library)
            here = os.path.dirname(os.path.abspath(bpy.data.filepath)) if bpy.data.filepath else None
            mat.neural_layers.texture_path = _relative_to(absolute, here) if here else absolute


_HANDLERS = (
    ("save_pre", remap_texture_paths),
    ("save_post", restore_texture_paths),
    ("blend_import_post", rebase_appended_texture_paths),
)


def register() -> None:
    for name, handler in _HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler not in handlers:
            handlers.append(handler)


def unregister() -> None:
    for name, handler in _HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler in handlers:
            handlers.remove(handler)


def preview_target(mat, stack):
    """``(stack, latent, notes)`` a sidebar preview of ``mat`` (whose sliders give ``stack``) shows: what F12 renders
    of the material. Its stack and its latent; or, where its maps drive it through a current bake, the stack of
    the maps' most common texel (``bake_inputs.representative_stack``) with no latent of its own and a note saying
    so. Maps not baked (or baked for other inputs) are not rendered: F12 renders the sliders' stack, and the note
    says that."""
    if not bake_inputs.has_maps(mat):
        return stack, stack_io.current_latent(mat), []
    if current_texture(mat)[0] is None:
        note = "its maps are not baked (or the bake is out of date): F12 renders the sliders' stack, previewed here"
        return stack, stack_io.current_latent(mat), [note]
    try:
        texel, share = bake_inputs.representative_stack(mat)
    except ValueError as e:  # a map that cannot be read: the sliders' stack, said
        return stack, stack_io.current_latent(mat), [f"previewing the sliders' stack: {e}"]
    note = f"previewing the stack of the most common texel of its maps ({share:.0%} of them): F12 renders the maps"
    return texel, None, [note]

"""Where a material's latent texture is baked to and whether the baked one is current.

Read by the bake operator (``bake_ops``) and by the scene export (``scene_export``), which renders
a material's baked texture only while ``baked_texture_state`` says it is current.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import zlib
from collections import OrderedDict

import bpy
import numpy as np

from ..core.neural.models import ModelFileError, load_models, resolve_size
from ..core.textures import files
from ..core.textures.bake import bake_key, model_key
from . import bake_inputs, images, stack_io
from .operator_base import UserError

DEFAULT_BAKE_FOLDER = "//textures/"


def blend_file_name() -> str:
    """The open .blend file's name ("shot01.blend"; "" while unsaved): what a bake records in its texture's header
    (``nlm:blend``) beside the material's name, so that a bake of another file is told apart from its own."""
    return os.path.basename(bpy.data.filepath)


def bake_folder(mat) -> str:
    """The absolute folder a bake of ``mat`` goes to: its Bake Folder, relative to the .blend file where it is not an
    absolute path ("//textures/" and "textures/" alike: a folder without "//" was resolved against Blender's working
    folder, wherever Blender was started). The default, ``//textures/``, is one folder per .blend file,
    ``//textures/<file name without .blend>/``: files in one folder each have a material "Material", and each file's
    bake overwrote the other's.

    A folder relative to the .blend file needs a saved file; without one it would resolve against the process's
    working folder, so the bake refuses instead.
    """
    chosen = mat.neural_layers.bake_directory or DEFAULT_BAKE_FOLDER
    folder = os.path.expanduser(chosen)
    if not folder.startswith("//") and not os.path.isabs(folder):
        folder = "//" + folder
    if folder.startswith("//") and not bpy.data.filepath:
        raise UserError(
            f"the Bake Folder {chosen!r} is relative to the .blend file, which is not saved: save the file first, "
            "or choose an absolute Bake Folder"
        )
    if folder.rstrip("/\\") == DEFAULT_BAKE_FOLDER.rstrip("/"):
        stem = os.path.splitext(blend_file_name())[0]
        folder = os.path.join(folder, files.safe_file_name(stem))
    return bpy.path.abspath(folder)


def texture_output_path(mat) -> str:
    """Where the bake of ``mat`` goes unless another bake holds that file (``bake_target``): ``<material>.exr`` in its
    Bake Folder (``bake_folder``), named as the bake command names it, so that two different material names never
    share a file ("a/b", "a_b")."""
    return os.path.join(bake_folder(mat), f"{files.safe_file_name(mat.name)}.exr")


# A bake looks this far for a file name of its own (``bake_target``): "Material.exr", "Material (2).exr", ...
FREE_NAMES = 1000


def bake_target(mat) -> tuple[str, str | None]:
    """``(path, note)``: the file a bake of ``mat`` writes, and a line for the user when it is a new one that is not
    the usual one (``texture_output_path``), else None. A file that holds what is not this material's bake is never
    overwritten (``_held_by_other``: another .blend file's or another material's bake, or a file that is not a latent
    texture): the bake takes the first name free or its own of ``<material> (2).exr``, ``(3)``, ... (not ".001", the
    name of a material's copy, whose own bake goes there). Two files in one folder with a material of the same name
    each overwrote the other's bake."""
    usual = texture_output_path(mat)
    stem = usual[: -len(".exr")]
    held = None
    for n in range(1, FREE_NAMES + 1):
        path = usual if n == 1 else f"{stem} ({n}).exr"
        holder = _held_by_other(mat, path)
        if holder is None:
            if n == 1 or _same_file_key(path) == _same_file_key(_rendered_path(mat)):  # its usual file, or its own
                return path, None
            return path, (
                f"{os.path.basename(usual)} holds {held}, which this bake keeps: baked to {os.path.basename(path)}"
            )
        held = held or holder
    raise UserError(
        f"the Bake Folder {os.path.dirname(usual)!r} holds {FREE_NAMES} files named like {os.path.basename(usual)!r}, "
        "none of them this material's bake: choose another Bake Folder"
    )


def _held_by_other(mat, path: str) -> str | None:
    """What the file at ``path`` holds when a bake of ``mat`` must not overwrite it, in words ("the bake of material
    'Material' in shot01.blend"), else None (no file, or this material's own bake). Its own: no other material of
    this file renders it, and its header says this material of this .blend file baked it; a header that names no
    .blend file (a bake in an unsaved file, or by a version that did not record it) where ``mat`` renders that file
    and its header's key is the one ``mat`` recorded."""
    if not os.path.lexists(path):
        return None
    header = _header(path) if os.path.isfile(path) else {}
    if "key" not in header:
        return "a file that is not a latent texture"
    target = _same_file_key(path)
    for other in bpy.data.materials:
        if other != mat and _same_file_key(_rendered_path(other)) == target:
            return f"the bake that material {other.name!r} of this file renders"
    if header.get("blend"):
        own = header["blend"] == blend_file_name() and header.get("material") == mat.name
    else:
        own = _same_file_key(_rendered_path(mat)) == target and header["key"] == mat.neural_layers.texture_key
    return None if own else f"the bake of {_baked_by(header)}"


def _baked_by(header: dict) -> str:
    """Whose bake a texture's header says it holds, in words: "material 'Material' in shot01.blend"."""
    where = f" in {header['blend']}" if header.get("blend") else ""
    return f"material {header.get('material', '?')!r}{where}"


def _rendered_path(mat) -> str:
    """The absolute path of the texture ``mat`` points at ("" for none): its Latent Texture resolved against the
    file that holds the material, or where the bake wrote it when that path leads nowhere (``current_texture``)."""
    s = mat.neural_layers
    if not s.texture_path:
        return ""
    # "//" is relative to the file that holds the material: a linked one's library, not the open file
    path = bpy.path.abspath(s.texture_path, library=getattr(mat, "original", mat).library)
    if not os.path.isfile(path) and s.texture_file and os.path.isfile(s.texture_file):
        path = s.texture_file  # where the bake wrote it: a linked material made local has lost its library's "//"
    return path


def _same_file_key(path: str):
    """A key equal for two paths of the same file (a link, "..", a name that differs in case on Windows)."""
    return os.path.normcase(os.path.realpath(path)) if path else None


def check_bake_folder(folder: str) -> None:
    """Make the bake folder ``folder`` where it is not there and check a file can be written into it, before the
    work, as the bake command checks its ``--out``; ``UserError`` saying what is wrong otherwise (a Bake Folder that
    is a file, or not writable, failed only after the whole bake, with a raw error)."""
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise UserError(f"the Bake Folder {folder!r} is a file, not a folder: choose a folder")
    try:
        os.makedirs(folder, exist_ok=True)
        probe = files.temp_path(os.path.join(folder, "write-test"))  # removed by the next bake if this one is killed
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise UserError(
            f"the Bake Folder {folder!r} cannot be written ({e.strerror or e}): choose a folder you can write to"
        ) from None


def attach_texture(mat, path: str, key: str, resolution) -> None:
    """Point ``mat`` at the texture baked at ``path`` (its bake key ``key``, at ``resolution``: height, width), as
    the sidebar's bake and the bake command's ``--attach`` do: the renderer uses it while it is current
    (``current_texture``). The path is kept relative to the saved .blend file ("//...") where it can be."""
    s = mat.neural_layers
    s.texture_path = _blend_relative(path)
    s.texture_file = os.path.abspath(path)
    s.texture_key = key
    s.texture_size = tuple(resolution)


def _blend_relative(path: str) -> str:
    """``path`` relative to the saved .blend file ("//..."), or as it is where it cannot be: no saved file, or
    another drive than the file's (Windows), where a relative path does not exist."""
    if not bpy.data.filepath:
        return path
    try:
        return bpy.path.relpath(path)
    except ValueError:  # os.path.relpath across drives
        return path


def bake_size(mat) -> str:
    """The decoder size a bake of ``mat`` uses: its model-size setting, "auto" resolved (``neural.resolve_size``)."""
    try:
        return resolve_size(stack_io.model_size(mat))
    except (ValueError, FileNotFoundError) as e:
        raise UserError(str(e)) from None


def bake_model_key(size: str, refine_s: float = 0.0) -> str:
    """The model part of the bake key of a bake with decoder ``size`` and refinement budget ``refine_s``:
    the size, the budget, the shipped decoder file's digest and the albedo calibration's settings, by the rule the
    bake command keys its textures by (``textures.bake.model_key``). Calibrated: the sidebar's bake calibrates its
    texture (``bake_stack``'s default, with ``neural_encoder``'s models), as the bake command does without
    ``--no-calibrate``, so a texture the bake command made of the material is current for it (it was keyed
    uncalibrated here, and no bake of the command ever was)."""
    try:
        return model_key(size, load_models(size).digest, refine_s, calibrated=True)
    except (ValueError, FileNotFoundError, ModelFileError) as e:
        raise UserError(str(e)) from None


def inputs_digest(mat, resolution, model: str) -> str:
    """A short hash of what the key of a bake of ``mat`` at ``resolution`` (height, width) with ``model`` (its
    ``bake_model_key``) covers besides its maps' pixels: its stack, its maps' settings and images
    (``bake_inputs.map_settings``) and the working space they decode into. A bake records it in its texture
    (``inputs``), so it still renders while its maps' images cannot be read and its settings are unchanged
    (``current_texture``). ValueError for maps that do not apply to their layers."""
    stack = stack_io.stack_from_material(mat)
    described = [
        stack.to_json() if stack is not None else None,
        bake_inputs.map_settings(mat),
        images.working_space(),
        [int(n) for n in resolution],
        model,
    ]
    return hashlib.sha256(json.dumps(described).encode()).hexdigest()[:16]


# The headers of the textures the exports checked (``current_texture``): path -> (the file's identity, header). F12
# exports on Blender's render thread, the viewport on the main one.
_HEADERS: OrderedDict = OrderedDict()
_HEADERS_LOCK = threading.Lock()
HEADERS_KEPT = 64


def _header(path: str) -> dict:
    """``texture_header(path)``, read once per version of the file (its inode, size and modification time)."""
    try:
        st = os.stat(path)
    except OSError:
        return {}
    identity = (st.st_ino, st.st_size, st.st_mtime_ns)
    with _HEADERS_LOCK:
        held = _HEADERS.get(path)
        if held is not None and held[0] == identity:
            _HEADERS.move_to_end(path)
            return held[1]
    header = texture_header(path)
    with _HEADERS_LOCK:
        _HEADERS[path] = (identity, header)
        while len(_HEADERS) > HEADERS_KEPT:
            _HEADERS.popitem(last=False)
    return header


def texture_header(path: str) -> dict:
    """The bake's entries in a latent texture's header (``nlm:key`` and the rest: ``LatentTexture.write_exr``), read
    without its texels; empty where the file cannot be opened."""
    from ..core.textures.latent_texture import oiio_module

    inp = oiio_module().ImageInput.open(path)
    if inp is None:
        return {}
    try:
        return {a.name[4:]: str(a.value) for a in inp.spec().extra_attribs if a.name.startswith("nlm:")}
    finally:
        inp.close()


def baked_texture_state(mat) -> tuple[str | None, str]:
    """(path of a current baked texture or None, a line for the user about its state)."""
    path, state, _ = current_texture(mat)
    return path, state


def current_texture(mat):
    """``baked_texture_state`` and the material's spatially varying stack the current texture was baked
    from (``textures.spatial.SpatialStack``, its maps read; None when there is no current texture). A current
    texture with no spatial stack is a bake rendered while its maps' images cannot be read
    (``_bake_of_unreadable_maps``): its state line is a note for the user, saying so."""
    s = mat.neural_layers
    if not s.texture_path:
        return None, "not baked", None
    path = _rendered_path(mat)
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
        except bake_inputs.MapUnreadable as e:
            return _bake_of_unreadable_maps(mat, path, res, model, str(e))
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
    # The file must hold this material's bake: another can sit at its path while the material's key still matches
    # its inputs (a file copied over it, an undo after a second bake, a bake by another program or version)
    header = _header(path)
    if header.get("key", s.texture_key) != s.texture_key:
        return None, f"{path} holds another bake (of {_baked_by(header)}): bake again", None
    return path, f"baked: {os.path.basename(path)}", spatial


def _bake_of_unreadable_maps(mat, path: str, resolution, model: str, why: str):
    """``current_texture`` of a material whose maps' images cannot be read (``why``): its bake, as a Cycles bake
    renders without its sources, where the texture at ``path`` is the material's own (its header's key is the one the
    material recorded) and made of the material as it is now but the maps' pixels (its ``inputs``: an edit of the
    stack, a map's range or image, the model or the resolution makes it stale). Reference mode shades the per-texel
    stacks the maps make, which cannot be read: it shades the constant stack (no spatial stack), and the line says
    so. A texture without ``inputs`` (made before bakes recorded them) cannot be checked: not rendered."""
    header = texture_header(path)
    if header.get("key") != mat.neural_layers.texture_key:
        return None, f"baked texture is out of date ({why}): bake again", None
    if "inputs" not in header:
        return None, f"{why}, and its bake records no settings to check them against: bake again", None
    try:
        current = inputs_digest(mat, resolution, model)
    except ValueError as e:
        return None, str(e), None
    if header["inputs"] != current:
        return None, f"baked texture is out of date ({why}): bake again", None
    note = (
        f"baked: {os.path.basename(path)}; {why}: rendering the bake made from its maps, which cannot be checked "
        "against them (reference mode shades its constant stack)"
    )
    return path, note, None


# The bake inputs of the last few materials the export checked (``current_texture``): their maps read and the key of
# their bake, by what they are read from (``_inputs_signature``). Every export checks every baked material, and the
# viewport exports at every edit: a 4096-pixel map took 0.4-1.2 s to read into a map and hash each time.
INPUTS_KEPT = 8
_INPUTS: OrderedDict = OrderedDict()


def _image_signature(image):
    """What a map's pixels are read from (``bake_inputs.map_pixels``), without turning them into a map: its
    identity, colour space (and the file's working space, which it decodes into) and alpha mode, and for an image
    read from its file (``images.pixels_file``) that file's path and identity (inode, size, modification time: a
    file saved again elsewhere is read again, before any Image > Reload, as the bake would read it), else the size
    and CRC-32 of the pixels Blender holds (about 0.1-0.2 s for a 4096-pixel map, of the 0.4-1.2 s its reading into
    a map and hashing takes; a checksum of every value: a sum and a sample of them missed a painted patch moved
    elsewhere)."""
    space = (image.colorspace_settings.name, images.working_space(), image.alpha_mode)
    path = images.pixels_file(image)
    if path is not None:
        try:
            st = os.stat(path)
            return (image.session_uid, *space, path, st.st_ino, st.st_size, st.st_mtime_ns)
        except OSError:
            pass  # gone since: Blender's pixels, as the map is read
    n = int(image.size[0]) * int(image.size[1]) * int(image.channels)
    if n == 0:
        return (image.session_uid, 0)
    pixels = np.empty(n, np.float32)
    image.pixels.foreach_get(pixels)
    return (image.session_uid, *space, tuple(image.size), zlib.crc32(pixels))


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

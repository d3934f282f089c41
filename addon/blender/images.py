"""Images in ``bpy.data.images``: pixels read as Cycles sees them, previews stored and shown.

``linear_pixels`` is the one way the add-on reads an image that feeds a material (base-colour
textures, environment images, parameter maps): byte images are decoded from their Color Space to
scene linear (the file's Working Color Space) with Blender's own OpenColorIO configuration, as
Cycles does (an sRGB byte 128 reads 0.216, the same byte in a Non-Color image reads 0.502); float
images are stored in scene linear already, and data (Non-Color) images are not transformed.
"""

from __future__ import annotations

import functools
import os
import re

import bpy
import numpy as np


def store_image(name: str, rgba: np.ndarray, metadata: dict | None = None):
    """Write an (H, W, 4) float image (rows top to bottom, colour premultiplied by alpha) into
    ``bpy.data.images[name]``.

    The image is float, linear, reused (and resized) if it exists, and kept by the file (a fake user).
    ``metadata`` goes into the image's custom properties (e.g. the timings of a comparison).
    """
    rgba = np.asarray(rgba, dtype=np.float32)
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise ValueError(f"preview image must be (H, W, 4), got {rgba.shape}")
    h, w = rgba.shape[:2]
    image = bpy.data.images.get(name)
    # A preview of ours is a generated float image, or one the file packed (``pack_previews``): written again, at
    # its size. One of another size is made anew: scaled, its buffer went back to the generated (or packed) size as
    # soon as its colour space was set, and the pixels did not fit (a Lobe Size changed from 24 to 16 failed).
    if image is not None and (
        not image.is_float
        or (image.source != "GENERATED" and not image.get(PREVIEW_KEY))
        or tuple(image.size) != (w, h)
    ):
        bpy.data.images.remove(image)
        image = None
    if image is None:
        image = bpy.data.images.new(name, width=w, height=h, alpha=True, float_buffer=True)
    image.colorspace_settings.name = "Linear Rec.709"
    # premultiplied, as Blender's float buffers and render results are (``Film.rgba``): marked Straight, the packed
    # EXR of a transparent film's preview came back from a save with its colour multiplied by its alpha again
    image.alpha_mode = "PREMUL"
    # Blender stores rows bottom to top
    image.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    image.update()
    for key, value in (metadata or {}).items():
        image[key] = value
    image[PREVIEW_KEY] = 1
    # kept by the file whether or not an Image Editor shows it: the sidebar's previews that no editor showed had no
    # user and were dropped at the second save and reload
    image.use_fake_user = True
    set_preview(image, rgba)
    return image


PREVIEW_KEY = "nlm_preview"  # marks the images ``store_image`` writes


@bpy.app.handlers.persistent
def pack_previews(*_args) -> None:
    """``save_pre``: the previews' pixels packed into the file (as OpenEXR, float). A generated image keeps no
    pixels in a .blend: a preview shown in the Image Editor came back black after a reload. The EXR is
    premultiplied, as the previews' pixels are (``store_image``)."""
    for image in bpy.data.images:
        if image.get(PREVIEW_KEY) and image.library is None and (image.is_dirty or image.packed_file is None):
            image.file_format = "OPEN_EXR"
            image.pack()


def register() -> None:
    if pack_previews not in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.append(pack_previews)


def unregister() -> None:
    if pack_previews in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(pack_previews)


PREVIEW_SIDE = 256  # largest side of the picture shown in the sidebar


def set_preview(image, rgba: np.ndarray) -> None:
    """Give ``image`` the picture the sidebar shows (``image.preview``, drawn by ``template_icon``):
    ``rgba`` (rows top to bottom, linear) subsampled to at most ``PREVIEW_SIDE`` and encoded for
    display (sRGB), so it is there at once, without waiting for Blender to render previews."""
    from ..core.render.film import to_srgb

    h, w = rgba.shape[:2]
    step = max(1, -(-max(h, w) // PREVIEW_SIDE))
    small = np.asarray(rgba, dtype=np.float32)[::step, ::step]
    shown = np.empty_like(small)
    shown[..., :3] = to_srgb(small[..., :3])
    shown[..., 3] = np.clip(small[..., 3], 0.0, 1.0)
    preview = image.preview_ensure()
    preview.image_size = (small.shape[1], small.shape[0])
    preview.image_pixels_float.foreach_set(np.ascontiguousarray(shown[::-1]).ravel())


def read_pixels(image) -> np.ndarray | None:
    """The raw (H, W, 4) float pixels of ``image``, row 0 at the top, or None if it has none
    (e.g. a missing file). Raw: byte images give their stored values / 255, no colour transform
    (what feeds a material is read through :func:`linear_pixels`)."""
    if image is None:
        return None
    try:
        w, h = image.size
        has = image.has_data or (w > 0 and h > 0)
    except (ReferenceError, RuntimeError):
        has, w, h = False, 0, 0
    if not has or w == 0 or h == 0:
        return None
    px = np.empty(w * h * 4, dtype=np.float32)
    image.pixels.foreach_get(px)
    return np.ascontiguousarray(px.reshape(h, w, 4)[::-1])


@functools.lru_cache(maxsize=None)
def _to_scene_linear(colorspace: str, working_space: str):
    """OpenColorIO CPU processor from ``colorspace`` to the file's scene linear: its Working Color Space (Blender
    5's ``bpy.data.colorspace.working_space``; the configuration's scene-linear role, Rec.709, where it is empty).
    The configuration's role stays Rec.709 whatever the file's space, where Cycles decodes into the file's."""
    import PyOpenColorIO as ocio  # bundled with Blender (bpy.utils.expose_bundled_modules)

    path = os.path.join(bpy.utils.system_resource("DATAFILES", path="colormanagement"), "config.ocio")
    config = ocio.Config.CreateFromFile(path)
    return config.getProcessor(colorspace, working_space or ocio.ROLE_SCENE_LINEAR).getDefaultCPUProcessor()


def working_space() -> str:
    """The open file's Working Color Space, "" where Blender has none (before 5.0)."""
    return getattr(getattr(bpy.data, "colorspace", None), "working_space", "") or ""


def linear_pixels(image, associate_alpha: bool = False) -> np.ndarray | None:
    """(H, W, 4) scene-linear float pixels of ``image``, row 0 at the top, decoded by its Color
    Space as Cycles does; None if it has no pixels. Alpha is left as stored. A UDIM image of several tiles is
    refused (ValueError): Blender gives its first tile's pixels alone, which would cover the whole uv square.

    ``associate_alpha``: the colour Cycles' Image Texture node gives where its Alpha output is unused. A byte
    image's colour is multiplied by its alpha *before* it is decoded (Straight or Premultiplied: Blender gives
    both straight); a float image's pixels are stored premultiplied already, and a data (Non-Color) image's, or
    one whose alpha is packed data or none, are not multiplied (measured against Cycles: a byte sRGB texel of alpha
    0.25 read 4.9 / 3.8 / 2.5 times too bright unmultiplied; a float one 0.25 times as bright multiplied)."""
    if image.source == "TILED" and len(image.tiles) > 1:
        raise ValueError(
            f"image {image.name!r} is a UDIM image of {len(image.tiles)} tiles, which this add-on cannot read: "
            "use a single image (one tile) for it"
        )
    return _decoded(image, read_pixels(image), image.is_float, associate_alpha)


def _decoded(image, px: np.ndarray | None, is_float: bool, associate_alpha: bool) -> np.ndarray | None:
    """``linear_pixels``' decoding of ``px`` (H, W, 4), the pixels Blender would hold for ``image``: a float
    buffer's (``is_float``: scene linear, premultiplied) as they are, a byte buffer's (stored values / 255) by the
    image's Color Space."""
    if px is None or is_float or image.colorspace_settings.is_data:
        return px
    rgb = np.ascontiguousarray(px[..., :3])
    if associate_alpha and image.alpha_mode in ("STRAIGHT", "PREMUL"):
        rgb *= px[..., 3:4]
    px[..., :3] = _to_working_space(image, rgb)
    return px


# OpenColorIO's CPU processors raise to powers by a fast approximation (its OPTIMIZATION_FAST_LOG_EXP_POW), off by up
# to 2.6e-5 on [0, 1] (measured on the sRGB curve): sRGB white decoded to 1.000024, outside an albedo's valid range,
# so an albedo map with a white texel could not be baked. A decoded value this close outside [0, 1] is put on its end,
# where the exact curve (Cycles' decoding) puts it (OpenColorIO's exact processor took twice the time: 0.42 s against
# 0.22 s for 2048 x 2048 texels). Far below a half float's step at 1 (1/1024): a value a file holds outside [0, 1]
# stays outside, and is refused where a parameter cannot take it.
DECODE_TOLERANCE = 5e-5


def _to_working_space(image, rgb: np.ndarray) -> np.ndarray:
    """``rgb`` (H, W, 3) float32, C-contiguous, decoded in place from ``image``'s Color Space to the file's
    working space; values within :data:`DECODE_TOLERANCE` outside [0, 1] put on its ends."""
    try:
        _to_scene_linear(image.colorspace_settings.name, working_space()).applyRGB(rgb)
    except Exception as e:  # an OpenColorIO failure: say which image and space
        raise ValueError(
            f"image {image.name!r}: cannot decode its colour space {image.colorspace_settings.name!r} to linear ({e})"
        ) from None
    np.copyto(rgb, 1.0, where=(rgb > 1.0) & (rgb <= 1.0 + DECODE_TOLERANCE))
    np.copyto(rgb, 0.0, where=(rgb < 0.0) & (rgb >= -DECODE_TOLERANCE))
    return rgb


def sequence_frame(image_user, frame: int) -> int:
    """The frame of an image sequence an Image Texture node shows at the scene's ``frame``: its Image User's Start
    Frame, Offset, Frames (its length) and Cyclic, as Blender counts them (``BKE_image_user_frame_get``)."""
    length = int(image_user.frame_duration)
    if length == 0:
        return 0
    n = int(frame) - int(image_user.frame_start) + 1
    if image_user.use_cyclic:
        n %= length
        n = n or length
    return min(max(n, 0), length) + int(image_user.frame_offset)


def file_path(image) -> str:
    """The absolute path of an image's file (relative to its .blend, or to its library's)."""
    return bpy.path.abspath(image.filepath, library=image.library)


def frame_path(image, number: int) -> str:
    """The absolute path of frame ``number`` of an image sequence: the last run of digits in its file's name, less
    its extension, replaced by the number, at least as many digits (Blender's ``BLI_path_sequence_encode``: a
    JPEG 2000 sequence's ".jp2" is not its frame)."""
    path = file_path(image)
    folder, name = os.path.split(path)
    stem, ext = os.path.splitext(name)
    match = re.search(r"(\d+)(?!.*\d)", stem)
    if match is None:
        return path
    digits = match.group(1)
    number = max(0, int(number))  # Blender writes no negative frame: 0 for a frame before the first
    return os.path.join(folder, stem[: match.start()] + str(number).zfill(len(digits)) + stem[match.end() :] + ext)


def sequence_pixels(image, image_user, frame: int, associate_alpha: bool = False) -> tuple[np.ndarray | None, str]:
    """``file_pixels`` of the frame of an image sequence its Image User shows at the scene's ``frame`` (Blender holds
    the pixels of the frame it last showed, not the frame rendered), and that frame's path."""
    path = frame_path(image, sequence_frame(image_user, frame))
    return file_pixels(image, path, associate_alpha), path


def pixels_file(image) -> str | None:
    """The absolute path of the file whose pixels ``image`` holds, where they are its file's; None for an image whose
    pixels are not (generated, packed, painted and not saved, a movie, tiles, a sequence), or not its file's first
    image (a multilayer OpenEXR's layer and pass, a view of a multi-view image), or whose file is not there. Such an
    image is read from its file (``file_pixels``), as Cycles reads it: Blender's own buffer is stale after an edit
    elsewhere until Image > Reload, and Blender's float buffer of a 16-bit PNG is premultiplied. The one rule for
    image textures (the scene export's ``_image_file_key``) and parameter maps."""
    if image.source != "FILE" or image.packed_file is not None or image.is_dirty:
        return None
    if image.type == "MULTILAYER" or getattr(image, "use_multiview", False):
        return None
    try:
        path = file_path(image)
    except ValueError:
        return None
    return path if os.path.isfile(path) else None


def file_pixels(image, path: str, associate_alpha: bool = False, straight: bool = False) -> np.ndarray | None:
    """``linear_pixels`` of ``image`` (its colour space and alpha mode) as read from the file at ``path``, as Cycles
    reads an image's file; None where the file cannot be read whole. An 8-bit file is a byte image, as Blender
    loads it: its colour as stored, straight (OpenImageIO's own reading multiplies it by its alpha); any other is a
    float one, premultiplied: its colour multiplied by its alpha and then decoded to scene linear, as Cycles reads
    it (an OpenEXR's pixels are premultiplied already; Blender's own float buffer of a 16-bit PNG decodes first,
    and read so, a texel of alpha 0.5 rendered 1.4-2.3x Cycles').

    ``straight``: the colour apart from its alpha whatever the file's bit depth, decoded to scene linear by its
    colour space: what a parameter map's values are, as the bake command reads its images (an albedo map of alpha
    0.5 drove half its albedo from a 16-bit PNG and all of it from an 8-bit one). The colour as the file stores it,
    but where the image says its colour is premultiplied (Alpha: Premultiplied, a colour image, not an OpenEXR):
    divided by its alpha there, as Blender loads such a byte image (a Non-Color one it leaves as stored)."""
    from ..core.textures.latent_texture import oiio_module

    oiio = oiio_module()
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    buf = oiio.ImageBuf(path, 0, 0, config)
    if buf.has_error or buf.spec().nchannels < 1:
        buf.geterror()  # taken: OpenImageIO prints an error never asked for when the buffer goes
        return None
    spec = buf.spec()
    px = buf.get_pixels(oiio.FLOAT)
    if buf.has_error or px is None:  # a file cut short: what was read is not the image
        buf.geterror()
        return None
    px = np.asarray(px, dtype=np.float32).reshape(spec.height, spec.width, -1)
    c = px.shape[2]
    rgba = np.ones(px.shape[:2] + (4,), np.float32)
    rgba[..., :3] = px[..., :3] if c >= 3 else px[..., :1]
    if c in (2, 4):
        rgba[..., 3] = px[..., c - 1]
    is_float = spec.format != oiio.UINT8
    if straight:
        if image.alpha_mode == "PREMUL" and not image.colorspace_settings.is_data and not path.lower().endswith(".exr"):
            alpha = rgba[..., 3:4]
            np.divide(rgba[..., :3], alpha, out=rgba[..., :3], where=alpha > 0.0)
        if not image.colorspace_settings.is_data:
            rgba[..., :3] = _to_working_space(image, np.ascontiguousarray(rgba[..., :3]))
        return rgba
    if is_float and not image.colorspace_settings.is_data:
        if not path.lower().endswith(".exr") and image.alpha_mode in ("STRAIGHT", "PREMUL"):
            rgba[..., :3] *= rgba[..., 3:4]  # premultiplied as it is stored, then decoded: as Cycles reads the file
        rgba[..., :3] = _to_working_space(image, np.ascontiguousarray(rgba[..., :3]))
    return _decoded(image, rgba, is_float, associate_alpha)


def _largest(areas):
    return max(areas, key=lambda a: a.width * a.height, default=None)


def show_in_image_editor(context, image):
    """Show ``image`` in an Image Editor; return the area or None.

    Uses an existing Image Editor (the current window's first, then any other window's).
    Otherwise, in the UI, opens a new window for it (as F12 renders do). In background mode
    there is no one to show it to: the image stays in ``bpy.data.images`` and no area of the
    file's screens is changed (turning the 3D viewport into an Image Editor would be saved with it).
    """
    windows = list(context.window_manager.windows)
    window = context.window or (windows[0] if windows else None)
    if window is None:
        return None
    ordered = [window] + [w for w in windows if w != window]
    areas = [a for w in ordered for a in w.screen.areas if a.type == "IMAGE_EDITOR"]
    if not areas:
        if bpy.app.background:
            return None
        try:
            with context.temp_override(window=window):
                bpy.ops.wm.window_new()
            window = context.window_manager.windows[-1]
            area = _largest(window.screen.areas)
            area.type = "IMAGE_EDITOR"
            areas = [area]
        except RuntimeError:
            return None
    area = areas[0]
    area.spaces.active.image = image
    area.tag_redraw()
    return area

"""Evaluated depsgraph -> ``addon.core.render.Scene`` (plain arrays; the core renders without bpy).

Only what renders: object instances of the evaluated depsgraph (modifiers applied, instances
expanded) that are not hidden from renders; triangles in world space with Blender's corner
normals (smooth, flat, auto-smooth and custom normals as Blender shades them) and the active UV
map; one material per triangle. Lights (point, spot, sun, area), the world (colour or
equirectangular environment image through a Background node) and the camera.

Materials with a layer stack (``stack_io.stack_from_material``) become ``LayeredSpec``; a Principled BSDF with
constant Metallic, Roughness, IOR and Specular IOR Level renders its specular layer over its base colour and its
metal (``PrincipledMaterial``); all others render as a Lambertian with their base colour (Principled "Base Color",
or the colour of a Diffuse BSDF, or the viewport colour); either is textured when an Image Texture node drives its
base colour. Problems (missing images, invalid stacks, unsupported camera types) become warnings, never failures.
"""

from __future__ import annotations

import contextvars
import math
import os
import threading
from types import SimpleNamespace

import numpy as np

from ..core.render import (
    AreaLight,
    Camera,
    Environment,
    ImageTexture,
    LambertMaterial,
    LayeredSpec,
    Mesh,
    PointLight,
    PrincipledMaterial,
    Scene,
    SpotLight,
    SunLight,
)
from . import images

GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES"}
VIEWPORT_SENSOR = 72.0  # mm: the 3D viewport's lens maps to this sensor width
DEFAULT_LENS = 50.0  # mm on a 36 mm sensor: Blender's lens for a scene camera that is an empty


def render_size(scene) -> tuple[int, int]:
    """The render's size in pixels, as Blender computes it: in integers (in floating point, 1280 at 70% was 895)."""
    r = scene.render
    pct = r.resolution_percentage
    return max(1, r.resolution_x * pct // 100), max(1, r.resolution_y * pct // 100)


# The scene frame an export renders (``export_scene``): the frame of an image sequence its nodes show.
_FRAME: contextvars.ContextVar[int | None] = contextvars.ContextVar("frame", default=None)


# What Cycles renders for an Image or Environment Texture node without an image, or whose image has no pixels (a
# missing file): magenta (its TEX_IMAGE_MISSING colour), which an artist knows to look for
MISSING_IMAGE_COLOUR = (1.0, 0.0, 1.0)
MISSING_IMAGE = "rendered magenta, as Cycles renders a missing image"


def _image_pixels(image, warnings: list[str], associate_alpha: bool = False, node=None) -> np.ndarray | None:
    """(H, W, 4) scene-linear float pixels, row 0 at the top (``images.linear_pixels``); None (with a warning) if
    unavailable. An image sequence gives the frame its ``node``'s Image User shows at the exported frame
    (``images.sequence_pixels``); a movie, the frame Blender holds, with a warning."""
    if image is None:
        return None
    user = getattr(node, "image_user", None)
    try:
        if image.source == "SEQUENCE" and user is not None:
            frame = _FRAME.get()
            px, path = images.sequence_pixels(
                image, user, user.frame_current if frame is None else frame, associate_alpha
            )
            if px is None:
                warnings.append(f"image {image.name!r}: its frame's file {path!r} cannot be read; {MISSING_IMAGE}")
                return None
            return np.ascontiguousarray(px, dtype=np.float32)
        key = _image_file_key(image, associate_alpha)
        with _LOCK:
            held = _IMAGES.get(key) if key is not None else None
            if held is not None:
                _IMAGES_USED.add(key)
                return held[0]
        # an image whose pixels are its file's is read from its file, as Cycles reads it, and kept by the file's
        # identity: Blender's own buffer is stale after an edit elsewhere until Image > Reload, and kept under the
        # new file's key it was served after the reload too; Blender's float buffer of a 16-bit PNG is decoded
        # before it is premultiplied, where Cycles' is premultiplied first
        px = images.file_pixels(image, key[0], associate_alpha) if key is not None else None
        if px is None:
            key = None  # a file OpenImageIO cannot read: Blender's pixels, read at every export
            px = images.linear_pixels(image, associate_alpha)
    except ValueError as e:
        warnings.append(f"{e}; {MISSING_IMAGE}")
        return None
    if px is None:
        warnings.append(f"image {image.name!r} has no pixels (missing file {image.filepath!r}?); {MISSING_IMAGE}")
        return None
    if key is not None:
        px = np.ascontiguousarray(px, dtype=np.float32)
        px.setflags(write=False)  # shared by the exports that find it
        with _LOCK:
            _IMAGES[key] = (px, {})  # the pixels, and the textures made of them (``_image_texture``)
            _IMAGES_USED.add(key)
    if image.source == "MOVIE":
        warnings.append(
            f"image {image.name!r} is a movie, whose frames this renderer does not read: every frame renders the one "
            "Blender last showed (render the movie to an image sequence to animate it)"
        )
    return np.ascontiguousarray(px, dtype=np.float32)


# Images read, as the pixels the materials take (``_image_pixels``) and the textures made of them (``_image_texture``),
# by ``_image_file_key``: the viewport exports the scene again at every edit, and reading, decoding and filtering a 4K
# texture took 1.4-1.8 s of each.
_IMAGES: dict[tuple, tuple[np.ndarray, dict]] = {}
_IMAGES_USED: set[tuple] = set()  # the keys this export read or reused (export_scene keeps only those)


def _image_file_key(image, associate_alpha: bool):
    """What an image's pixels are, where they are its file's: its file's path (first) and identity (inode, size,
    modification time: an edit outside Blender gives another), its size, colour space, alpha mode and the working
    space it decodes into. None for an image whose pixels are not its file's (generated, packed, painted and not
    saved, a movie, tiles), or not its file's first image (a multilayer OpenEXR's layer and pass, a view of a
    multi-view image, which the node chooses), which is read from Blender at every export. A file rewritten with
    its inode, size and modification time kept is not told from the one before."""
    path = images.pixels_file(image)
    try:
        st = os.stat(path) if path is not None else None
    except OSError:
        return None
    if st is None:
        return None
    return (
        path, st.st_ino, st.st_size, st.st_mtime_ns, tuple(image.size), image.colorspace_settings.name,
        image.alpha_mode, images.working_space(), associate_alpha,
    )  # fmt: skip


def _image_texture(image, px: np.ndarray, associate_alpha: bool, uv_map, extension: str) -> ImageTexture:
    """``ImageTexture(px, uv_map, extension)``, made once for each version of ``image``'s file (``_IMAGES``)."""
    key = _image_file_key(image, associate_alpha)
    with _LOCK:
        held = _IMAGES.get(key) if key is not None else None
    if held is None or held[0] is not px:  # pixels not kept, or read again since
        return ImageTexture(px[:, :, :3], uv_map, extension)
    texture_key = (None if uv_map is None else np.asarray(uv_map, np.float64).tobytes(), extension)
    with _LOCK:
        texture = held[1].get(texture_key)
    if texture is None:
        texture = ImageTexture(px[:, :, :3], uv_map, extension)
        with _LOCK:
            held[1][texture_key] = texture
    return texture


def _source(socket):
    """The output socket whose value reaches the input ``socket``, as Cycles follows the links: past muted, invalid
    and unavailable links (as if absent), through Reroute nodes and muted nodes (Blender's muting: each output passes
    on the input its internal link names; a muted BSDF, Emission or Image Texture names none and passes nothing).
    None where nothing reaches it: the socket keeps its own value (Cycles gives it that too where the chain ends at
    an unlinked input of a Reroute or muted node: a muted Mix node's A colour was not rendered, Base Color was)."""
    for _ in range(256):  # a chain of reroutes and muted nodes, never a loop
        if socket is None or not socket.is_linked:
            return None
        link = next((lk for lk in socket.links if _live(lk)), None)
        if link is None:
            return None
        node, out = link.from_node, link.from_socket
        if node.type != "REROUTE" and not node.mute:
            return out
        socket = next((il.from_socket for il in node.internal_links if il.to_socket.identifier == out.identifier), None)
    return None


def _live(link) -> bool:
    """Whether Cycles follows a link: not muted, valid (no loop, no type it refuses) and between available sockets."""
    return (
        not getattr(link, "is_muted", False)
        and getattr(link, "is_valid", True)
        and getattr(link.from_socket, "enabled", True)
        and getattr(link.to_socket, "enabled", True)
    )


def _linked_image(socket):
    """The image of an Image/Environment Texture node feeding ``socket`` (through reroutes, ``_source``), False for
    such a node without an image, else None."""
    source = _source(socket)
    if source is not None and source.node.type in ("TEX_IMAGE", "TEX_ENVIRONMENT"):
        return source.node.image if source.node.image is not None else False
    return None


def _constant_colour(socket) -> tuple | None:
    """The colour an input ``socket`` renders with where it is constant: its own value, or a Color (RGB) or Value
    node's feeding it (a value as grey, as Cycles converts it); None where a node computes it."""
    source = _source(socket)
    if source is None:
        return tuple(socket.default_value[:3])
    if source.node.type == "RGB":
        return tuple(source.default_value[:3])
    if source.node.type == "VALUE":
        return (float(source.default_value),) * 3
    return None


def _output_node(tree):
    """The output node Cycles renders ``tree`` with (material or world), or None: Blender's own choice for Cycles
    (``ShaderNodeTree.get_output_node('CYCLES')``, which Cycles itself calls): an output targeted at Cycles, else one
    targeted at All, the active one among several; never one targeted at EEVEE alone."""
    return tree.get_output_node("CYCLES")


def _node_title(node) -> str:
    """A node as its header names it: its label, a group node's node group, else its kind (``bl_label``: "Glossy
    BSDF", "Color Ramp")."""
    if node.label:
        return node.label
    if node.type == "GROUP" and getattr(node, "node_tree", None) is not None:
        return node.node_tree.name
    return node.bl_label


def _a_node(node) -> str:
    """A node as a warning names it: "a Glossy BSDF node", "an Emission node", and with its own name where its
    header shows one (a label, a node group's): "a Group node 'Wood'"."""
    kind = node.bl_label
    title = _node_title(node)
    return f"{_article(kind)} {kind} node" + (f" {title!r}" if title != kind else "")


def _article(word: str) -> str:
    """ "a" or "an" before ``word``, as it is said ("an Emission", "a UV Map")."""
    vowel = word[:1].upper() in "AEIOU" and not word.upper().startswith(("UV", "UNI", "USE", "EU", "ONE"))
    return "an" if vowel else "a"


def _listed(names: list[str]) -> str:
    """ "A", "A and B", "A, B and C"."""
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


SURFACE_NODES = ("BSDF_PRINCIPLED", "BSDF_DIFFUSE")  # the surface nodes an unmanaged material is read from
# Principled BSDF inputs a Lambertian of its base colour leaves out, with the value at which they do nothing.
_PRINCIPLED_DROPPED = (
    ("Metallic", 0.0), ("Transmission Weight", 0.0), ("Coat Weight", 0.0), ("Subsurface Weight", 0.0),
    ("Sheen Weight", 0.0), ("Emission Strength", 0.0), ("Alpha", 1.0), ("Diffuse Roughness", 0.0),
    ("Anisotropic", 0.0), ("Thin Film Thickness", 0.0),
)  # fmt: skip
# The inputs of a Principled BSDF's dielectric specular layer, which the Lambertian leaves out (``_specular_note``).
_SPECULAR_INPUTS = ("Specular IOR Level", "IOR", "Roughness", "Specular Tint")
# The Principled BSDF inputs ``PrincipledMaterial`` renders when each is a constant (``_principled_layers``).
_LAYER_INPUTS = ("Metallic", "Roughness", "IOR", "Specular IOR Level")
# the share of Cycles' reflected light whose absence a warning names: a Lambertian Principled BSDF's (one of its
# ``_LAYER_INPUTS`` linked) missing specular layer (``_specular_note``)
SPECULAR_NOTICEABLE = 0.05
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec.709's, the core's colour space


def _surface_node(mat):
    """The node on the Surface of the output Cycles renders (``_output_node``), through Reroute and muted nodes
    (``_source``), or None when nothing reaches it (or there is no output): Cycles renders such a material black."""
    tree = getattr(mat, "node_tree", None)
    if tree is None:
        return None
    out = _output_node(tree)
    source = _source(out.inputs["Surface"]) if out is not None else None
    return source.node if source is not None else None


def _dropped_inputs(node, rendered: tuple[str, ...] = ()) -> list[str]:
    """The inputs of a Principled or Diffuse BSDF that change Cycles' image and that a Lambertian of its colour
    leaves out: set away from their neutral value, or linked (the specular layer: ``_specular_note``); those named
    in ``rendered`` are rendered (a ``PrincipledMaterial``'s Metallic)."""
    if node.type == "BSDF_DIFFUSE":
        rough = node.inputs.get("Roughness")
        linked = rough is not None and _source(rough) is not None
        return ["Roughness"] if rough is not None and (linked or rough.default_value > 0.0) else []
    dropped = []
    for name, neutral in _PRINCIPLED_DROPPED:
        socket = node.inputs.get(name)
        if socket is None or name in rendered:
            continue
        linked = _source(socket) is not None
        if linked or abs(float(socket.default_value) - neutral) > 1e-6:
            colour = node.inputs.get("Emission Color")
            if (
                name == "Emission Strength"
                and not linked
                and colour is not None
                and _source(colour) is None
                and not any(colour.default_value[:3])
            ):
                continue  # a strength of a black emission: nothing emitted
            dropped.append(name.removesuffix(" Weight").removesuffix(" Strength").removesuffix(" Thickness"))
    return dropped


def specular_albedo(ior: float, level: float, tint) -> float:
    """About the share of light a Principled BSDF's dielectric specular layer reflects (its albedo, as luminance),
    by Cycles' rule for it (``svm_node_closure_bsdf``, Principled: "Apply IOR adjustment" and "Specular
    component"): Specular IOR Level sets the layer's index (``core.bsdf.specular_ior``: it scales the
    normal-incidence reflectance F0 = ((n - 1) / (n + 1))^2 by 2 x level); Specular Tint tints F0, the Fresnel
    curve rising from it to 1 at grazing (a generalized Schlick on the exact curve: F0t + (1 - F0t) (F - F0) /
    (1 - F0), averaged here)."""
    from ..core.bsdf.specular_diffuse import fresnel_dielectric_average, specular_ior

    if float(level) <= 0.0:
        return 0.0
    eta = specular_ior(ior, level)
    f0 = ((eta - 1.0) / (eta + 1.0)) ** 2
    if f0 >= 0.999:
        return 1.0
    tinted = f0 * float(np.clip(np.asarray(tint[:3], dtype=np.float64), 0.0, None) @ _LUMINANCE)
    return tinted + (1.0 - tinted) * (float(fresnel_dielectric_average(eta)) - f0) / (1.0 - f0)


def specular_share(albedo: float, base: float) -> float:
    """The share of the light Cycles' Principled BSDF reflects that a Lambertian of its base colour (luminance
    ``base``) leaves out, with a specular layer of albedo E (``specular_albedo``) over it. Cycles weights the layer
    under a specular one by 1 - E (``closure_layering_weight``; the albedo-scaling layering of Kulla and Conty,
    "Revisiting Physically Based Shading at Imageworks", SIGGRAPH 2017), so the surface reflects about
    E + (1 - E) b where the Lambertian reflects b: E (1 - b) / (b + E (1 - b)) of it is left out. An average over
    directions: under one light, away from its highlight, less is."""
    base = min(max(base, 0.0), 1.0)
    missing = albedo * (1.0 - base)
    return missing / (base + missing) if base + missing > 0.0 else 0.0


def _specular_note(node, base: float) -> str | None:
    """What a Principled BSDF's specular layer (``_SPECULAR_INPUTS``) changes in Cycles' image that its
    Lambertian leaves out (the surface is one where an input of ``_LAYER_INPUTS`` is linked: ``_principled_layers``),
    or None where that is little: linked inputs, or a layer that reflects more than SPECULAR_NOTICEABLE of the light
    (``specular_share``) over a base colour of luminance ``base`` (a pale base, the default 0.8: 2%, within 1.5% of
    Cycles' image; a black one reflects only its specular layer)."""
    inputs = {name: node.inputs.get(name) for name in _SPECULAR_INPUTS}
    if any(s is None for s in inputs.values()):
        return None
    level = inputs["Specular IOR Level"]
    if _source(level) is None and level.default_value <= 0.0:
        return None  # no specular layer at all
    linked = [name for name, s in inputs.items() if _source(s) is not None]
    if linked:
        return (
            f"its specular reflection is left out (its {_listed(linked)} {'is' if len(linked) == 1 else 'are'} linked)"
        )
    ior, tint = inputs["IOR"].default_value, inputs["Specular Tint"].default_value
    share = specular_share(specular_albedo(ior, level.default_value, tint), base)
    if share <= SPECULAR_NOTICEABLE:
        return None
    return (
        f"its specular reflection is left out (IOR {ior:.3g}, Specular IOR Level {level.default_value:.3g}: about "
        f"{share:.0%} of the light Cycles' surface reflects)"
    )


def _principled_layers(node) -> dict | None:
    """The constant Metallic, Roughness, IOR and Specular IOR Level of a Principled BSDF, as ``PrincipledMaterial``'s
    arguments, or None where one of them is linked (then the surface renders as a Lambertian of its base colour,
    and ``_specular_note`` and ``_dropped_inputs`` name what that leaves out)."""
    sockets = [node.inputs.get(name) for name in _LAYER_INPUTS]
    if any(s is None or _source(s) is not None for s in sockets):
        return None
    metallic, roughness, ior, level = (float(s.default_value) for s in sockets)
    return {"metallic": metallic, "roughness": roughness, "ior": ior, "specular_level": level}


def _tint_note(node, layers: dict) -> str | None:
    """A Specular Tint away from white on a rendered specular layer or metal, which ``PrincipledMaterial`` leaves
    out (Cycles tints the layer's normal-incidence reflectance and the metal's edge with it)."""
    tint = node.inputs.get("Specular Tint")
    if tint is None or (layers["specular_level"] <= 0.0 and layers["metallic"] <= 0.0):
        return None
    if _source(tint) is not None:
        return "its Specular Tint is left out (it is linked)"
    if np.allclose(tint.default_value[:3], 1.0, atol=1e-6):
        return None
    return "its Specular Tint is left out (an untinted specular reflection)"


def _layer_notes(node, layers: dict | None, base: float) -> list[str]:
    """What a surface node's layers above its base colour (of luminance ``base``) change in Cycles' image that is
    left out: a rendered Principled BSDF's Specular Tint (``_tint_note``), or a Lambertian's missing specular layer
    (``_specular_note``)."""
    if layers is not None:
        note = _tint_note(node, layers)
    else:
        note = _specular_note(node, base) if node.type == "BSDF_PRINCIPLED" else None
    return [note] if note is not None else []


def _luminance(colour) -> float:
    """The luminance of an RGB colour (its first three values), each channel clipped to [0, 1]: a reflectance's."""
    return float(np.clip(np.asarray(colour, dtype=np.float64)[:3], 0.0, 1.0) @ _LUMINANCE)


def _relief_notes(mat, node) -> list[str]:
    """A bump or normal map on the surface node's Normal, and the material output's Displacement (Blender's default
    displacement is a bump): this renderer shades with the mesh's own normals, where Cycles' image shows the relief."""
    notes = []
    normal = _source(node.inputs.get("Normal"))
    if normal is not None:
        notes.append(f"its Normal input ({_a_node(normal.node)}: shaded with the mesh's normals)")
    out = _output_node(mat.node_tree)
    if out is not None and _source(out.inputs.get("Displacement")) is not None:
        notes.append("its Displacement (not rendered: the surface is shaded flat)")
    return notes


def _image_node_notes(node) -> list[str]:
    """What an Image Texture node feeding a base colour sets that this renderer's lookup does not do (it repeats
    the image over the render UV map, filtered linearly with the ray's footprint; a Mapping node: ``_uv_mapping``)."""
    notes = []
    if node.type != "TEX_IMAGE":  # an Environment Texture node: its settings are the sky's
        return [f"its base colour is {_a_node(node)}'s (looked up with the UV map)"]

    if node.interpolation == "Closest":
        notes.append("its Closest interpolation (looked up filtered)")
    if node.projection != "FLAT":
        notes.append(f"its {node.projection.title()} projection (looked up as Flat)")
    return notes


def _uv_mapping(node, notes: list[str]):
    """The (2, 3) affine uv map of what feeds an Image Texture node's Vector (None: the uv as they are): a Mapping
    node (Point, Texture or Vector) of the UV coordinates, its location, Z rotation and scale in the uv plane, as
    Blender applies them. What it cannot follow (another source, a rotation about X or Y, a Normal mapping, inputs
    driven by nodes, a UV Map node naming another map) goes into ``notes``. Reroute and muted nodes pass their
    input on (``_source``)."""
    source = _source(node.inputs.get("Vector"))
    if source is None:
        return None
    mapping = None
    if source.node.type == "MAPPING":
        mapping, source = source.node, _source(source.node.inputs["Vector"])
    if source is None:
        notes.append("its Mapping node maps no coordinates (Cycles looks one point up; the UV map is looked up here)")
    elif not _is_uv_source(source):
        notes.append(f"its Vector is {_a_node(source.node)}'s {source.name} output (looked up with the UV map)")
    if mapping is None:
        return None
    inputs = [mapping.inputs.get(n) for n in ("Location", "Rotation", "Scale")]  # a Vector mapping has no Location
    if any(i is not None and _source(i) is not None for i in inputs) or mapping.vector_type == "NORMAL":
        notes.append("its Mapping node (driven inputs, or a Normal mapping) is not applied")
        return None
    neutral = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    (lx, ly, _), (rx, ry, rz), (sx, sy, _) = (
        tuple(i.default_value) if i is not None else n for i, n in zip(inputs, neutral, strict=True)
    )
    if abs(rx) > 1e-6 or abs(ry) > 1e-6:
        notes.append("its Mapping node's X and Y rotations are not applied (its location, Z rotation and scale are)")
    c, s = math.cos(rz), math.sin(rz)
    m = np.array([[c * sx, -s * sy], [s * sx, c * sy]])  # R S
    t = np.array([lx, ly]) if mapping.vector_type == "POINT" else np.zeros(2)
    if mapping.vector_type == "TEXTURE":  # the inverse: S^-1 R^-1 (v - T)
        if abs(sx * sy) < 1e-12:
            return np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
        inv = np.linalg.inv(m)
        return np.hstack([inv, (-inv @ np.array([lx, ly]))[:, None]])
    return np.hstack([m, t[:, None]])


def _is_uv_source(source) -> bool:
    """Whether an output socket gives the render UV map's coordinates: Texture Coordinate's UV, or a UV Map node
    naming no map or the one every mesh object of its material renders with (``_render_uv_names``)."""
    node = source.node
    if node.type == "TEX_COORD":
        return source.name == "UV"
    if node.type != "UVMAP":
        return False
    return not node.uv_map or _render_uv_names(node.id_data) == {node.uv_map}


def _render_uv_names(tree) -> set[str]:
    """The names of the UV maps the mesh objects whose materials hold the node tree ``tree`` render with (the one
    marked for renders, else the active one, as ``_mesh_arrays`` reads them); empty where no mesh object holds it (a
    node group's tree: its materials are not followed)."""
    import bpy

    tree = getattr(tree, "original", tree)  # an evaluated material's tree: the one the data's materials hold
    names = set()
    for ob in bpy.data.objects:
        holds = any(s.material is not None and s.material.node_tree == tree for s in ob.material_slots)
        if ob.type != "MESH" or not holds:
            continue
        layers = ob.data.uv_layers
        layer = next((lay for lay in layers if lay.active_render), layers.active)
        names.add(layer.name if layer is not None else "")
    return names


def unmanaged_material(mat, warnings: list[str]) -> LambertMaterial | PrincipledMaterial:
    """A Principled BSDF with constant Metallic, Roughness, IOR and Specular IOR Level as a ``PrincipledMaterial``
    (its specular layer over its base colour, and its metal), any other surface as a Lambertian with the material's
    base colour; either with its base-colour texture. What it leaves out that changes Cycles' image is named in one
    warning. A material whose output has no surface is black, as in Cycles."""
    if mat is None:
        return LambertMaterial()
    if getattr(mat, "node_tree", None) is None:
        return LambertMaterial(tuple(mat.diffuse_color[:3]))
    node = _surface_node(mat)
    if node is None:
        return LambertMaterial((0.0, 0.0, 0.0))
    notes: list[str] = []
    if node.type not in SURFACE_NODES:
        colour = node.inputs.get("Color")
        color = _constant_colour(colour) if colour is not None else None
        notes.append(
            f"its surface is {_a_node(node)}, which this renderer does not evaluate; rendered as a Lambertian of "
            + ("its Color" if color is not None else "the viewport colour")
            + (" (it emits no light here)" if node.type == "EMISSION" else "")
        )
        _warn_material(mat, notes, warnings)
        return LambertMaterial(color if color is not None else tuple(mat.diffuse_color[:3]))
    layers = _principled_layers(node) if node.type == "BSDF_PRINCIPLED" else None
    layered = layers is not None and _has_layers(layers)
    dropped = _dropped_inputs(node, rendered=("Metallic",) if layers is not None else ())
    if dropped:
        verb = "is" if len(dropped) == 1 else "are"
        instead = "" if layered else " (a Lambertian of its base colour)"  # else: the rest of it renders
        notes.append(f"its {_node_title(node)}'s {_listed(dropped)} {verb} left out{instead}")
    color, texture, base = tuple(mat.diffuse_color[:3]), None, None
    socket = node.inputs.get("Base Color") or node.inputs.get("Color")
    source = _source(socket)
    image = _linked_image(socket)
    if image is False:
        warnings.append(f"material {mat.name!r}: its {_node_title(source.node)} node has no image; {MISSING_IMAGE}")
    elif image is not None:
        image_node = source.node
        if source.name != "Color":
            notes.append(f"its base colour is the image's {source.name} (its Color is read)")
        notes += _image_node_notes(image_node)
        uv_map = _uv_mapping(image_node, notes)
        alpha_out = image_node.outputs.get("Alpha")  # an Environment Texture node has none
        associate = alpha_out is not None and not any(_live(lk) for lk in alpha_out.links)
        px = _image_pixels(image, warnings, associate_alpha=associate, node=image_node)
        if px is not None:
            extension = image_node.extension if image_node.type == "TEX_IMAGE" else "REPEAT"
            extension = extension if extension in ImageTexture.EXTENSIONS else "REPEAT"
            texture = _image_texture(image, px, associate, uv_map, extension)
            step = max(1, max(px.shape[:2]) // 256)  # a few thousand texels stand for a 4K image's mean
            base = _luminance(px[::step, ::step, :3].reshape(-1, 3).mean(axis=0))
    if texture is not None:
        color = (1.0, 1.0, 1.0)
    elif image is not None:  # an Image Texture node without an image or its pixels: magenta, as in Cycles
        color = MISSING_IMAGE_COLOUR
    elif (constant := _constant_colour(socket)) is not None:
        color = constant
    else:
        notes.append(
            f"its {socket.name} comes from {_a_node(source.node)}, which this renderer does not evaluate (only an "
            "Image Texture, a Color or a Value node is); using the viewport colour"
        )
    base = _luminance(color) if base is None else base
    notes += _layer_notes(node, layers if layered else None, base)
    notes += _relief_notes(mat, node)
    _warn_material(mat, notes, warnings)
    if not layered:  # a Lambertian: nothing above the base (the exact surface), or a layer's input is linked
        return LambertMaterial(color, texture)
    return PrincipledMaterial(color, texture=texture, **layers)


def _has_layers(layers: dict) -> bool:
    """Whether a Principled BSDF of constant ``layers`` (``_principled_layers``) has anything above its base colour:
    a metal, or a specular layer whose index is not 1 (``core.bsdf.specular_ior``: Specular IOR Level 0, or an IOR
    of 1, leaves none). Every such surface renders as a ``PrincipledMaterial``, however little its layer reflects
    (the default material's 2% of its light: its soft highlights), in one compiled pass a bounce; the others are
    exactly the Lambertian of their base colour, which costs less."""
    from ..core.bsdf.specular_diffuse import specular_ior

    return layers["metallic"] > 0.0 or specular_ior(layers["ior"], layers["specular_level"]) != 1.0


def _warn_material(mat, notes: list[str], warnings: list[str]) -> None:
    if notes:
        warnings.append(f"material {mat.name!r}: " + "; ".join(notes))


def _baked_texture(mat, warnings: list[str]):
    """``(texture, spatial)``: the material's baked latent texture if it is current and the spatially
    varying stack it was baked from (what reference mode shades), else ``(None, None)`` (with a warning if
    it is stale)."""
    if not mat.neural_layers.texture_path:
        from . import bake_inputs

        if bake_inputs.has_maps(mat):
            warnings.append(
                f"material {mat.name!r}: its maps are not baked (Latent Texture > Bake Latent Texture); rendering "
                "its constant stack"
            )
        return None, None
    from . import bake_state

    path, state, spatial = bake_state.current_texture(mat)
    if path is None:
        warnings.append(f"material {mat.name!r}: {state}; rendering its constant stack")
        return None, None
    try:
        texture = _read_texture(path)
    except (OSError, ValueError, RuntimeError) as e:
        warnings.append(f"material {mat.name!r}: cannot read its latent texture ({e}); rendering its constant stack")
        return None, None
    # The file must hold this material's bake: another bake can sit at its path while the material's key still
    # matches its inputs (another .blend file's material of the same name in the same folder, a renamed material
    # and a new one of its old name, an undo after a second bake, names that differ in case only).
    found = texture.metadata.get("key")
    if found is not None and found != mat.neural_layers.texture_key:
        warnings.append(
            f"material {mat.name!r}: {path} holds another bake (of material {texture.metadata.get('material', '?')!r}"
            f"): bake again; rendering its constant stack"
        )
        return None, None
    if spatial is None:  # a bake rendered while its maps' images cannot be read: the state says so
        warnings.append(f"material {mat.name!r}: {state}")
    return texture, spatial


# Latent textures read, by absolute path: (the file's identity, the texture). The viewport exports the scene
# again at every edit and every view change, and reading a 1024 x 1024 texture takes seconds.
_TEXTURES: dict[str, tuple[tuple[int, int, int], object]] = {}
_USED: set[str] = set()  # the paths this export read or reused (export_scene keeps only those)
_LOCK = threading.Lock()  # F12 exports on Blender's render thread, the viewport on the main one


def _read_texture(path: str):
    """The latent texture at ``path``, read once per version of the file: again when the file's inode, size or
    modification time differ (a bake publishes a new file by renaming it into place)."""
    from ..core.textures import LatentTexture

    st = os.stat(path)
    identity = (st.st_ino, st.st_size, st.st_mtime_ns)
    with _LOCK:
        _USED.add(path)
        held = _TEXTURES.get(path)
    if held is not None and held[0] == identity:
        return held[1]
    texture = LatentTexture.read_exr(path)
    with _LOCK:
        _TEXTURES[path] = (identity, texture)
    return texture


def forget_textures() -> None:
    """Let go of every latent texture and image the exports keep (another file was opened, or the add-on is
    disabled)."""
    with _LOCK:
        _TEXTURES.clear()
        _USED.clear()
        _IMAGES.clear()
        _IMAGES_USED.clear()


def _refined_latent(mat, stack, info: list[str]):
    """``(z, size)`` of the material's refined latent while it is current (``stack_io.refined_latent``), else None,
    with a line in ``info`` when a refined latent is there but stale."""
    from . import stack_io

    latent, why = stack_io.refined_latent(mat, stack)
    if why:
        info.append(why)
    return latent


def export_material(mat, warnings: list[str], info: list[str] | None = None):
    """LayeredSpec for a material with a layer stack, else an unmanaged Lambertian.

    A material without a current baked texture renders its current refined latent when it has one
    (``_refined_latent``); ``info`` receives the lines about stale ones."""
    stack = None
    try:
        from . import stack_io

        stack = stack_io.stack_from_material(mat)
    except ImportError:
        stack = None
    except ValueError as e:
        warnings.append(f"material {mat.name!r}: {e}; rendering it as a Lambertian")
    if stack is not None:
        texture, spatial = _baked_texture(mat, warnings)
        latent = _refined_latent(mat, stack, [] if info is None else info) if texture is None else None
        spatial = spatial if spatial is not None and spatial.stack == stack else None
        return LayeredSpec(stack, texture, mat.name, latent=latent, spatial=spatial)
    return unmanaged_material(mat, warnings)


def _mesh_arrays(ob):
    """Object-space triangles of an evaluated object: positions, corner normals, uvs, slot index."""
    mesh = ob.to_mesh()
    try:
        if mesh is None or len(mesh.polygons) == 0:
            return None
        mesh.calc_loop_triangles()
        nt = len(mesh.loop_triangles)
        if nt == 0:
            return None
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        tri_v = np.empty(nt * 3, np.int32)
        mesh.loop_triangles.foreach_get("vertices", tri_v)
        tri_l = np.empty(nt * 3, np.int32)
        mesh.loop_triangles.foreach_get("loops", tri_l)
        mat_i = np.empty(nt, np.int32)
        mesh.loop_triangles.foreach_get("material_index", mat_i)
        cn = np.empty(len(mesh.loops) * 3, np.float32)
        mesh.corner_normals.foreach_get("vector", cn)
        positions = co.reshape(-1, 3)[tri_v].reshape(nt, 3, 3)
        normals = cn.reshape(-1, 3)[tri_l].reshape(nt, 3, 3)
        uvs = None
        # the UV map marked for renders (the camera icon), as Cycles textures with it; the active one otherwise
        layer = next((lay for lay in mesh.uv_layers if lay.active_render), mesh.uv_layers.active)
        if layer is not None and len(layer.data):
            uv = np.empty(len(mesh.loops) * 2, np.float32)
            layer.data.foreach_get("uv", uv)
            uvs = uv.reshape(-1, 2)[tri_l].reshape(nt, 3, 2)
        return positions, normals, uvs, mat_i
    finally:
        ob.to_mesh_clear()


def render_views(render) -> list[str]:
    """The views F12 renders, each into its own image (Output > Stereoscopy: Stereo 3D's left and right, or
    Multi-View's views in use); one unnamed view without Stereoscopy."""
    if not render.use_multiview:
        return [""]
    names = [v.name for v in render.views if v.use]
    if render.views_format == "STEREO_3D":
        names = [n for n in names if n in ("left", "right")]
    return names or [""]


def stereo_view_camera(engine, scene, width: int, height: int, warnings: list[str]) -> Camera:
    """The core camera of the view ``engine`` renders (``RenderEngine.active_view_set``): the view's camera (a
    Multi-View view's own, ``camera_override``: the scene camera's name with the view's suffix; else the scene
    camera) moved and shifted as Blender places each eye of a stereo pair (``camera_model_matrix``,
    ``camera_shift_x``)."""
    cam_ob, r = engine.camera_override or scene.camera, scene.render
    if cam_ob is None:
        raise ValueError(f"scene {scene.name!r} has no active camera; add one or set Scene > Camera")
    matrix = np.array(engine.camera_model_matrix(cam_ob), dtype=np.float64)
    shift_x = float(engine.camera_shift_x(cam_ob)) if cam_ob.type == "CAMERA" else None
    return _camera(
        cam_ob,
        width,
        height,
        warnings,
        (r.pixel_aspect_x, r.pixel_aspect_y),
        matrix,
        shift_x,
        _renders_motion_blur(scene, scene.view_layers),
    )


def _renders_motion_blur(scene, view_layers) -> bool:
    """Whether Cycles renders ``scene`` with motion blur in one of ``view_layers`` (the one rendered; a stereo view's
    camera, which knows no view layer: any of the scene's in use): Render Properties > Motion Blur, and the view
    layer's own Use > Motion Blur."""
    used = [vl for vl in view_layers if getattr(vl, "use", True)]
    return bool(scene.render.use_motion_blur) and any(vl.use_motion_blur for vl in used)


def _camera(
    cam_ob,
    width: int,
    height: int,
    warnings: list[str],
    pixel_aspect=(1.0, 1.0),
    matrix=None,
    shift_x=None,
    motion_blur: bool = False,
) -> Camera:
    """The core camera of a Blender camera for an image of ``width`` x ``height`` pixels of ``pixel_aspect``
    (the render's Aspect X and Y), as Blender frames it (``BKE_camera_params_compute_viewplane``): the sensor fit
    decided on the image's displayed sides, the lens shift in units of the fitted side, and the clipping
    planes. ``matrix`` and ``shift_x``: a stereo view's, in place of the camera's own (``stereo_view_camera``).
    What it does not model and Cycles renders is said in ``warnings``: a camera type other than perspective, depth of
    field, and the render's Motion Blur (``motion_blur``: ``_renders_motion_blur``), which rendered sharp silently."""
    if cam_ob.type != "CAMERA":  # Blender renders an empty or a light set as the camera with a lens of its own
        lens = DEFAULT_LENS
        if cam_ob.type == "LIGHT":  # Cycles frames a light by its spot size (45 degrees stored for other kinds)
            spot = float(getattr(cam_ob.data, "spot_size", math.radians(45.0)))
            lens = 16.0 / math.tan(min(spot, math.pi - 1e-3) / 2.0)
        warnings.append(
            f"the scene camera {cam_ob.name!r} is a {cam_ob.type.lower()}, not a camera; rendering its view with "
            f"a {lens:.3g} mm lens, as Cycles does"
        )
        cam = SimpleNamespace(
            type="PERSP", sensor_fit="AUTO", sensor_width=36.0, sensor_height=24.0, lens_unit="MILLIMETERS",
            lens=lens, angle=0.0, shift_x=0.0, shift_y=0.0, clip_start=0.0, clip_end=math.inf,
        )  # fmt: skip
    else:
        cam = cam_ob.data
    if cam.type != "PERSP":
        warnings.append(f"camera {cam_ob.name!r} is {cam.type}; rendering it as a perspective camera")
    if getattr(getattr(cam, "dof", None), "use_dof", False):
        warnings.append(f"camera {cam_ob.name!r}: Depth of Field is not rendered here; every depth renders sharp")
    if motion_blur:
        warnings.append("Motion Blur (Render Properties) is not rendered here; the frame renders as at its own time")
    ax, ay = (float(a) for a in pixel_aspect)
    shown_w, shown_h = width * ax, height * ay  # the image's sides as displayed
    fit = cam.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if shown_w >= shown_h else "VERTICAL"
        sensor = cam.sensor_width
    else:
        sensor = cam.sensor_width if fit == "HORIZONTAL" else cam.sensor_height
    if cam.lens_unit == "FOV":
        tan_fit = math.tan(cam.angle / 2)
    else:
        tan_fit = sensor / (2.0 * cam.lens)
    aspect = shown_w / shown_h
    tan = (tan_fit, tan_fit / aspect) if fit == "HORIZONTAL" else (tan_fit * aspect, tan_fit)
    # Blender shifts by the fitted side; ``Camera.shift`` counts in the larger side's pixels
    fitted = shown_w if fit == "HORIZONTAL" else shown_h
    big = max(width, height)
    shift_x = cam.shift_x if shift_x is None else shift_x
    shift = (shift_x * fitted / (ax * big), cam.shift_y * fitted / (ay * big))
    clip = (max(0.0, float(cam.clip_start)), float(cam.clip_end))
    if not clip[0] < clip[1]:  # Blender's fields allow it
        warnings.append(f"camera {cam_ob.name!r}: Clip End is not beyond Clip Start; rendering without clipping")
        clip = (0.0, math.inf)
    matrix = np.array(cam_ob.matrix_world) if matrix is None else matrix
    return Camera(matrix, width, height, tan, shift, clip)


def view_clip(region_3d, space, scene) -> tuple[float, float]:
    """The clipping planes of a 3D viewport's view: in camera view the scene camera's, else the viewport's own
    (its View > Clip Start and End); none for an orthographic view, which renders as a perspective one."""
    src = space
    if region_3d.view_perspective == "CAMERA" and scene.camera is not None and scene.camera.type == "CAMERA":
        src = scene.camera.data
        if src.type != "PERSP":
            return (0.0, math.inf)
    elif not region_3d.is_perspective:
        return (0.0, math.inf)
    start, end = max(0.0, float(src.clip_start)), float(src.clip_end)
    return (start, end) if start < end else (0.0, math.inf)


def view_camera(region_3d, lens: float, width: int, height: int, clip=(0.0, math.inf)) -> Camera:
    """The camera of a 3D viewport, for an image of ``width`` x ``height``: its view matrix, and its projection
    (``window_matrix``: the viewport's own lens, or in camera view the scene camera's field of view, zoom and
    offset as the viewport frames it) with the field of view of its larger side on the image's larger side
    (the viewport's region itself: its projection exactly). An orthographic view has no pinhole camera: the
    viewport's ``lens`` (mm, on its 72 mm sensor) gives a perspective one of the same view. ``clip``: its
    clipping planes (``view_clip``)."""
    m = np.array(region_3d.view_matrix.inverted())
    big = max(width, height)
    if not region_3d.is_perspective:
        t = VIEWPORT_SENSOR / (2.0 * lens)
        return Camera(m, width, height, (t * width / big, t * height / big), clip=clip)
    p = np.array(region_3d.window_matrix)
    tan_x, tan_y = 1.0 / p[0, 0], 1.0 / p[1, 1]  # the region's half extents at unit distance
    t = max(tan_x, tan_y)  # on the region's larger side
    tan = (t * width / big, t * height / big)
    # the centre's offset (camera view: the frame's place in the region), as ``Camera.shift`` counts it
    off_x, off_y = p[0, 2] / p[0, 0], p[1, 2] / p[1, 1]
    shift = (off_x * width / (2.0 * tan[0] * big), off_y * height / (2.0 * tan[1] * big))
    return Camera(m, width, height, tan, shift, clip)


# what a transform that is not finite is said to be (a driver or a constraint can make one)
_NOT_A_NUMBER = "its location, rotation or scale is not a number (NaN or infinite: a driver or a constraint?)"


def _light(ob, matrix: np.ndarray, warnings: list[str], info: list[str] | None = None):
    """The core light of a Blender light object, or None for one that sheds no light here (with a warning where the
    user may not expect it). Blender allows what the core lights refuse: a negative power (Cycles subtracts light;
    this renderer does not), a light scaled to nothing (an animator's way to hide it), an area light of size 0, and
    a 180-degree spot, whose float32 angle is just above pi. A point or spot light's Radius (with its Soft Falloff),
    a sun's Angle, Normalize, the object's Camera ray visibility and Cycles' per-light Max Bounces render as in
    Cycles; an area light that is a Cycles portal emits nothing there, and is left out with a line in ``info``."""
    light = ob.data
    z = -matrix[:3, 2]  # lights point along their local -z
    # what of its transform each kind reads: a point light its location, a sun its direction, a spot or an area
    # light the whole (a NaN elsewhere, a sun's location say, leaves it shining, as in Cycles)
    used = {"POINT": matrix[:3, 3], "SUN": matrix[:3, 2]}.get(light.type, matrix)
    if not np.isfinite(used).all():
        warnings.append(f"light {ob.name!r}: {_NOT_A_NUMBER}; skipped")
        return None
    if light.type not in ("POINT", "SPOT", "SUN", "AREA"):
        warnings.append(f"light {ob.name!r} has unsupported type {light.type}; skipped")
        return None
    cycles = getattr(light, "cycles", None)
    if light.type == "AREA" and getattr(cycles, "is_portal", False):
        if info is not None:
            info.append(
                f"light {ob.name!r} is a portal, which only guides Cycles' sampling of the world through it and emits "
                "nothing: left out (the world lights the scene as it does in Cycles)"
            )
        return None
    linking = getattr(ob, "light_linking", None)
    linked = [what for what, collection in (("Light Linking", "receiver_collection"), ("Shadow Linking",
              "blocker_collection")) if getattr(linking, collection, None) is not None]  # fmt: skip
    if linked:
        warnings.append(
            f"light {ob.name!r}: its {' and '.join(linked)} {'is' if len(linked) == 1 else 'are'} not rendered here; "
            "it lights every surface, and every surface casts its shadow"
        )
    hidden_from = [ray for ray in ("diffuse", "glossy", "transmission") if not getattr(ob, f"visible_{ray}", True)]
    if hidden_from:
        warnings.append(
            f"light {ob.name!r}: its ray visibility ({', '.join(r.title() for r in hidden_from)} off) is not rendered "
            "here; it lights every surface"
        )
    if not light.energy > 0.0:
        if light.energy < 0.0:
            warnings.append(
                f"light {ob.name!r} has a negative power ({light.energy:g}), which this renderer does "
                "not subtract; skipped"
            )
        return None
    color = _light_color(light)
    power = light.energy * 2.0 ** float(getattr(light, "exposure", 0.0))  # Blender's Exposure: stops
    scale = np.linalg.norm(matrix[:3, :3], axis=0)
    if light.type in ("SPOT", "SUN") and not scale[2] > 0.0:
        return None  # its direction scaled to nothing: hidden
    shadow = _light_settings(ob, light, cycles)
    if light.type == "POINT":
        return PointLight(matrix[:3, 3], power, color, **shadow)
    if light.type == "SPOT":
        spot_size = min(float(light.spot_size), math.pi)
        axes = matrix[:3, :3] if (scale > 0.0).all() and abs(np.linalg.det(matrix[:3, :3])) > 1e-30 else None
        return SpotLight(
            matrix[:3, 3], power, color, direction=z, spot_size=spot_size, blend=light.spot_blend, axes=axes, **shadow
        )
    if light.type == "SUN":
        return SunLight(z, power, color, **shadow)
    shape = light.shape
    size_y = light.size_y if shape in ("RECTANGLE", "ELLIPSE") else light.size
    if not (light.size > 0.0 and size_y > 0.0 and scale[0] > 0.0 and scale[1] > 0.0):
        return None  # no area: it emits nothing (scaled to nothing, or of size 0)
    return AreaLight(
        matrix, power, color, light.size, size_y, ellipse=shape in ("DISK", "ELLIPSE"),
        normalize=bool(getattr(light, "normalize", True)),
        spread=min(float(getattr(light, "spread", math.pi)), math.pi),
        camera_visible=bool(getattr(ob, "visible_camera", True)), **shadow,
    )  # fmt: skip


def _light_settings(ob, light, cycles) -> dict:
    """The keyword settings of a point, spot or sun light's core light: Cast Shadow and Cycles' per-light Max Bounces
    (an area light's too), Normalize, the object's Camera ray visibility, and its size: a sun's Angle, a point or spot
    light's Radius (not scaled with the object, as in Cycles) and Soft Falloff."""
    settings = dict(
        casts_shadow=bool(getattr(light, "use_shadow", True)),
        max_bounces=max(int(getattr(cycles, "max_bounces", 1024)), 0),
    )
    if light.type == "AREA":
        return settings
    settings["normalize"] = bool(getattr(light, "normalize", True))
    settings["camera_visible"] = bool(getattr(ob, "visible_camera", True))
    if light.type == "SUN":
        settings["angle"] = min(max(float(getattr(light, "angle", 0.0)), 0.0), math.pi)
    else:
        settings["radius"] = max(float(getattr(light, "shadow_soft_size", 0.0)), 0.0)
        settings["soft_falloff"] = bool(getattr(light, "use_soft_falloff", True))
    return settings


def _light_color(light) -> tuple:
    """A light's colour as Cycles lights with it: its Color, times its blackbody colour where Temperature is on
    (the Color then tints it)."""
    color = np.array(light.color[:3], dtype=np.float64)
    if getattr(light, "use_temperature", False):
        color *= np.array(light.temperature_color[:3], dtype=np.float64)
    return tuple(color)


def _world(world, warnings: list[str]) -> Environment | None:
    """The world as Cycles lights with it: the Background node on the Surface of the world output Cycles renders
    (``_output_node``; through Reroute and muted nodes, ``_source``), its colour or sky image times its strength;
    a world without nodes, its colour. None: a black world (nothing reaches the output)."""
    if world is None:
        return None
    tree = getattr(world, "node_tree", None)
    if tree is not None:
        out = _output_node(tree)
        source = _source(out.inputs["Surface"]) if out is not None else None
        if source is not None:
            bg = source.node
            if bg.type == "BACKGROUND":
                strength = float(bg.inputs["Strength"].default_value)
                if strength < 0.0:
                    warnings.append(
                        f"world {world.name!r}: a negative Strength ({strength:g}) adds no light here; black world"
                    )
                    return None
                socket = bg.inputs["Color"]
                colour = _source(socket)
                image = _linked_image(socket)
                if image:
                    px = _image_pixels(image, warnings, node=colour.node)
                    if px is not None:
                        turn = _environment_turn(colour.node, world, warnings)
                        return Environment(image=turned_image(px[:, :, :3], turn), strength=strength)
                if image is not None:  # no image, or no pixels: magenta, as in Cycles
                    if image is False:
                        node = _node_title(colour.node)
                        warnings.append(f"world {world.name!r}: its {node} node has no image; {MISSING_IMAGE}")
                    return Environment(MISSING_IMAGE_COLOUR, strength=strength)
                if (constant := _constant_colour(socket)) is not None:
                    return Environment(constant, strength=strength)
                flat = socket.default_value[:3]
                warnings.append(
                    f"world {world.name!r}: the Background colour comes from {_a_node(colour.node)}, which this "
                    f"renderer does not evaluate (only an Environment or Image Texture, a Color or a Value node "
                    f"is); lighting with the socket's flat colour {tuple(round(c, 3) for c in flat)}"
                )
                return Environment(tuple(socket.default_value[:3]), strength=strength)
            warnings.append(
                f"world {world.name!r}: its surface is {_a_node(bg)}, not a Background; using the world colour"
            )
        elif out is not None:
            return None  # nothing connected: a black world
    return Environment(tuple(world.color))


def _environment_turn(node, world, warnings: list[str]) -> float:
    """How far (radians) the sky of an Environment or Image Texture node is turned about the world's z: the Z
    rotation of a Mapping node on its Vector (an HDRI's usual rotation). What else maps the directions (a
    Mapping node's X or Y rotation, location or scale, another node, a Mirror Ball projection) is named in a
    warning and left out."""
    where = f"world {world.name!r}"
    if getattr(node, "projection", "EQUIRECTANGULAR") != "EQUIRECTANGULAR":
        warnings.append(f"{where}: the sky's {node.projection} projection is rendered as equirectangular")
    vector = _source(node.inputs.get("Vector"))
    if vector is None:
        return 0.0
    mapping = vector.node
    if mapping.type != "MAPPING":
        warnings.append(f"{where}: the sky's Vector comes from {_a_node(mapping)}, which is not evaluated here")
        return 0.0
    source = _source(mapping.inputs["Vector"])
    if source is None or source.node.type != "TEX_COORD" or source.name not in ("Generated", "Object"):
        what = "nothing" if source is None else f"{_a_node(source.node)}'s {source.name} output"
        warnings.append(
            f"{where}: the sky's Mapping node maps {what}, not the view direction (Texture Coordinate Generated or "
            "Object); rendered as if it did"
        )
    inputs = {name: mapping.inputs.get(name) for name in ("Location", "Rotation", "Scale")}
    if any(i is not None and _source(i) is not None for i in inputs.values()):
        warnings.append(f"{where}: the sky's Mapping node has linked inputs, which are not evaluated here")
        return 0.0
    rx, ry, rz = (float(v) for v in inputs["Rotation"].default_value)
    location = inputs["Location"].default_value if inputs["Location"] is not None else (0.0, 0.0, 0.0)
    scale = inputs["Scale"].default_value if inputs["Scale"] is not None else (1.0, 1.0, 1.0)
    mode = mapping.vector_type
    if (
        abs(rx) > 1e-6
        or abs(ry) > 1e-6
        or mode == "NORMAL"
        or any(abs(v - 1.0) > 1e-6 for v in scale)
        or (mode in ("POINT", "TEXTURE") and any(abs(v) > 1e-6 for v in location))
    ):
        warnings.append(
            f"{where}: only the Z rotation of the sky's Mapping node is applied (not its X/Y rotation, location, "
            f"scale or {mode.title()} type)"
        )
    return -rz if mode == "TEXTURE" else rz  # a Texture mapping is the inverse transform


def turned_image(image: np.ndarray, turn: float) -> np.ndarray:
    """An equirectangular image (H, W, C) turned by ``turn`` radians about z: what a Mapping node's Z rotation
    does to the directions it looks up (``Rz(turn) d``), as the pixels' own image: its columns moved by
    turn / (2 pi) of the width, whole columns exactly and a fraction by linear interpolation between two
    neighbours."""
    w = image.shape[1]
    shift = (turn / (2.0 * math.pi)) * w % w
    whole = int(math.floor(shift))
    frac = shift - whole
    out = np.roll(image, whole, axis=1)
    if frac > 1e-6:
        out = (1.0 - frac) * out + frac * np.roll(out, 1, axis=1)
    return np.ascontiguousarray(out, dtype=image.dtype)


def _object_arrays(ob, material_slot, materials, names, warnings: list[str], kept=None, key=None):
    """``_mesh_arrays`` of an evaluated object plus its scene material indices (``material_slot``'s, into
    ``materials`` and their ``names``); None (with a warning for an object without a mesh form, e.g. empty curves)
    when it has no triangles. An object without a UV map whose materials read a texture is warned of. ``kept``
    (a :class:`GeometryCache`) holds the arrays of the geometry ``key`` when they did not change since."""
    try:
        arrays = _mesh_arrays(ob) if kept is None else kept.arrays_of(key, lambda: _mesh_arrays(ob))
    except RuntimeError as e:
        if ob.type == "CURVES":  # hair: Cycles renders its strands; here only a mesh its modifiers make
            warnings.append(
                f"object {ob.name!r}: hair curves are not rendered here (only a mesh made of them); skipped"
            )
        else:
            warnings.append(f"object {ob.name!r} has no mesh to render ({str(e).strip()}); skipped")
        return None
    if arrays is None:
        return None
    slots = [material_slot(s.material) for s in ob.material_slots] or [material_slot(None)]
    if arrays[2] is None:
        textured = sorted({names[i] for i in slots if _reads_uvs(materials[i])})
        if textured:
            warnings.append(
                f"object {ob.name!r} has no UV map, and its textured material(s) {', '.join(map(repr, textured))} "
                "sample their texture at uv (0, 0): add a UV map (UV Editing)"
            )
    return arrays + (np.asarray(slots, np.int32),)


UNRENDERED_TYPES = {"POINTCLOUD": "point cloud", "VOLUME": "volume"}  # objects Cycles renders, with no geometry here


def _instance_reader(depsgraph, object_arrays, warnings: list[str], info: list[str] | None = None):
    """``add(instance, placed, lights)``: one instance of the depsgraph into ``placed`` (its geometry's key -> the
    geometry's arrays and the matrices of its instances, for ``_world_mesh``) or into the lights, if it renders
    (``_render_visibility``). An object's geometry is read once (``object_arrays``) however many times it is
    instanced, and what it sets that is not rendered is said once."""
    rendered = _render_visibility(depsgraph)
    holdouts = _holdout_collections(depsgraph)
    cache: dict = {}
    told: set = set()

    def add(inst, placed: dict, lights: list) -> None:
        ob = inst.object
        original = ob.original if not inst.is_instance else ob
        if not rendered(inst, original):
            return
        matrix = np.array(inst.matrix_world, dtype=np.float64)
        if ob.type == "LIGHT":
            light = _light(ob, matrix, warnings, info)
            if light is not None:
                lights.append(light)
            return
        first = ob.name not in told
        told.add(ob.name)
        if ob.type not in GEOMETRY_TYPES:
            if ob.type in UNRENDERED_TYPES and first:
                warnings.append(
                    f"object {ob.name!r} is a {UNRENDERED_TYPES[ob.type]}, which this renderer does not render"
                )
            return
        if not np.isfinite(matrix).all():
            if first:
                warnings.append(f"object {ob.name!r}: {_NOT_A_NUMBER}; skipped")
            return
        if first:
            _warn_visibility(ob, holdouts, warnings)
            _warn_particle_hair(ob, warnings)
        # The object (its material slots) and its geometry, by identity: a linked object beside a local one of the
        # same name, and the geometries that Geometry Nodes instance (each a temporary object named after its
        # instancer, its mesh named "Mesh"), are each their own.
        key = (_identity(original), _identity(ob.data) if ob.data is not None else None)
        if key not in cache:
            cache[key] = object_arrays(ob, key)
        if cache[key] is not None:
            placed.setdefault(key, (cache[key], []))[1].append(matrix)

    return add


def _holdout_collections(depsgraph) -> set:
    """The ``session_uid`` of the collections set as holdouts in the depsgraph's view layer, with those inside them."""
    found: set = set()

    def walk(layer_collection, inside: bool):
        for child in layer_collection.children:
            holdout = inside or child.holdout
            if holdout:
                found.add(child.collection.session_uid)
            walk(child, holdout)

    walk(depsgraph.view_layer.layer_collection, False)
    return found


def _warn_particle_hair(ob, warnings: list[str]) -> None:
    """Name the particle systems of an evaluated object that render as hair strands in Cycles (Hair, rendered as
    Path) and have strands: they are not rendered here, and the object rendered without them, silently. A hair system
    rendered as objects or a collection renders (its instances are the depsgraph's)."""
    for system in getattr(ob, "particle_systems", ()):
        settings = system.settings
        if settings.type == "HAIR" and settings.render_type == "PATH" and len(system.particles):
            warnings.append(
                f"object {ob.name!r}: particle hair {system.name!r} is not rendered here (Cycles renders its "
                "strands); the object renders without it"
            )


def _warn_visibility(ob, holdouts: set, warnings: list[str]) -> None:
    """Name the visibility settings of a surface that Cycles honours and this renderer does not: a holdout (the
    object's, or its collection's, ``holdouts``) renders as seen, an object hidden from camera rays is seen, one
    that casts no shadow casts it."""
    left = []
    users = {c.session_uid for c in getattr(ob.original, "users_collection", ())}
    if getattr(ob.original, "is_holdout", False) or users & holdouts:
        left.append("Holdout")
    if getattr(ob, "is_shadow_catcher", False):
        left.append("Shadow Catcher")
    if not getattr(ob, "visible_camera", True):
        left.append("Camera ray visibility off")
    if not getattr(ob, "visible_shadow", True):
        left.append("Shadow ray visibility off")
    if left:
        warnings.append(f"object {ob.name!r}: {', '.join(left)} is not rendered here; it renders as any surface")


def _reads_uvs(material) -> bool:
    """Whether a scene material looks anything up by uv: an image texture, a baked latent texture, parameter maps."""
    if isinstance(material, (LambertMaterial, PrincipledMaterial)):
        return material.texture is not None
    return getattr(material, "latent_texture", None) is not None or getattr(material, "spatial", None) is not None


# the data-blocks an object's geometry is (``GeometryCache.forget``: their update names the geometries they are)
_GEOMETRY_DATA = {"Mesh", "Curve", "TextCurve", "SurfaceCurve", "MetaBall", "Curves", "PointCloud", "Volume"}


class GeometryCache:
    """What a viewport's exports keep of the geometry from one edit to the next (``export_scene``'s ``kept``): each
    geometry's object-space arrays, by its key (its object's and its data's identity), and the last scene mesh with
    what it was made of. Every edit exported the scene whole on the main thread: a light moved in a scene of
    500,000 triangles blocked the viewport 0.5-1.3 s, one of 20,000 instances 1.6-2.5 s."""

    def __init__(self):
        self.arrays: dict = {}  # geometry key -> (version, its _mesh_arrays)
        self._version = 0
        self._mesh = None  # (what the last mesh was made of, the mesh)

    def forget(self, updates) -> None:
        """Drop what the depsgraph's ``updates`` (``Depsgraph.updates``: an edit's) say changed: the arrays of a
        geometry whose object or data was updated in its geometry, every geometry's for an update of anything else
        in its geometry (a node group, a collection)."""
        changed = set()
        for u in updates:
            if not getattr(u, "is_updated_geometry", False):
                continue
            data_block = getattr(u.id, "original", None) or u.id
            if not hasattr(data_block, "session_uid"):
                continue
            if hasattr(data_block, "matrix_world") or type(data_block).__name__ in _GEOMETRY_DATA:
                changed.add(data_block.session_uid)
            else:
                self.arrays.clear()
                return
        if changed:
            self.arrays = {k: v for k, v in self.arrays.items() if not (k[0] in changed or k[1] in changed)}

    def arrays_of(self, key, read):
        """The arrays of geometry ``key``: those kept, or ``read()``'s (kept when there are any)."""
        held = self.arrays.get(key)
        if held is not None:
            return held[1]
        arrays = read()
        if arrays is not None:
            self._version += 1
            self.arrays[key] = (self._version, arrays)
        return arrays

    def mesh_of(self, placed: dict) -> Mesh:
        """``_world_mesh(placed)``, or the last one where it was made of the same arrays, material slots and
        instances' matrices (an edit of a material, a light or the world leaves it as it was, and the tracer and the
        surface arrays it keeps with it); what no geometry of ``placed`` uses is let go."""
        made_of = tuple(
            (key, self.arrays[key][0] if key in self.arrays else None, arrays[-1].tobytes(), np.array(m).tobytes())
            for key, (arrays, m) in placed.items()
        )
        if self._mesh is None or self._mesh[0] != made_of or any(v is None for _, v, _, _ in made_of):
            self._mesh = (made_of, _world_mesh(placed))
        self.arrays = {k: v for k, v in self.arrays.items() if k in placed}
        return self._mesh[1]


def _world_mesh(placed: dict) -> Mesh:
    """The scene's triangles in world space, of every geometry in ``placed`` (key -> its arrays, the matrices of its
    instances; ``_instance_reader``), one mesh checked once: each geometry's instances at once (positions by their
    matrices, normals by their inverse transposes, material slots mapped to the scene's material indices). Each
    instance made a mesh of its own, checked, and checked again in the scene's: 90,000 instances of a scatter took
    18.7 s where the same triangles realised took 3.6 s."""
    parts = [_placed_arrays(arrays, np.array(matrices, dtype=np.float64)) for arrays, matrices in placed.values()]
    if not parts:
        return Mesh(np.zeros((0, 3, 3), np.float32))
    uvs = None
    if any(p[2] is not None for p in parts):
        uvs = np.concatenate([p[2] if p[2] is not None else np.zeros(p[0].shape[:2] + (2,), np.float32) for p in parts])
    return Mesh(*(np.concatenate([p[i] for p in parts]) for i in (0, 1)), uvs, np.concatenate([p[3] for p in parts]))


def _placed_arrays(arrays, matrices: np.ndarray) -> tuple:
    """(positions, normals, uvs or None, material indices) of the K instances of one geometry, ``matrices`` (K, 4,
    4): K x T triangles. A mirroring matrix (a negative scale) turns the corners' order: reversed, the face normal
    that their order gives points out again, with the corner normals (else every corner normal disagreed with its
    face and the surface shaded flat)."""
    pos, nrm, uvs, mat_i, slots = arrays
    k, t = len(matrices), len(pos)
    rot = matrices[:, :3, :3]
    world_pos = np.einsum("kij,tcj->ktci", rot.astype(np.float32), pos) + matrices[:, None, None, :3, 3].astype(
        np.float32
    )
    # each inverse from its rows' cross products (numpy's batched inverse took 0.7 s for 10,000 matrices)
    a, b, c = rot[:, 0], rot[:, 1], rot[:, 2]
    adjugate = np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=2)
    det = np.einsum("ki,ki->k", a, adjugate[:, :, 0])
    invertible = np.abs(det) > 1e-30
    inverse = np.broadcast_to(np.eye(3), rot.shape).copy()
    inverse[invertible] = adjugate[invertible] / det[invertible, None, None]
    world_nrm = np.einsum("tcj,kji->ktci", nrm, inverse.astype(np.float32))  # n @ inv(R): the inverse transpose
    uv = None if uvs is None else np.broadcast_to(uvs, (k,) + uvs.shape).copy()
    mirrored = det < 0
    if mirrored.any():
        for corners in (world_pos, world_nrm) + ((uv,) if uv is not None else ()):
            corners[mirrored] = corners[mirrored][:, :, [0, 2, 1]]
    slot = np.tile(slots[np.clip(mat_i, 0, len(slots) - 1)], k)
    merge = lambda a: None if a is None else a.reshape((k * t,) + a.shape[2:])  # noqa: E731
    return merge(world_pos), merge(world_nrm), merge(uv), slot


def _shown_collections(depsgraph) -> set:
    """The ``session_uid`` of every collection of the depsgraph's view layer that renders: neither disabled for
    renders nor excluded, nor inside one that is."""
    shown: set = set()

    def walk(layer_collection):
        for child in layer_collection.children:
            if not (child.exclude or child.collection.hide_render):
                shown.add(child.collection.session_uid)
                walk(child)

    top = depsgraph.view_layer.layer_collection
    shown.add(top.collection.session_uid)
    walk(top)
    return shown


def _instancer_hidden(ob) -> bool:
    """An instancer whose own geometry F12 leaves out (Show Instancer for renders off; a particle emitter's Show
    Emitter): a viewport's ``show_self`` follows the viewport's setting, not the render's."""
    instancing = bool(len(getattr(ob, "particle_systems", ()))) or getattr(ob, "instance_type", "NONE") != "NONE"
    return instancing and not getattr(ob, "show_instancer_for_render", True)


def _instanced_collection_objects(instancer) -> set:
    """The ``session_uid`` of every object in the collections ``instancer`` instances as collections: its
    particle systems' (Render As Collection), and its Geometry Nodes modifiers' (every collection a node of their
    trees is given, in nested groups too, and the modifiers' Collection inputs). A collection a tree is given but
    does not instance leaves its objects out too: the viewport may then leave out an object F12 renders."""
    collections = []
    for system in getattr(instancer, "particle_systems", ()):
        if system.settings.render_type == "COLLECTION" and system.settings.instance_collection is not None:
            collections.append(system.settings.instance_collection)
    seen: set = set()

    def walk(tree):
        if tree is None or tree.session_uid in seen:
            return
        seen.add(tree.session_uid)
        for node in tree.nodes:
            # any collection a node of the tree is given (a Collection Info's own, or a node group's input that a
            # Collection Info inside it reads: a scatter asset's usual layout), at any depth of groups
            for socket in node.inputs:
                value = getattr(socket, "default_value", None) if socket.type == "COLLECTION" else None
                if value is not None and not socket.is_linked:
                    collections.append(value)
            if node.type == "GROUP":
                walk(node.node_tree)

    for modifier in getattr(instancer, "modifiers", ()):
        if modifier.type == "NODES":
            walk(modifier.node_group)
            inputs = (modifier.get(k) for k in modifier.keys())
            collections += [v for v in inputs if hasattr(v, "all_objects")]  # its Collection inputs' values
    return {ob.session_uid for c in collections for ob in c.all_objects}


def _render_visibility(depsgraph):
    """``visible(instance, original)``: whether an instance of the depsgraph renders in F12. A render's depsgraph
    holds only what renders; a viewport's (Render Preview, the viewport's Rendered mode) holds what the viewport
    shows, so there an object disabled for renders, in a collection disabled or excluded for them, or instanced by
    such an object, is left out too. An instancer whose own geometry is hidden for renders (a particle emitter's
    Show Emitter off) is left out in both."""
    viewport = getattr(depsgraph, "mode", "RENDER") != "RENDER"
    shown = _shown_collections(depsgraph) if viewport else set()

    def hidden(ob) -> bool:
        if ob is None:
            return False
        if getattr(ob, "hide_render", False):
            return True
        users = [c.session_uid for c in getattr(ob, "users_collection", ())] if viewport else []
        return bool(users) and not any(uid in shown for uid in users)

    members: dict = {}  # per instancer, the objects of the collections it instances

    def visible(inst, original) -> bool:
        if inst.is_instance:
            if not viewport:  # F12's depsgraph holds the instances that render
                return True
            parent = inst.parent.original if inst.parent is not None else None
            if hidden(parent):
                return False
            if not getattr(original, "hide_render", False):
                return True
            # An object hidden for renders that particles or Geometry Nodes instance by itself (the usual scatter's
            # source) renders in F12; one instanced as a member of a collection (a collection instance, a particle
            # system's or Collection Info's collection), or by vertices or faces, does not.
            if parent is None or getattr(parent, "instance_type", "NONE") != "NONE":
                return False
            if parent.session_uid not in members:
                members[parent.session_uid] = _instanced_collection_objects(parent)
            return original.original.session_uid not in members[parent.session_uid]
        if getattr(original, "hide_render", False):
            return False
        if not viewport:
            return getattr(inst, "show_self", True)
        return not (_instancer_hidden(original) or hidden(original))

    return visible


def _identity(data_block) -> int:
    """What tells one data-block from another within a session, whatever its name and library: its original's
    ``session_uid`` (an evaluated copy has its original's; a temporary one, as Geometry Nodes' instanced geometry,
    its own)."""
    original = getattr(data_block, "original", None) or data_block
    return original.session_uid


EXPORT_WORLD = object()  # ``export_scene``'s default environment: the scene's world, exported


def export_scene(
    depsgraph,
    width: int | None = None,
    height: int | None = None,
    camera: Camera | None = None,
    info: list[str] | None = None,
    environment=EXPORT_WORLD,
    kept: "GeometryCache | None" = None,
):
    """The depsgraph's scene as a core ``Scene``; returns ``(scene, warnings)``.

    ``width``/``height`` default to the render resolution (with its percentage); ``camera``
    replaces the scene camera (e.g. the viewport's). Raises ValueError if there is no camera.
    ``info`` (a list) receives the lines that are not warnings (a stale refined latent ignored).
    ``environment``: the world as an export made it before (an ``Environment`` or None), when the world has not
    changed since (the viewport's edits elsewhere: an 8K sky image is seconds to read and tabulate). ``kept``: what
    the exports before this one kept of the geometry (the viewport's :class:`GeometryCache`, told of the edits
    since): each geometry read again only when it changed, and the scene's mesh itself when nothing of it did.
    """
    # evaluated, as Cycles reads it: an animation render evaluates the frame it renders in the depsgraph's copies
    # only, and the original world kept its first frame's values (a keyed Background Strength rendered 1, 1, 1)
    scene = depsgraph.scene_eval
    frame = _FRAME.set(scene.frame_current)
    try:
        return _export_scene(depsgraph, scene, width, height, camera, info, environment, kept)
    finally:
        _FRAME.reset(frame)


def _export_scene(depsgraph, scene, width, height, camera, info, environment, kept):
    """``export_scene`` of ``depsgraph``'s evaluated ``scene``."""
    warnings: list[str] = []
    with _LOCK:
        _USED.clear()
        _IMAGES_USED.clear()
    if width is None or height is None:
        width, height = render_size(scene)
    if camera is None:
        if scene.camera is None:
            raise ValueError(f"scene {scene.name!r} has no active camera; add one or set Scene > Camera")
        r = scene.render
        camera = _camera(
            scene.camera.evaluated_get(depsgraph), width, height, warnings, (r.pixel_aspect_x, r.pixel_aspect_y),
            motion_blur=_renders_motion_blur(scene, [depsgraph.view_layer]),
        )  # fmt: skip

    material_index: dict[str, int] = {}
    materials: list = []
    names: list[str] = []

    def material_slot(mat) -> int:
        # By identity, not by name: a linked "Material [lib.blend]" and a local "Material" are two materials.
        key = _identity(mat) if mat is not None else None
        if key not in material_index:
            material_index[key] = len(materials)
            materials.append(export_material(mat, warnings, info) if mat is not None else LambertMaterial())
            names.append(mat.name_full if mat is not None else "")
        return material_index[key]

    override = getattr(depsgraph.view_layer, "material_override", None)
    if override is not None:  # the view layer's Material Override: every surface in it
        slot = material_slot(override.evaluated_get(depsgraph))
        material_slot = lambda mat, slot=slot: slot  # noqa: E731
    placed: dict = {}
    lights: list = []
    add = _instance_reader(
        depsgraph,
        lambda ob, key: _object_arrays(ob, material_slot, materials, names, warnings, kept, key),
        warnings,
        info,
    )
    for inst in depsgraph.object_instances:
        add(inst, placed, lights)
    mesh = _world_mesh(placed) if kept is None else kept.mesh_of(placed)
    world = _world(scene.world, warnings) if environment is EXPORT_WORLD else environment
    out = Scene(camera, mesh, materials, lights, world, names)
    with _LOCK:
        for path in set(_TEXTURES) - _USED:  # textures no material renders any more: let them go
            del _TEXTURES[path]
        for key in set(_IMAGES) - _IMAGES_USED:  # and images
            del _IMAGES[key]
    return out, warnings

"""The layer stack stored on a material (``Material.neural_layers``) and its latent cache.

Layers are kept bottom to top in ``neural_layers.layers`` (index 0 = base); the sidebar shows
them reversed so the base sits at the bottom. Each layer holds the fields of every layer type;
the UI shows only those of its ``layer_type``. Soft limits are the ranges the neural models were
trained on (``addon.core.stack.TRAINED_RANGES``); hard limits are the physically valid ranges
(``VALID_RANGES``). Roughness is shown as the artist's roughness (as in the Principled BSDF);
the core gets the GGX alpha = roughness^2.

Conversion to and from ``addon.core.stack.Stack`` lives in ``stack_io``.
"""

from __future__ import annotations

import json
import math

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    IntVectorProperty,
    PointerProperty,
    StringProperty,
)

from ..core.neural.models import DEFAULT_SIZE, MODEL_DIR, SIZES
from ..core.stack import TRAINED_RANGES, VALID_RANGES
from ..core.textures.bake import DEFAULT_MAX_SIDE
from . import layer_types

_ALPHA_LO, _ALPHA_HI = TRAINED_RANGES["roughness"]
_ROUGH_SOFT = (math.sqrt(_ALPHA_LO), math.sqrt(_ALPHA_HI))


def _on_layer_changed(layer, context) -> None:
    material = layer.id_data
    if isinstance(material, bpy.types.Material):
        from . import stack_io

        stack_io.on_stack_changed(material)


def _on_auto_latent(settings, context) -> None:
    _on_layer_changed(settings, context)


def _on_texture_changed(settings, context) -> None:
    """Which baked texture a material renders may have changed (a bake finished, Clear, or the bake's refine
    budget, part of the texture's key): tag the material, so that the evaluated copies the viewport and the
    render operators read get the new values (a property without an update callback tags nothing)."""
    material = settings.id_data
    if isinstance(material, bpy.types.Material):
        from . import stack_io

        stack_io.tag_changed(material)


def _range_text(key: str) -> str:
    lo, hi = TRAINED_RANGES[key]
    vlo, vhi = VALID_RANGES[key]
    return (
        f"Trained range {lo:g} to {hi:g} (valid {vlo:g} to {vhi:g}; outside the trained range the neural models clamp)"
    )


MAP_PARAMETERS = [
    ("ROUGHNESS", "Roughness", "Artist roughness (alpha = value squared) of a rough layer"),
    ("ALBEDO", "Albedo", "Diffuse base colour"),
    ("F0", "F0", "Normal-incidence colour of a conductor given by colour"),
    ("ETA", "Eta", "Real index of a conductor given by complex IOR"),
    ("K", "K", "Extinction of a conductor given by complex IOR"),
    ("IOR", "IOR", "Index of refraction of a dielectric or coating"),
    ("MEDIUM_ALBEDO", "Medium Albedo", "Single-scattering albedo of a coating's medium"),
    ("THICKNESS", "Thickness", "Optical thickness of a coating's medium"),
]


def model_size_items(
    auto_description: str | None = None,
    size_description: str = "The {size} decoder",
) -> list[tuple[str, str, str]]:
    """EnumProperty items of a decoder-size setting: Auto, then every size of the model set
    (``addon.core.neural.SIZES``), each described by ``size_description`` (``{size}`` is filled
    in) and its model card's parameter count. The render settings' Decoder uses it too."""
    auto = auto_description or (
        f"The neural runtime's default size, {DEFAULT_SIZE} (or the first size shipped when it is not)"
    )
    items = [("AUTO", "Auto", auto)]
    for size in SIZES:
        items.append((size.upper(), size.title(), _size_description(size, size_description.format(size=size))))
    return items


def _size_description(size: str, text: str) -> str:
    try:  # the card's figures; the digests are checked when the models load, not here
        card = json.loads((MODEL_DIR / f"decoder_{size}.json").read_text())
        parameters = f"{int(card['parameters']):,} parameters"
    except (OSError, ValueError, KeyError, TypeError):
        return f"{text} (its model card is missing)"
    default = "; the Auto choice" if size == DEFAULT_SIZE else ""
    return f"{text}: {parameters}, more is slower and closer to the reference{default}"


class NLM_ParameterMap(bpy.types.PropertyGroup):
    """An image driving one parameter of its layer: value = low + (high - low) * pixel. Add Parameter Map sets Low and
    High to the parameter's trained range (``bake_inputs.map_range``); 0 and 1 are the defaults of a map made
    otherwise."""

    parameter: EnumProperty(
        name="Parameter",
        items=MAP_PARAMETERS,
        default="ROUGHNESS",
        description="Which parameter of the layer the image drives",
        update=_on_layer_changed,
    )
    image: PointerProperty(
        type=bpy.types.Image,
        name="Image",
        description="Image whose pixel values (0 to 1) drive the parameter, decoded by its "
        "Color Space as Cycles does: use Non-Color for data such as roughness, sRGB for colours",
        update=_on_layer_changed,
    )
    low: FloatProperty(
        name="Low", default=0.0, description="Parameter value where the image is 0", update=_on_layer_changed
    )
    high: FloatProperty(
        name="High", default=1.0, description="Parameter value where the image is 1", update=_on_layer_changed
    )


class NLM_Layer(bpy.types.PropertyGroup):
    """One layer; ``name`` (built in) is the label shown in the list."""

    layer_type: EnumProperty(
        name="Type",
        items=layer_types.enum_items(),
        default="DIFFUSE",
        description="What this layer is: a base (Diffuse, Conductor, Dielectric) or a Coating above it",
        update=_on_layer_changed,
    )
    roughness: FloatProperty(
        name="Roughness",
        description=(
            "Artist roughness, as in the Principled BSDF: the GGX alpha is its square. "
            f"Trained alpha {_ALPHA_LO:g} to {_ALPHA_HI:g}, "
            f"i.e. roughness {_ROUGH_SOFT[0]:.1f} to {_ROUGH_SOFT[1]:.1f}; "
            "smoother surfaces are clamped by the neural models"
        ),
        default=0.3,
        min=0.0,
        max=1.0,
        soft_min=_ROUGH_SOFT[0],
        soft_max=_ROUGH_SOFT[1],
        subtype="FACTOR",
        update=_on_layer_changed,
    )
    albedo: FloatVectorProperty(
        name="Albedo",
        description="Diffuse reflectance (linear RGB, 0 to 1)",
        size=3,
        default=(0.8, 0.8, 0.8),
        min=0.0,
        max=1.0,
        subtype="COLOR",
        update=_on_layer_changed,
    )
    conductor_mode: EnumProperty(
        name="Specify",
        items=[
            ("F0", "Colour", "Normal-incidence reflectance colour F0 (mapped to eta = 1 and k)"),
            ("ETA_K", "Complex IOR", "Measured complex index of refraction eta + i k per RGB channel"),
        ],
        default="F0",
        description="How the metal is specified",
        update=_on_layer_changed,
    )
    f0: FloatVectorProperty(
        name="F0",
        description="Reflectance at normal incidence (linear RGB, 0 to 1); "
        "converted to eta = 1 and k = 2 sqrt(F0 / (1 - F0))",
        size=3,
        default=(0.95, 0.64, 0.54),
        min=0.0,
        max=1.0,
        subtype="COLOR",
        update=_on_layer_changed,
    )
    eta: FloatVectorProperty(
        name="Eta",
        description="Real part of the metal's index of refraction per RGB channel. " + _range_text("eta"),
        size=3,
        default=(0.2, 0.9, 1.1),
        min=VALID_RANGES["eta"][0],
        max=VALID_RANGES["eta"][1],
        soft_min=TRAINED_RANGES["eta"][0],
        soft_max=TRAINED_RANGES["eta"][1],
        update=_on_layer_changed,
    )
    k: FloatVectorProperty(
        name="K",
        description="Imaginary part (extinction) of the metal's index per RGB channel. " + _range_text("k"),
        size=3,
        default=(3.9, 2.4, 2.2),
        min=VALID_RANGES["k"][0],
        max=VALID_RANGES["k"][1],
        soft_min=TRAINED_RANGES["k"][0],
        soft_max=TRAINED_RANGES["k"][1],
        update=_on_layer_changed,
    )
    ior: FloatProperty(
        name="IOR",
        description="Index of refraction of the dielectric (relative to the medium above). " + _range_text("ior"),
        default=1.5,
        min=VALID_RANGES["ior"][0],
        max=VALID_RANGES["ior"][1],
        soft_min=TRAINED_RANGES["ior"][0],
        soft_max=TRAINED_RANGES["ior"][1],
        update=_on_layer_changed,
    )
    medium_albedo: FloatVectorProperty(
        name="Medium Albedo",
        description="Single-scattering albedo of the coating's medium (linear RGB, 0 to 1): 0 absorbs, 1 only scatters",
        size=3,
        default=(0.0, 0.0, 0.0),
        min=0.0,
        max=1.0,
        subtype="COLOR",
        update=_on_layer_changed,
    )
    thickness: FloatProperty(
        name="Thickness",
        description="Optical thickness of the coating's medium (extinction x depth, no unit); 0 = clear coat. "
        + _range_text("thickness"),
        default=0.0,
        min=VALID_RANGES["thickness"][0],
        max=VALID_RANGES["thickness"][1],
        soft_min=TRAINED_RANGES["thickness"][0],
        soft_max=TRAINED_RANGES["thickness"][1],
        update=_on_layer_changed,
    )
    maps: CollectionProperty(
        type=NLM_ParameterMap,
        name="Parameter Maps",
        description="Images that drive parameters of this layer per texel (baked into a latent texture)",
    )
    g: FloatProperty(
        name="Anisotropy g",
        description="Henyey-Greenstein asymmetry of the medium's scattering (-1 back, 0 isotropic, 1 forward). "
        "The neural models are trained at g = 0 only; other values are clamped to 0 by them",
        default=0.0,
        min=VALID_RANGES["g"][0],
        max=VALID_RANGES["g"][1],
        update=_on_layer_changed,
    )


class NLM_MaterialSettings(bpy.types.PropertyGroup):
    layers: CollectionProperty(type=NLM_Layer, name="Layers", description="The stack, bottom (base) to top")
    active_index: IntProperty(
        name="Active Layer",
        default=0,
        min=0,
        description="The layer shown for editing (index into the stack, 0 = the base)",
    )
    latent: FloatVectorProperty(
        name="Latent",
        description="Latent code of the stack from the neural encoder: 32 floats per RGB channel",
        size=(3, 32),
        default=[[0.0] * 32] * 3,
    )
    latent_hash: StringProperty(
        name="Latent Stack Hash",
        description="Hash of the stack the latent was computed from; the latent is current when it matches",
        default="",
    )
    latent_size: StringProperty(
        name="Latent Decoder Size",
        description="Decoder size the stored latent belongs to (each size has its own latent space)",
        default="",
    )
    model_size: EnumProperty(
        name="Model Size",
        items=model_size_items(),
        default="AUTO",
        description="Neural decoder size of the latent, the previews and the bake (each size has its own latent space)",
        update=_on_auto_latent,
    )
    auto_latent: BoolProperty(
        name="Auto Update Latent",
        description="Recompute the latent whenever the stack changes (when the neural models are available)",
        default=True,
        update=_on_auto_latent,
    )
    refine_budget: FloatProperty(
        name="Refine Budget",
        description="Seconds the Refine button may take for this material: the reference walks (about a second), then "
        "the fit (at most 300 steps). A refinement this budget cut short says so: give it more time",
        default=8.0,
        min=0.5,
        max=600.0,
        unit="TIME_ABSOLUTE",
    )
    # preview settings
    preview_method: EnumProperty(
        name="Method",
        items=[
            ("AUTO", "Auto", "Neural runtime when its models are available, else the Monte Carlo reference"),
            ("NEURAL", "Neural", "Neural runtime only; fail if its models are not available"),
            ("REFERENCE", "Reference", "Position-free Monte Carlo reference (slow, noisy, exact on average)"),
        ],
        default="AUTO",
        description="How the previews evaluate the stack's BRDF",
    )
    theta_i: FloatProperty(
        name="Incident Angle",
        description="Angle of the incident light from the normal, for the lobe preview and the comparison",
        default=math.radians(30.0),
        min=0.0,
        max=math.radians(89.0),
        subtype="ANGLE",
    )
    lobe_resolution: IntProperty(
        name="Lobe Size", description="Lobe image size in pixels", default=128, min=8, max=1024
    )
    sphere_resolution: IntProperty(
        name="Sphere Size", description="Sphere image size in pixels", default=128, min=8, max=1024
    )
    env_samples: IntProperty(
        name="Environment Samples",
        description="Sky directions per pixel of the sphere preview (more = smoother sky lighting, slower); "
        "the reference traces this many times Walks analog walks per pixel",
        default=8,
        min=1,
        max=256,
    )
    # latent texture bake
    bake_resolution: IntProperty(
        name="Bake Resolution",
        description="Largest side of the baked latent texture in texels (a bake is never finer than its images); "
        "0 = the driving images' resolution. A bake's peak memory: about 0.9 GB at 1024, 2 GB at 2048, 5.5-8 GB "
        "at 4096",
        default=DEFAULT_MAX_SIDE,
        min=0,
        max=16384,
    )
    bake_fit_camera: BoolProperty(
        name="Fit to Camera",
        description="Bake no finer than the material's smallest on-screen footprint, seen through the scene camera "
        "at the render resolution (also capped by Bake Resolution and the images)",
        default=False,
    )
    bake_refine: FloatProperty(
        name="Refine (s)",
        description="Seconds in all for refining the baked latents against the reference (distinct texels in "
        "order, each at most 10 s; cached in the bake folder's .refine), as the bake command's --refine; "
        "0 = off: the encoder's latents as they are",
        default=0.0,
        min=0.0,
        soft_max=600.0,
        unit="TIME_ABSOLUTE",
        update=_on_texture_changed,  # the bake key holds the budget: a change makes the texture stale
    )
    texture_size: IntVectorProperty(
        name="Latent Texture Size",
        description="(height, width) the latent texture was baked at",
        size=2,
        default=(0, 0),
    )
    bake_directory: StringProperty(
        name="Bake Folder",
        description="Folder for baked latent textures (EXR)",
        default="//textures/",
        subtype="DIR_PATH",
        options={"PATH_SUPPORTS_BLEND_RELATIVE"},
    )
    texture_path: StringProperty(
        name="Latent Texture",
        description="The baked latent texture the renderer uses for this material",
        default="",
        subtype="FILE_PATH",
        options={"PATH_SUPPORTS_BLEND_RELATIVE"},
        update=_on_texture_changed,
    )
    texture_file: StringProperty(
        name="Latent Texture File",
        description="Where the bake wrote the latent texture, as an absolute path: found again by it when a "
        "relative Latent Texture path no longer leads to the file (a linked material made local)",
        default="",
        options={"HIDDEN"},
    )
    texture_key: StringProperty(
        name="Latent Texture Key",
        description="Hash of the inputs the texture was baked from",
        default="",
        update=_on_texture_changed,
    )
    walks: IntProperty(
        name="Walks",
        description="Monte Carlo walks per direction pair for the reference (more = less noise, slower)",
        default=16,
        min=1,
        max=4096,
    )


_CLASSES = (NLM_ParameterMap, NLM_Layer, NLM_MaterialSettings)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_CLASSES)


def register() -> None:
    _register_classes()
    bpy.types.Material.neural_layers = PointerProperty(
        type=NLM_MaterialSettings, name="Neural Layers", description="Layer stack of the neural layered material"
    )


def unregister() -> None:
    if hasattr(bpy.types.Material, "neural_layers"):
        del bpy.types.Material.neural_layers
    _unregister_classes()

"""The one table of the sidebar's layer types: identifier, label, tooltip, icon, core class, base or not.

The enum of ``NLM_Layer.layer_type``, the list's icons, the stack conversion's labels and the
defaults of Add Layer all read this table. No bpy here.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..core.stack import Coating, Conductor, Dielectric, Diffuse, Layer


@dataclass(frozen=True)
class LayerType:
    identifier: str  # the enum item stored in .blend files: never rename
    label: str
    description: str  # the tooltip
    icon: str
    core: type  # the addon.core.stack class of a layer of this type
    is_base: bool  # a stack has one base, at the bottom; coatings go above it

    def default(self) -> Layer:
        """A new layer of this type with the core's default parameters."""
        return self.core()


LAYER_TYPES: tuple[LayerType, ...] = (
    LayerType("DIFFUSE", "Diffuse", "Base: Lambertian surface with an RGB albedo", "SHADING_SOLID", Diffuse, True),
    LayerType(
        "CONDUCTOR",
        "Conductor",
        "Base: rough metal (GGX), by F0 colour or by complex index eta + i k",
        "SHADING_RENDERED",
        Conductor,
        True,
    ),
    LayerType(
        "DIELECTRIC",
        "Dielectric",
        "Base: rough dielectric reflection over black (GGX)",
        "SHADING_TEXTURE",
        Dielectric,
        True,
    ),
    LayerType(
        "COATING",
        "Coating",
        "A rough dielectric interface over a slab of scattering medium; goes above the base",
        "MOD_THICKNESS",
        Coating,
        False,
    ),
)
BY_ID: dict[str, LayerType] = {t.identifier: t for t in LAYER_TYPES}
BASE_LAYER_TYPES = frozenset(t.identifier for t in LAYER_TYPES if t.is_base)


def enum_items() -> list[tuple[str, str, str, str, int]]:
    """``LAYER_TYPES`` as the items of a Blender EnumProperty (identifier, name, tooltip, icon, number)."""
    return [(t.identifier, t.label, t.description, t.icon, i) for i, t in enumerate(LAYER_TYPES)]


def label(identifier: str) -> str:
    """The label of a layer type, or the identifier itself when it is unknown (an error message's)."""
    t = BY_ID.get(identifier)
    return t.label if t is not None else identifier


def identifier_of(layer: Layer) -> str:
    """The layer type of a core layer; ValueError for a class the sidebar does not know."""
    for t in LAYER_TYPES:
        if type(layer) is t.core:
            return t.identifier
    raise ValueError(
        f"cannot store a layer of type {type(layer).__name__}; "
        f"the sidebar knows {[t.core.__name__ for t in LAYER_TYPES]}"
    )

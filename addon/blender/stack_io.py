"""Material <-> ``addon.core.stack.Stack``, and the latent stored on the material.

``stack_from_material(mat)`` is what every consumer (operators, the render engine's scene export)
calls: it returns the material's ``Stack``, ``None`` when the material has no layer stack, and
raises ``ValueError`` with a message for the user when the stack is not valid.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Optional

import numpy as np

from ..core import preview
from ..core.stack import (
    VALID_RANGES,
    Coating,
    Conductor,
    Dielectric,
    Diffuse,
    Layer,
    Stack,
    alpha_from_artist_roughness,
    artist_roughness_from_alpha,
)
from . import layer_types

# While True, property update callbacks do not react (bulk writes of a whole stack).
_suspend_updates = False


def settings(mat):
    return mat.neural_layers


def _stored(value, key: str):
    """A property's value (a number or an RGB triple) for the core: Blender holds it in float32 and keeps it within
    the property's min and max, which are the core's valid range; float32's rounding of an end (0.01 is
    0.0099999998, 0.99 is 0.9900000095) is taken back to the end, where the core refused it and the stack with it."""
    lo, hi = VALID_RANGES[key]
    if isinstance(value, float):
        return min(max(value, lo), hi)
    return tuple(min(max(float(v), lo), hi) for v in value)


def layer_from_item(item) -> Layer:
    """The core layer of one ``NLM_Layer`` item; ``ValueError`` names the layer if a value is invalid."""
    kind = item.layer_type
    alpha = alpha_from_artist_roughness(item.roughness)
    try:
        if kind == "DIFFUSE":
            return Diffuse(albedo=tuple(item.albedo))
        if kind == "CONDUCTOR":
            if item.conductor_mode == "F0":
                return Conductor.from_f0(tuple(item.f0), roughness=alpha)
            return Conductor(roughness=alpha, eta=_stored(item.eta, "eta"), k=_stored(item.k, "k"))
        if kind == "DIELECTRIC":
            return Dielectric(roughness=alpha, ior=_stored(item.ior, "ior"))
        if kind == "COATING":
            return Coating(
                roughness=alpha,
                ior=_stored(item.ior, "ior"),
                albedo=tuple(item.medium_albedo),
                thickness=_stored(item.thickness, "thickness"),
                g=_stored(item.g, "g"),
            )
    except ValueError as e:
        raise ValueError(f"layer {item.name!r}: {e}") from None
    raise ValueError(f"layer {item.name!r} has unknown type {kind!r}; expected one of {sorted(layer_types.BY_ID)}")


def stack_from_material(mat) -> Optional[Stack]:
    """The material's layer stack, or ``None`` if it has none (no material, or no layers).

    Raises ``ValueError`` when the layers do not form a valid stack (a coating at the bottom, a
    second base above the base, or a value outside its valid range).
    """
    if mat is None or not hasattr(mat, "neural_layers"):
        return None
    layers = list(mat.neural_layers.layers)
    if not layers:
        return None
    bottom = layers[0]
    if bottom.layer_type not in layer_types.BASE_LAYER_TYPES:
        raise ValueError(
            f"layer {bottom.name!r} ({layer_types.label(bottom.layer_type)}) is at the bottom of "
            f"the stack of material {mat.name!r}; the bottom layer must be a base: Diffuse, Conductor or Dielectric"
        )
    for item in layers[1:]:
        if item.layer_type != "COATING":
            raise ValueError(
                f"layer {item.name!r} ({layer_types.label(item.layer_type)}) is above the base of "
                f"material {mat.name!r}; only Coating layers can go above the base "
                "(move it to the bottom or change its type)"
            )
    return Stack(base=layer_from_item(bottom), coatings=tuple(layer_from_item(i) for i in layers[1:]))


def default_layer_name(kind: str, existing: set[str]) -> str:
    base = layer_types.BY_ID[kind].label
    if base not in existing:
        return base
    n = 1
    while f"{base}.{n:03d}" in existing:
        n += 1
    return f"{base}.{n:03d}"


def write_layer(item, layer: Layer) -> None:
    """Fill an ``NLM_Layer`` item from a core layer (ValueError for a kind the sidebar does not know)."""
    item.layer_type = layer_types.identifier_of(layer)
    if isinstance(layer, Diffuse):
        item.albedo = layer.albedo
        return
    item.roughness = artist_roughness_from_alpha(layer.roughness)
    if isinstance(layer, Conductor):
        item.conductor_mode = "ETA_K"
        item.eta = layer.eta
        item.k = layer.k
    elif isinstance(layer, Dielectric):
        item.ior = layer.ior
    elif isinstance(layer, Coating):
        item.ior = layer.ior
        item.medium_albedo = layer.albedo
        item.thickness = layer.thickness
        item.g = layer.g


def tag_changed(mat) -> None:
    """Tell the depsgraph that ``mat`` changed (its evaluated copy is made again, the viewport updates): a
    property set from Python or by an operator tags its ID only when it has an update callback."""
    original = getattr(mat, "original", mat)
    if original is not None and hasattr(original, "update_tag"):
        original.update_tag()


@contextmanager
def bulk_edit(mat):
    """Edit several layer fields at once: the latent is refreshed once, at the end."""
    global _suspend_updates
    outer = _suspend_updates
    _suspend_updates = True
    try:
        yield settings(mat)
    finally:
        _suspend_updates = outer
    on_stack_changed(mat)


def stack_to_material(stack: Stack, mat) -> None:
    """Replace the material's layers with ``stack`` (bottom to top) and refresh its latent."""
    with bulk_edit(mat) as s:
        s.layers.clear()
        names: set[str] = set()
        for layer in stack.layers:
            item = s.layers.add()
            write_layer(item, layer)
            item.name = default_layer_name(item.layer_type, names)
            names.add(item.name)
        s.active_index = len(s.layers) - 1


# --------------------------------------------------------------------------------------------
# Latent stored on the material


def latent_of(mat) -> np.ndarray:
    return np.array(settings(mat).latent, dtype=np.float32).reshape(3, 32)


def latent_is_current(mat) -> bool:
    """True when the stored latent was computed from the material's current stack."""
    try:
        stack = stack_from_material(mat)
    except ValueError:
        return False
    if stack is None:
        return False
    return settings(mat).latent_hash == preview.stack_hash(stack)


def model_size(mat) -> str:
    """The decoder size chosen on the material ("auto", "tiny", "small", ...)."""
    return settings(mat).model_size.lower()


def compute_latent(mat, size: str | None = None) -> list[str]:
    """Encode the material's stack, store latent, decoder size and stack hash on it; return notes.

    ``size`` defaults to the material's model size setting.

    Raises ``ValueError`` (no or invalid stack) or ``preview.NeuralUnavailable``; on failure the
    stored hash is cleared so the latent reads as stale.
    """
    stack = stack_from_material(mat)
    if stack is None:
        raise ValueError(f"material {mat.name!r} has no layer stack; add a base layer first")
    s = settings(mat)
    try:
        z, used, notes = preview.encode_latent(stack, size or model_size(mat))
    except preview.NeuralUnavailable:
        s.latent_hash = ""
        raise
    s.latent = z.tolist()
    s.latent_size = used
    s.latent_hash = preview.stack_hash(stack)
    refined = getattr(mat, "neural_refine", None)
    if refined is not None and refined.kept == "yes":  # the refined latent this replaced: no longer what renders
        refined.kept = "replaced"
    return notes


def current_latent(mat):
    """``(z (3, 32), decoder size)`` when the stored latent is current, else None: also None for a stored refined
    latent that F12 would not render (``refined_latent``), so that the previews show what it renders."""
    if not latent_is_current(mat):
        return None
    refined = getattr(getattr(mat, "original", mat), "neural_refine", None)
    if refined is not None and refined.key and refined.kept == "yes":
        latent, _ = refined_latent(mat, stack_from_material(mat))
        if latent is None:
            return None
    return latent_of(mat), settings(mat).latent_size


def refined_latent(mat, stack):
    """``((z, size), None)`` for the material's refined latent (the sidebar's *Refine*) while it is current: refined
    from this stack, stored for the size it was refined for, by this version of the refinement (its key is the one
    a Refine would have now) and for the decoder file still shipped. Else ``(None, why)``, ``why`` a line for the
    user when a refined latent is there but stale (None when the material was never refined, or the refinement
    kept the encoded latent)."""
    mat = getattr(mat, "original", mat)  # Refine writes the original; a depsgraph copy may predate it
    refined = getattr(mat, "neural_refine", None)
    if refined is None or not refined.key or refined.kept not in ("yes", "replaced"):
        return None, None
    from ..core.neural.models import ModelFileError, load_models

    s = mat.neural_layers
    now = preview.stack_hash(stack)
    again = "; rendering the stack encoded again: press Refine to refine it again"
    if refined.stack_hash != now or s.latent_hash != now or s.latent_size != refined.size:
        return None, (
            f"material {mat.name!r}: its refined latent is out of date (the stack or model size changed "
            f"since Refine){again}"
        )
    if refined.kept == "replaced":  # the same stack and size, encoded again over the refined latent
        return None, (
            f"material {mat.name!r}: its refined latent was replaced by the stack encoded again (Evaluate, an "
            "edit undone by hand, a model size setting that resolves to the same size); rendering the encoded "
            "latent: press Refine to refine it again"
        )
    try:
        shipped = load_models(refined.size).digest
    except (ValueError, FileNotFoundError, ModelFileError):
        shipped = None  # the renderer reports the missing models itself
    if shipped != refined.decoder_digest:
        return None, (
            f"material {mat.name!r}: its latent was refined for another decoder_{refined.size}.onnx than "
            f"the shipped one{again}"
        )
    if shipped is not None and refined.key != _refine_key(stack, refined.size):
        return None, (
            f"material {mat.name!r}: its latent was refined by an earlier version (of the refinement, its "
            f"reference or the models it depends on){again}"
        )
    return (latent_of(mat), refined.size), None


def _refine_key(stack, size: str) -> str | None:
    """The key a Refine of ``stack`` at ``size`` would have now (the operator's default settings), or None when
    a model file it depends on is missing."""
    from ..core.neural.refine import RefineSettings, refine_key

    try:
        return refine_key(stack, size, RefineSettings())
    except OSError:
        return None


def on_stack_changed(mat) -> None:
    """Called after every edit of the stack: tag the material, and recompute the latent when automatic and
    possible.

    The tag tells the depsgraph, and so the viewport and the evaluated copies the render operators export,
    that the material changed: removing or moving a layer from Python (the sidebar's operators) tags nothing
    by itself. Failures leave the latent stale (its hash no longer matches); the evaluate operator reports why.
    """
    if _suspend_updates:
        return
    tag_changed(mat)
    s = settings(mat)
    if not s.auto_latent:
        return
    try:
        if latent_is_current(mat) and s.latent_size == preview.resolve_size(model_size(mat)):
            return  # the stack and size it was made for (an edit undone, a map changed): kept, refined or not
        compute_latent(mat)
    except (ValueError, preview.NeuralUnavailable):
        s.latent_hash = ""

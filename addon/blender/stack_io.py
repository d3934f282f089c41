"""Material <-> ``addon.core.stack.Stack``, and the latent stored on the material.

``stack_from_material(mat)`` is what every consumer (operators, the render engine's scene export)
calls: it returns the material's ``Stack``, ``None`` when the material has no layer stack, and
raises ``ValueError`` with a message for the user when the stack is not valid.

``stack_text`` / ``stack_from_text`` are the text a layer preset and the layer stack clipboard hold, and
``follow_layers`` keeps a material's keyframes and drivers on their layers when the editor reorders them.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Optional, Sequence

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


def stack_to_material(stack: Stack, mat, sidebar: Sequence[dict] | None = None) -> None:
    """Replace the material's layers with ``stack`` (bottom to top) and refresh its latent.

    ``sidebar`` (from ``stack_from_text``): one entry per layer with what the core stack does not hold, its name
    and, for a conductor given by its colour, that colour; without it the layers get default names."""
    with bulk_edit(mat) as s:
        s.layers.clear()
        names: set[str] = set()
        for i, layer in enumerate(stack.layers):
            item = s.layers.add()
            write_layer(item, layer)
            entry = sidebar[i] if sidebar is not None else {}
            if "f0" in entry:
                item.conductor_mode = "F0"
                item.f0 = entry["f0"]
            item.name = entry.get("name") or default_layer_name(item.layer_type, names)
            names.add(item.name)
        s.active_index = len(s.layers) - 1


# --------------------------------------------------------------------------------------------
# The text of a layer preset and of the layer stack clipboard

# What a preset holds beside ``Stack.to_dict()``: each layer's name and a conductor's F0 colour. ``Stack.from_dict``
# reads no other top-level key, so the add-on's versions before this one apply such a text too (without the names and
# colours), and a text without it (a preset saved by them) applies here with default names.
SIDEBAR_KEY = "sidebar"


def stack_text(mat) -> str:
    """The material's layer stack as a layer preset and the clipboard hold it: ``Stack.to_json()``'s object with a
    ``"sidebar"`` list, bottom to top, of each layer's ``name`` and, for a conductor given by its colour (Specify:
    Colour), its ``f0``. Parameter maps (image references) and the latent are left out. ``ValueError`` for a stack
    that is not valid (``stack_from_material``)."""
    stack = stack_from_material(mat)
    if stack is None:
        raise ValueError(f"material {mat.name!r} has an empty layer stack: add a base layer or pick a preset")
    sidebar = []
    for item in mat.neural_layers.layers:
        entry = {"name": item.name}
        if item.layer_type == "CONDUCTOR" and item.conductor_mode == "F0":
            entry["f0"] = [float(v) for v in item.f0]
        sidebar.append(entry)
    return json.dumps({**stack.to_dict(), SIDEBAR_KEY: sidebar}, sort_keys=True)


def stack_from_text(text: str) -> tuple[Stack, list[dict] | None]:
    """``(stack, sidebar)`` from a layer preset's or the clipboard's text (``stack_text``; a bare ``Stack.to_json()``
    too, whose ``sidebar`` is None). ``ValueError`` says in words why a text is not a layer stack (the callers say
    whose text it was)."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"the text is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg.lower()})") from None
    if not isinstance(data, dict) or "base" not in data:
        raise ValueError(
            "the text holds no 'base' layer (a layer stack is a JSON object with a 'base' layer and a list of "
            "'coatings', as Add Layer Preset and Copy Layer Stack write it)"
        )
    _check_layer_order(data)
    try:
        stack = Stack.from_dict(data)
    except (ValueError, TypeError, KeyError) as e:
        raise ValueError(str(e)) from None
    sidebar = data.get(SIDEBAR_KEY)
    return stack, (None if sidebar is None else _checked_sidebar(sidebar, stack))


def _check_layer_order(data: dict) -> None:
    """A coating as the base, or a base above it, said as the sidebar says it (the core's message names its fields)."""
    bases = {cls.__name__ for cls in (Diffuse, Conductor, Dielectric)}
    base = data["base"]
    if isinstance(base, dict) and base.get("type") == "Coating":
        raise ValueError(
            "its bottom layer is a Coating; the bottom layer must be a base: Diffuse, Conductor or Dielectric"
        )
    coatings = data.get("coatings")
    for i, layer in enumerate(coatings if isinstance(coatings, list) else []):
        if isinstance(layer, dict) and layer.get("type") in bases:
            raise ValueError(
                f"layer {i + 2} from the bottom is a {layer['type']} above the base; only Coating layers go above it"
            )


def _checked_sidebar(sidebar, stack: Stack) -> list[dict]:
    """The ``"sidebar"`` entries of a stack's text, checked: a name (text) and, for a conductor, an F0 colour in its
    valid range. Keys this version does not know are left out (a newer version's)."""
    n = len(stack.layers)
    if not isinstance(sidebar, list) or len(sidebar) != n:
        raise ValueError(f"the '{SIDEBAR_KEY}' entry must list one entry per layer ({n}), bottom to top")
    checked = []
    for i, (entry, layer) in enumerate(zip(sidebar, stack.layers, strict=True)):
        where = "the base" if i == 0 else f"layer {i + 1} from the bottom"
        if not isinstance(entry, dict):
            raise ValueError(f"the '{SIDEBAR_KEY}' entry of {where} must be an object with its 'name'")
        kept = {}
        name = entry.get("name")
        if name is not None:
            if not isinstance(name, str) or not name.strip():
                raise ValueError(f"the name of {where} must be a text that is not empty, got {name!r}")
            kept["name"] = name.strip()
        if "f0" in entry:
            if not isinstance(layer, Conductor):
                raise ValueError(f"{where} has an F0 colour but is a {type(layer).__name__}: only a Conductor has one")
            f0 = entry["f0"]
            if not isinstance(f0, list) or len(f0) != 3:
                raise ValueError(f"the F0 colour of {where} must be three numbers (red, green, blue), got {f0!r}")
            Conductor.from_f0(tuple(f0))  # ValueError naming the channel, the value and the valid range
            kept["f0"] = tuple(float(v) for v in f0)
        checked.append(kept)
    return checked


# --------------------------------------------------------------------------------------------
# Animation of the layers: keyframes and drivers follow their layer

# Blender keys a layer's animation by its position: ``neural_layers.layers[2].thickness``.


@dataclass
class LayerAnimation:
    """What ``follow_layers`` did to a material's animation of its layers (F-curves and drivers)."""

    moved: int = 0  # curves kept, on their layer's new position (the same position too)
    removed: Counter = field(default_factory=Counter)  # old layer index -> curves removed with that layer
    copied: int = 0  # curves copied onto a duplicate
    # (action, its copy) names: an action whose slot another data-block uses too, copied for this material
    separated: list = field(default_factory=list)

    @property
    def total(self) -> int:
        """Curves on the layers before the edit."""
        return self.moved + sum(self.removed.values())


def _channelbags(action, slot):
    """The channelbags of ``slot`` in ``action``'s layers (none where either is missing)."""
    if action is None or slot is None:
        return
    for layer in action.layers:
        for strip in layer.strips:
            bag = strip.channelbag(slot)
            if bag is not None:
                yield bag


def _nla_strips(anim):
    """Every NLA strip of ``anim``, a meta strip's strips too."""

    def strips(collection):
        for strip in collection:
            yield strip
            yield from strips(strip.strips)

    for track in anim.nla_tracks:
        yield from strips(track.strips)


def _curve_collections(anim):
    """Every collection of F-curves that animates the data-block of ``anim``: the channelbags of its action's slot and
    of its NLA strips' actions (each once), then its drivers; ``(collection, is_drivers)``."""
    seen = set()
    for action, slot in [(anim.action, anim.action_slot), *((s.action, s.action_slot) for s in _nla_strips(anim))]:
        for bag in _channelbags(action, slot):
            if bag.as_pointer() not in seen:
                seen.add(bag.as_pointer())
                yield bag.fcurves, False
    yield anim.drivers, True


def _separate_shared_actions(owner, anim, edits) -> list[tuple[str, str]]:
    """Give ``owner`` its own copy of each action (its active one, its NLA strips') whose slot for it another
    data-block uses too and whose curves of that slot ``edits(fcurves)`` would change, as Blender's "make single
    user" of an action does: the copy is named as Blender names copies ("Action.001") and ``owner`` keeps its slot in
    it, so the others keep their animation exactly while ``owner``'s curves follow its layers. A material copied with
    its action shared (``Material.copy()``, Shift+D with Duplicate Data > Action off, a slot assigned to two) had
    its layer edits rewrite the other's keyframes. Returns (action, copy) names."""

    def shared(action, slot):
        return (
            action is not None
            and slot is not None
            and any(user != owner for user in slot.users())
            and any(edits(bag.fcurves) for bag in _channelbags(action, slot))
        )

    strips = [strip for strip in _nla_strips(anim) if shared(strip.action, strip.action_slot)]
    tweaking = anim.use_tweak_mode  # its action is then the tweaked strip's (among the strips)
    active = not tweaking and shared(anim.action, anim.action_slot)
    if not (strips or active):
        return []
    if tweaking:  # no action can be changed while a strip is tweaked: tweak mode is left and entered again
        anim.use_tweak_mode = False
    copies = {}

    def own_copy(action):
        if action.as_pointer() not in copies:
            copies[action.as_pointer()] = action.copy()
        return copies[action.as_pointer()]

    def reassign(holder):  # the AnimData or a strip: its action's copy, with the same slot
        handle = holder.action_slot.handle
        copy = own_copy(holder.action)
        holder.action = copy
        holder.action_slot = next(slot for slot in copy.slots if slot.handle == handle)

    separated = []
    for holder in ([anim] if active else []) + strips:
        name = holder.action.name
        reassign(holder)
        if (name, holder.action.name) not in separated:
            separated.append((name, holder.action.name))
    if tweaking:
        anim.use_tweak_mode = True
    return separated


def follow_layers(mat, new_index_of: Sequence[int | None], copies: dict[int, int] | None = None) -> LayerAnimation:
    """Keep ``mat``'s keyframes and drivers on their layers after the layers moved: Blender stores them by position
    (``neural_layers.layers[i]``), so without this an edit that inserts, removes or moves a layer leaves them on
    whichever layer takes the position.

    ``new_index_of[i]`` is the new position of the layer that was at ``i``, None when it was removed (its curves are
    removed); ``copies`` maps an old position to the position of a copy of that layer (Duplicate), which gets copies
    of its curves. Curves of the action's slot for ``mat``, of its NLA strips' actions and its drivers are followed;
    curves on positions ``new_index_of`` does not cover (no layer before the edit) and paths that name a layer by its
    name (``layers["Coat"]``, which follow it anyway) are left as they are. Where another data-block uses the same
    action slot (a copy of the material), ``mat`` first gets its own copy of the action, so the other's animation stays
    as it was (``_separate_shared_actions``; the result's ``separated``). Undo restores it with the edit."""
    return _follow(mat, "neural_layers.layers", new_index_of, copies or {})


def follow_maps(mat, layer: int, new_index_of: Sequence[int | None]) -> LayerAnimation:
    """:func:`follow_layers` for the parameter maps of layer ``layer``: Blender keys a map's animation by its position
    too (``neural_layers.layers[i].maps[j]``), so removing a map handed its keyframes to the next one."""
    return _follow(mat, f"neural_layers.layers[{layer}].maps", new_index_of, {})


def _follow(mat, prefix: str, new_index_of: Sequence[int | None], copies: dict[int, int]) -> LayerAnimation:
    """Move the curves of the items of collection ``prefix`` (a data path) to their items' new positions, remove those
    of removed items and copy those of copied ones (:func:`follow_layers`)."""
    pattern = re.compile(re.escape(prefix) + r"\[(\d+)\](.*)$", re.DOTALL)
    done = LayerAnimation()
    anim = getattr(mat, "animation_data", None)
    if anim is None:
        return done

    def followed(curve):  # (old position, rest of the path) of a curve on an item the edit covers, else None
        match = pattern.match(curve.data_path)
        if match is None or int(match.group(1)) >= len(new_index_of):
            return None
        return int(match.group(1)), match.group(2)

    def edits(curves):  # whether following changes any of ``curves``
        found = (followed(curve) for curve in curves)
        return any(f is not None and (new_index_of[f[0]] != f[0] or f[0] in copies) for f in found)

    done.separated = _separate_shared_actions(mat, anim, edits)
    for curves, is_drivers in _curve_collections(anim):
        to_copy = []
        for curve in list(curves):
            found = followed(curve)
            if found is None:
                continue
            old, rest = found
            new = new_index_of[old]
            if new is None:
                curves.remove(curve)
                done.removed[old] += 1
                continue
            if new != old:
                curve.data_path = f"{prefix}[{new}]{rest}"
            done.moved += 1
            if old in copies:
                to_copy.append((curve, f"{prefix}[{copies[old]}]{rest}"))
        done.copied += _copy_curves(curves, is_drivers, to_copy)
    return done


def _copy_curves(curves, is_drivers: bool, to_copy) -> int:
    """Copy each (curve, data path) of ``to_copy`` into ``curves`` (F-curves or drivers) at that path."""
    for curve, path in to_copy:
        if is_drivers:
            curves.from_existing(src_driver=curve).data_path = path
        else:
            curves.new_from_fcurve(curve, data_path=path)
    return len(to_copy)


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

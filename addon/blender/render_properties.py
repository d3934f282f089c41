"""Render settings of the Neural Layered engine, stored on the scene (``scene.neural_render``)."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty

from ..core.render import RenderSettings
from .properties import model_size_items

DENOISE_GROUP = "Neural Layered Denoise"
DENOISING_PASSES = (("Denoising Normal", 3, "XYZ", "VECTOR"), ("Denoising Albedo", 3, "RGB", "COLOR"))


_DENOISE_MARK = "neural_layered_denoise"  # an ID property on the compositor groups *Denoise* makes, and on its nodes
_MADE_KEY = "neural_layered_denoise_made"  # the group's contents as *Denoise* last left them (``_contents``)


def _is_denoise_group(group) -> bool:
    """Whether ``group`` is a compositor that *Denoise* made (marked, or by its name in files from before the mark)."""
    return bool(group.get(_DENOISE_MARK)) or group.name == DENOISE_GROUP or group.name.startswith(DENOISE_GROUP + ".")


def _foreign_compositor_note(scene) -> str | None:
    """A note when the scene already has a compositor of its own (left alone), else None."""
    group = scene.compositing_node_group
    if group is not None and not _is_denoise_group(group):
        return (
            f"the scene already has the compositor {group.name!r}: connect its Render Layers' Denoising "
            "Normal and Denoising Albedo to a Denoise node"
        )
    return None


def denoise_note(scene) -> str | None:
    """Why *Denoise* cannot act fully on ``scene``: the scene already has a compositor of its own (left alone), has
    none (a scene copied with Copy Settings, a group removed), does not composite (Post Processing > Compositing
    off), or ours lacks its guides; else None. What it advises keeps the nodes a user added to our compositor
    (``ensure_denoise_compositor`` adds only what is missing)."""
    note = _foreign_compositor_note(scene)
    if note is not None:
        return note
    group = scene.compositing_node_group
    if group is None:
        return "the scene has no compositor (copied from another, or removed): turn Denoise off and on again"
    if not scene.render.use_compositing:
        return "Output > Post Processing > Compositing is off: turn it on"
    denoise = _node_of(group, "CompositorNodeDenoise")
    if denoise is not None and denoise.mute:
        return f"the Denoise node of the compositor {group.name!r} is muted: unmute it (M in the compositor)"
    if _guides_unlinked(group):
        # Denoise turned on (by a script) before the engine was this one: the Render Layers node had no guide
        # outputs to link then, and OpenImageDenoise ran on the image alone
        return (
            "its Denoise node has no albedo and normal guides linked: turn Denoise off and on again to link them "
            "(nodes added to its compositor are kept)"
        )
    return None


def denoise_off_note(scene) -> str | None:
    """With *Denoise* off, a line for its panel when the scene's compositor is ours and was kept, its Denoise node
    muted, because it holds nodes or links of the user's (``_denoise_changed``); else None."""
    group = scene.compositing_node_group
    if scene.neural_render.denoise or group is None or not _is_denoise_group(group):
        return None
    denoise = _node_of(group, "CompositorNodeDenoise")
    if denoise is None or not denoise.mute:
        return None
    return f"Compositor {group.name!r} kept (it holds your edits), its Denoise node muted"


def _node_of(group, bl_idname: str):
    """The node of type ``bl_idname`` that *Denoise* made in ``group`` (marked), else the first of that type, else
    None."""
    nodes = [n for n in group.nodes if n.bl_idname == bl_idname]
    return next((n for n in nodes if n.get(_DENOISE_MARK)), nodes[0] if nodes else None)


def _guides_unlinked(group) -> bool:
    """Whether our compositor's Denoise node lacks a link to its Normal or Albedo input."""
    denoise = _node_of(group, "CompositorNodeDenoise")
    return denoise is not None and not (denoise.inputs["Normal"].is_linked and denoise.inputs["Albedo"].is_linked)


def _socket_value(socket):
    """An unlinked input's value as plain Python (a colour as a tuple), or None where it has none."""
    value = getattr(socket, "default_value", None)
    return tuple(value) if hasattr(value, "__len__") and not isinstance(value, str) else value


def _contents(group) -> str:
    """What ``group`` holds, as one string: its nodes (type, muted, its unlinked inputs' values) and links (their
    nodes' types and sockets), in an order of their own; not the nodes' places or names."""
    nodes = sorted(
        repr((n.bl_idname, n.mute, [(s.identifier, _socket_value(s)) for s in n.inputs if not s.is_linked]))
        for n in group.nodes
    )
    links = sorted(
        repr((k.from_node.bl_idname, k.from_socket.identifier, k.to_node.bl_idname, k.to_socket.identifier))
        for k in group.links
    )
    return repr((nodes, links))


# What *Denoise* made before it recorded its groups' contents: its nodes' types, and its links as (from node's type,
# socket, to node's type, socket), by the sockets' names
_FIRST_NODES = sorted(("CompositorNodeRLayers", "CompositorNodeDenoise", "NodeGroupOutput"))
_FIRST_LINKS = {
    ("CompositorNodeRLayers", "Image", "CompositorNodeDenoise", "Image"),
    ("CompositorNodeRLayers", "Denoising Normal", "CompositorNodeDenoise", "Normal"),
    ("CompositorNodeRLayers", "Denoising Albedo", "CompositorNodeDenoise", "Albedo"),
    ("CompositorNodeDenoise", "Image", "NodeGroupOutput", "Image"),
}


def _holds_only_what_denoise_made(group) -> bool:
    """Whether ``group`` holds exactly what *Denoise* left in it: no node, link or setting added or changed since
    (a group from a file saved before the option recorded it: its three nodes, unmuted, and its links alone)."""
    made = group.get(_MADE_KEY)
    if made is not None:
        return made == _contents(group)
    links = {(k.from_node.bl_idname, k.from_socket.name, k.to_node.bl_idname, k.to_socket.name) for k in group.links}
    nodes = group.nodes
    return (
        sorted(n.bl_idname for n in nodes) == _FIRST_NODES and not any(n.mute for n in nodes) and links <= _FIRST_LINKS
    )


def ensure_denoise_compositor(scene) -> str | None:
    """Set the scene's compositor to Render Layers -> Denoise (image, normal, albedo) -> output,
    Blender's own OpenImageDenoise; returns a note when the scene already has another compositor
    (left alone). Each scene has a group of its own: one shared by two scenes would render one scene's layers in
    the other's compositor. A group of ours that exists gets only what it lacks (a node, a link), and its Denoise
    node unmuted: nothing a user added to it (a Glare, a File Output, links of theirs) goes; it cleared every node
    at each set, the same value included."""
    note = _foreign_compositor_note(scene)
    if note is not None:
        return note
    group = scene.compositing_node_group
    if group is None or group.users > 1:  # none yet, or shared with another scene (a copied scene's)
        group = bpy.data.node_groups.new(DENOISE_GROUP, "CompositorNodeTree")
        group[_DENOISE_MARK] = True
        scene.compositing_node_group = group
    untouched = len(group.nodes) == 0 or _holds_only_what_denoise_made(group)
    if not group.interface.items_tree:
        group.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    made = {}
    for kind, location in (("CompositorNodeRLayers", (-300, 0)), ("CompositorNodeDenoise", (0, 0)),
                           ("NodeGroupOutput", (250, 0))):  # fmt: skip
        node = _node_of(group, kind)
        if node is None:
            node = group.nodes.new(kind)
            node.location = location
            node[_DENOISE_MARK] = True
            if kind == "CompositorNodeRLayers":
                node.scene = scene
        made[kind] = node
    layers, denoise, out = made.values()
    denoise.mute = False
    wanted = [(layers.outputs["Image"], denoise.inputs["Image"]), (denoise.outputs["Image"], out.inputs[0])]
    wanted += [
        (layers.outputs[name], denoise.inputs[socket])
        for name, socket in (("Denoising Normal", "Normal"), ("Denoising Albedo", "Albedo"))
        if name in layers.outputs
    ]
    for source, target in wanted:
        if not target.is_linked:  # linked already: by us, or through nodes of the user's
            group.links.new(source, target)
    if untouched:  # still the option's alone: turning it off may remove it
        group[_MADE_KEY] = _contents(group)
    scene.render.use_compositing = True
    return None


def _denoise_changed(self, context):
    """*Denoise* set (the same value too: a script, a preset). On: our compositor, made or completed. Off: our
    compositor goes where it holds nothing but what *Denoise* made; where it holds the user's nodes or links, it stays
    with its Denoise node muted (the panel says so, ``denoise_off_note``); where another scene shares it, this scene
    lets go of it."""
    scene = self.id_data
    if self.denoise:
        ensure_denoise_compositor(scene)  # a scene with its own compositor: F12 says so (``denoise_note``)
        return
    group = scene.compositing_node_group
    if group is None or not _is_denoise_group(group):
        return
    if group.users > 1 or _holds_only_what_denoise_made(group):
        scene.compositing_node_group = None
        if group.users == 0:
            bpy.data.node_groups.remove(group)
        return
    denoise = _node_of(group, "CompositorNodeDenoise")
    if denoise is not None:
        denoise.mute = True  # the image passes through the user's nodes undenoised


class NLM_RenderSettings(bpy.types.PropertyGroup):
    samples: IntProperty(
        name="Render Samples",
        description="Paths per pixel of a render (F12, Render Animation, the command line). The 3D viewport's "
        "Rendered mode uses Viewport Samples",
        default=64,
        min=1,
        max=65536,
    )
    viewport_samples: IntProperty(
        name="Viewport Samples",
        description="Paths per pixel the 3D viewport's Rendered mode accumulates before it stops (Cycles' "
        "Viewport > Max Samples)",
        default=64,
        min=1,
        max=65536,
    )
    preview_samples: IntProperty(
        name="Render Preview Samples",
        description="Paths per pixel of the Render Preview operator (Render > Render Preview), when it is not given "
        "its own; not the 3D viewport's (Viewport Samples)",
        default=16,
        min=1,
        max=65536,
    )
    max_bounces: IntProperty(
        name="Max Bounces",
        description="Bounces of light after the first hit, as Cycles counts them: 0 is direct lighting only",
        default=6,
        min=0,
        max=1024,
    )
    seed: IntProperty(name="Seed", description="Random seed: the same seed gives the same image", default=0, min=0)
    mode: EnumProperty(
        name="Layered Materials",
        items=[
            (
                "neural",
                "Neural",
                "Evaluate layered materials with the neural decoder (the reference where its models are not available)",
            ),
            (
                "reference",
                "Reference",
                "Evaluate layered materials with the position-free Monte Carlo estimator "
                "(slow; ground truth on average)",
            ),
        ],
        default="neural",
        description="How layered materials are evaluated while rendering",
    )
    reference_walks: IntProperty(
        name="Reference Walks",
        description="Walks per layered-BRDF evaluation in reference mode",
        default=8,
        min=1,
        max=4096,
    )
    decoder_quality: EnumProperty(
        name="Decoder",
        items=model_size_items(
            "Per material, the smallest decoder whose measured error on its stack is shown to be under the "
            "tolerance, reference noise included (measured once per stack and cached; the most accurate one, with a "
            "warning, when none is)",
            "Every layered material on the {size} decoder",
        ),
        default="AUTO",
        description="Neural decoder of layered materials in neural mode. A material's refined latent or baked latent "
        "texture keeps the size it was made for, whatever this says (F12's info names it)",
    )
    time_budget: FloatProperty(
        name="Time Budget",
        description="Auto decoder choice: sizes whose predicted decoder time for the frame (the paths' hits on "
        "layered materials, from a pilot of camera rays, at the size's measured speed, and a fixed cost per batch "
        "of queries) is over this many seconds are not considered, so the paper-sized decoder is only chosen for a "
        "frame it fits",
        default=120.0,
        min=1.0,
        soft_max=3600.0,
        subtype="TIME_ABSOLUTE",
        unit="TIME_ABSOLUTE",
    )
    denoise: BoolProperty(
        name="Denoise",
        description="Write Denoising Normal and Denoising Albedo passes and denoise the image with Blender's "
        "compositor (Denoise node, OpenImageDenoise)",
        default=False,
        update=_denoise_changed,
    )
    calibrate: BoolProperty(
        name="Calibrate Albedo",
        description="Scale each layered material's decoded reflection so that its brightness at every angle "
        "matches the reference (about a second of reference walks per material, once per session; the "
        "viewport makes it after its first full pass, thumbnails use one only once made)",
        default=True,
    )
    tolerance: FloatProperty(
        name="Tolerance",
        description="Largest relative lobe error (against the reference) the Auto decoder choice accepts",
        default=0.2,
        min=0.01,
        max=1.0,
        subtype="FACTOR",
    )

    def calibration(self, viewport: bool = False):
        """The core ``calibrate`` setting: True for renders, "cached" for the viewport (no reference walks
        before its first images; its session makes them after its first full pass) and thumbnails, False when
        Calibrate Albedo is off."""
        return ("cached" if viewport else True) if self.calibrate else False

    def to_core(self, samples: int | None = None, scene=None, viewport: bool = False) -> RenderSettings:
        """Core settings; with ``scene``, its render thread setting (Blender's Threads: Auto or Fixed)
        decides how many cores the path tracer and the networks use. ``samples`` default: Viewport Samples for the
        viewport (``viewport``), else Render Samples."""
        threads = 0 if scene is None else RenderSettings.threads_for(scene.render.threads_mode, scene.render.threads)
        return RenderSettings(
            samples=samples or (self.viewport_samples if viewport else self.samples),
            max_bounces=self.max_bounces,
            seed=self.seed,
            mode=self.mode,
            reference_walks=self.reference_walks,
            threads=threads,
            calibrate=self.calibration(viewport),
            transparent=bool(scene is not None and scene.render.film_transparent),
        )

    def assign_decoders(
        self, core_scene, samples: int | None = None, info: list | None = None, viewport: bool = False, stop=None
    ) -> list[str]:
        """Put the layered materials of an exported scene on their decoders (neural mode), calibrated
        as :meth:`calibration` says; returns warnings.

        *Auto* only considers the sizes whose predicted decoder time for this frame (``samples``
        per pixel, default Samples) fits Time Budget; ``info`` (a list) receives each material's
        size and the reason for it."""
        return self.decoder_assignment(samples, viewport)(core_scene, info, stop)

    def decoder_assignment(self, samples: int | None = None, viewport: bool = False):
        """:meth:`assign_decoders` as a function of ``(core_scene, info, stop)`` that reads no Blender data: the
        settings are read here, on the main thread, and the choice (Auto's measurements, the calibrations:
        seconds) can run on a worker thread."""
        if self.mode != "neural":
            return lambda core_scene, info=None, stop=None: []
        from ..core import quality

        size = "auto" if self.decoder_quality == "AUTO" else self.decoder_quality.lower()
        tolerance, budget, calibrate = self.tolerance, self.time_budget, self.calibration(viewport)
        samples, bounces = samples or self.samples, self.max_bounces

        def assign(core_scene, info: list | None = None, stop=None) -> list[str]:
            pixels = core_scene.camera.width * core_scene.camera.height
            hits = quality.scene_decoder_hits(core_scene, bounces) if size == "auto" else None
            queries = quality.frame_decoder_queries(pixels, samples, bounces, hits)
            chosen = sum(quality.auto_spec(m) is not None for m in core_scene.materials)
            lines: list[str] = []  # the budget's line, and the sizes materials' own latents fix
            core_scene.materials, choices, notes = quality.assign_decoders(
                core_scene,
                size,
                tolerance,
                budget_seconds=budget,
                evaluations=queries,
                batches=quality.frame_decoder_batches(pixels, samples, bounces, chosen),
                calibrate=calibrate,
                only_cached=viewport,  # the viewport reads what renders measured, never stops to measure an edit
                stop=stop,  # F12's Esc, in the measurements and the calibrations (render.Cancelled)
                info=lines,
            )
            if info is not None:
                info += [quality.choice_reason(name, c) for name, c in choices.items()] + lines
            return notes

        return assign


def register() -> None:
    bpy.utils.register_class(NLM_RenderSettings)
    bpy.types.Scene.neural_render = PointerProperty(type=NLM_RenderSettings, name="Neural Layered Render")


def unregister() -> None:
    if hasattr(bpy.types.Scene, "neural_render"):
        del bpy.types.Scene.neural_render
    if getattr(NLM_RenderSettings, "is_registered", False):
        bpy.utils.unregister_class(NLM_RenderSettings)

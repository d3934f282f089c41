"""Settings of a material thumbnail (Blender's material preview renders through this engine).

A thumbnail is small (Blender asks for about 128 x 128 pixels, more on high-DPI screens) and
redrawn on every edit of the material, so it must cost a fraction of a second: a few samples
per pixel, few bounces, the fastest decoder for every layered material (a fixed size: no *Auto*
measurement, whose reference walks cost seconds per stack), neural mode whatever the scene's
mode says (a stack the runtime can encode never meets the reference's walks; one it cannot is
shaded by the reference with the fewest walks), no denoising, and an albedo calibration only where
one was already made (this session, or kept on disk) (``neural.calibrate``: it costs about a second of walks per stack).
"""

from __future__ import annotations

from .integrator import RenderSettings

THUMBNAIL_SAMPLES = 4
THUMBNAIL_BOUNCES = 1
THUMBNAIL_DECODER = "tiny"  # the fastest shipped size (addon.core.neural.models.SIZES[0])
THUMBNAIL_REFERENCE_WALKS = 1
THUMBNAIL_MAX_SIDE = 512  # Blender's largest preview (a 2x-DPI icon) is well below this


def thumbnail_settings(width: int, height: int, threads: int = 0, seed: int = 0) -> RenderSettings:
    """The :class:`RenderSettings` of a ``width`` x ``height`` material thumbnail.

    Raises ``ValueError`` for a size that is not a thumbnail (under 1 or over
    ``THUMBNAIL_MAX_SIDE`` pixels on a side): a full-size frame must not be rendered with
    thumbnail settings by mistake."""
    for name, value in (("width", width), ("height", height)):
        if not 1 <= int(value) <= THUMBNAIL_MAX_SIDE:
            raise ValueError(f"a thumbnail's {name} must be 1..{THUMBNAIL_MAX_SIDE} pixels, got {value}")
    return RenderSettings(
        samples=THUMBNAIL_SAMPLES,
        max_bounces=THUMBNAIL_BOUNCES,
        seed=seed,
        mode="neural",
        reference_walks=THUMBNAIL_REFERENCE_WALKS,
        threads=threads,
        calibrate="cached",
    )


def prepare_thumbnail(scene, threads: int = 0) -> tuple[RenderSettings, list[str]]:
    """Put an exported thumbnail ``scene``'s layered materials on ``THUMBNAIL_DECODER`` and return
    the thumbnail's settings (for its camera's size) with the decoder choice's notes."""
    from .. import quality

    scene.materials, _, notes = quality.assign_decoders(scene, THUMBNAIL_DECODER, calibrate="cached")
    return thumbnail_settings(scene.camera.width, scene.camera.height, threads=threads), notes

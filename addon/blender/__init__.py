"""Blender glue: registers the sub-modules listed in ``_MODULES`` in order (unregisters in reverse).

Every module in the list has ``register()`` and ``unregister()``. To add one, import it here and
append it to ``_MODULES``. ``register()`` is idempotent: calling it twice re-registers cleanly, and
``unregister()`` removes every class and property the modules added.
"""

from __future__ import annotations

from . import bake_ops, bake_state, engine, images, operators, properties, refine_ops, ui

_MODULES = [
    properties,
    operators,
    refine_ops,
    bake_ops,
    bake_state,
    images,
    ui,
    engine,
]

_registered = False


def register() -> None:
    global _registered
    import bpy

    # OpenImageIO (latent-texture EXRs) ships inside Blender; the bpy module keeps it apart.
    expose = getattr(bpy.utils, "expose_bundled_modules", None)
    if expose is not None:
        expose()
    if _registered:
        unregister()
    done = []
    try:
        for module in _MODULES:
            module.register()
            done.append(module)
    except Exception:
        for module in reversed(done):
            module.unregister()
        raise
    from ..core import quality
    from ..core.neural import calibrate

    # albedo calibrations and Auto's measured errors kept across sessions: a scene's first render in a new
    # session walks no reference again for the stacks a session before rendered
    calibrate.use_disk_cache(extension_folder("calibrations"))
    quality.use_disk_cache(extension_folder("quality"))
    _registered = True


def unregister() -> None:
    global _registered
    if not _registered:
        return
    from ..core import quality
    from ..core.neural import calibrate

    calibrate.use_disk_cache(None)
    quality.use_disk_cache(None)
    for module in reversed(_MODULES):
        module.unregister()
    from ..core import release

    release()  # the networks' threads and what the renders kept: a disabled add-on holds none of it
    _registered = False


def extension_folder(name: str) -> str | None:
    """The extension's own user folder ``name`` (Blender keeps it across sessions and upgrades), made if missing; None
    when the add-on is not installed as an extension (registered from a checkout)."""
    import bpy

    parts = (__package__ or "").split(".")
    if parts[0] != "bl_ext" or len(parts) < 3:  # an installed extension is the package bl_ext.<repository>.<id>
        return None
    try:
        return bpy.utils.extension_path_user(".".join(parts[:3]), path=name, create=True)
    except (ValueError, AttributeError, OSError):
        return None

"""Blender glue: registers the sub-modules listed in ``_MODULES`` in order (unregisters in reverse).

Every module in the list has ``register()`` and ``unregister()``. To add one, import it here and
append it to ``_MODULES``. ``register()`` is idempotent: calling it twice re-registers cleanly, and
``unregister()`` removes every class and property the modules added.
"""

from __future__ import annotations

from . import bake_ops, engine, operators, properties, refine_ops, ui

_MODULES = [
    properties,
    operators,
    refine_ops,
    bake_ops,
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
    _registered = True


def unregister() -> None:
    global _registered
    if not _registered:
        return
    for module in reversed(_MODULES):
        module.unregister()
    _registered = False

"""Blender extension entry point: forwards to ``addon.blender``.

Inside Blender this package is ``bl_ext.<repository>.<id>`` and everything below it imports
relatively, so the extension never claims a top-level module name. The tests and the command-line
tools import the same code as the package ``addon`` with the repository root on ``sys.path``.
"""

from __future__ import annotations

import sys

# The modules the extension's zips bundle as wheels (``scripts/build_extension.py``): a package built without them
# (the checkout built as it is) cannot run the renderer.
BUNDLED = ("numba", "llvmlite", "onnxruntime", "embreex")


# What the renderer imports of each bundled module: a wheel that is installed but cannot load on this system (a
# Mac older than the wheels were built for) fails here, not later as a damaged model or an unencodable stack.
RUNTIMES = ("numba", "llvmlite.binding", "onnxruntime", "embreex.rtcore_scene")


def register() -> None:
    import importlib
    import importlib.util

    missing = [name for name in BUNDLED if importlib.util.find_spec(name) is None]
    if missing:
        raise ImportError(
            f"the Neural Layered extension is missing its bundled modules {', '.join(missing)}: install a zip made "
            "by scripts/build_extension.py for your platform (a package built from the source folder has no wheels)"
        )
    broken = []
    for name in RUNTIMES:
        try:
            importlib.import_module(name)
        except Exception as e:  # an ImportError of a native library, an OSError of its loader, ...
            broken.append(f"{name.split('.')[0]} ({type(e).__name__}: {e})")
    if broken:
        import platform

        raise ImportError(
            f"the Neural Layered extension's bundled {'; '.join(broken)} cannot be loaded on this system "
            f"({platform.platform()}): on a Mac its zips need macOS 13 or newer (Intel) or 14 or newer (Apple "
            "silicon); elsewhere, install the zip made for this platform (scripts/build_extension.py)"
        )
    from .addon import blender

    blender.register()


def unregister() -> None:
    from .addon import blender

    blender.unregister()
    # Forget our modules so that enabling again (or an updated version) imports fresh code.
    for name in [n for n in sys.modules if n.startswith(__name__ + ".")]:
        del sys.modules[name]

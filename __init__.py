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


def register() -> None:
    import importlib.util

    missing = [name for name in BUNDLED if importlib.util.find_spec(name) is None]
    if missing:
        raise ImportError(
            f"the Neural Layered extension is missing its bundled modules {', '.join(missing)}: install a zip made "
            "by scripts/build_extension.py for your platform (a package built from the source folder has no wheels)"
        )
    from .addon import blender

    blender.register()


def unregister() -> None:
    from .addon import blender

    blender.unregister()
    # Forget our modules so that enabling again (or an updated version) imports fresh code.
    for name in [n for n in sys.modules if n.startswith(__name__ + ".")]:
        del sys.modules[name]

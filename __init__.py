"""Blender extension entry point: forwards to ``addon.blender``.

The project's code imports itself as the top-level package ``addon`` (as the tests and the
command-line tools do), so this folder goes on ``sys.path`` while the extension is enabled.
"""

from __future__ import annotations

import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))


def _check_addon_package() -> None:
    module = sys.modules.get("addon")
    if module is None:
        return
    path = os.path.dirname(os.path.abspath(getattr(module, "__file__", "") or ""))
    if not path.startswith(_HERE):
        raise ImportError(
            f"another package named 'addon' is already loaded from {path}; "
            "the Neural Layered Materials extension needs that name for its own code"
        )


def register() -> None:
    if _HERE not in sys.path:
        sys.path.insert(0, _HERE)
    _check_addon_package()
    from addon import blender

    blender.register()


def unregister() -> None:
    from addon import blender

    blender.unregister()
    if _HERE in sys.path:
        sys.path.remove(_HERE)
    # Forget our modules so that enabling again (or an updated version) imports fresh code.
    for name in [n for n in sys.modules if n == "addon" or n.startswith("addon.")]:
        path = getattr(sys.modules[name], "__file__", None) or ""
        if os.path.abspath(path).startswith(_HERE):
            del sys.modules[name]

"""Blender extension entry point: forwards to ``addon.blender``.

The project's code imports itself by the absolute name ``addon`` (as the tests and the
command-line tools do, with the repository root on ``sys.path``). Inside Blender this package is
``bl_ext.<repository>.<id>``, so while the extension is enabled its ``addon`` sub-package is
also registered under the top-level name ``addon``; disabling removes it again.
"""

from __future__ import annotations

import importlib
import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))


def _ours(module) -> bool:
    path = getattr(module, "__file__", None) or ""
    return os.path.abspath(path).startswith(_HERE + os.sep)


def _alias_addon_package() -> None:
    existing = sys.modules.get("addon")
    if existing is not None and not _ours(existing):
        raise ImportError(
            f"another package named 'addon' is already loaded from {getattr(existing, '__file__', '?')}; "
            "the Neural Layered Materials extension needs that name for its own code"
        )
    if existing is None:
        sys.modules["addon"] = importlib.import_module(".addon", __name__)


def register() -> None:
    _alias_addon_package()
    from addon import blender

    blender.register()


def unregister() -> None:
    from addon import blender

    blender.unregister()
    # Forget our modules so that enabling again (or an updated version) imports fresh code.
    for name in [n for n in sys.modules if n == "addon" or n.startswith("addon.")]:
        if _ours(sys.modules[name]):
            del sys.modules[name]
    for name in [n for n in sys.modules if n.startswith(__name__ + ".addon")]:
        del sys.modules[name]

"""Blender extension entry point: forwards to ``addon.blender``.

Inside Blender this package is ``bl_ext.<repository>.<id>`` and everything below it imports
relatively, so the extension never claims a top-level module name. The tests and the command-line
tools import the same code as the package ``addon`` with the repository root on ``sys.path``.
"""

from __future__ import annotations

import sys


def register() -> None:
    from .addon import blender

    blender.register()


def unregister() -> None:
    from .addon import blender

    blender.unregister()
    # Forget our modules so that enabling again (or an updated version) imports fresh code.
    for name in [n for n in sys.modules if n.startswith(__name__ + ".")]:
        del sys.modules[name]

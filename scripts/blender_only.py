"""Run a Python script in an interpreter that holds only what Blender ships: bpy and its numpy.

    python scripts/blender_only.py SCRIPT [ARGS...]

The script runs with ``python -S -P`` (no site-packages, no script folder on the path) and a
``PYTHONPATH`` of one temporary folder holding links to this environment's ``bpy`` package (which
carries its own libraries, scripts and bundled modules such as OpenImageIO inside its folder) and
``numpy`` (with its libraries): no Pillow, scipy, torch, checkout or virtual environment, as in
Blender 5.0. ``HOME``, Blender's user resources and user extensions point into that temporary
folder too, so an extension installed there starts fresh. Used by the Blender-only test
(``tests/blender/test_blender_only.py``) and by ``scripts/user_guide_images.py``.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def blender_only_path(folder: Path) -> Path:
    """``folder`` with links to bpy and numpy (and numpy's shared libraries) of this environment."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("bpy", "numpy"):
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            raise FileNotFoundError(f"{name} is not installed as a package in {sys.executable}'s environment")
        package = Path(list(spec.submodule_search_locations)[0])
        (folder / name).symlink_to(package, target_is_directory=True)
        libs = package.with_name(name + ".libs")  # the shared libraries of a manylinux wheel
        if libs.is_dir():
            (folder / libs.name).symlink_to(libs, target_is_directory=True)
    return folder


def blender_only_env(root: Path) -> dict[str, str]:
    """The environment of a Blender-only run under ``root`` (created): path, home, user folders."""
    home = root / "home"
    home.mkdir(parents=True, exist_ok=True)
    return {
        "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
        "HOME": str(home),
        "PYTHONPATH": str(blender_only_path(root / "blender_python")),
        "BLENDER_USER_RESOURCES": str(home / "blender"),
        "BLENDER_USER_EXTENSIONS": str(home / "extensions"),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"),
    }


def run(
    script: Path, args: list[str], root: Path, cwd: Path | None = None, timeout: float = 900, capture: bool = True
) -> subprocess.CompletedProcess:
    """Run ``script`` with ``args`` Blender-only, with its temporary folders under ``root``."""
    env = blender_only_env(root)
    return subprocess.run(
        [sys.executable, "-S", "-P", str(script), *args],
        cwd=cwd or root,
        env=env,
        capture_output=capture,
        text=True,
        timeout=timeout,
    )


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="blender_only_") as tmp:
        return run(Path(argv[0]).resolve(), argv[1:], Path(tmp), cwd=Path.cwd(), capture=False).returncode


if __name__ == "__main__":
    sys.exit(main())

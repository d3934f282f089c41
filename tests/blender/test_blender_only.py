"""The installed extension in an interpreter that holds only what Blender 5.0 ships.

The linux-x64 zip is built with ``scripts/build_extension.py`` and installed into a fresh
user-extensions folder by a Python run with ``-S -P`` (no site-packages, no script folder on the
path) whose ``PYTHONPATH`` is a folder of links to the ``bpy`` package and ``numpy`` alone, as in
Blender (``scripts/blender_only.py``): no Pillow, scipy, torch, checkout or virtual environment. There
``blender_only_session.py`` presses every button with its default settings, from an unsaved and
from a saved .blend, and this test checks that no step raised or reported an error (except the
bake's refusal in an unsaved file, which must say to save it), that every output exists and is
finite, and that nothing was written into the process's working folder.
"""

from __future__ import annotations

import json
import platform
import sys
from pathlib import Path

import pytest

pytest.importorskip("bpy")

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts"))
import blender_only  # noqa: E402
import build_extension  # noqa: E402

SESSION = Path(__file__).with_name("blender_only_session.py")
DEFAULT_PATH_STEPS = (
    "preset_apply",
    "evaluate_latent",
    "preview_lobe",
    "preview_sphere",
    "compare_reference",
    "draw NLM_PT_view3d_stack",
    "draw NLM_PT_view3d_preview",
    "draw NLM_PT_view3d_bake",
    "render_preview png",
    "render_preview exr",
    "F12",
    "reload",
    "F12 after reload",
)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    if (platform.system(), platform.machine()) != ("Linux", "x86_64"):
        pytest.skip("the Blender-only session installs the linux-x64 zip")
    tmp = tmp_path_factory.mktemp("blender_only")
    try:
        zips = build_extension.build(
            ["linux-x64"], tmp / "dist", ROOT / "cache" / "wheels", tmp / "build", log=lambda *_: None
        )
    except build_extension.RegistryUnreachable as e:
        pytest.skip(f"package index unreachable and wheels not cached: {e}")
    work = tmp / "work"
    work.mkdir()
    proc = blender_only.run(SESSION, [str(zips[0]), str(work)], tmp, cwd=work, timeout=600)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-4000:] + proc.stderr[-4000:]
    result = json.loads(lines[-1][len("RESULT ") :])
    # what Blender printed (reports, warnings, tracebacks), without the result line itself
    result["log"] = "\n".join(line for line in proc.stdout.splitlines() if not line.startswith("RESULT ")) + proc.stderr
    return result


def test_interpreter_holds_only_what_blender_ships(session):
    assert session["blocked"] == {"PIL": False, "scipy": False, "torch": False, "addon": False, "pytest": False}
    assert session["install"] == ["FINISHED"] and session["enabled"]


@pytest.mark.parametrize("label", ["unsaved", "saved"])
def test_every_default_path_runs_without_error(session, label):
    steps = session["steps"]
    for name in DEFAULT_PATH_STEPS:
        assert steps[f"{label}: {name}"] in (["FINISHED"], "ok"), (name, steps[f"{label}: {name}"])
    errors = [line for line in session["log"].splitlines() if line.startswith("Error:")]
    assert all("save the file first" in line for line in errors), errors
    assert "Traceback" not in session["log"], session["log"][-4000:]
    assert session["notes"] == [], session["notes"]  # no step raised anything but an operator report


def test_bake_refuses_in_an_unsaved_file_and_bakes_in_a_saved_one(session):
    unsaved = session["steps"]["unsaved: bake_texture"]
    assert "save the file first" in unsaved, unsaved
    assert session["outputs"]["unsaved"]["working folder after bake"] == []
    assert session["steps"]["saved: bake_texture"] == ["FINISHED"]
    saved = session["outputs"]["saved"]
    assert saved["texture_path"].startswith("//textures/"), saved["texture_path"]
    for key in ("texture", "texture after reload"):
        assert saved[key]["exists"] and saved[key]["readable"] and saved[key]["finite"], (key, saved[key])
        assert saved[key]["shape"][2] == 100  # 3 x 32 latent channels, 2 sampling-proxy and 2 top-coat channels


@pytest.mark.parametrize("label", ["unsaved", "saved"])
def test_every_output_exists_and_is_finite(session, label):
    out = session["outputs"][label]
    for name in ("Lobe Material", "Sphere Material", "Compare Material"):
        assert out[name]["exists"] and out[name]["finite"] and out[name]["max"] > 0, (name, out[name])
    for name in ("render_preview png", "render_preview exr", "F12", "F12 after reload"):
        image = out[name]
        assert image["exists"] and image["readable"] and image["finite"], (name, image)
        assert image["shape"][:2] == [24, 32] and image["mean"] > 0, (name, image)
    assert out["reloaded layers"] == 3
    icons = [e for e in out["NLM_PT_view3d_preview"] if e[0] == "template_icon"]
    assert len(icons) == 3, out["NLM_PT_view3d_preview"]  # lobe, sphere and comparison, in the sidebar too


def test_the_renders_calibrations_and_measured_errors_are_kept_in_the_extensions_user_folder(session):
    """A render's albedo calibrations and *Auto*'s measured errors are stored in the extension's own user folder
    (Blender's ``extension_path_user``), so that a later session's first render of the same stacks walks no
    reference."""
    for label in ("unsaved", "saved"):
        names = session["outputs"][label]["calibrations on disk"]
        assert names and all(n.startswith("calibration_") and n.endswith(".npz") for n in names), names
        assert session["outputs"][label]["measured errors on disk"], session["outputs"][label]

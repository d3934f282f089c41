"""The extension package: the manifest validates, the built zip installs into a fresh user
extension folder with ``bpy.ops.extensions.package_install_files``, enables, and its operators run.

The zip is built for this machine's platform only (wheels are cached in ``cache/wheels/``); the
install runs in a separate Python process so that the installed copy, not this checkout, is
what gets imported.
"""

from __future__ import annotations

import importlib.metadata
import json
import platform
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

pytest.importorskip("bpy")

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts"))
import build_extension  # noqa: E402

HOST = {
    ("linux", "x86_64"): "linux-x64",
    ("linux", "aarch64"): "linux-arm64",
    ("darwin", "arm64"): "macos-arm64",
    ("darwin", "x86_64"): "macos-x64",
    ("windows", "amd64"): "windows-x64",
}.get((platform.system().lower(), platform.machine().lower()))


def test_source_manifest_validates():
    cli = build_extension.blender_ext_cli()
    proc = build_extension.run_cli(cli, ["validate", str(ROOT)])
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_manifest_with_wheels_keeps_tables_after_keys():
    src = 'id = "x"\n\n[permissions]\nfiles = "y"\n'
    out = build_extension.manifest_with_wheels(src, ["a-1-py3-none-any.whl"], ["linux-x64"])
    import tomllib

    data = tomllib.loads(out)
    assert data["wheels"] == ["./wheels/a-1-py3-none-any.whl"] and data["platforms"] == ["linux-x64"]
    assert data["permissions"] == {"files": "y"}


def test_unreachable_index_is_told_apart_from_a_missing_wheel(tmp_path, monkeypatch):
    monkeypatch.setattr(build_extension, "_pip_download", lambda req, platform, folder: False)
    with pytest.raises(build_extension.RegistryUnreachable, match="package index is unreachable"):
        build_extension.build(
            ["linux-x64"], tmp_path / "dist", tmp_path / "cache", tmp_path / "build", log=lambda *_: None
        )
    # index reachable, but one platform lacks a required wheel: skipped and named
    monkeypatch.setattr(
        build_extension,
        "_pip_download",
        lambda req, platform, folder: (
            req == "packaging" and ((folder / "packaging-26.0-py3-none-any.whl").write_bytes(b"") is not None)
        ),
    )
    logs = []
    with pytest.raises(RuntimeError, match="onnxruntime"):
        build_extension.build(
            ["windows-arm64"], tmp_path / "dist", tmp_path / "cache2", tmp_path / "build", log=logs.append
        )
    assert any("skipped, no zip: missing onnxruntime" in line for line in logs)


@pytest.fixture(scope="module")
def built_zip(tmp_path_factory):
    if HOST is None:
        pytest.skip(f"no extension platform for this machine ({platform.system()} {platform.machine()})")
    tmp = tmp_path_factory.mktemp("extension")
    try:
        zips = build_extension.build(
            [HOST], tmp / "dist", ROOT / "cache" / "wheels", tmp / "build", log=lambda *_: None
        )
    except build_extension.RegistryUnreachable as e:
        pytest.skip(f"package index unreachable and wheels not cached: {e}")
    assert len(zips) == 1
    return zips[0]


def test_zip_contents(built_zip):
    with zipfile.ZipFile(built_zip) as z:
        names = z.namelist()
        manifest = z.read("blender_manifest.toml").decode()
    assert "__init__.py" in names and "addon/blender/__init__.py" in names and "addon/core/stack.py" in names
    assert "LICENSE" in names  # the text of the GPL-3.0-or-later the manifest declares
    assert "GNU GENERAL PUBLIC LICENSE" in zipfile.ZipFile(built_zip).read("LICENSE").decode()[:200]
    wheels = [n for n in names if n.startswith("wheels/")]
    for dist in ("onnxruntime", "embreex", "protobuf", "flatbuffers", "packaging"):
        assert any(Path(w).name.startswith(dist + "-") for w in wheels), f"no {dist} wheel in {wheels}"
    assert not any(Path(w).name.startswith("numpy") for w in wheels)
    for excluded in ("tests/", "benchmarks/", "onnx_export/", ".venv/", "cache/", "bake/"):
        assert not any(n.startswith(excluded) for n in names), excluded
    assert not any("__pycache__" in n for n in names)
    shipped = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "addon" / "models").glob("*") if p.is_file())
    for model in shipped:
        assert model in names, f"{model} missing from the zip"
    assert f'platforms = ["{HOST}"]' in manifest


INSTALL_SCRIPT = textwrap.dedent(
    """
    import json, os, sys
    import bpy
    out = {}
    zip_path, ext_dir = sys.argv[1], os.environ["BLENDER_USER_EXTENSIONS"]
    def snapshot():
        ids = ("Material", "Scene", "Object", "World", "Light", "WindowManager", "Image")
        props = [t + "." + k for t in ids for k in getattr(bpy.types, t).bl_rna.properties.keys()]
        return sorted(dir(bpy.types)) + props
    before = snapshot()
    out["install"] = sorted(bpy.ops.extensions.package_install_files(
        filepath=zip_path, repo="user_default", enable_on_install=True))
    module = "bl_ext.user_default.neural_layered_materials"
    out["enabled"] = module in bpy.context.preferences.addons
    out["top_level_addon"] = "addon" in sys.modules  # the extension must not claim a global name
    out["addon_file"] = sys.modules[module + ".addon"].__file__
    out["package_dir_on_path"] = any(
        os.path.basename(os.path.normpath(p)) == "neural_layered_materials" for p in sys.path)
    site = os.path.join(ext_dir, ".local", "lib", "python3.11", "site-packages")
    out["wheels_installed"] = (
        sorted(n for n in os.listdir(site) if not n.endswith("-info")) if os.path.isdir(site) else [])

    bpy.ops.wm.read_homefile(app_template="")
    ops = bpy.ops.neural_layers
    results = {}
    def run(name, **kw):
        try:
            results[name] = sorted(getattr(ops, name)(**kw))
        except RuntimeError as e:
            results[name] = "report: " + str(e).strip()
    run("preset_apply", preset="white_diffuse")
    mat = bpy.context.object.active_material
    s = mat.neural_layers
    s.lobe_resolution, s.sphere_resolution, s.env_samples, s.walks = 16, 16, 2, 2
    for name in ("evaluate_latent", "preview_lobe", "preview_sphere", "compare_reference"):
        run(name)
    run("layer_add", layer_type="COATING")
    run("preview_lobe")
    out["ops"] = results
    out["images"] = sorted(i.name for i in bpy.data.images)

    bpy.ops.preferences.addon_disable(module=module)
    out["after_disable"] = hasattr(bpy.types.Material, "neural_layers") or hasattr(bpy.types, "NLM_PT_view3d_stack")
    out["left_behind"] = sorted(set(snapshot()) - set(before))
    out["modules_left"] = sorted(n for n in sys.modules if n.startswith(module + "."))
    bpy.ops.preferences.addon_enable(module=module)
    out["after_enable"] = hasattr(bpy.types.Material, "neural_layers") and hasattr(bpy.types, "NLM_PT_view3d_stack")
    print("RESULT " + json.dumps(out))
    """
)


def test_zip_installs_enables_and_runs(built_zip, tmp_path):
    script = tmp_path / "install.py"
    script.write_text(INSTALL_SCRIPT)
    env = {k: v for k, v in __import__("os").environ.items() if k not in ("PYTHONPATH",)}
    env["BLENDER_USER_EXTENSIONS"] = str(tmp_path / "extensions")
    proc = subprocess.run(
        [sys.executable, str(script), str(built_zip)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = json.loads(lines[-1][len("RESULT ") :])
    assert out["install"] == ["FINISHED"] and out["enabled"]
    assert not out["package_dir_on_path"]  # imports are relative: sys.path is left alone
    assert not out["top_level_addon"]
    # the installed copy is what runs, not this checkout
    assert Path(out["addon_file"]).resolve().is_relative_to((tmp_path / "extensions").resolve())
    assert "onnxruntime" in out["wheels_installed"] and "embreex" in out["wheels_installed"]
    assert "numpy" not in out["wheels_installed"]
    ops = out["ops"]
    for name in ("preset_apply", "preview_lobe", "preview_sphere", "layer_add"):
        assert ops[name] == ["FINISHED"], (name, ops[name])
    for name in ("evaluate_latent", "compare_reference"):
        # neural operators run when a decoder is shipped; otherwise they report why
        assert ops[name] == ["FINISHED"] or "neural models not available" in ops[name], (name, ops[name])
    assert {"Lobe Material", "Sphere Material"} <= set(out["images"])
    assert not out["after_disable"] and out["after_enable"]
    assert out["left_behind"] == []  # disabling removes every type and property the extension added
    assert out["modules_left"] == []  # disabling forgets the code: enabling an update imports it afresh


def _fake_wheel(folder: Path, name: str) -> Path:
    """A minimal valid wheel file (Blender's builder reads wheels as zips)."""
    folder.mkdir(parents=True, exist_ok=True)
    dist, version = name.split("-")[:2]
    path = folder / name
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{dist}/__init__.py", "")
        z.writestr(f"{dist}-{version}.dist-info/METADATA", f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n")
    return path


def test_each_zip_holds_its_own_platforms_wheels_only(tmp_path, monkeypatch):
    """A pure-Python wheel one platform needs (protobuf here) stays out of the other zips, where
    Blender's duplicate-wheel tie-break would pick it over the native one; a platform without
    embreex gets no zip, and the log says why."""
    native = {
        "linux-x64": "cp311-cp311-manylinux_2_28_x86_64",
        "macos-arm64": "cp311-cp311-macosx_14_0_arm64",
    }

    def fake_download(dist, platform, folder, log):
        if dist == "embreex" and platform == "linux-arm64":
            return None
        if dist == "protobuf":
            tag = "py3-none-any" if platform == "macos-arm64" else "cp310-abi3-manylinux2014_x86_64"
        elif dist in ("packaging", "flatbuffers"):
            tag = "py3-none-any"
        else:
            tag = native.get(platform, "cp311-cp311-manylinux_2_28_aarch64")
        return _fake_wheel(folder, f"{dist}-1.0-{tag}.whl")

    monkeypatch.setattr(build_extension, "download", fake_download)
    logs = []
    zips = build_extension.build(
        ["linux-x64", "macos-arm64", "linux-arm64"],
        tmp_path / "dist",
        tmp_path / "cache",
        tmp_path / "build",
        log=logs.append,
    )
    assert sorted(z.name for z in zips) == [
        "neural_layered_materials-0.1.0-linux_x64.zip",
        "neural_layered_materials-0.1.0-macos_arm64.zip",
    ]
    for z in zips:
        with zipfile.ZipFile(z) as f:
            protobufs = [Path(n).name for n in f.namelist() if Path(n).name.startswith("protobuf-")]
            manifest = f.read("blender_manifest.toml").decode()
        assert len(protobufs) == 1, (z.name, protobufs)
        assert ("none-any" in protobufs[0]) == ("macos" in z.name), (z.name, protobufs)
        if "macos" in z.name:
            assert "needs macOS 14.0 or newer" in manifest
        assert "lists none" not in manifest and "#:" not in manifest  # the source's own notes stay behind
        # the stand-in wheels are version 1.0: not what the tests run against, and the manifest says so
        assert f"bundles onnxruntime 1.0, not the tested {importlib.metadata.version('onnxruntime')}" in manifest
    assert any("linux-arm64" in line and "embreex" in line and "no fallback ray caster" in line for line in logs), logs


def test_a_package_without_its_bundled_modules_says_what_is_missing_when_enabled(monkeypatch):
    """The checkout built as it is has no wheels: enabling it names the missing modules and the zips that hold
    them, where it failed deep in an import ("No module named 'llvmlite'")."""
    import importlib.util

    import __init__ as entry  # the extension's entry point (the repository root on sys.path)

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "llvmlite" else real(name, *a))
    with pytest.raises(ImportError, match="missing its bundled modules llvmlite: install a zip made by"):
        entry.register()


def test_a_bundled_runtime_that_cannot_load_is_named_when_enabled(monkeypatch):
    """A wheel installed but not loadable here (a Mac older than the wheels): enabling succeeded, then Evaluate
    called the model "not a loadable ONNX model", F12 said no decoder could encode the stack and rendered with the
    reference, and with embreex broken F12 failed with a bare ImportError. Enabling now names the runtime."""
    import importlib

    import __init__ as entry

    real = importlib.import_module

    def broken(name, *a, **k):
        if name == "onnxruntime":
            raise ImportError("onnxruntime_pybind11_state: symbol not found")
        return real(name, *a, **k)

    monkeypatch.setattr(importlib, "import_module", broken)
    with pytest.raises(
        ImportError, match=r"bundled onnxruntime \(ImportError: onnxruntime_pybind11_state.*\) cannot be"
    ):
        entry.register()

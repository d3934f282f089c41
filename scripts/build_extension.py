"""Build the Blender extension zip(s), with bundled wheels, using Blender's own extension builder.

    python scripts/build_extension.py                          # every platform with wheels
    python scripts/build_extension.py --platforms linux-x64    # one platform (faster)

Steps:
1. download (once; cached in ``cache/wheels/<platform>/``, git-ignored) the cp311 binary wheels
   of onnxruntime, its runtime dependencies (flatbuffers, protobuf, packaging; never numpy,
   which Blender ships) and embreex, with ``pip download --only-binary=:all: --no-deps``;
2. assemble ``build/extension/``: the root ``__init__.py``, ``addon/`` (models included) and a
   ``blender_manifest.toml`` that lists the wheels and platforms;
3. run Blender's extension CLI (``blender_ext.py build --split-platforms``, shipped in the ``bpy``
   wheel) into ``dist/``, then ``blender_ext.py validate`` on every zip.

Each platform's zip is assembled and built on its own, so that it holds its own wheels only (a
pure-Python wheel one platform needs never lands in the others' zips, where Blender's
duplicate-wheel tie-break would pick it over the native one). A platform is built when every
required wheel exists: onnxruntime (the neural runtime) and embreex (the path tracer's ray
casting; there is no fallback ray caster, so a zip without it would render nothing). The log
names each skipped platform and why; today that is linux-arm64 and windows-arm64 (embreex has no
wheel for them). A macOS zip needs the macOS version
its wheels were built for, which the log and the zip's manifest state (macOS 14 for onnxruntime
1.32 on macos-arm64).
Exit status: 0 on success, 1 when nothing could be built or a zip does not validate, 3 when the
package index cannot be reached and the cache does not hold the wheels.
"""

from __future__ import annotations

import argparse
import glob
import importlib.metadata
import importlib.util
import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXTENSION_ID = "neural_layered_materials"

# Blender platform -> wheel platform tags pip may pick for it (cp311; Blender 4.2+ needs glibc 2.28
# on Linux and macOS 11.2 on Mac).
PLATFORM_TAGS: dict[str, list[str]] = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"],
    "linux-arm64": [
        "manylinux_2_28_aarch64",
        "manylinux_2_27_aarch64",
        "manylinux_2_17_aarch64",
        "manylinux2014_aarch64",
    ],
    "macos-arm64": [f"macosx_{v}_0_arm64" for v in (11, 12, 13, 14)]
    + [f"macosx_{v}_universal2" for v in ("10_9", "11_0")],
    "macos-x64": [f"macosx_{v}_x86_64" for v in ("10_9", "10_15", "11_0", "12_0", "13_0")]
    + [f"macosx_{v}_universal2" for v in ("10_9", "11_0")],
    "windows-x64": ["win_amd64"],
    "windows-arm64": ["win_arm64"],
}

# (distribution, what it is for): a platform is built only when every one has a wheel for it.
PACKAGES: list[tuple[str, str]] = [
    ("packaging", "a dependency of onnxruntime"),
    ("onnxruntime", "the neural runtime"),
    ("flatbuffers", "a dependency of onnxruntime"),
    ("protobuf", "a dependency of onnxruntime"),
    ("embreex", "the path tracer's ray casting; there is no fallback ray caster"),
    ("numba", "the renderer's compiled loops (addon/core/kernels.py)"),
    ("llvmlite", "numba's compiler"),
]
# A pure-Python wheel every platform gets: when even this cannot be downloaded, the package index
# is unreachable (pip's own connection errors are not always printed).
PROBE = "packaging"
PINNED_FROM_ENV = ("onnxruntime", "embreex", "numba", "llvmlite")  # ship the versions the tests run against
NEVER_BUNDLE = ("numpy",)


class RegistryUnreachable(RuntimeError):
    pass


def blender_ext_cli() -> Path:
    """Path of Blender's extension CLI inside the installed ``bpy`` wheel."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.origin:
        raise FileNotFoundError("the bpy module is not installed (pip install bpy); it ships Blender's extension CLI")
    hits = glob.glob(
        str(Path(spec.origin).parent / "*" / "scripts" / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py")
    )
    if not hits:
        raise FileNotFoundError(f"blender_ext.py not found under {Path(spec.origin).parent}")
    return Path(sorted(hits)[-1])


def requirement(dist: str) -> str:
    if dist in PINNED_FROM_ENV:
        try:
            return f"{dist}=={importlib.metadata.version(dist)}"
        except importlib.metadata.PackageNotFoundError:
            pass
    return dist


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def cached_wheel(folder: Path, dist: str, version: str | None = None) -> Path | None:
    hits = sorted(
        p
        for p in folder.glob("*.whl")
        if _norm(p.name.split("-")[0]) == _norm(dist) and (version is None or p.name.split("-")[1] == version)
    )
    return hits[-1] if hits else None


def _pip_download(req: str, platform: str, folder: Path) -> bool:
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--only-binary=:all:",
        "--no-deps",
        "--python-version",
        "3.11",
        "--implementation",
        "cp",
        "--disable-pip-version-check",
        "-q",
        "-d",
        str(folder),
    ]
    for tag in PLATFORM_TAGS[platform]:
        cmd += ["--platform", tag]
    proc = subprocess.run(cmd + [req], capture_output=True, text=True)
    if proc.returncode == 0:
        return True
    text = proc.stderr + proc.stdout
    _pip_download.last_error = (text.strip().splitlines() or ["(no output)"])[-1]
    if re.search(
        r"(NewConnectionError|Max retries|Temporary failure in name resolution|Network is unreachable|"
        r"Connection refused|ConnectTimeout|ProxyError|SSLError|ReadTimeout)",
        text,
    ):
        raise RegistryUnreachable(f"pip cannot reach the package index: {text.strip().splitlines()[-1]}")
    return False


def download(dist: str, platform: str, folder: Path, log) -> Path | None:
    """The cached or freshly downloaded wheel of ``dist`` for ``platform``, or None if none exists.

    The version the tests run against is preferred; where it has no wheel for ``platform``, the
    newest version that has one is used and the log says so.
    """
    folder.mkdir(parents=True, exist_ok=True)
    req = requirement(dist)
    pinned = req.split("==")[1] if "==" in req else None
    hit = cached_wheel(folder, dist, pinned)
    if hit is not None:
        return hit
    if _pip_download(req, platform, folder):
        return cached_wheel(folder, dist, pinned)
    if req != dist and _pip_download(dist, platform, folder):
        w = cached_wheel(folder, dist)
        log(f"  {platform}: {req} has no cp311 wheel; using {w.name} instead")
        return w
    if dist == PROBE:
        raise RegistryUnreachable(
            f"cannot download even the pure-Python wheel {PROBE!r}, so the package index is unreachable "
            f"(pip: {getattr(_pip_download, 'last_error', '?')})"
        )
    log(f"  {platform}: no cp311 wheel of {dist}")
    return None


def _macos_minimum(wheels: list[Path]) -> str | None:
    versions = [
        tuple(int(x) for x in m.groups()) for w in wheels for m in [re.search(r"macosx_(\d+)_(\d+)_", w.name)] if m
    ]
    return ".".join(map(str, max(versions))) if versions else None


def collect_wheels(platforms: list[str], cache: Path, log) -> tuple[dict[str, list[Path]], dict[str, list[str]]]:
    """Wheels per buildable platform, and per platform what is missing (with what it is for)."""
    wheels: dict[str, list[Path]] = {}
    missing: dict[str, list[str]] = {}
    for platform in platforms:
        got, lost = [], []
        for dist, purpose in PACKAGES:
            w = download(dist, platform, cache / platform, log)
            if w is None:
                lost.append(f"{dist}, {purpose}")
            else:
                got.append(w)
        missing[platform] = lost
        if lost:
            log(f"  {platform}: skipped, no zip: missing {', '.join(lost)}")
            continue
        for w in got:
            if _norm(w.name.split("-")[0]) in NEVER_BUNDLE:
                raise RuntimeError(f"refusing to bundle {w.name}: Blender ships its own numpy")
        wheels[platform] = got
    return wheels, missing


def manifest_with_wheels(source: str, wheel_names: list[str], platforms: list[str], notes: list[str] = ()) -> str:
    """The source manifest with ``wheels`` and ``platforms`` added as top-level keys (before any
    table), and ``notes`` as comments above them; its source-only comments (lines beginning ``#:``, which say the
    source lists no wheels) left out."""
    source = "".join(line for line in source.splitlines(keepends=True) if not line.startswith("#:"))
    if re.search(r"^\s*(wheels|platforms)\s*=", source, re.M):
        raise ValueError(
            "the source blender_manifest.toml already lists wheels/platforms; the build script writes them"
        )
    keys = "".join(f"# {n}\n" for n in notes) + "platforms = {}\nwheels = [\n{}]\n\n".format(
        json.dumps(platforms), "".join(f'  "./wheels/{n}",\n' for n in wheel_names)
    )
    m = re.search(r"^\[", source, re.M)
    at = m.start() if m else len(source)
    return source[:at] + keys + source[at:]


def platform_notes(platform: str, wheels: list[Path]) -> list[str]:
    """What a user of ``platform`` must know beyond Blender's own requirements: the oldest macOS its wheels run on,
    and each bundled module of another version than the one the tests run against (``download`` takes the newest
    one with a wheel for the platform where the tested one has none), which the tests have not run."""
    notes = []
    if platform.startswith("macos") and (mac := _macos_minimum(wheels)):
        notes.append(f"{platform}: needs macOS {mac} or newer (the bundled wheels are built for it)")
    for w in wheels:
        dist, version = w.name.split("-")[:2]
        tested = next((requirement(d) for d in PINNED_FROM_ENV if _norm(d) == _norm(dist)), "")
        if "==" in tested and tested.split("==")[1] != version:
            notes.append(
                f"{platform}: bundles {dist} {version}, not the tested {tested.split('==')[1]} (which has no wheel "
                "for this platform)"
            )
    return notes


def assemble(build: Path, platform: str, wheels: list[Path]) -> None:
    """The package source of one platform's zip: the add-on, that platform's wheels, the manifest."""
    if build.exists():
        shutil.rmtree(build)
    build.mkdir(parents=True)
    shutil.copy2(ROOT / "__init__.py", build / "__init__.py")
    shutil.copy2(ROOT / "LICENSE", build / "LICENSE")  # the GPL-3.0-or-later the manifest declares, its text
    shutil.copytree(ROOT / "addon", build / "addon", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    (build / "wheels").mkdir()
    for w in wheels:
        shutil.copy2(w, build / "wheels" / w.name)
    source = (ROOT / "blender_manifest.toml").read_text()
    names = sorted(w.name for w in wheels)
    manifest = manifest_with_wheels(source, names, [platform], platform_notes(platform, wheels))
    (build / "blender_manifest.toml").write_text(manifest)


def run_cli(cli: Path, args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(cli), *args], capture_output=True, text=True)


def build(platforms: list[str], out: Path, cache: Path, build_dir: Path, log=print) -> list[Path]:
    """Build and validate one zip per buildable platform; return their paths. Raises on failure
    (see module docstring)."""
    unknown = [p for p in platforms if p not in PLATFORM_TAGS]
    if unknown:
        raise ValueError(f"unknown platform(s) {unknown}; known: {sorted(PLATFORM_TAGS)}")
    cli = blender_ext_cli()
    log(f"wheels (cache {cache}):")
    wheels, missing = collect_wheels(platforms, cache, log)
    if not wheels:
        raise RuntimeError(f"no platform has all required wheels; missing: {missing}")
    for platform, ws in sorted(wheels.items()):
        notes = "".join(f"; {n.split(': ', 1)[1]}" for n in platform_notes(platform, ws))
        log(f"  {platform}: {', '.join(w.name for w in ws)}{notes}")
    out.mkdir(parents=True, exist_ok=True)
    version = tomllib.loads((ROOT / "blender_manifest.toml").read_text())["version"]
    zips = []
    for platform, ws in sorted(wheels.items()):
        source = build_dir / platform
        assemble(source, platform, ws)
        z = out / f"{EXTENSION_ID}-{version}-{platform.replace('-', '_')}.zip"
        z.unlink(missing_ok=True)
        proc = run_cli(cli, ["build", "--source-dir", str(source), "--output-dir", str(out), "--split-platforms"])
        if proc.returncode != 0:
            raise RuntimeError(f"blender_ext.py build failed for {platform}:\n{proc.stdout}{proc.stderr}")
        if not z.exists():
            raise RuntimeError(f"blender_ext.py build did not write {z.name}:\n{proc.stdout}{proc.stderr}")
        v = run_cli(cli, ["validate", str(z)])
        if v.returncode != 0:
            raise RuntimeError(f"{z.name} does not validate:\n{v.stdout}{v.stderr}")
        log(f"built and validated {z} ({z.stat().st_size / 1e6:.1f} MB)")
        zips.append(z)
    skipped = sorted(set(platforms) - set(wheels))
    if skipped:
        log("no zip for " + "; ".join(f"{p} (missing {' and '.join(missing[p])})" for p in skipped))
    return zips


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--platforms",
        default=",".join(PLATFORM_TAGS),
        help=f"comma-separated Blender platforms (default: all of {', '.join(PLATFORM_TAGS)})",
    )
    ap.add_argument("--out", type=Path, default=ROOT / "dist", help="folder for the zips (default: dist/)")
    ap.add_argument(
        "--cache", type=Path, default=ROOT / "cache" / "wheels", help="wheel cache (default: cache/wheels/)"
    )
    ap.add_argument(
        "--build-dir",
        type=Path,
        default=ROOT / "build" / "extension",
        help="staging folder for the package source (default: build/extension/)",
    )
    args = ap.parse_args(argv)
    platforms = [p.strip() for p in args.platforms.split(",") if p.strip()]
    try:
        build(platforms, args.out, args.cache, args.build_dir)
    except RegistryUnreachable as e:
        print(f"error: {e}", file=sys.stderr)
        return 3
    except (RuntimeError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

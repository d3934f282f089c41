"""A user's session with the installed extension, run by ``test_blender_only.py`` in an interpreter
that holds only what Blender ships (bpy and its numpy; no Pillow, scipy, torch, checkout or venv).

    python -S -P blender_only_session.py EXTENSION.zip WORKDIR     (PYTHONPATH: bpy and numpy only)

Installs the zip into a fresh user-extensions folder, then presses every button with its default
settings, from an unsaved and from a saved .blend. Resolutions and sample counts are lowered only
where the setting is not what a step exercises. Prints one line ``RESULT {json}``: what each step
gave, every report, and the outputs it checked (exists, finite).
"""

from __future__ import annotations

import json
import os
import sys
import traceback

import numpy as np

RESULT: dict = {"steps": {}, "reports": [], "outputs": {}, "notes": []}


def blocked_imports() -> dict:
    """What an interpreter holding only Blender's modules must not be able to import."""
    import importlib.util

    return {name: importlib.util.find_spec(name) is not None for name in ("PIL", "scipy", "torch", "addon", "pytest")}


MODULE = "bl_ext.user_default.neural_layered_materials"


def step(name: str, fn) -> object:
    try:
        value = fn()
        operator_result = isinstance(value, list) and all(isinstance(v, str) for v in value)
        RESULT["steps"][name] = value if operator_result else "ok"
        return value
    except RuntimeError as e:  # an operator's ERROR report (Blender's rule for Python callers)
        RESULT["steps"][name] = f"report: {str(e).strip()}"
        return None
    except Exception as e:  # anything else is a bug: recorded with its traceback, the session goes on
        RESULT["steps"][name] = f"{type(e).__name__}: {e}"
        RESULT["notes"].append(f"{name}: {traceback.format_exc()}")
        return None


def op(path: str, **kwargs):
    """Call bpy.ops.<path>; an ERROR report becomes a RuntimeError (Blender's rule for Python callers)."""
    import bpy

    module, name = path.split(".")
    result = getattr(getattr(bpy.ops, module), name)(**kwargs)
    return sorted(result)


def finite_image(path: str) -> dict:
    """Read a written image back (OpenImageIO, as Blender ships it): size and whether every value is finite."""
    import OpenImageIO as oiio  # noqa: N813

    if not os.path.isfile(path):
        return {"exists": False}
    inp = oiio.ImageInput.open(path)
    if inp is None:
        return {"exists": True, "readable": False, "error": oiio.geterror()}
    try:
        spec = inp.spec()
        px = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float"), dtype=np.float64)
    finally:
        inp.close()
    return {
        "exists": True,
        "readable": True,
        "shape": [spec.height, spec.width, spec.nchannels],
        "finite": bool(np.all(np.isfinite(px))),
        "max": float(np.max(px)),
        "mean": float(np.mean(px[..., :3])),
    }


def image_stats(name: str) -> dict:
    import bpy

    image = bpy.data.images.get(name)
    if image is None:
        return {"exists": False}
    w, h = image.size
    px = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(px)
    rgb = px.reshape(h, w, 4)[..., :3]
    return {
        "exists": True,
        "size": [w, h],
        "finite": bool(np.all(np.isfinite(rgb))),
        "max": float(rgb.max()),
        "mean": float(rgb.mean()),
    }


def small_scene() -> None:
    """Lower only what no step is about: the render size and sample counts, the preview image sizes."""
    import bpy

    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 32, 24, 100
    scene.neural_render.samples = 2
    scene.neural_render.preview_samples = 2
    s = bpy.context.object.active_material.neural_layers
    s.lobe_resolution = s.sphere_resolution = 16


def panel_draw(panel: str) -> list:
    """Draw a sidebar panel into a recording layout (headless: no window to draw into); a failure
    to draw is recorded as the step's error."""
    from types import SimpleNamespace

    import bpy

    log: list = []

    class Layout:
        enabled, alert = True, False

        def __getattr__(self, name):
            def record(*args, **kwargs):
                log.append(
                    [name]
                    + [a for a in args if isinstance(a, (str, int))]
                    + [f"{k}={v}" for k, v in kwargs.items() if isinstance(v, (str, int))]
                )
                return Layout()

            return record

    getattr(bpy.types, panel).draw(SimpleNamespace(layout=Layout()), bpy.context)
    return log


def session(label: str, work: str, saved: bool) -> None:
    import bpy

    out = RESULT["outputs"].setdefault(label, {})
    bpy.ops.wm.read_homefile(app_template="")
    blend = os.path.join(work, f"{label}.blend")
    if saved:
        bpy.ops.wm.save_as_mainfile(filepath=blend)
    step(f"{label}: preset_apply", lambda: op("neural_layers.preset_apply", preset="red_car_paint"))
    small_scene()
    mat = bpy.context.object.active_material
    mat_name = mat.name
    for name in ("evaluate_latent", "preview_lobe", "preview_sphere", "compare_reference"):
        step(f"{label}: {name}", lambda n=name: op(f"neural_layers.{n}"))
    for image in (f"Lobe {mat.name}", f"Sphere {mat.name}", f"Compare {mat.name}"):
        out[image] = image_stats(image)
    for panel in ("NLM_PT_view3d_stack", "NLM_PT_view3d_preview", "NLM_PT_view3d_bake"):
        out[panel] = step(f"{label}: draw {panel}", lambda p=panel: panel_draw(p))

    bake = step(f"{label}: bake_texture", lambda: op("neural_layers.bake_texture"))
    out["texture_path"] = mat.neural_layers.texture_path
    if bake == ["FINISHED"]:
        out["texture"] = finite_image(bpy.path.abspath(mat.neural_layers.texture_path))
    out["working folder after bake"] = sorted(os.listdir(os.getcwd()))

    for ext in ("png", "exr"):
        path = os.path.join(work, f"{label} preview.{ext}")
        step(f"{label}: render_preview {ext}", lambda p=path: op("neural_layers.render_preview", filepath=p))
        out[f"render_preview {ext}"] = finite_image(path)

    scene = bpy.context.scene
    scene.render.engine = "NEURAL_LAYERED"
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = os.path.join(work, f"{label} f12.png")
    step(f"{label}: F12", lambda: op("render.render", write_still=True))
    out["F12"] = finite_image(scene.render.filepath)
    calibrations = bpy.utils.extension_path_user(MODULE, path="calibrations")
    out["calibrations on disk"] = sorted(os.listdir(calibrations)) if os.path.isdir(calibrations) else None
    errors = os.path.join(bpy.utils.extension_path_user(MODULE, path="quality"), "decoder_errors.json")
    out["measured errors on disk"] = len(json.load(open(errors))) if os.path.isfile(errors) else None

    if not saved:
        bpy.ops.wm.save_as_mainfile(filepath=blend)
    else:
        bpy.ops.wm.save_mainfile()
    step(f"{label}: reload", lambda: op("wm.open_mainfile", filepath=blend))
    mat = bpy.data.materials[mat_name]
    out["reloaded layers"] = len(mat.neural_layers.layers)
    if mat.neural_layers.texture_path:
        out["texture after reload"] = finite_image(bpy.path.abspath(mat.neural_layers.texture_path))
    scene = bpy.context.scene
    scene.render.filepath = os.path.join(work, f"{label} f12 reloaded.png")
    step(f"{label}: F12 after reload", lambda: op("render.render", write_still=True))
    out["F12 after reload"] = finite_image(scene.render.filepath)


def main() -> None:
    zip_path, work = sys.argv[1], sys.argv[2]
    RESULT["blocked"] = blocked_imports()
    import bpy

    bpy.utils.expose_bundled_modules()  # OpenImageIO, to read outputs back as Blender would
    RESULT["install"] = step(
        "install",
        lambda: op("extensions.package_install_files", filepath=zip_path, repo="user_default", enable_on_install=True),
    )
    RESULT["enabled"] = MODULE in bpy.context.preferences.addons
    if RESULT["enabled"]:
        cwd = os.path.join(work, "cwd")
        os.makedirs(cwd, exist_ok=True)
        os.chdir(cwd)  # the process's working folder: nothing may land here unasked
        session("unsaved", work, saved=False)
        session("saved", work, saved=True)
    print("RESULT " + json.dumps(RESULT))


if __name__ == "__main__":
    main()

"""docs/user_guide.md step by step, in an interpreter that holds only what Blender ships.

Run by ``scripts/user_guide_images.py`` (through ``scripts/blender_only.py``); not on its own. It
installs the extension zip as the guide's section 1 says, then follows sections 2 to 4 with the
default settings and the red car paint preset: presets menu, Evaluate, Lobe, Sphere, Compare with
Reference, a roughness map and Bake Latent Texture (in a saved file), the Neural Layered engine
with F12 and Render Preview. Every step's result and report goes to stdout; the pictures the guide
shows are written by the add-on itself into OUT (headless Blender has no window to take
screenshots of, so the guide shows what the buttons produce, not the sidebar).

    python -S -P scripts/user_guide_walk.py EXTENSION.zip OUT WORK
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np

MODULE = "bl_ext.user_default.neural_layered_materials"
STEPS: list[dict] = []


def step(section: str, what: str, fn):
    import bpy

    try:
        result = fn()
        outcome = sorted(result) if isinstance(result, set) else "ok"
    except RuntimeError as e:  # an operator's ERROR report
        outcome = f"report: {str(e).strip()}"
    STEPS.append({"section": section, "step": what, "result": outcome})
    print(f"[{section}] {what}: {outcome}", flush=True)
    return bpy


def addon(name: str):
    """A module of the installed extension (bl_ext...), e.g. its film writer."""
    return sys.modules[f"{MODULE}.{name}"]


def write_preview(image_name: str, path: str, normalise: bool) -> None:
    """An image of bpy.data as the guide's PNG, through the add-on's own writer (OpenImageIO)."""
    import bpy

    image = bpy.data.images[image_name]
    w, h = image.size
    px = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(px)
    rgb = px.reshape(h, w, 4)[::-1, :, :3]
    exposure = 1.0 / max(float(np.quantile(rgb, 0.999)), 1e-6) if normalise else 1.0
    addon("addon.core.render.film").write_png(path, rgb, exposure=exposure)


def main() -> None:
    zip_path, out, work = sys.argv[1], sys.argv[2], sys.argv[3]
    os.makedirs(out, exist_ok=True)
    import bpy

    bpy.utils.expose_bundled_modules()
    step(
        "1",
        "Install from Disk",
        lambda: bpy.ops.extensions.package_install_files(
            filepath=zip_path, repo="user_default", enable_on_install=True
        ),
    )
    bpy.ops.wm.read_homefile(app_template="")
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(work, "guide.blend"))
    ops = bpy.ops.neural_layers
    mat = bpy.context.object.active_material
    step("2", "Layer Stack > presets menu > Red Car Paint", lambda: ops.preset_apply(preset="red_car_paint"))
    s = mat.neural_layers
    step("2", "Latent and Previews > Evaluate", lambda: ops.evaluate_latent())
    step("2", "Latent and Previews > Lobe", lambda: ops.preview_lobe())
    step("2", "Latent and Previews > Sphere", lambda: ops.preview_sphere())
    step("2", "Latent and Previews > Compare with Reference", lambda: ops.compare_reference())
    write_preview(f"Lobe {mat.name}", os.path.join(out, "user_guide_lobe.png"), normalise=True)
    write_preview(f"Sphere {mat.name}", os.path.join(out, "user_guide_sphere.png"), normalise=False)
    write_preview(f"Compare {mat.name}", os.path.join(out, "user_guide_compare.png"), normalise=True)

    # section 3: a roughness map on the coating, then the bake
    s.active_index = len(s.layers) - 1
    step("3", "Add Parameter Map > Roughness", lambda: ops.map_add(parameter="ROUGHNESS"))
    rough = bpy.data.images.new("rough", width=64, height=64)
    rough.colorspace_settings.name = "Non-Color"
    ramp = np.repeat(np.linspace(0.0, 1.0, 64)[None, :], 64, axis=0)
    rough.pixels.foreach_set(np.repeat(ramp[..., None], 4, axis=2).astype(np.float32).ravel())
    pmap = s.layers[s.active_index].maps[0]
    pmap.image, pmap.low, pmap.high = rough, 0.05, 0.6
    step("3", "Latent Texture > Bake Latent Texture", lambda: ops.bake_texture())
    STEPS.append({"section": "3", "step": "texture", "result": s.texture_path})

    # section 4: the engine
    scene = bpy.context.scene
    scene.render.engine = "NEURAL_LAYERED"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 320, 240, 100
    scene.render.filepath = os.path.join(work, "f12.png")
    step("4", "Render Properties > Neural Layered; F12", lambda: bpy.ops.render.render(write_still=True))
    step("4", "Render Preview", lambda: ops.render_preview(filepath=os.path.join(out, "user_guide_render.png")))
    print("RESULT " + json.dumps(STEPS))


if __name__ == "__main__":
    main()

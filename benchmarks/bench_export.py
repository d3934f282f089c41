"""Seconds the scene export takes where the viewport meets it, written to docs/export_speed.md.

    python benchmarks/bench_export.py [--out docs/export_speed.md]

Each case in the bpy module (Blender's own export path, ``addon.blender.scene_export.export_scene``), the median of
``--repeats`` exports after a first one:

- a 500,000-triangle sphere: a light moved, and the sphere moved, with the viewport's ``GeometryCache`` told of the
  edit (as ``view_update`` tells it), and from scratch (no cache: every export before the cache);
- a 4K image texture on the startup cube: the first export and the ones after it (the image read, decoded and
  filtered once for each version of its file);
- a Geometry Nodes scatter of 90,000 instances (1.8 M triangles), not realised and realised: one export each.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _timed(f) -> float:
    t = time.perf_counter()
    f()
    return time.perf_counter() - t


def _update(ob) -> list:
    """What the depsgraph reports to ``view_update`` after ``ob`` moved."""
    return [SimpleNamespace(id=ob, is_updated_geometry=False, is_updated_transform=True)]


def big_mesh(bpy, scene_export, repeats: int) -> list[str]:
    bpy.ops.wm.read_homefile(app_template="")
    bpy.ops.mesh.primitive_uv_sphere_add(segments=512, ring_count=490, radius=1.2)  # 500,000 triangles
    sphere, light = bpy.context.object, bpy.context.scene.objects["Light"]
    kept = scene_export.GeometryCache()

    def export(moved, cache):
        moved.location.x += 0.01
        graph = bpy.context.evaluated_depsgraph_get()
        if cache is not None:
            cache.forget(_update(moved))
        scene_export.export_scene(graph, 640, 360, kept=cache)

    scene_export.export_scene(bpy.context.evaluated_depsgraph_get(), 640, 360, kept=kept)
    rows = []
    for what, moved in (("a light moved", light), ("the sphere moved", sphere)):
        cached = statistics.median(_timed(lambda m=moved: export(m, kept)) for _ in range(repeats))
        fresh = statistics.median(_timed(lambda m=moved: export(m, None)) for _ in range(repeats))
        rows.append(f"| 500,000-triangle sphere, {what} | {fresh:.3f} | {cached:.3f} |")
    return rows


def texture(bpy, scene_export, repeats: int, folder: Path) -> list[str]:
    bpy.ops.wm.read_homefile(app_template="")
    img = bpy.data.images.new("big", 4096, 4096)
    img.pixels.foreach_set(np.random.default_rng(0).random(4096 * 4096 * 4).astype(np.float32))
    img.filepath_raw, img.file_format = str(folder / "big4k.png"), "PNG"
    img.save()
    bpy.data.images.remove(img)
    mat = bpy.data.materials["Material"]
    node = mat.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = bpy.data.images.load(str(folder / "big4k.png"))
    mat.node_tree.links.new(node.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    graph = bpy.context.evaluated_depsgraph_get()
    first = _timed(lambda: scene_export.export_scene(graph, 64, 48))
    after = statistics.median(_timed(lambda: scene_export.export_scene(graph, 64, 48)) for _ in range(repeats))
    return [f"| startup cube, a 4K image texture: first export, the exports after it | {first:.3f} | {after:.3f} |"]


def scatter(bpy, scene_export, n: int = 300) -> list[str]:
    rows = []
    for realise in (False, True):
        bpy.ops.wm.read_homefile(app_template="")
        bpy.ops.mesh.primitive_grid_add(x_subdivisions=n, y_subdivisions=n, size=10)
        grid = bpy.context.object
        tree = bpy.data.node_groups.new("scatter", "GeometryNodeTree")
        tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        gi, go = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
        on_points, ico = tree.nodes.new("GeometryNodeInstanceOnPoints"), tree.nodes.new("GeometryNodeMeshIcoSphere")
        ico.inputs["Radius"].default_value, ico.inputs["Subdivisions"].default_value = 0.02, 1
        tree.links.new(gi.outputs[0], on_points.inputs["Points"])
        tree.links.new(ico.outputs["Mesh"], on_points.inputs["Instance"])
        last = on_points
        if realise:
            last = tree.nodes.new("GeometryNodeRealizeInstances")
            tree.links.new(on_points.outputs[0], last.inputs[0])
        tree.links.new(last.outputs[0], go.inputs[0])
        grid.modifiers.new("scatter", "NODES").node_group = tree
        graph = bpy.context.evaluated_depsgraph_get()
        scenes = []
        seconds = _timed(lambda: scenes.append(scene_export.export_scene(graph, 64, 48)[0]))
        what = "realised" if realise else "instances"
        rows.append(
            f"| {n * n:,} icospheres scattered, {what} ({scenes[0].mesh.triangle_count:,} triangles): one export | "
            f"{seconds:.3f} | |"
        )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "export_speed.md")
    args = ap.parse_args(argv)
    import bpy

    from addon import blender

    blender.register()
    from addon.blender import scene_export

    with tempfile.TemporaryDirectory() as folder:
        rows = big_mesh(bpy, scene_export, args.repeats)
        rows += texture(bpy, scene_export, args.repeats, Path(folder))
    rows += scatter(bpy, scene_export)
    for row in rows:
        print(row, flush=True)
    command = "python benchmarks/bench_export.py" + (f" --repeats {args.repeats}" if args.repeats != 3 else "")
    args.out.write_text(
        f"""# Scene export: seconds where the viewport meets them

Written by `{command}`: the bpy module, one process, medians of {args.repeats} exports after a first one (the
scatter: one export each). The viewport's Rendered mode exports the scene at every edit, on Blender's main thread.

| case | from scratch s | with what the exports before kept s |
|---|---|---|
"""
        + "\n".join(rows)
        + """

"From scratch" is every export before the viewport kept anything (no `GeometryCache`); the 4K texture's first
export reads, decodes and filters the image, the ones after it find it kept for that version of its file.
"""
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

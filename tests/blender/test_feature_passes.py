"""The Denoising Normal and Denoising Albedo passes F12 writes, against Cycles' passes of the same scene: a denoiser
built for Cycles' passes (OpenImageDenoise through the compositor's Denoise node) reads them as it reads Cycles'."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

SKY = (0.2, 0.4, 0.6)  # the world's colour, each channel under 1: Cycles' albedo there is the sky's own


def _read_channels(path) -> np.ndarray:
    """(H, W, 3) of a one-layer multilayer EXR that the compositor's File Output wrote, by channel names (R, G, B or
    X, Y, Z, whatever order the file keeps them in)."""
    bpy.utils.expose_bundled_modules()
    import OpenImageIO as oiio  # noqa: N813

    buf = oiio.ImageBuf(str(path))
    assert not buf.has_error, buf.geterror()
    pixels = buf.get_pixels(oiio.FLOAT)
    index = {"R": 0, "X": 0, "G": 1, "Y": 1, "B": 2, "Z": 2}
    out = np.zeros(pixels.shape[:2] + (3,), np.float32)
    for i, name in enumerate(buf.spec().channelnames):
        if name.split(".")[-1] in index:
            out[..., index[name.split(".")[-1]]] = pixels[..., i]
    return out


def _passes(scene, engine: str, folder) -> dict[str, np.ndarray]:
    """F12 of ``scene`` with ``engine``: its Denoising Normal, Denoising Albedo and Depth passes, each written by a
    File Output node of the compositor (Cycles' with its Denoising Data on, this engine's with Denoise on)."""
    scene.render.engine = engine
    layer = scene.view_layers[0]
    layer.use_pass_z = True
    if engine == "CYCLES":
        layer.cycles.denoising_store_passes = True
        scene.cycles.samples = 16
        scene.cycles.use_denoising = False
        group = bpy.data.node_groups.new("passes", "CompositorNodeTree")
        group.nodes.new("CompositorNodeRLayers")
        scene.compositing_node_group = group
    else:
        scene.neural_render.denoise = True  # its compositor: Render Layers -> Denoise -> output
        scene.neural_render.samples = 16
    group = scene.compositing_node_group
    scene.render.use_compositing = True
    layers = next(n for n in group.nodes if n.bl_idname == "CompositorNodeRLayers")
    folder.mkdir()
    for name in ("Denoising Normal", "Denoising Albedo", "Depth"):
        tag = name.replace(" ", "_")
        out = group.nodes.new("CompositorNodeOutputFile")
        out.directory, out.file_name = str(folder) + "/", tag
        out.format.file_format, out.format.color_depth = "OPEN_EXR_MULTILAYER", "32"
        out.file_output_items.new("RGBA", tag)
        group.links.new(layers.outputs[name], out.inputs[0])
    scene.render.filepath = str(folder / "frame.png")
    bpy.ops.render.render(write_still=True)
    return {name: _read_channels(next(folder.glob(name.replace(" ", "_") + "*"))) for name in
            ("Denoising Normal", "Denoising Albedo", "Depth")}  # fmt: skip


def _inside(mask: np.ndarray) -> np.ndarray:
    """The pixels of ``mask`` whose four neighbours are in it too, none on the frame's border."""
    inside = np.zeros_like(mask)
    inside[1:-1, 1:-1] = mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
    return inside


def test_the_denoising_normal_and_albedo_passes_are_cycles_own(fresh_scene, tmp_path):
    """Denoising Normal was in world space (mean |difference| 0.585 from Cycles', which is in the camera's frame),
    and Denoising Albedo 0 where the camera sees the sky, where Cycles writes the sky's colour."""
    scene = fresh_scene.scene
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 48, 27, 100
    scene.neural_render.max_bounces = scene.cycles.max_bounces = 1
    background = scene.world.node_tree.nodes["Background"]
    background.inputs["Color"].default_value = (*SKY, 1.0)
    background.inputs["Strength"].default_value = 1.0
    cycles = _passes(scene, "CYCLES", tmp_path / "cycles")
    scene.compositing_node_group = None
    ours = _passes(scene, "NEURAL_LAYERED", tmp_path / "ours")
    # surfaces: pixels whose neighbours met the cube too, in both (an edge pixel's normal is a mean of two faces')
    hit = _inside((cycles["Depth"][..., 0] < 1e9) & (ours["Depth"][..., 0] < 1e9))
    assert hit.sum() > 100
    normal = np.abs(ours["Denoising Normal"] - cycles["Denoising Normal"])[hit].mean()
    assert normal < 0.05, normal
    # the sky: pixels whose neighbours did not meet the cube either (Cycles' depth is its first sample's: an edge
    # pixel may read none)
    sky = _inside((cycles["Depth"][..., 0] >= 1e9) & (ours["Depth"][..., 0] >= 1e9))
    assert sky.sum() > 500
    np.testing.assert_allclose(cycles["Denoising Albedo"][sky], np.broadcast_to(SKY, (sky.sum(), 3)), atol=1e-3)
    np.testing.assert_allclose(ours["Denoising Albedo"][sky], cycles["Denoising Albedo"][sky], atol=1e-3)

"""Latent textures: per-texel latent codes (3 x 32), the two sampling-proxy channels and the top coating's two.

Channel layout (docs/architecture.md, Conventions): ``z.R.00 .. z.R.31, z.G.00 .. z.B.31, proxy.sigma, proxy.w,
top.alpha, top.ior``, 100 channels in all. The top coating's roughness and index are what a remainder
decoder's exact top lobe needs (``addon.core.neural.top_lobe``); a file written before they existed (98
channels) reads with every texel uncoated (``top_lobe.NO_TOP``).

Stored as a tiled, mip-mapped, half-float OpenEXR through OpenImageIO.
OpenImageIO ships inside Blender and the bpy wheel; inside Blender's Python (or after
``bpy.utils.expose_bundled_modules()``) it is importable as ``OpenImageIO``.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import kernels
from ..neural.top_lobe import NO_TOP
from ..stack import LATENT as LATENT_DIM
from . import files
from .mip import (
    HALF_MAX,
    MipChain,
    build_mip_chain,
    first_row_beyond_half,
    float32_texels,
    store_texels,
    trilinear_lookup,
)

CHANNELS = 3
LATENT_CHANNELS = [f"z.{c}.{i:02d}" for c in "RGB" for i in range(LATENT_DIM)]
PROXY_CHANNELS = ["proxy.sigma", "proxy.w"]
TOP_CHANNELS = ["top.alpha", "top.ior"]
CHANNEL_NAMES = LATENT_CHANNELS + PROXY_CHANNELS + TOP_CHANNELS
TILE = 64
# texels projected at once (``LatentTexture.projected``): a band's float32 latents and products stay under a few MB
PROJECT_TEXELS = 8192
_PROJECTING = threading.Lock()
# rows of a level read at once (``_read_level``): below malloc's largest mmap threshold (32 MB), so that each band's
# buffer reuses the last one's memory; 64 MB bands were mapped and faulted in afresh, 2 s of a 2048 x 2048 read
READ_BAND_BYTES = 16 << 20


def oiio_module():
    """The OpenImageIO module: importable inside Blender; with the bpy wheel it lies in the
    wheel's bundled site-packages, which is found here without importing bpy."""
    try:
        import OpenImageIO as oiio  # noqa: N813

        return oiio
    except ImportError:
        pass
    import importlib.util
    import sys

    spec = importlib.util.find_spec("bpy")
    roots = list(spec.submodule_search_locations or []) if spec is not None else []
    for root in roots:
        for site in sorted(Path(root).glob("*/python/lib/python3*/site-packages")):
            if (site / "OpenImageIO").is_dir():
                sys.path.append(str(site))
                try:
                    import OpenImageIO as oiio  # noqa: N813

                    return oiio
                except ImportError:
                    sys.path.remove(str(site))
    raise RuntimeError(
        "OpenImageIO is not importable: it ships with Blender and the bpy wheel (pip install bpy); "
        "latent textures and EXR output need it"
    )


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Any image OpenImageIO reads (PNG, EXR, TIFF, JPEG, ...) as (H, W, C) float32, rows top to bottom.

    Values are the file's raw values (8/16-bit integers normalised to [0, 1]), colour as stored beside its alpha
    (not multiplied by it, as Blender reads them); no colour transform is applied here (``read_image_file`` also
    tells how the file is encoded, for the colour-space rule of ``colour_maps``).
    """
    return read_image_file(path)[0]


def read_image_file(path: str | os.PathLike) -> tuple[np.ndarray, bool, str, int]:
    """(raw pixels as ``read_image``, stored as floats?, the ``oiio:ColorSpace`` tag or '', alpha channel or -1)."""
    oiio = oiio_module()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    # OpenImageIO multiplies colour by alpha when it reads a file that stores them apart (PNG, TGA, TIFF) unless
    # told not to: a map with transparent pixels came out darkened there (0.216 stored, 0.014 read at alpha 1/4)
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise ValueError(f"cannot read {path} as an image: {oiio.geterror()}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise ValueError(f"cannot read pixels of {path}: {inp.geterror()}")
        is_float = str(spec.format) in ("half", "float", "double")
        return (
            np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels),
            is_float,
            spec.get_string_attribute("oiio:ColorSpace"),
            spec.alpha_channel,
        )
    finally:
        inp.close()


@dataclass
class LatentTexture:
    """A mip chain of (H, W, 100) latent texels; ``levels[0]`` is the finest, held as a ``MipChain`` of half floats
    (baked, read from a file or built :meth:`from_texels`: the values its file stores), or float32 where a list of
    levels is given."""

    levels: list[np.ndarray]
    metadata: dict = field(default_factory=dict)
    # ``projected``'s textures, by decoder
    _projections: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        if not isinstance(self.levels, MipChain):
            self.levels = MipChain(self.levels)

    @classmethod
    def from_texels(cls, texels: np.ndarray, metadata: dict | None = None) -> "LatentTexture":
        """Build the mip chain (box filter in latent space) from (H, W, 100) base texels, in half floats (ValueError
        for a texel beyond their range)."""
        texels = np.asarray(texels, dtype=np.float32)
        if texels.ndim != 3 or texels.shape[2] != len(CHANNEL_NAMES):
            raise ValueError(f"latent texels must have shape (H, W, {len(CHANNEL_NAMES)}), got {texels.shape}")
        if not np.isfinite(texels).all():
            raise ValueError("latent texels must be finite")
        return cls(build_mip_chain(texels, dtype=np.float16), dict(metadata or {}))

    @property
    def filter_levels(self) -> int:
        """How many levels (finest first) lookups use: the bake's measurement (``textures.filtering``, the
        metadata's ``filter_levels``), else all of them."""
        return _filter_levels(self.metadata, len(self.levels))

    @property
    def width(self) -> int:
        return self.levels[0].shape[1]

    @property
    def height(self) -> int:
        return self.levels[0].shape[0]

    def lookup(
        self, uv: np.ndarray, footprint, pick_seed: int | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Latents (N, 3, 32), proxy parameters (N, 2) and top coatings (N, 2: alpha, ior) at uv with a
        footprint in uv units, on the levels the bake found filterable (``filter_levels``): blended, or with
        ``pick_seed`` one texel a row picked with the probability of its weight (``mip.trilinear_lookup``), as the
        renderer reads them."""
        z, rest = trilinear_lookup(
            self.levels, uv, footprint, self.filter_levels, split=CHANNELS * LATENT_DIM, pick_seed=pick_seed
        )
        return z.reshape(-1, CHANNELS, LATENT_DIM), rest[:, :2], rest[:, 2:]

    def projected(self, key, project, width: int) -> "ProjectedTexture":
        """This texture as a decoder's fused graph reads it (:class:`ProjectedTexture`), made once per ``key`` (the
        decoder's size and folder), then kept with the texture (whose texels are not written after it is made).
        ``project(z (N, 3, 32)) -> (N, 3 width)`` is the decoder's ``ModelSet.project_latents``; ``width`` its first
        layer's. The texels are projected as the texture holds them, a band at a time, and stored in its type."""
        with _PROJECTING:
            made = self._projections.get(key)
            if made is not None:
                return made
            zc = CHANNELS * int(width)
            latents = CHANNELS * LATENT_DIM
            c = self.levels[0].shape[2]
            channels = zc + c - latents
            shapes = [(level.shape[0], level.shape[1], channels) for level in self.levels]
            chain = MipChain.__new__(MipChain)
            chain._allocate(shapes, self.levels.dtype)
            src, dst = self.levels.flat.reshape(-1, c), chain.flat.reshape(-1, channels)
            for start in range(0, len(src), PROJECT_TEXELS):  # a loop over bands of texels
                band = src[start : start + PROJECT_TEXELS]
                out = project(float32_texels(band[:, :latents]).reshape(-1, CHANNELS, LATENT_DIM))
                d = dst[start : start + len(band)]
                store_texels(out, d[:, :zc], "a latent texture's texels through the decoder's first layer")
                d[:, zc:] = band[:, latents:]
            made = ProjectedTexture(self.metadata, chain, zc)
            self._projections[key] = made
            return made

    def write_exr(self, path: str | os.PathLike) -> None:
        """Write a tiled, mip-mapped, half-float EXR, published atomically (see ``files.publishing``):
        nothing is left at ``path`` or beside it if writing fails or is interrupted."""
        oiio = oiio_module()
        path = Path(path)
        for i, level in enumerate(self.levels):
            for rows in range(0, level.shape[0], TILE):  # bands of rows: no level-sized temporaries
                band = level[rows : rows + TILE]
                if first_row_beyond_half(band) >= 0:
                    raise ValueError(
                        f"cannot write {path}: mip level {i} holds values outside the half-float range "
                        f"[-{HALF_MAX:g}, {HALF_MAX:g}] (non-finite, or magnitudes up to {np.nanmax(np.abs(band)):.9g} "
                        f"in rows {rows} .. {rows + len(band) - 1})"
                    )
        with files.publishing(path) as tmp:
            out = oiio.ImageOutput.create(str(tmp))
            if out is None:
                raise RuntimeError(f"cannot create an EXR writer for {path}: {oiio.geterror()}")
            try:
                self._write_levels(out, tmp, path)
            finally:
                out.close()
                # A writer of several mip levels finishes the file only when it is destroyed (its close() returned
                # with the file open and short): dropped here, before ``publishing`` flushes and renames it.
                del out

    def _write_levels(self, out, tmp: Path, path: Path) -> None:
        for i, level in enumerate(self.levels):
            h, w, c = level.shape
            spec = oiio_module().ImageSpec(w, h, c, "half")
            spec.channelnames = tuple(CHANNEL_NAMES)
            spec.tile_width = TILE
            spec.tile_height = TILE
            spec.attribute("compression", "zip")
            for key, value in self.metadata.items():
                spec.attribute(f"nlm:{key}", str(value))
            mode = "Create" if i == 0 else "AppendMIPLevel"
            if i == 0:
                spec.attribute("textureformat", "Plain Texture")  # tells the EXR writer: MIPMAP_LEVELS
                spec.attribute("openexr:levelmode", 1)
                spec.attribute("openexr:roundingmode", 0)  # ROUND_DOWN
            if not out.open(str(tmp), spec, mode):
                raise RuntimeError(f"cannot write {path}: {out.geterror()}")
            pixels = level if level.dtype == np.float16 else np.ascontiguousarray(level, dtype=np.float32)
            if not out.write_image(pixels):  # a half-float level as it is held, bit for bit
                raise RuntimeError(f"cannot write level {i} of {path}: {out.geterror()}")

    @classmethod
    def read_exr(cls, path: str | os.PathLike) -> "LatentTexture":
        """Read a latent texture EXR written by :meth:`write_exr` (all mip levels), into a half-float chain: the
        file's values exactly, in half the memory of float32.

        Raises ``FileNotFoundError`` for a missing file and :class:`LatentTextureError` (a
        ``ValueError``) for anything else that is not a valid latent texture: not an image,
        damaged, other channels, a mip chain of the wrong sizes, or non-finite texels. A caller
        can therefore fall back (to the constant stack) on one exception type.
        """
        oiio = oiio_module()
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"latent texture not found: {path}")
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise LatentTextureError(f"cannot read {path} as an image: {oiio.geterror()}")
        try:
            spec = inp.spec()
            names = list(spec.channelnames)
            # OpenEXR stores channels sorted by name: map them back to the layout by name.
            before_top = sorted(names) == sorted(LATENT_CHANNELS + PROXY_CHANNELS)
            if sorted(names) != sorted(CHANNEL_NAMES) and not before_top:
                raise LatentTextureError(
                    f"{path} is not a latent texture: expected {len(CHANNEL_NAMES)} channels "
                    f"{CHANNEL_NAMES[0]} .. {CHANNEL_NAMES[-1]}, got {len(names)}: {names[:4]}..."
                )
            metadata = {a.name[4:]: a.value for a in spec.extra_attribs if a.name.startswith("nlm:")}
            wanted = CHANNEL_NAMES[: len(names)]
            levels = _read_levels(inp, path, [names.index(n) for n in wanted], spec.height, spec.width)
        finally:
            inp.close()
        if not str(metadata.get("filter_levels", "1")).isdigit() or int(metadata.get("filter_levels", 1)) < 1:
            raise LatentTextureError(
                f"{path}: filter_levels must be a positive count, got {metadata['filter_levels']!r}"
            )
        return cls(levels, metadata)


@dataclass(frozen=True)
class ProjectedTexture:
    """A latent texture as a decoder's fused graph reads it (``LatentTexture.projected``): per texel the latents
    through the decoder's first layer (``zc``, 3W channels), then the proxy's and top coating's channels, on the
    same levels. The product is affine and a lookup's weights sum to 1, so a lookup here is the projection of the
    latents' lookup (to rounding): each hit's query rows then skip the latents' layer."""

    metadata: dict  # the texture's (its ``filter_levels``), not the texture: no cycle keeps a texture alive
    levels: MipChain
    projected_channels: int

    def lookup(
        self, uv: np.ndarray, footprint, pick_seed: int | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(zc (N, 3W), proxy (N, 2), top (N, 2))`` at uv, as ``LatentTexture.lookup``."""
        levels = _filter_levels(self.metadata, len(self.levels))
        zc, rest = trilinear_lookup(
            self.levels, uv, footprint, levels, split=self.projected_channels, pick_seed=pick_seed
        )
        return zc, rest[:, :2], rest[:, 2:]


def _filter_levels(metadata: dict, n_levels: int) -> int:
    """``LatentTexture.filter_levels`` of a texture with ``metadata`` and ``n_levels`` levels."""
    return max(1, min(int(metadata.get("filter_levels", n_levels)), n_levels))


class LatentTextureError(ValueError):
    """A file that is not a valid latent texture (damaged, other content, non-finite texels)."""


def _read_levels(inp, path: Path, order: list[int], height: int, width: int) -> MipChain:
    """The file's levels, read straight into a :class:`MipChain` for a (height, width) base (the levels a chain of
    that base has; a file with others is refused), channels in ``CHANNEL_NAMES`` order from the file's ``order``.
    A file written before the top-coat channels existed gets them as uncoated (``NO_TOP``)."""
    if height < 1 or width < 1:
        raise LatentTextureError(f"{path} holds no image levels")
    chain = MipChain.empty(height, width, len(CHANNEL_NAMES), dtype=np.float16)
    level = 0
    while inp.seek_subimage(0, level):
        lspec = inp.spec_dimensions(0, level)
        if level >= len(chain):
            raise LatentTextureError(
                f"{path}: mip level {level} ({lspec.width}x{lspec.height}) comes after the 1x1 level a latent "
                "texture's chain ends at"
            )
        h, w = chain[level].shape[:2]
        if (lspec.height, lspec.width) != (h, w):
            raise LatentTextureError(
                f"{path}: mip level {level} is {lspec.width}x{lspec.height}, expected {w}x{h} "
                "(each level halves the one above, rounding down)"
            )
        _read_level(inp, path, level, lspec, order, chain[level])
        level += 1
    if inp.has_error:
        raise LatentTextureError(f"cannot read {path} (damaged file?): {inp.geterror()}")
    if level < len(chain):
        last = chain[level - 1].shape[:2] if level else (height, width)
        raise LatentTextureError(
            f"{path}: the mip chain stops at {last[1]}x{last[0]}; a latent texture's chain goes down to 1x1"
        )
    return chain


def _read_level(inp, path: Path, level: int, lspec, order: list[int], out: np.ndarray) -> None:
    """Mip level ``level`` into ``out`` (h, w, 100) half floats, in bands of whole tiles (or scanlines) of about
    :data:`READ_BAND_BYTES`: the file's channels come sorted by name, so each band is read, then reordered into
    ``out`` and checked finite in one compiled pass (``kernels.take_half_channels``); only a band, not the whole
    level, is held besides the chain."""
    h, w, n = lspec.height, lspec.width, len(order)
    order = np.asarray(order, dtype=np.int64)
    tile = lspec.tile_height if lspec.tile_width else 1
    band_rows = max(1, READ_BAND_BYTES // (w * n * 2) // tile) * tile
    for y in range(0, h, band_rows):
        end = min(h, y + band_rows)
        if lspec.tile_width:
            pixels = inp.read_tiles(
                0, level, lspec.x, lspec.x + w, lspec.y + y, lspec.y + end, lspec.z, lspec.z + 1, 0, n, "half"
            )
        else:
            pixels = inp.read_scanlines(0, level, lspec.y + y, lspec.y + end, lspec.z, 0, n, "half")
        if pixels is None or np.size(pixels) != (end - y) * w * n:
            raise LatentTextureError(f"cannot read mip level {level} of {path} (damaged file?): {inp.geterror()}")
        band = np.ascontiguousarray(pixels, dtype=np.float16).reshape((end - y) * w, n)
        rows = out[y:end]  # contiguous: its texels as (rows x w, 100) are a view
        bad, row, c = kernels.take_half_channels(
            band.view(np.uint16), order, rows.reshape(-1, out.shape[2]).view(np.uint16)
        )
        if n < len(CHANNEL_NAMES):  # written before the top-coat channels: every texel uncoated
            rows[:, :, n:] = NO_TOP
        if bad:  # checked a band at a time, as it is copied: a level-sized mask took 0.4 GB at 2048 x 2048
            x, row = row % w, row // w
            raise LatentTextureError(
                f"{path}: {bad} non-finite value(s) in mip level {level}, first {rows[row, x, c]} at "
                f"(x={x}, y={y + row}) in channel {CHANNEL_NAMES[c]}; latent texels must be finite (re-bake the "
                "texture)"
            )

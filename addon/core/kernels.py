"""Compiled per-row loops of the renderer (numba, nopython, GIL released).

The wavefront renderer spends most of its time outside rays and networks in long chains of small
numpy operations per bounce: each one streams whole arrays through memory and allocates its
temporaries. The loops here do one pass over the rows for such a chain, with scalars in registers.
They hold the renderer's bookkeeping and geometry (texture taps, the surface at a hit, the lights,
path continuation) and the shading of a bounce; the BSDF formulas they evaluate are those of
``addon.core.bsdf`` and ``addon.core.neural.top_lobe``, written once as formulas
(``addon.core.formula``) that numpy, torch and these loops all run.

Every kernel:

- takes and returns numpy arrays (float64 unless said), never Python objects; one whose output has a row per
  hit, ray or path writes it into ``out`` arrays it is given (a layout constant beside it says which), so that
  the renderer can keep them from one bounce to the next (``render.scratch``);
- releases the GIL (``nogil``), so the renderer's chunk threads run them at once;
- is compiled on first use and cached on disk beside this file (or in the user's cache folder
  where that is read-only), so a later process loads it in milliseconds;
- is the one implementation of what it computes: the numpy callers it replaced are gone.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic, overload

from .bsdf.base import sample_ok
from .bsdf.dielectric import INDEX_MATCHED_TOL
from .bsdf.frame import basis, reflected
from .bsdf.ggx import MIN_ALPHA, visible_normal
from .bsdf.lambert import concentric_disk, lambert_f, lambert_pdf, lambert_sample
from .bsdf.specular_diffuse import curve_at, principled_eval, principled_sample, principled_view
from .formula import quarter_cos_sin, turn_cos_sin
from .neural.calibration_formulas import azimuth_cell
from .neural.top_formulas import top_reflection, top_share_cos

_JIT = dict(nogil=True, cache=True, error_model="numpy")
F8, I8, B1 = np.dtype(np.float64), np.dtype(np.int64), np.dtype(np.bool_)
F4 = np.dtype(np.float32)  # rays as embree takes them


def rows_of(layout, n: int) -> tuple[np.ndarray, ...]:
    """New arrays of ``n`` rows for a loop's ``out`` of ``layout`` (``SURFACE_HITS_OUT`` and the like: a
    (columns, dtype) pair per array, 0 columns for a flat one). The renderer passes views of buffers it keeps
    instead (``render.scratch.Scratch``)."""
    return tuple(np.empty((n, c) if c else n, dtype=dt) for c, dt in layout)


def float64_rows(a) -> np.ndarray:
    """``a`` as the loops take their float arrays: contiguous float64 (no copy when it is already)."""
    return np.ascontiguousarray(a, dtype=np.float64)


# --- mip chains --------------------------------------------------------------------------------


def _native_half() -> bool:
    """Whether the loops' compile target converts half floats in hardware (x86 with F16C, 64-bit ARM): there
    LLVM's ``fpext`` is one instruction per 8 values; elsewhere it would call a runtime function that the JIT
    may not have, so the conversion is done in integer operations (:func:`_half_bits_to_float32`)."""
    import platform

    from numba.core import config

    if config.CPU_NAME not in (None, "host") or config.CPU_FEATURES:  # a target set by hand
        return False
    if platform.machine().lower() in ("arm64", "aarch64"):
        return True
    from llvmlite import binding

    try:
        return bool(binding.get_host_cpu_features().get("f16c"))
    except RuntimeError:
        return False


NATIVE_HALF = _native_half()


@intrinsic
def _half_to_float32(typingctx, bits):
    """The float32 of the half float whose bit pattern is the uint16 ``bits``, converted by the CPU (``fpext``:
    needs :data:`NATIVE_HALF`). Exact."""
    if not (isinstance(bits, types.Integer) and bits.bitwidth == 16):
        return None

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

    return types.float32(bits), codegen


@intrinsic
def _float32_to_half_bits(typingctx, x):
    """The bit pattern (uint16) of the float32 ``x`` rounded to a half float, to nearest with ties to even as
    numpy rounds it, by the CPU (``fptrunc``: needs :data:`NATIVE_HALF`; elsewhere LLVM would call a runtime
    function the JIT may not have)."""
    if not (isinstance(x, types.Float) and x.bitwidth == 32):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))

    return types.uint16(x), codegen


@intrinsic
def _half_bits_to_float32(typingctx, bits):
    """The float32 of the half float whose bit pattern is the uint16 ``bits``, in three 32-bit integer operations
    and one product: sign, exponent and mantissa shifted into a float32's places (sign-extended, shifted, the
    three bits between masked off), then scaled by 2^(127 - 15). Exact for normal and subnormal halves;
    infinities and NaNs come out finite (a latent texture holds none: its reader refuses them). 13-17% slower
    in the texture taps than :func:`_half_to_float32`, for targets without it."""
    if not (isinstance(bits, types.Integer) and bits.bitwidth == 16):
        return None

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        wide = builder.shl(builder.sext(args[0], i32), ir.Constant(i32, 13))
        f = builder.bitcast(builder.and_(wide, ir.Constant(i32, 0x8FFFE000)), ir.FloatType())
        return builder.fmul(f, ir.Constant(ir.FloatType(), 2.0**112))

    return types.float32(bits), codegen


@intrinsic
def _sqrt(typingctx, x):
    """``math.sqrt(x)`` of a float as the CPU's square root instruction: the same value (both are correctly
    rounded; nan below zero). numba's ``math.sqrt`` calls the C library's function wherever the compiler cannot
    prove its argument non-negative, to keep ``errno``, which nothing here reads: the lengths of vectors (a sum
    of squares may be nan) were such calls."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.sqrt", [args[0].type])
        return builder.call(fn, [args[0]])

    return x(x), codegen


def texel(flat, i):
    """``flat[i]`` as float32, where ``flat`` holds float32 values or the bit patterns of half floats
    (uint16: numba has no float16 on the CPU). For the compiled loops; see its overload below."""
    return np.float32(flat.view(np.float16)[i] if flat.dtype == np.uint16 else flat[i])


@overload(texel, jit_options=dict(inline="always"))
def _texel(flat, i):
    if flat.dtype == types.uint16:
        if NATIVE_HALF:
            return lambda flat, i: _half_to_float32(flat[i])
        return lambda flat, i: _half_bits_to_float32(flat[i])
    return lambda flat, i: flat[i]


@njit(**_JIT)
def halves_to_float32(bits, out):
    """``out[i]`` (float32) = the half float whose bit pattern is ``bits[i]`` (uint16; both flat): :func:`texel`'s
    conversion, by the CPU where it has one (numpy converts half floats in software: 12 times as long here)."""
    for i in range(len(bits)):
        out[i] = texel(bits, i)


def _within(value, limit):
    """Whether ``value`` is finite and within +-``limit``; a uint16 is a half float's bit pattern, finite unless its
    exponent bits are all set (a finite half is within 65504). For the compiled loops; see its overload below."""
    if isinstance(value, np.uint16):
        return (value & 0x7C00) != 0x7C00
    return abs(value) <= limit


@overload(_within, jit_options=dict(inline="always"))
def _within_overload(value, limit):
    if value == types.uint16:
        return lambda value, limit: (value & 0x7C00) != 0x7C00
    return lambda value, limit: abs(value) <= limit  # nan fails it


@njit(**_JIT)
def first_row_beyond(values, limit):
    """The first row of ``values`` (N, C) holding a value that is not finite or beyond +-``limit``, -1 for none:
    float32 values, or half floats as their bit patterns (uint16: only the non-finite ones)."""
    for i in range(values.shape[0]):
        ok = True
        for k in range(values.shape[1]):  # no exit inside a row: the test vectorises (a branch per value: 2.4x)
            ok &= _within(values[i, k], limit)
        if not ok:
            return i
    return -1


@njit(**_JIT)
def float32_to_halves(values, limit, bits):
    """``bits[i, k]`` = the bit pattern of ``values[i, k]`` (float32; both (N, C)) rounded to a half float, to
    nearest with ties to even (as numpy rounds), when every value is finite and within +-``limit``; returns -1.
    Otherwise returns the row of the first value that is not (:func:`first_row_beyond`), having written nothing.
    Needs :data:`NATIVE_HALF`."""
    bad = first_row_beyond(values, limit)
    if bad >= 0:
        return bad
    for i in range(values.shape[0]):
        for k in range(values.shape[1]):
            bits[i, k] = _float32_to_half_bits(values[i, k])
    return -1


@njit(inline="always", **_JIT)
def _tap_channels(flat, a, b, d, e, gx, fx, top, bottom, first, out, i, add):
    """Channels ``first`` .. ``first + out.shape[1]`` of a bilinear tap whose corner texels start at ``a``, ``b``,
    ``d``, ``e`` in ``flat`` (weights ``gx``, ``fx`` across, ``top``, ``bottom`` down): added to row ``i`` of
    ``out`` (``add``) or written into it. The row is indexed, not sliced: a slice is an array whose reference
    count the loop would raise and drop for every row."""
    # Unsigned offsets: numba then drops its negative-index check and the channel loops vectorise.
    first = np.uint64(first)
    if add:
        for k in range(np.uint64(out.shape[1])):
            j = first + k
            out[i, k] += (texel(flat, a + j) * gx + texel(flat, b + j) * fx) * top + (
                texel(flat, d + j) * gx + texel(flat, e + j) * fx
            ) * bottom
    else:
        for k in range(np.uint64(out.shape[1])):
            j = first + k
            out[i, k] = (texel(flat, a + j) * gx + texel(flat, b + j) * fx) * top + (
                texel(flat, d + j) * gx + texel(flat, e + j) * fx
            ) * bottom


@njit(inline="always", **_JIT)
def _wrap(i, n):
    """``i % n`` (repeat addressing), without the integer division where ``i`` is within a step of [0, n): uv
    inside [0, 1], as a floor's or a sphere's are. A tap's four divisions were a fifth to a third of a 3-channel
    lookup (55-72 ns a row of random uv in [0, 1), one thread; 43-46 ns without them)."""
    if 0 <= i < n:
        return i
    if i == -1:
        return n - 1
    return i % n


@njit(inline="always", **_JIT)
def _bilinear_tap(flat, offset, h, w, c, u, v, weight, out, rest, i, add):
    """``weight`` times the bilinear tap (repeat addressing, v = 0 at the bottom row) of the level stored at
    ``flat[offset:]`` as (h, w, c), in float32: its first ``out.shape[1]`` channels added to row ``i`` of ``out``
    (``add``) or written into it, the others to row ``i`` of ``rest``."""
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5
    x0f = math.floor(x)
    y0f = math.floor(y)
    fx = np.float32(x - x0f)
    fy = np.float32(y - y0f)
    x0 = _wrap(int(x0f), w)
    y0 = _wrap(int(y0f), h)
    x1 = x0 + 1 if x0 + 1 < w else 0
    y1 = y0 + 1 if y0 + 1 < h else 0
    gx = np.float32(1.0) - fx
    top = np.float32(weight) * (np.float32(1.0) - fy)
    bottom = np.float32(weight) * fy
    a = np.uint64(offset + (y0 * w + x0) * c)
    b = np.uint64(offset + (y0 * w + x1) * c)
    d = np.uint64(offset + (y1 * w + x0) * c)
    e = np.uint64(offset + (y1 * w + x1) * c)
    _tap_channels(flat, a, b, d, e, gx, fx, top, bottom, 0, out, i, add)
    if rest.shape[1]:
        _tap_channels(flat, a, b, d, e, gx, fx, top, bottom, out.shape[1], rest, i, add)


@njit(inline="always", **_JIT)
def hashed_uniform(seed, i):
    """A uniform number in [0, 1) of ``seed`` and row ``i``: splitmix64's finaliser of seed + i times the golden
    ratio (each (seed, row) its own, no state to carry between rows or threads), its top 53 bits."""
    z = np.uint64(seed) + np.uint64(i) * np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(inline="always", **_JIT)
def _picked_tap(flat, offset, h, w, c, u, v, r, out, rest, i):
    """One texel of the bilinear tap of :func:`_bilinear_tap`, picked by ``r`` in [0, 1) with the probability of its
    bilinear weight, copied into row ``i`` of ``out`` and ``rest``: the tap's expected value, one texel's."""
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5
    x0f = math.floor(x)
    y0f = math.floor(y)
    fx = x - x0f
    fy = y - y0f
    xi = _wrap(int(x0f), w)
    yi = _wrap(int(y0f), h)
    if r < 1.0 - fx:
        r = r / (1.0 - fx)
    else:
        xi = xi + 1 if xi + 1 < w else 0
        r = (r - (1.0 - fx)) / fx
    if r >= 1.0 - fy:
        yi = yi + 1 if yi + 1 < h else 0
    a = np.uint64(offset + (yi * w + xi) * c)
    first = np.uint64(out.shape[1])
    for k in range(first):
        out[i, k] = texel(flat, a + np.uint64(k))
    for k in range(np.uint64(rest.shape[1])):
        rest[i, k] = texel(flat, a + first + np.uint64(k))


@njit(**_JIT)
def trilinear(flat, offsets, heights, widths, channels, uv, lod, out, rest, pick_seed=-1):
    """Trilinear lookup into a mip chain packed in ``flat`` (float32, or half floats as their uint16 bit patterns:
    :func:`texel`; level k at ``offsets[k]``, shape
    (heights[k], widths[k], channels)): row i of ``out`` and ``rest`` (float32, written, not read: pass them
    uninitialised) gets levels floor(lod[i]) and the next one (the last level: itself) blended by the fraction
    of lod[i], its first ``out.shape[1]`` channels in ``out`` and the others in ``rest`` (``rest`` may have no
    columns). Two arrays, so that a latent texture's latents come out contiguous, as the decoder and the
    calibration's choice of table read them, where a slice of one array would be copied once more per bounce.

    Writing before reading matters: a zeroed array fresh from the system (``np.zeros`` of megabytes) has its
    pages mapped on first touch, and a loop that adds into them takes a read fault and then a write fault per
    page; on the demo floor's latents (100 channels per hit) that cost more than the taps.

    With ``pick_seed`` (>= 0): one texel a row instead, of one of the two levels, picked with the probability of
    its weight in the lookup above (``hashed_uniform`` of the seed and the row): stochastic filtering. Its expected
    value is the lookup's; what it is for is what is computed from it: a decoder does not turn a blend of latents
    into the blend of their BRDFs (a checker of two coats one texel wide rendered 11-31% dark at 80 degrees, blended;
    within 2% picked), and with one texel a hit the pixel's samples average the shaded texels."""
    n_levels = len(offsets)
    for i in range(len(lod)):
        k = int(math.floor(lod[i]))
        t = lod[i] - k
        # Repeat addressing once for every tap, exactly (u - floor(u) is exact): the taps' texels are then within a
        # step of the level, where :func:`_wrap` needs no integer division. A texture repeated across a floor
        # (the demo's tiles: uv up to 10) took four divisions a lookup: 38-39 -> 30-31 ns a hit of the demo floor.
        u, v = uv[i, 0], uv[i, 1]
        u, v = u - math.floor(u), v - math.floor(v)
        if pick_seed >= 0:
            r = hashed_uniform(pick_seed, i)
            if k + 1 < n_levels and r < t:
                k, r = k + 1, r / t
            elif k + 1 < n_levels:
                r = (r - t) / (1.0 - t)
            r = min(r, 1.0 - 1e-16)
            _picked_tap(flat, offsets[k], heights[k], widths[k], channels, u, v, r, out, rest, i)
            continue
        if k + 1 >= n_levels:
            _bilinear_tap(flat, offsets[k], heights[k], widths[k], channels, u, v, 1.0, out, rest, i, False)
        else:
            _bilinear_tap(flat, offsets[k], heights[k], widths[k], channels, u, v, 1.0 - t, out, rest, i, False)
            _bilinear_tap(flat, offsets[k + 1], heights[k + 1], widths[k + 1], channels, u, v, t, out, rest, i, True)


@njit(**_JIT)
def take_half_channels(src, order, out):
    """``out[i, k] = src[i, order[k]]`` for half floats held as their bit patterns (uint16; src (N, C), out (N, K)
    with K >= len(order), both C-contiguous; columns from len(order) on are left as they are): a file's channels,
    stored sorted by name, in a latent texture's order. One pass, which also finds the values that are not finite
    (exponent bits all set: inf or nan). Returns how many are not, and the row and column in ``out`` of the first
    (-1, -1 for none)."""
    bad, first_row, first_col = 0, -1, -1
    for i in range(src.shape[0]):
        for k in range(order.shape[0]):
            bits = src[i, order[k]]
            out[i, k] = bits
            if bits & 0x7C00 == 0x7C00:
                if bad == 0:
                    first_row, first_col = i, k
                bad += 1
    return bad, first_row, first_col


# --- surfaces ----------------------------------------------------------------------------------


# What ``closest_hits`` writes (``out``, a row per ray): the distance, triangle and barycentrics.
CLOSEST_HITS_OUT = ((0, F8), (0, I8), (0, F8), (0, F8))


@njit(**_JIT)
def closest_hits(out, prim_id, tfar, u, v):
    """An intersection query's results (embree's float32 ``tfar``, ``u``, ``v`` and int32 ``primID``, -1 for a
    miss) as the loops read them, in one pass, into ``out`` (:data:`CLOSEST_HITS_OUT`): the distance (inf on a
    miss), the triangle (int64) and the barycentrics, in float64. The numpy conversions it replaces made five
    passes and two temporaries: 0.71 ms for the demo scene's first bounce (129,600 rays), where this takes 0.21 ms."""
    t, prim, bu, bv = out
    for i in range(len(prim_id)):
        p = prim_id[i]
        prim[i] = p
        t[i] = tfar[i] if p >= 0 else np.inf
        bu[i] = u[i]
        bv[i] = v[i]
    return out


@njit(**_JIT)
def texture_footprint(width, cos_o, tri_uv_scale):
    """Footprint in uv units of a ray cone of ``width`` (world units) hitting a surface at |cos|
    ``cos_o`` (floored at 0.05: grazing hits do not blow up) on triangles of uv scale
    ``tri_uv_scale``: the width stretched by 1 / sqrt(cos) (the mean of its two axes). Scalars or
    arrays."""
    return width / np.sqrt(np.maximum(np.abs(cos_o), 0.05)) * tri_uv_scale


# What ``surface_hits`` writes (``out``, a row per hit): p, ng, ns, uv, width, footprint, ts, tt, wo, distance,
# front, offset.
SURFACE_HITS_OUT = (
    (3, F8), (3, F8), (3, F8), (2, F8), (0, F8), (0, F8), (3, F8), (3, F8), (3, F8), (0, F8), (0, B1), (0, F8)
)  # fmt: skip

# How far a ray leaving a surface starts off it, and how far short of a light a blocker must be (``_unblocked_before``):
# OFFSET_SCALE of the largest coordinate of the hit point (about 8 float32 roundings of it: the ray's origin is
# rounded to float32 for Embree, which moves it off the plane by less than one) and TRIANGLE_OFFSET_SCALE of its
# triangle's extent (about 4 roundings of it: Embree intersects in float32 with the corners taken relative to the
# ray's origin, so its plane's error goes with the triangle's size, not with where it lies). It was one offset for
# the whole scene, 1e-4 of its largest coordinate plus 1e-4: a triangle a kilometre away made every offset 0.1 and
# took a small object's contact shadow away; a scene a ten-thousandth the size lost its shadows to the 1e-4. Then
# 1e-5 of the hit's coordinates and 1e-6 of its triangle's: a 1 cm object 1 km from the origin (a site's
# coordinates) cast no shadow, its rays starting 2 cm off the floor. With a floor of 1 km a side made of two
# triangles, a 0.1 m sphere's contact shadow in direct light is the same as on a 4 m floor (and at 10 km); a 1 cm
# sphere 1 km from the origin casts the shadow it casts at the origin, but for a sample or two at its edge.
OFFSET_SCALE = 1e-6
TRIANGLE_OFFSET_SCALE = 5e-7


def triangle_offsets(corners) -> np.ndarray:
    """(T,) each triangle's part of the offset of the rays leaving it: :data:`TRIANGLE_OFFSET_SCALE` times the
    largest coordinate of its corners (``corners`` (T, 3, >= 3), positions first)."""
    c = np.asarray(corners)[:, :, :3]
    return TRIANGLE_OFFSET_SCALE * np.abs(c - c[:, :1]).max(axis=(1, 2))


@njit(fastmath={"contract"}, **_JIT)
def surface_hits(out, corners, face_normals, uv_scale, tri_offset, hit, prim, bu, bv, d, t, width, spread):
    """The surface where rays ``d`` (unit, world) land: ray ``hit[i]`` of the intersection's results (the
    triangles ``prim``, barycentrics (bu, bv) and distances ``t`` of every ray) for row i of ``d``, ``width``
    and ``spread``. Position, geometric and shading normals, uv, the ray cone's width there
    (``width + spread * t``) and its footprint in uv units.

    ``corners`` (T, 3, 8): each corner's position, normal and uv. The shading normal is the
    interpolated one, normalised; where it is zero or disagrees with the geometric normal, the
    geometric one. Both are turned toward the viewer, and a shading normal the viewer sees at
    grazing (cos <= 1e-6) falls back to the geometric one.
    The shading frame is ``frame.basis`` of the shading normal, and ``wo`` the direction back along the ray
    in it. Writes and returns ``out`` (:data:`SURFACE_HITS_OUT`): p, ng, ns (N, 3), uv (N, 2), width,
    footprint (N,), the tangents ts, tt (N, 3), wo (N, 3), the distance (N,), ``front`` (N,), whether the ray
    came from the side the triangle's face normal points to (the outside of a closed mesh whose faces point
    out): the frame is turned toward the viewer either way, so a material that lets light through tells
    entering from leaving by it; and the offset (N,) of the rays that leave the hit (:data:`OFFSET_SCALE`: of
    the hit point's largest coordinate, plus the triangle's ``tri_offset``, ``triangle_offsets``).

    Its sums of products (the interpolations, the dot products, the frame) may be fused into multiply-adds
    (``fastmath`` "contract", nothing else: each fused sum is rounded once, where it was rounded at every step),
    which shortens their chains: 45-46 -> 37-39 ns a hit in a one-thread demo render. The shading loops and
    ``continue_paths`` measured no faster so, and the sky's lookup must not be: there a product's difference that
    is exactly zero (a direction on a column's edge) must stay zero.
    """
    p, ng, ns, uv, width_out, footprint, ts, tt, wo, dist, front, offset = out
    for i in range(len(hit)):
        h = hit[i]
        k = prim[h]
        b1, b2 = bu[h], bv[h]
        dist[i] = t[h]
        b0 = 1.0 - b1 - b2
        c0, c1, c2 = corners[k, 0], corners[k, 1], corners[k, 2]
        for j in range(3):
            p[i, j] = b0 * c0[j] + b1 * c1[j] + b2 * c2[j]
        offset[i] = OFFSET_SCALE * max(abs(p[i, 0]), abs(p[i, 1]), abs(p[i, 2])) + tri_offset[k]
        uv[i, 0] = b0 * c0[6] + b1 * c1[6] + b2 * c2[6]
        uv[i, 1] = b0 * c0[7] + b1 * c1[7] + b2 * c2[7]
        sx = b0 * c0[3] + b1 * c1[3] + b2 * c2[3]
        sy = b0 * c0[4] + b1 * c1[4] + b2 * c2[4]
        sz = b0 * c0[5] + b1 * c1[5] + b2 * c2[5]
        gx, gy, gz = face_normals[k, 0], face_normals[k, 1], face_normals[k, 2]
        length = _sqrt(sx * sx + sy * sy + sz * sz)
        if length > 0.0:
            sx, sy, sz = sx / length, sy / length, sz / length
        if not (sx * gx + sy * gy + sz * gz > 0.0):  # inconsistent or zero: the geometric normal
            sx, sy, sz = gx, gy, gz
        ox, oy, oz = -d[i, 0], -d[i, 1], -d[i, 2]
        cos_g = gx * ox + gy * oy + gz * oz
        front[i] = cos_g >= 0.0
        if cos_g < 0.0:  # turned toward the viewer
            gx, gy, gz, sx, sy, sz, cos_g = -gx, -gy, -gz, -sx, -sy, -sz, -cos_g
        if not (sx * ox + sy * oy + sz * oz > 1e-6):  # grazing: the geometric normal
            sx, sy, sz = gx, gy, gz
        ng[i, 0], ng[i, 1], ng[i, 2] = gx, gy, gz
        ns[i, 0], ns[i, 1], ns[i, 2] = sx, sy, sz
        ax, ay, az, bx, by, bz = basis(sx, sy, sz)
        ts[i, 0], ts[i, 1], ts[i, 2] = ax, ay, az
        tt[i, 0], tt[i, 1], tt[i, 2] = bx, by, bz
        wo[i, 0] = ox * ax + oy * ay + oz * az
        wo[i, 1] = ox * bx + oy * by + oz * bz
        wo[i, 2] = ox * sx + oy * sy + oz * sz
        w = width[i] + spread[i] * t[h]
        width_out[i] = w
        footprint[i] = texture_footprint(w, cos_g, uv_scale[k])
    return out


@njit(**_JIT)
def film_add(sums, squares, count, feature_sum, first, pixels, radiance, features, depth):
    """A chunk's samples into the film (``render.film.Film.add``), in one pass: row i of ``radiance`` (N, 3) and
    its square into pixel ``pixels[i]`` (``first + i`` where ``pixels`` is empty: a run of pixels), one more sample
    counted, and its ``features`` (N, C; none where empty) summed, but for column ``depth``, of which the least is
    kept."""
    contiguous = len(pixels) == 0
    with_features = features.shape[0] > 0
    for i in range(len(radiance)):
        q = first + i if contiguous else pixels[i]
        for k in range(3):
            v = radiance[i, k]
            sums[q, k] += v
            squares[q, k] += v * v
        count[q] += 1
        if with_features:
            for k in range(features.shape[1]):
                if k == depth:
                    feature_sum[q, k] = min(feature_sum[q, k], features[i, k])
                else:
                    feature_sum[q, k] += features[i, k]


@njit(**_JIT)
def first_hit_features(features, row, weight, ns, dist, d, forward):
    """What a denoiser is guided by, into ``features[row]`` (``render.film``): the first sample's weight, at least 0
    (its mean is the directional albedo; ``Film.features`` clips the mean to [0, 1], not each weight, which made the
    mean of a material sampled by a proposal 15% low), the world shading normal, the depth as Cycles' Z pass has it
    (the hit's distance ``dist`` from the camera along its ray ``d``, projected on the camera's axis ``forward``: a
    floor facing the camera is one depth across the frame), and 1 for coverage (the ray met a surface: a transparent
    film's alpha)."""
    for i in range(len(row)):
        r = row[i]
        for k in range(3):
            features[r, k] = max(weight[i, k], 0.0)
            features[r, 3 + k] = ns[i, k]
        features[r, 6] = dist[i] * (d[i, 0] * forward[0] + d[i, 1] * forward[1] + d[i, 2] * forward[2])
        features[r, 7] = 1.0


# --- lights ------------------------------------------------------------------------------------
#
# Every light the renderer samples is a row of a light table: its kind and N_PARAMS float parameters
# (``lights.Light.table_row``). The environment's image and its tables travel beside the light table as one
# tuple, ``env`` (``lights.Environment.image_arrays``; ``lights.NO_IMAGE`` where there is none): the image
# (H, W, 3), each pixel's solid-angle pdf (H * W,), the alias table (keep, alias) that picks a pixel, the
# rows' edge heights z ((H + 1,), decreasing), a first guess of the row per even bin of z, the columns' edge
# directions (W + 1, 2) and a first guess of the column per even bin of :func:`_pseudo_angle`.

POINT, SPOT, SUN, AREA_RECT, AREA_ELLIPSE, ENVIRONMENT = range(6)  # an environment of one colour is a 1 x 1 image
# A point or spot light of a radius (Blender's Radius): a sphere (Soft Falloff off) or a disk of that radius facing the
# point it lights (Soft Falloff on, Blender's default), as Cycles' are; and a sun of an angle (Blender's Angle): a disk
# of the sky, every direction within half the angle of its own. Rays can hit them, as they hit an area light.
SPHERE, FACING_DISK, SUN_DISK = range(6, 9)
N_PARAMS = 23
RADIUS = 17  # a sphere's or a facing disk's radius
CAMERA_VISIBLE = 19  # a light rays can hit: 1 where camera rays see it (the object's Camera ray visibility)
NO_SHADOW = 20  # every row's: 1 for a light that casts no shadow (Blender's Cast Shadow off)
BY_AREA = 21  # a rectangle light's: 1 to sample it by area, not by solid angle (a comparison's: ``AreaLight``)
MAX_BOUNCES = 22  # every row's: the deepest bounce whose hits sample the light (Cycles' per-light Max Bounces)


@njit(inline="always", **_JIT)
def _equirect_uv(x, y, z):
    """Blender's equirectangular mapping: world direction -> (u, v) in [0, 1]^2, v = 1 at +z."""
    return -math.atan2(y, x) / (2.0 * math.pi) + 0.5, math.atan2(z, math.hypot(x, y)) / math.pi + 0.5


@njit(inline="always", **_JIT)
def _equirect_azimuth(u):
    """The angle from +x (counterclockwise seen from +z) of image column position u in Blender's mapping."""
    return -(u - 0.5) * 2.0 * math.pi


@njit(inline="always", **_JIT)
def _equirect_direction(u, v):
    phi = _equirect_azimuth(u)
    el = (v - 0.5) * math.pi
    c = math.cos(el)
    return c * math.cos(phi), c * math.sin(phi), math.sin(el)


@njit(**_JIT)
def equirect_uv(d):
    """(N, 2) equirectangular uv of world directions d (N, 3)."""
    out = np.empty((len(d), 2))
    for i in range(len(d)):
        out[i, 0], out[i, 1] = _equirect_uv(d[i, 0], d[i, 1], d[i, 2])
    return out


@njit(**_JIT)
def equirect_direction(uv):
    """(N, 3) world directions of equirectangular uv (N, 2)."""
    out = np.empty((len(uv), 3))
    for i in range(len(uv)):
        out[i, 0], out[i, 1], out[i, 2] = _equirect_direction(uv[i, 0], uv[i, 1])
    return out


@njit(inline="always", **_JIT)
def _pseudo_angle(x, y):
    """A number in [0, 4) that grows with the angle of (x, y) counterclockwise from +x, as atan2 does (taken in
    [0, 2 pi)), with no transcendental function: the position along the diamond |x| + |y| = 1, a quarter per
    quadrant. 0 for (0, 0) and NaN."""
    s = abs(x) + abs(y)
    p = y / s if s > 0.0 else 0.0
    a = 2.0 - p if x < 0.0 else p  # written as selects, not branches: a direction's quadrant is unpredictable
    return a + 4.0 if a < 0.0 else a


@njit(inline="always", **_JIT)
def _env_pixel(image, z_edges, row_of_bin, edges, column_of_bin, dx, dy, dz):
    """The pixel (row, column) of the environment image that unit direction (dx, dy, dz) falls in by Blender's
    mapping (:func:`_equirect_uv`, then floor), found with no transcendental function: a table guesses the row
    from z and the column from :func:`_pseudo_angle` (bins ``lights.GUESS_BINS`` times finer than the pixels, so
    the guess is within a step), and comparisons with the edges settle it. Row y holds z_edges[y + 1] < z <=
    z_edges[y]; column x the directions from edge x + 1 (exclusive) counterclockwise to edge x. Where the arc
    tangents of the mapping made a lookup 110 ns (the demo sky's misses), the pixel takes about 20 here."""
    h, w = image.shape[0], image.shape[1]
    nz = len(row_of_bin)
    y = row_of_bin[min(max(int((1.0 - dz) * 0.5 * nz), 0), nz - 1)]
    while y < h - 1 and dz <= z_edges[y + 1]:
        y += 1
    while y > 0 and dz > z_edges[y]:
        y -= 1
    na = len(column_of_bin)
    x = column_of_bin[min(max(int(_pseudo_angle(dx, dy) * 0.25 * na), 0), na - 1)]
    for _ in range(w):  # a step at most from the guess; bounded whatever the input
        if edges[x, 0] * dy - edges[x, 1] * dx > 0.0:  # counterclockwise past the column's upper edge
            x = x - 1 if x > 0 else w - 1
        elif edges[x + 1, 0] * dy - edges[x + 1, 1] * dx <= 0.0:  # at or clockwise of its lower edge
            x = x + 1 if x < w - 1 else 0
        else:
            break
    return y, x


@njit(forceinline=True, **_JIT)
def _env_lookup(image, pixel_pdf, z_edges, row_of_bin, edges, column_of_bin, dx, dy, dz):
    """Radiance arriving from unit world direction (dx, dy, dz) and the pdf of sampling it (the arrays of
    ``env``, taken out of the tuple by the caller once, not per row). One path for every environment: a branch
    on a constant colour here took the lookups in ``add_emission`` from 24 to 78 ns a row (the demo sky's
    misses).

    Inlined by LLVM (``forceinline``), as the calibration's and the top coat's table helpers below are, not by
    numba (``inline="always"``): numba's inlining binds the arrays to new names, and with this helper's searches
    the loop raised and dropped their reference counts for every row (``add_emission`` 22-23 ns a ray that way,
    17-18 this way; ``decoded_brdf`` 123-127 ns a row, 105-116)."""
    y, x = _env_pixel(image, z_edges, row_of_bin, edges, column_of_bin, dx, dy, dz)
    return image[y, x, 0], image[y, x, 1], image[y, x, 2], pixel_pdf[y * image.shape[1] + x]


@njit(**_JIT)
def clean_environment(src, strength, image, lum):
    """An environment image as the renderer keeps it, in one pass over its pixels: ``src`` (H, W, >= 3) float, its
    first three channels times ``strength`` into ``image`` (H, W, 3) float32, a non-finite or negative value as 0,
    and each pixel's luminance (Rec. 709) into ``lum`` (H, W). numpy's copies and masks took 5 s of an 8K
    image's 7.8 s."""
    h, w = src.shape[0], src.shape[1]
    for y in range(h):
        for x in range(w):
            total = 0.0
            for c in range(3):
                v = float(src[y, x, c])
                v = v * strength if v > 0.0 and v < np.inf else 0.0  # NaN fails both tests
                if not v < 3.4028234663852886e38:  # a finite value the strength took past float32's largest
                    v = 0.0
                stored = np.float32(v)
                image[y, x, c] = stored
                total += float(stored) * (0.2126 if c == 0 else (0.7152 if c == 1 else 0.0722))
            lum[y, x] = total


@njit(**_JIT)
def alias_table(p):
    """Walker's alias table of the probabilities ``p`` (N,), summing to 1 (Vose's O(N) construction):
    cell i keeps i with probability ``keep[i]`` and gives the rest to ``alias[i]``, so that a uniform
    cell and one comparison draw index k with probability p[k]. Sampling costs the same for any N,
    where a binary search over a cdf costs log2(N) dependent, mispredicted steps."""
    n = len(p)
    scaled = p * n
    keep = np.ones(n)
    alias = np.arange(n)
    small = np.empty(n, dtype=np.int64)
    large = np.empty(n, dtype=np.int64)
    ns = nl = 0
    for i in range(n):
        if scaled[i] < 1.0:
            small[ns] = i
            ns += 1
        else:
            large[nl] = i
            nl += 1
    while ns > 0 and nl > 0:
        ns -= 1
        s = small[ns]
        g = large[nl - 1]
        keep[s] = scaled[s]
        alias[s] = g
        scaled[g] = (scaled[g] + scaled[s]) - 1.0
        if scaled[g] < 1.0:  # g moves to the small list
            nl -= 1
            small[ns] = g
            ns += 1
    return keep, alias  # cells left on either list keep themselves: their mass is 1 up to rounding


@njit(**_JIT)
def environment_radiance(env, d):
    """Radiance (N, 3) from unit world directions d (N, 3) and the solid-angle pdf (N,) of sampling them."""
    image, pixel_pdf, _, _, z_edges, row_of_bin, edges, column_of_bin = env
    n = len(d)
    rad = np.empty((n, 3))
    pdf = np.empty(n)
    for i in range(n):
        rad[i, 0], rad[i, 1], rad[i, 2], pdf[i] = _env_lookup(
            image, pixel_pdf, z_edges, row_of_bin, edges, column_of_bin, d[i, 0], d[i, 1], d[i, 2]
        )
    return rad, pdf


@njit(**_JIT)
def is_delta(kind):
    """Whether lights of ``kind`` are delta lights (a point, a spot, the sun, of no radius or angle): no area to hit,
    pdf 1."""
    return kind == POINT or kind == SPOT or kind == SUN


# An orthogonal rectangle (Blender's square and rectangle lights, unsheared) is sampled by solid angle (Ureña et
# al., "An Area-Preserving Parametrization for Spherical Rectangles", 2013), as Cycles samples it, from every point
# of its lit side but those in its plane (:func:`_rect_window`). Near or far: a floor under the demo's tilted
# light, three to five of its radii away, had 14 times the variance sampled by area (the variance of a sample's
# irradiance over its squared mean, 0.04-0.09 there, against 0.002), which a render's other noise did not hide;
# a sample costs about 60 ns more, 3-5% of a demo render (docs/light_sampling.md).


@njit(forceinline=True, **_JIT)
def _rect_window(params, j, px, py, pz):
    """Where solid-angle sampling draws rectangle light ``params[j]`` from at point (px, py, pz): ``ok`` (False: a
    sheared light, one marked :data:`BY_AREA`, or a point on its dark side or in its plane: sample its area), the
    light's unit axes x and y, and the window's edges relative to the point, x0 < x1 along x, y0 < y1 along y and z0
    < 0 along the light's normal. The window is the light, or under a *Spread* the part of it within the cone the
    point sees it through (Cycles' clamp: beyond it the light sends the point nothing); an empty window has x0 = x1."""
    ux, uy, uz, vx, vy, vz = params[j, 3], params[j, 4], params[j, 5], params[j, 6], params[j, 7], params[j, 8]
    uu, vv, uv = ux * ux + uy * uy + uz * uz, vx * vx + vy * vy + vz * vz, ux * vx + uy * vy + uz * vz
    cx, cy, cz = params[j, 0] - px, params[j, 1] - py, params[j, 2] - pz
    z0 = cx * params[j, 9] + cy * params[j, 10] + cz * params[j, 11]
    radius2 = params[j, 16]
    # A point within 1e-6 of the light's size of its plane (Ureña's angles lose their digits there: samples not
    # even, some not found by the intersection) and a light whose axes' shear moves its short edges by over 1e-5
    # of their length (a float32 matrix's rounding: 1e-7 of the long side) are sampled by area.
    flat = z0 * z0 < 1e-12 * radius2
    sheared = uv * uv > 1e-10 * min(uu, vv) ** 2
    if not z0 < 0.0 or flat or sheared or params[j, BY_AREA] != 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    lu, lv = _sqrt(uu), _sqrt(vv)
    xx, xy, xz, yx, yy, yz = ux / lu, uy / lu, uz / lu, vx / lv, vy / lv, vz / lv
    a0, a1, b0, b1 = -lu, lu, -lv, lv
    ca, cb = cx * xx + cy * xy + cz * xz, cx * yx + cy * yy + cz * yz  # the centre's coordinates from the point
    tan_half = params[j, 17]
    if tan_half > 0.0 and not math.isinf(tan_half):
        r = -z0 * tan_half  # the cone's radius where it meets the light's plane, about the point's foot at -ca, -cb
        a0, a1, b0, b1 = max(a0, -ca - r), min(a1, -ca + r), max(b0, -cb - r), min(b1, -cb + r)
        if a0 >= a1 or b0 >= b1:
            a1, b1 = a0, b0
    return True, xx, xy, xz, yx, yy, yz, ca + a0, ca + a1, cb + b0, cb + b1, z0


@njit(forceinline=True, **_JIT)
def _rect_solid_angle(x0, x1, y0, y1, z0):
    """The solid angle of the rectangle [x0, x1] x [y0, y1] at height z0 < 0 below a point: the sum of its two
    triangles' (Van Oosterom and Strackee: tan(a / 2) of each is its corners' triple product, the same for both,
    over a sum of their lengths and dot products), as the argument of the product of the two, with no
    cancellation at small angles and one arc tangent."""
    z2 = z0 * z0
    l00, l10 = _sqrt(x0 * x0 + y0 * y0 + z2), _sqrt(x1 * x1 + y0 * y0 + z2)
    l11, l01 = _sqrt(x1 * x1 + y1 * y1 + z2), _sqrt(x0 * x0 + y1 * y1 + z2)
    d00_10, d00_11, d00_01 = x0 * x1 + y0 * y0 + z2, x0 * x1 + y0 * y1 + z2, x0 * x0 + y0 * y1 + z2
    d10_11, d11_01 = x1 * x1 + y0 * y1 + z2, x0 * x1 + y1 * y1 + z2
    num = -z0 * (x1 - x0) * (y1 - y0)
    re0 = l00 * l10 * l11 + d00_10 * l11 + d00_11 * l10 + d10_11 * l00
    re1 = l00 * l11 * l01 + d00_11 * l01 + d00_01 * l11 + d11_01 * l00
    re, im = re0 * re1 - num * num, num * (re0 + re1)
    half = math.atan2(im, re)  # in [0, pi): half the solid angle
    if half < 0.0:  # rounding's sign at either end
        half = math.pi if re < 0.0 else 0.0
    return 2.0 * half


@njit(forceinline=True, **_JIT)
def _rect_point(x0, x1, y0, y1, z0, solid, u0, u1):
    """The point (x, y) of the rectangle of :func:`_rect_solid_angle` whose direction uniforms (u0, u1) give, evenly
    in solid angle (Ureña et al.: the angle au = u0 S + k fixes x, then y lies evenly in the sine of its
    elevation). The cosine and sine of k = 2 pi - g2 - g3 (g2, g3 the spherical rectangle's inner angles at
    its far corners) come from the corners' normals, and au's from turning k by u0 S: no arc cosine."""
    z2 = z0 * z0
    n0, n2 = -y0 / _sqrt(z2 + y0 * y0), y1 / _sqrt(z2 + y1 * y1)
    n3 = -x0 / _sqrt(z2 + x0 * x0)
    c2, c3 = -n2 * n3, -n3 * n0  # cos g2, cos g3
    s2, s3 = _sqrt(max(1.0 - c2 * c2, 0.0)), _sqrt(max(1.0 - c3 * c3, 0.0))
    ck, sk = c2 * c3 - s2 * s3, -(s2 * c3 + c2 * s3)  # e^(i k) = e^(-i (g2 + g3))
    cs, ss = turn_cos_sin(u0 * solid * (0.5 / math.pi))
    cu_a, su_a = ck * cs - sk * ss, sk * cs + ck * ss  # cos au, sin au
    fu = (cu_a * n0 - n2) / su_a
    # x = -cu z0 / sqrt(1 - cu^2) with cu = sign(fu) / sqrt(fu^2 + b0^2): one root, one division
    xu = -z0 / _sqrt(max(fu * fu + n0 * n0 - 1.0, 1e-300))
    xu = min(max(xu if fu > 0.0 else -xu, x0), x1)
    d2 = xu * xu + z2
    h0, h1 = y0 / _sqrt(d2 + y0 * y0), y1 / _sqrt(d2 + y1 * y1)
    hv = h0 + u1 * (h1 - h0)
    yv = hv * _sqrt(d2 / (1.0 - hv * hv)) if hv * hv < 1.0 else y1
    return xu, min(max(yv, y0), y1)


@njit(forceinline=True, **_JIT)
def _sample_local_light(kind, params, j, px, py, pz, u0, u1, near):
    """One sample of light ``params[j]`` (a point, a spot, the sun, one of a radius or an angle:
    :func:`_sample_soft_light`, or an area light: any kind but the environment) from point (px, py, pz): direction
    toward it (unit), distance (inf for the sun), arriving
    radiance (for delta lights the intensity / distance^2 or the irradiance, the distance taken as at least
    ``near``: a point light on the surface lights it finitely) and solid-angle pdf (1 for delta
    lights). The light is indexed, not sliced: a slice passed to a function is an array whose reference count the
    caller would raise and drop for every row."""
    inf = np.inf
    if kind == POINT or kind == SPOT:
        dx, dy, dz = params[j, 0] - px, params[j, 1] - py, params[j, 2] - pz
        dist = _sqrt(dx * dx + dy * dy + dz * dz)
        safe = max(dist, 1e-9)
        wx, wy, wz = dx / safe, dy / safe, dz / safe
        mask = _spot_mask(params, j, wx, wy, wz) if kind == SPOT else 1.0
        scale = mask / max(safe, near) ** 2
        return wx, wy, wz, dist, params[j, 3] * scale, params[j, 4] * scale, params[j, 5] * scale, 1.0
    if kind == SUN:
        return params[j, 0], params[j, 1], params[j, 2], inf, params[j, 3], params[j, 4], params[j, 5], 1.0
    if kind >= SPHERE:
        return _sample_soft_light(kind, params, j, px, py, pz, u0, u1)
    # AREA_RECT, AREA_ELLIPSE
    if kind == AREA_RECT:
        ok, xx, xy, xz, yx, yy, yz, x0, x1, y0, y1, z0 = _rect_window(params, j, px, py, pz)
        if ok:  # by solid angle
            if not x0 < x1:
                return 0.0, 0.0, 1.0, inf, 0.0, 0.0, 0.0, 0.0
            solid = _rect_solid_angle(x0, x1, y0, y1, z0)
            if not solid > 0.0:
                return 0.0, 0.0, 1.0, inf, 0.0, 0.0, 0.0, 0.0
            a, b = _rect_point(x0, x1, y0, y1, z0, solid, u0, u1)
            nx, ny, nz = params[j, 9], params[j, 10], params[j, 11]
            dx, dy, dz = a * xx + b * yx + z0 * nx, a * xy + b * yy + z0 * ny, a * xz + b * yz + z0 * nz
            dist = _sqrt(dx * dx + dy * dy + dz * dz)
            wx, wy, wz = dx / dist, dy / dist, dz / dist
            g = spread_factor(params, j, -z0 / dist)
            return wx, wy, wz, dist, params[j, 12] * g, params[j, 13] * g, params[j, 14] * g, 1.0 / solid
    if kind == AREA_ELLIPSE:  # the concentric square-to-disk map (even in area)
        a, b = concentric_disk(u0, u1)
    else:
        a, b = 2.0 * u0 - 1.0, 2.0 * u1 - 1.0
    dx = params[j, 0] + a * params[j, 3] + b * params[j, 6] - px
    dy = params[j, 1] + a * params[j, 4] + b * params[j, 7] - py
    dz = params[j, 2] + a * params[j, 5] + b * params[j, 8] - pz
    dist = _sqrt(dx * dx + dy * dy + dz * dz)
    safe = max(dist, 1e-9)
    wx, wy, wz = dx / safe, dy / safe, dz / safe
    cos_l = -(wx * params[j, 9] + wy * params[j, 10] + wz * params[j, 11])
    if cos_l > 1e-8:
        g = spread_factor(params, j, cos_l)
        pdf = safe * safe / (cos_l * params[j, 15])
        return wx, wy, wz, dist, params[j, 12] * g, params[j, 13] * g, params[j, 14] * g, pdf
    return wx, wy, wz, dist, 0.0, 0.0, 0.0, 0.0


@njit(forceinline=True, **_JIT)
def _spot_mask(params, j, wx, wy, wz):
    """The share of spot light ``params[j]``'s light that reaches the point whence the unit direction (wx, wy, wz)
    leads to the light: Blender's smoothstep over the cone's edge, in the light's own (scaled) frame (the inverse axes
    in ``params[j, 6:15]``, the cosine of the edge and the blend's width in 15 and 16). The row of a point light of a
    radius holds the identity and an edge's cosine of -2: 1 everywhere."""
    lx = wx * params[j, 6] + wy * params[j, 7] + wz * params[j, 8]
    ly = wx * params[j, 9] + wy * params[j, 10] + wz * params[j, 11]
    lz = wx * params[j, 12] + wy * params[j, 13] + wz * params[j, 14]
    c = lz / max(_sqrt(lx * lx + ly * ly + lz * lz), 1e-300)  # the cosine from the light's -z to the point
    cos_edge, smooth = params[j, 15], params[j, 16]
    if smooth <= 0.0:
        return 1.0 if c > cos_edge else 0.0
    s = min(max((c - cos_edge) / smooth, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


@njit(forceinline=True, **_JIT)
def _cone_direction(ax, ay, az, one_minus_cos, u0, u1):
    """A unit direction evenly in solid angle within the cone about the unit axis (ax, ay, az) whose half angle has
    the cosine 1 - ``one_minus_cos`` (given as that difference: a sun's half a degree keeps its digits), and its
    cosine to the axis."""
    w = u0 * one_minus_cos  # 1 - cos theta
    cos_t = 1.0 - w
    sin_t = _sqrt(max(w * (2.0 - w), 0.0))
    c, s = turn_cos_sin(u1)
    sx, sy, sz, tx, ty, tz = basis(ax, ay, az)
    x, y = sin_t * c, sin_t * s
    return x * sx + y * tx + cos_t * ax, x * sy + y * ty + cos_t * ay, x * sz + y * tz + cos_t * az, cos_t


@njit(forceinline=True, **_JIT)
def _sphere_cone(params, j, px, py, pz):
    """What a sphere light ``params[j]`` looks like from point (px, py, pz): the unit direction to its centre, the
    distance d to it, and 1 - cos of the half angle of the cone it fills (0 from inside it, d <= its radius),
    computed as sin^2 / (1 + cos) so that a small or far sphere keeps its digits."""
    cx, cy, cz = params[j, 0] - px, params[j, 1] - py, params[j, 2] - pz
    d2 = cx * cx + cy * cy + cz * cz
    d = max(_sqrt(d2), 1e-300)
    r = params[j, RADIUS]
    s2 = r * r / max(d2, 1e-300)
    one_minus_cos = s2 / (1.0 + _sqrt(1.0 - s2)) if s2 < 1.0 else 0.0
    return cx / d, cy / d, cz / d, d, one_minus_cos


@njit(forceinline=True, **_JIT)
def _sample_soft_light(kind, params, j, px, py, pz, u0, u1):
    """:func:`_sample_local_light` of a light of :data:`SPHERE`, :data:`FACING_DISK` or :data:`SUN_DISK`, as Cycles
    samples them: a sphere and a sun's disk evenly in the solid angle of the cone they fill (from inside a sphere,
    evenly over every direction), a facing disk evenly in its area. Their radiance (``params[j, 3:6]``) is even over
    their surface, a spot's cone (:func:`_spot_mask`) taken of the direction each point of it sends the light in (from
    inside a sphere, none)."""
    inf = np.inf
    if kind == SUN_DISK:
        one_minus_cos = params[j, 7]
        wx, wy, wz, _ = _cone_direction(params[j, 0], params[j, 1], params[j, 2], one_minus_cos, u0, u1)
        pdf = 1.0 / (2.0 * math.pi * one_minus_cos)
        return wx, wy, wz, inf, params[j, 3], params[j, 4], params[j, 5], pdf
    r = params[j, RADIUS]
    if kind == SPHERE:
        ax, ay, az, d, one_minus_cos = _sphere_cone(params, j, px, py, pz)
        if one_minus_cos > 0.0:  # outside: the near side, the law of cosines
            wx, wy, wz, cos_t = _cone_direction(ax, ay, az, one_minus_cos, u0, u1)
            sin2 = max((1.0 - cos_t) * (1.0 + cos_t), 0.0)
            dist = d * cos_t - _sqrt(max(r * r - d * d * sin2, 0.0))
            mask = _spot_mask(params, j, wx, wy, wz)
            pdf = 1.0 / (2.0 * math.pi * one_minus_cos)
        else:  # inside: every direction meets it, at the far side
            z = 1.0 - 2.0 * u0
            rho = _sqrt(max(1.0 - z * z, 0.0))
            c, s = turn_cos_sin(u1)
            wx, wy, wz = rho * c, rho * s, z
            along = wx * ax + wy * ay + wz * az
            dist = d * along + _sqrt(max(r * r - d * d * (1.0 - along * along), 0.0))
            mask, pdf = 1.0, 1.0 / (4.0 * math.pi)
    else:  # FACING_DISK: a point of the disk about the centre, square to the line from the point
        cx, cy, cz = params[j, 0] - px, params[j, 1] - py, params[j, 2] - pz
        d = _sqrt(cx * cx + cy * cy + cz * cz)
        if not d > 0.0:
            return 0.0, 0.0, 1.0, inf, 0.0, 0.0, 0.0, 0.0
        ax, ay, az = cx / d, cy / d, cz / d
        sx, sy, sz, tx, ty, tz = basis(ax, ay, az)
        a, b = concentric_disk(u0, u1)
        a, b = a * r, b * r
        dx, dy, dz = cx + a * sx + b * tx, cy + a * sy + b * ty, cz + a * sz + b * tz
        dist = _sqrt(dx * dx + dy * dy + dz * dz)
        wx, wy, wz = dx / dist, dy / dist, dz / dist
        cos_l = wx * ax + wy * ay + wz * az
        mask = _spot_mask(params, j, wx, wy, wz)
        pdf = dist * dist / (cos_l * math.pi * r * r) if cos_l > 0.0 else 0.0
    return wx, wy, wz, dist, params[j, 3] * mask, params[j, 4] * mask, params[j, 5] * mask, pdf


@njit(inline="always", **_JIT)
def spread_factor(params, j, cos_l):
    """What area light ``params[j]`` emits toward a direction at cosine ``cos_l`` to its normal, relative to its
    radiance without a *Spread*: Cycles' soft-box grid (``lights.spread_table``: the tangent of the half angle in
    ``params[j, 17]``, inf for none, and the factor that keeps the power in ``params[j, 18]``). A spread of 0 emits
    along the normal only, as Cycles' does."""
    tan_half = params[j, 17]
    if math.isinf(tan_half):
        return 1.0
    tan_a = _sqrt(max(1.0 - cos_l * cos_l, 0.0)) / cos_l
    if tan_half == 0.0:
        return math.pi if tan_a <= 1e-5 else 0.0
    return max((tan_half - tan_a) * params[j, 18], 0.0)


# An environment at least this wide turns its column's edge by less than pi / 4 to place a sample: within the
# reach of ``formula.quarter_cos_sin``.
SMALL_ANGLE_COLUMNS = 8


@njit(**_JIT)
def _sample_environment(image, pixel_pdf, alias_p, alias_i, z_edges, edges, u0, u1):
    """One sample of the environment: direction (unit), distance (inf), radiance and solid-angle pdf. One
    uniform picks the pixel through the alias table (its remainder, rescaled, is the jitter across the pixel), the
    second places the direction down it evenly in z, so evenly in solid angle: the direction lies inside the chosen
    pixel, its radiance is that pixel's and its density the pixel's probability over its solid angle, one number
    per pixel.

    The azimuth turns the column's edge direction (``edges``, as ``env`` holds them) by the jitter's share of the
    column (``formula.quarter_cos_sin``) in an image of at least :data:`SMALL_ANGLE_COLUMNS` columns; a narrower
    one (a constant colour is one pixel) takes the C library's cos and sin of the azimuth."""
    h, w = image.shape[0], image.shape[1]
    n = h * w
    s = u0 * n
    cell = min(int(s), n - 1)
    f = min(max(s - cell, 0.0), 1.0)
    keep = alias_p[cell]
    if f < keep:
        idx, fx = cell, f / keep
    else:
        idx, fx = alias_i[cell], (f - keep) / max(1.0 - keep, 1e-300)
    fx = min(max(fx, 0.0), 1.0 - 1e-9)
    y, x = idx // w, idx % w
    z = z_edges[y + 1] + u1 * (z_edges[y] - z_edges[y + 1])
    r = _sqrt(max(0.0, 1.0 - z * z))
    if w >= SMALL_ANGLE_COLUMNS:  # the column's edge x turned clockwise by fx of the column: no sincos call
        c, s = quarter_cos_sin(fx * (2.0 * math.pi / w))
        dx, dy = edges[x, 0] * c + edges[x, 1] * s, edges[x, 1] * c - edges[x, 0] * s
    else:
        phi = _equirect_azimuth((x + fx) / w)
        dx, dy = math.cos(phi), math.sin(phi)
    return r * dx, r * dy, z, np.inf, image[y, x, 0], image[y, x, 1], image[y, x, 2], pixel_pdf[idx]


@njit(forceinline=True, **_JIT)
def _sample_light(kind, params, j, image, pixel_pdf, alias_p, alias_i, z_edges, edges, px, py, pz, u0, u1, near):
    """One sample of light ``params[j]`` from point (px, py, pz): :func:`_sample_local_light`, or
    :func:`_sample_environment` for the environment.

    The local lights' formulas are inlined into the caller's loop; the environment's sample, with its image and
    tables, is a call of its own. When all of them were one call, its arrays (39 words) went onto the stack for
    every hit, whatever the light: an area light's sample took 38.7 ns a hit in ``sample_lights``, and takes 25.7
    inlined (the demo scene's lights, 60,000 points, each light alone). Inlining the environment's sample too
    measured the same as calling it."""
    if kind == ENVIRONMENT:
        return _sample_environment(image, pixel_pdf, alias_p, alias_i, z_edges, edges, u0, u1)
    return _sample_local_light(kind, params, j, px, py, pz, u0, u1, near)


@njit(**_JIT)
def sample_light(kind, prm, env, p, u):
    """One light's samples from points p (N, 3) with uniforms u (N, 2): directions (N, 3), distances,
    radiance (N, 3), pdfs (the fields of ``lights.LightSample``, its delta flag aside)."""
    image, pixel_pdf, alias_p, alias_i, z_edges, edges = env[0], env[1], env[2], env[3], env[4], env[6]
    n = len(p)
    wi = np.empty((n, 3))
    dist = np.empty(n)
    rad = np.empty((n, 3))
    pdf = np.empty(n)
    params = prm.copy().reshape((1, len(prm)))
    for i in range(n):
        wi[i, 0], wi[i, 1], wi[i, 2], dist[i], rad[i, 0], rad[i, 1], rad[i, 2], pdf[i] = _sample_light(
            kind, params, 0, image, pixel_pdf, alias_p, alias_i, z_edges, edges, p[i, 0], p[i, 1], p[i, 2], u[i, 0],
            u[i, 1], 1e-9,
        )  # fmt: skip
    return wi, dist, rad, pdf


# What ``sample_lights`` writes (``out``, a row per hit): local direction, radiance, pdf, delta, useful, and the
# shadow rays' rows, origins, directions and lengths (their first rows only: one per useful sample), the rays in
# float32 as embree takes them.
LIGHT_SAMPLES_OUT = ((3, F8), (3, F8), (0, F8), (0, B1), (0, B1), (0, I8), (3, F4), (3, F4), (0, F4))

# The longest shadow ray handed to embree: a light at infinity (the sun, the sky) is this far.
FAR = 1e30


@njit(inline="always", **_JIT)
def _unblocked_before(dist, eps):
    """How far short of a local light at ``dist`` a surface must be to block it: a relative 1e-4 and ``eps``, so
    that a light flush with a surface (an area light on a ceiling, in float32 rays) shines. The one rule of both
    ways to reach a light: the shadow rays of next-event estimation end there, and :func:`add_emission` takes the
    light a ray finds unless a surface is nearer than that (with a strict ``<`` there, a light flush with a
    ceiling was found by half the sampled directions that light sampling took as reaching it)."""
    return dist * (1.0 - 1e-4) - eps


@njit(**_JIT)
def sample_lights(out, kinds, params, env, p, ng, ts, tt, ns, u, eps, depth):
    """Next-event estimation's light samples: one light of the table per hit, chosen uniformly by
    u[:, 0] (its remainder is not reused), a point on it from u[:, 1:3]. Returns, per hit, the direction
    in the shading frame (ts, tt, ns), the radiance (N, 3), pdf, delta flag and whether the sample can
    contribute (``useful``: pdf and radiance non-zero, the direction on the same side of the geometric
    normal ``ng`` as of the shading normal, so light never leaks through the surface, and the hits' bounce
    ``depth``, 0 for the camera rays' hits, no deeper than the light's :data:`MAX_BOUNCES`, as Cycles skips a light
    past its Max Bounces; the choice of the light is as likely as ever); and the shadow rays
    of the useful samples of lights that cast shadows (:data:`NO_SHADOW`) only: their rows, origins offset by
    ``eps`` (a row per hit: ``surface_hits``' offset) off the surface on the light's side, world directions and
    lengths (:data:`FAR` to the sun or the sky; else :func:`_unblocked_before` the light), in float32 for embree
    (each value rounded once, as numpy's cast rounds it). Writes them into ``out`` (:data:`LIGHT_SAMPLES_OUT`) and
    returns them, the shadow rays' arrays cut to their count."""
    image, pixel_pdf, alias_p, alias_i, z_edges, edges = env[0], env[1], env[2], env[3], env[4], env[6]
    n = len(p)
    n_lights = len(kinds)
    wi_local, rad, pdf, delta, useful, rows, org, d, tmax = out
    m = 0
    for i in range(n):
        j = min(int(u[i, 0] * n_lights), n_lights - 1)
        wx, wy, wz, dist, r0, r1, r2, pd = _sample_light(
            kinds[j], params, j, image, pixel_pdf, alias_p, alias_i, z_edges, edges, p[i, 0], p[i, 1], p[i, 2],
            u[i, 1], u[i, 2], eps[i],  # no nearer than the shadow ray's start: a scene's size is its own
        )  # fmt: skip
        c = wx * ng[i, 0] + wy * ng[i, 1] + wz * ng[i, 2]
        lz = wx * ns[i, 0] + wy * ns[i, 1] + wz * ns[i, 2]
        wi_local[i, 0] = wx * ts[i, 0] + wy * ts[i, 1] + wz * ts[i, 2]
        wi_local[i, 1] = wx * tt[i, 0] + wy * tt[i, 1] + wz * tt[i, 2]
        wi_local[i, 2] = lz
        rad[i, 0], rad[i, 1], rad[i, 2] = r0, r1, r2
        pdf[i], delta[i] = pd, is_delta(kinds[j])
        same_side = (c > 0.0 and lz > 0.0) or (c < 0.0 and lz < 0.0)
        ok = pd > 0.0 and max(r0, r1, r2) > 0.0 and same_side and depth <= params[j, MAX_BOUNCES]
        useful[i] = ok
        if ok and params[j, NO_SHADOW] == 0.0:  # a light that casts no shadow reaches the surface untested
            off = eps[i] if c > 0.0 else -eps[i]
            rows[m] = i
            for k in range(3):
                org[m, k] = p[i, k] + ng[i, k] * off
            d[m, 0], d[m, 1], d[m, 2] = wx, wy, wz
            length = FAR if math.isinf(dist) else _unblocked_before(dist, eps[i])
            tmax[m] = FAR if length > FAR else length
            m += 1
    return wi_local, rad, pdf, delta, useful, rows[:m], org[:m], d[:m], tmax[:m]


@njit(inline="always", **_JIT)
def _intersect_area(params, j, ellipse, ox, oy, oz, dx, dy, dz):
    """Distance along a unit ray to the emitting side of area light ``params[j]`` (inf where missed) and the
    solid-angle pdf of sampling that point. The light is indexed, not sliced (as ``_sample_light``'s).

    A ray whose line passes the light's centre farther than the light's bounding radius (its square in
    ``params[j, 16]``, with a margin) misses it: most rays, rejected with no division. The demo's area light, rays
    of random directions: 13 -> 4 ns a ray more than with no area light; in a render ``add_emission`` 18 -> 15 ns
    a ray, the image the same to the bit."""
    cx, cy, cz = params[j, 0] - ox, params[j, 1] - oy, params[j, 2] - oz
    along = cx * dx + cy * dy + cz * dz
    if cx * cx + cy * cy + cz * cz - along * along > params[j, 16]:
        return np.inf, 0.0
    nx, ny, nz = params[j, 9], params[j, 10], params[j, 11]
    denom = dx * nx + dy * ny + dz * nz
    height = cx * nx + cy * ny + cz * nz  # (centre - origin) . normal
    # Only rays arriving against the emitting normal, from its lit side, can hit it.
    if not (denom < -1e-12 and height < 0.0):
        return np.inf, 0.0
    t = height / denom
    qx, qy, qz = ox + t * dx - params[j, 0], oy + t * dy - params[j, 1], oz + t * dz - params[j, 2]
    # the point's coordinates (a, b) in the axes u, v: q = a u + b v, as the sampling places points (solved with
    # the axes' Gram matrix: a matrix that shears the light leaves u and v oblique)
    ux, uy, uz, vx, vy, vz = params[j, 3], params[j, 4], params[j, 5], params[j, 6], params[j, 7], params[j, 8]
    uu, vv, uv = ux * ux + uy * uy + uz * uz, vx * vx + vy * vy + vz * vz, ux * vx + uy * vy + uz * vz
    qu, qv = qx * ux + qy * uy + qz * uz, qx * vx + qy * vy + qz * vz
    gram = uu * vv - uv * uv
    a, b = (qu * vv - qv * uv) / gram, (qv * uu - qu * uv) / gram
    inside = (a * a + b * b <= 1.0) if ellipse else (abs(a) <= 1.0 and abs(b) <= 1.0)
    if not (inside and t > 1e-6):
        return np.inf, 0.0
    if not ellipse:
        ok, xx, xy, xz, yx, yy, yz, x0, x1, y0, y1, z0 = _rect_window(params, j, ox, oy, oz)
        if ok:  # sampled by solid angle from here (a point outside a spread's window gets nothing from the light)
            solid = _rect_solid_angle(x0, x1, y0, y1, z0) if x0 < x1 else 0.0
            return t, (1.0 / solid if solid > 0.0 else 0.0)
    return t, t * t / (-denom * params[j, 15])


@njit(**_JIT)
def intersect_area(prm, ellipse, o, d):
    """:func:`_intersect_area` for rays o, d (N, 3): distances and pdfs (N,)."""
    n = len(o)
    t = np.empty(n)
    pdf = np.empty(n)
    params = prm.copy().reshape((1, len(prm)))
    for i in range(n):
        t[i], pdf[i] = _intersect_area(params, 0, ellipse, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2])
    return t, pdf


@njit(inline="always", **_JIT)
def _intersect_soft(kind, params, j, ox, oy, oz, dx, dy, dz):
    """Where a unit ray meets light ``params[j]`` of :data:`SPHERE`, :data:`FACING_DISK` or :data:`SUN_DISK`, as
    Cycles finds them: the distance (inf for a sun's disk), the solid-angle pdf of :func:`_sample_soft_light` choosing
    that direction from the ray's origin, and the share of the light's radiance sent along the ray (a spot's cone:
    :func:`_spot_mask`); a share of 0 where the ray misses. A sphere is met once, where the ray enters it (from
    inside, where it leaves it); a facing disk is the one square to the line from the ray's origin."""
    inf = np.inf
    if kind == SUN_DISK:
        if dx * params[j, 0] + dy * params[j, 1] + dz * params[j, 2] < params[j, 6]:
            return inf, 0.0, 0.0
        return inf, 1.0 / (2.0 * math.pi * params[j, 7]), 1.0
    r = params[j, RADIUS]
    if kind == SPHERE:
        ax, ay, az, d, one_minus_cos = _sphere_cone(params, j, ox, oy, oz)
        along = d * (ax * dx + ay * dy + az * dz)
        outside = one_minus_cos > 0.0
        if outside and along < 0.0:
            return inf, 0.0, 0.0
        off2 = max(d * d - along * along, 0.0)  # the squared distance from the centre to the ray's line
        if off2 > r * r:
            return inf, 0.0, 0.0
        half = _sqrt(r * r - off2)
        t = along - half if outside else along + half
        if not t > 0.0:
            return inf, 0.0, 0.0
        if not outside:
            return t, 1.0 / (4.0 * math.pi), 1.0
        return t, 1.0 / (2.0 * math.pi * one_minus_cos), _spot_mask(params, j, dx, dy, dz)
    # FACING_DISK
    cx, cy, cz = params[j, 0] - ox, params[j, 1] - oy, params[j, 2] - oz
    d = _sqrt(cx * cx + cy * cy + cz * cz)
    cos_l = (cx * dx + cy * dy + cz * dz) / max(d, 1e-300)  # the ray's cosine to the disk's normal
    if not cos_l > 0.0:
        return inf, 0.0, 0.0
    t = d / cos_l
    qx, qy, qz = t * dx - cx, t * dy - cy, t * dz - cz
    if qx * qx + qy * qy + qz * qz > r * r:
        return inf, 0.0, 0.0
    return t, t * t / (cos_l * math.pi * r * r), _spot_mask(params, j, dx, dy, dz)


@njit(inline="always", **_JIT)
def _soft_light_reached(kind, params, j, ox, oy, oz, dx, dy, dz, t, eps, far):
    """What a ray that meets a surface at ``t`` (inf: none) finds of light ``params[j]`` of :data:`SPHERE`,
    :data:`FACING_DISK` or :data:`SUN_DISK` (:func:`_intersect_soft`): the share of its radiance (0 where the ray
    misses it, a surface blocks it as :func:`_unblocked_before` says, or it lies beyond ``far``, the camera's far
    clipping plane), the pdf, and whether it is a light of the scene (not a sun's disk, found where the ray escapes,
    as the sky is, whatever the clipping plane)."""
    tl, pdf_l, g = _intersect_soft(kind, params, j, ox, oy, oz, dx, dy, dz)
    if math.isinf(tl):
        return (g if math.isinf(t) else 0.0), pdf_l, False
    if tl > far or t < _unblocked_before(tl, eps):
        return 0.0, pdf_l, True
    return g, pdf_l, True


@njit(**_JIT)
def intersect_soft(kind, prm, o, d):
    """:func:`_intersect_soft` for rays o, d (N, 3): distances, pdfs and shares of the radiance (N,) each."""
    n = len(o)
    t = np.empty(n)
    pdf = np.empty(n)
    share = np.empty(n)
    params = prm.copy().reshape((1, len(prm)))
    for i in range(n):
        t[i], pdf[i], share[i] = _intersect_soft(kind, params, 0, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2])
    return t, pdf, share


# --- multiple importance sampling and path bookkeeping ------------------------------------------

MIS, LIGHT_ONLY, BSDF_ONLY = range(3)  # the integrator's strategies, in its STRATEGIES order


@njit(inline="always", **_JIT)
def _power_heuristic(a, b):
    a2, b2 = a * a, b * b
    return a2 / (a2 + b2) if a2 + b2 > 0.0 else 0.0


@njit(inline="always", **_JIT)
def _emission_weight(strategy, p_select, pdf_light, prev_pdf, prev_delta, prev_mis):
    """Weight of emission a BSDF-sampled ray finds, against next-event estimation's sample of it."""
    if strategy == BSDF_ONLY:
        return 1.0
    if prev_delta:
        return 1.0
    if strategy == LIGHT_ONLY or not prev_mis:  # without a BSDF pdf, next-event estimation alone
        return 0.0
    return _power_heuristic(prev_pdf, p_select * pdf_light)


@njit(**_JIT)
def add_emission(
    hit_kinds, hit_params, has_env, env, strategy, p_select,
    o, d, t, row, throughput, prev_pdf, prev_delta, prev_mis, L, eps, camera, reach, features, bounce,
):  # fmt: skip
    """Add to ``L[row]`` the emission rays (o, d) reach before distance ``t``: every light of the table of lights rays
    can hit (``hit_kinds``, ``hit_params``: area lights, spheres, facing disks, suns' disks) that no surface blocks
    (the surface at ``t`` is not nearer than :func:`_unblocked_before` the light, as for the shadow rays, with
    ``eps`` the offset of each ray's origin: 0 for the camera's; a sun's disk where the ray escapes), toward the ray as
    its spread or a spot's cone lets it (:func:`spread_factor`, :func:`_spot_mask`), and not when the rays are the
    camera's (``camera``) and the light is hidden from them (:data:`CAMERA_VISIBLE` 0) or lies beyond the far clipping
    plane (``reach``, each camera ray's length to it; empty: none); a camera ray that meets a light of the scene covers
    its pixel (``features[row, 7]``, the film's coverage: 1), and the environment ``env`` where the ray escapes (t =
    inf; with ``has_env``), each weighted by how the ray was sampled (:func:`_emission_weight`). The rays left hits of
    bounce ``bounce`` (-1: the camera's): a light's emission counts there as the direct light of those hits, up to the
    light's :data:`MAX_BOUNCES`, as next-event estimation's does (``sample_lights``), whatever the strategy."""
    image, pixel_pdf, _, _, z_edges, row_of_bin, edges, column_of_bin = env
    for i in range(len(o)):
        ox, oy, oz, dx, dy, dz = o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2]
        r = row[i]
        for j in range(len(hit_params)):
            if (camera and hit_params[j, CAMERA_VISIBLE] == 0.0) or bounce > hit_params[j, MAX_BOUNCES]:
                continue
            kind = hit_kinds[j]
            if kind == AREA_RECT or kind == AREA_ELLIPSE:
                tl, pdf_l = _intersect_area(hit_params, j, kind == AREA_ELLIPSE, ox, oy, oz, dx, dy, dz)
                if camera and len(reach) and tl > reach[i]:
                    continue
                if not math.isinf(tl) and t[i] >= _unblocked_before(tl, eps[i]):
                    w = _emission_weight(strategy, p_select, pdf_l, prev_pdf[i], prev_delta[i], prev_mis[i])
                    cos_l = -(dx * hit_params[j, 9] + dy * hit_params[j, 10] + dz * hit_params[j, 11])
                    w *= spread_factor(hit_params, j, cos_l)
                    for k in range(3):
                        L[r, k] += throughput[i, k] * hit_params[j, 12 + k] * w
                    if camera:
                        features[r, 7] = 1.0
                continue
            far = reach[i] if camera and len(reach) else np.inf
            g, pdf_l, local = _soft_light_reached(kind, hit_params, j, ox, oy, oz, dx, dy, dz, t[i], eps[i], far)
            if not g > 0.0:
                continue
            if camera and local:
                features[r, 7] = 1.0
            w = g * _emission_weight(strategy, p_select, pdf_l, prev_pdf[i], prev_delta[i], prev_mis[i])
            for k in range(3):
                L[r, k] += throughput[i, k] * hit_params[j, 3 + k] * w
        if has_env and math.isinf(t[i]):
            r0, r1, r2, pdf_e = _env_lookup(image, pixel_pdf, z_edges, row_of_bin, edges, column_of_bin, dx, dy, dz)
            w = _emission_weight(strategy, p_select, pdf_e, prev_pdf[i], prev_delta[i], prev_mis[i])
            L[r, 0] += throughput[i, 0] * r0 * w
            L[r, 1] += throughput[i, 1] * r1 * w
            L[r, 2] += throughput[i, 2] * r2 * w


@njit(**_JIT)
def add_direct(L, hits, row, throughput, f, light_wi, radiance, p_select, light_pdf, delta, pdf_bsdf, weighted):
    """Add next-event estimation's contribution f |cos| L / pdf of the hits ``hits`` (V,) to their paths'
    pixels ``L[row[hit]]``: ``f`` (V, 3) at the light directions, the rest per hit (``light_wi`` local, the
    light sample's radiance, pdf and delta flag), the pdf times ``p_select``, the probability of choosing
    its light; ``weighted``: against BSDF sampling by the power heuristic (``pdf_bsdf`` (V,)), delta lights
    excepted."""
    for k in range(len(hits)):
        i = hits[k]
        pdf_light = p_select * light_pdf[i]
        w = 1.0
        if weighted and not delta[i]:
            w = _power_heuristic(pdf_light, pdf_bsdf[k])
        s = abs(light_wi[i, 2]) * w / pdf_light
        r = row[i]
        for c in range(3):
            L[r, c] += throughput[i, c] * f[k, c] * s * radiance[i, c]


# The paths' fields (``integrator._Paths``, in order), as ``continue_paths`` writes them.
PATHS_OUT = ((0, I8), (3, F8), (3, F8), (3, F8), (0, F8), (0, B1), (0, B1), (0, F8), (0, F8), (0, F8))


@njit(**_JIT)
def continue_paths(
    out, wi_local, ts, tt, ns, weight, pdf, delta, mis, p, ng, row, throughput, width, spread, u_rr, roulette,
    eps,
):  # fmt: skip
    """The next rays of the paths at a bounce: throughput times the sample weight, with Russian
    roulette where ``roulette`` (survival probability the largest throughput component, clipped to
    [0.05, 1], drawn against ``u_rr``; survivors reweighted by 1 / q); paths whose sample is zero or
    would leave through the wrong side of the geometric surface (``wi_local`` in the shading frame
    (ts, tt, ns), taken to world space here) are dropped. The survivors' origins are offset by ``eps`` (a row per
    hit: ``surface_hits``' offset) off the surface on their side, and a non-specular bounce widens the ray cone's
    spread to at least 0.2. Returns row, origin, direction, throughput, pdf, delta, mis, width, spread and offset
    (for :func:`add_emission`) of the survivors: the first rows
    of ``out`` (:data:`PATHS_OUT`, a row per path; not the arrays of the paths it reads).

    One pass, each survivor written as it is found: a first pass that decided and a second that compacted, with
    rows of their own between them, took 27 ns a path where this takes 25 (one-thread demo renders)."""
    n = len(row)
    o_row, o_org, o_dir, o_thr, o_pdf, o_delta, o_mis, o_width, o_spread, o_eps = out
    j = 0
    for i in range(n):
        lx, ly, lz = wi_local[i, 0], wi_local[i, 1], wi_local[i, 2]
        wx = lx * ts[i, 0] + ly * tt[i, 0] + lz * ns[i, 0]
        wy = lx * ts[i, 1] + ly * tt[i, 1] + lz * ns[i, 1]
        wz = lx * ts[i, 2] + ly * tt[i, 2] + lz * ns[i, 2]
        c = wx * ng[i, 0] + wy * ng[i, 1] + wz * ng[i, 2]
        same_side = (c > 0.0 and lz > 0.0) or (c < 0.0 and lz < 0.0)
        ok = max(weight[i, 0], weight[i, 1], weight[i, 2]) > 0.0 and same_side
        s = 1.0
        if ok and roulette:
            q = max(throughput[i, 0] * weight[i, 0], throughput[i, 1] * weight[i, 1], throughput[i, 2] * weight[i, 2])
            q = min(max(q, 0.05), 1.0)
            ok = u_rr[i] < q
            s = 1.0 / q
        if not ok:
            continue
        side = eps[i] if c > 0.0 else -eps[i]
        o_row[j] = row[i]
        o_org[j, 0] = p[i, 0] + ng[i, 0] * side
        o_org[j, 1] = p[i, 1] + ng[i, 1] * side
        o_org[j, 2] = p[i, 2] + ng[i, 2] * side
        o_dir[j, 0], o_dir[j, 1], o_dir[j, 2] = wx, wy, wz
        for k in range(3):
            o_thr[j, k] = throughput[i, k] * weight[i, k] * s
        o_pdf[j], o_delta[j], o_mis[j], o_width[j] = pdf[i], delta[i], mis[i], width[i]
        o_spread[j] = spread[i] if delta[i] else max(spread[i], 0.2)
        o_eps[j] = eps[i]
        j += 1
    count = j
    return (
        o_row[:count], o_org[:count], o_dir[:count], o_thr[:count], o_pdf[:count], o_delta[:count], o_mis[:count],
        o_width[:count], o_spread[:count], o_eps[:count],
    )  # fmt: skip


@njit(**_JIT)
def hits_by_material(out, prim, material_of_triangle, n_materials):
    """The rays that hit a triangle (``prim`` >= 0), ordered by the material of the triangle (stable:
    a counting sort), and where each material's rows start (``n_materials + 1`` offsets). ``out``: int64, a row
    per ray; the first rows, one per hit, are written and returned."""
    counts = np.zeros(n_materials + 1, dtype=np.int64)
    for i in range(len(prim)):
        if prim[i] >= 0:
            counts[material_of_triangle[prim[i]] + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    order = out[: starts[-1]]
    for i in range(len(prim)):
        if prim[i] >= 0:
            m = material_of_triangle[prim[i]]
            order[fill[m]] = i
            fill[m] += 1
    return order, starts


# The fields of the paths that hit a surface, as the shading reads them (``integrator._HitPaths``, in order).
HIT_PATHS_OUT = ((0, I8), (3, F8), (3, F8), (0, F8), (0, F8))


@njit(**_JIT)
def take_paths(out, keep, row, d, throughput, width, spread):
    """The fields the shading reads of the paths at rows ``keep`` (row, direction, throughput, cone width and
    spread), in one pass, into ``out`` (:data:`HIT_PATHS_OUT`, a row per kept path). The origin and how the ray
    was sampled are read before, by the intersection and ``add_emission``, and not after: gathering them too
    (six of the fifteen values a path) took the loop 9 ns a path where it takes 5 (a render's split of the
    rest, two rounds)."""
    o_row, o_d, o_thr, o_width, o_spread = out
    for j in range(len(keep)):
        i = keep[j]
        o_row[j] = row[i]
        for k in range(3):
            o_d[j, k], o_thr[j, k] = d[i, k], throughput[i, k]
        o_width[j], o_spread[j] = width[i], spread[i]
    return out


# --- the shading of a bounce ----------------------------------------------------------------------


@njit(inline="always", **_JIT)
def _keep_sample(wi, weight, pdf, valid, i, x, y, z, w0, w1, w2, p, ok):
    """Row i of a sample's arrays: the sample where ``bsdf.base.sample_ok`` passes it, else zeros (as
    ``BSDFSample.build``). Returns whether it passed."""
    ok = sample_ok(ok, p, w0, w1, w2, x, y, z)
    if not ok:
        x = y = z = w0 = w1 = w2 = p = 0.0
    wi[i, 0], wi[i, 1], wi[i, 2] = x, y, z
    weight[i, 0], weight[i, 1], weight[i, 2] = w0, w1, w2
    pdf[i], valid[i] = p, ok
    return ok


@njit(**_JIT)
def tinted_albedo(texels, color):
    """A textured Lambertian's albedo (N, 3) float64: the texture's texels (N, 3) float32, a negative one as 0 (one
    above 1 kept, as Cycles keeps a base colour's), times ``color`` (3,), as ``np.maximum(texels, 0) * color``
    computes it (the product in float64), in one pass: numpy's two took 0.71-0.86 ms for 60,000 hits, this loop
    0.08."""
    n = len(texels)
    out = np.empty((n, 3))
    for i in range(n):
        for c in range(3):
            out[i, c] = max(texels[i, c], np.float32(0.0)) * color[c]
    return out


@njit(**_JIT)
def lambert_shade(albedo, wo, light_wi, light_rows, u):
    """A Lambertian's answer to a bounce (``render.materials``): f (V, 3) and pdf (V,) at the next-event
    directions ``light_wi`` of rows ``light_rows``, and one cosine-weighted sample per hit (wi, weight,
    pdf, valid, as ``Lambertian.sample``; ``u`` (N, 2)). ``albedo`` is (1, 3) shared or (N, 3) per hit.

    Two loops, each compiled on its own: written as one function, the same two loops took 60 ns a hit where
    they take 32 (a bounce of the demo scene's floor recorded and replayed)."""
    f, pdf_light = _lambert_at_lights(albedo, wo, light_wi, light_rows)
    wi, weight, pdf, valid = _lambert_samples(albedo, wo, u)
    return f, pdf_light, wi, weight, pdf, valid


@njit(**_JIT)
def _lambert_at_lights(albedo, wo, light_wi, light_rows):
    v = len(light_rows)
    shared = albedo.shape[0] == 1
    f = np.empty((v, 3))
    pdf_light = np.empty(v)
    for k in range(v):
        i = light_rows[k]
        j = 0 if shared else i
        iz, oz = light_wi[k, 2], wo[i, 2]
        for c in range(3):
            f[k, c] = lambert_f(iz, oz, albedo[j, c])
        pdf_light[k] = lambert_pdf(iz, oz)
    return f, pdf_light


@njit(**_JIT)
def _lambert_samples(albedo, wo, u):
    n = len(wo)
    shared = albedo.shape[0] == 1
    wi = np.empty((n, 3))
    weight = np.empty((n, 3))
    pdf = np.empty(n)
    valid = np.empty(n, dtype=np.bool_)
    for i in range(n):
        j = 0 if shared else i
        x, y, z, p, ok = lambert_sample(wo[i, 2], u[i, 0], u[i, 1])
        _keep_sample(wi, weight, pdf, valid, i, x, y, z, albedo[j, 0], albedo[j, 1], albedo[j, 2], p, ok)
    return wi, weight, pdf, valid


@njit(**_JIT)
def principled_shade(base, k, lobes, e_curve, e1_curve, wo, light_wi, light_rows, u_lobe, u):
    """A Principled BSDF's answer to a bounce (``bsdf.SpecularDiffuse``, ``render.PrincipledMaterial``): f (V, 3)
    and the sampler's pdf (V,) at the next-event directions ``light_wi`` of rows ``light_rows``, and one sample per
    hit (wi, weight, pdf, delta, valid, as ``SpecularDiffuse.sample``; ``u_lobe`` (N,), ``u`` (N, 2)). The
    material's arrays are ``SpecularDiffuse.shading_arrays``: ``base`` and ``k`` (1, 3) shared or (N, 3) per hit,
    ``lobes`` (alpha, ior, metallic, Fresnel average, E1_avg), the albedo curves over mu of the layer and of E1.
    The formulas are ``specular_diffuse``'s (``principled_view``, ``principled_eval``, ``principled_sample``),
    which SpecularDiffuse runs on columns. Two loops, each compiled on its own, as :func:`lambert_shade`'s."""
    f, pdf_light = _principled_at_lights(base, k, lobes, e_curve, e1_curve, wo, light_wi, light_rows)
    wi, weight, pdf, delta, valid = _principled_samples(base, k, lobes, e_curve, e1_curve, wo, u_lobe, u)
    return f, pdf_light, wi, weight, pdf, delta, valid


@njit(**_JIT)
def _principled_at_lights(base, k, lobes, e_curve, e1_curve, wo, light_wi, light_rows):
    v = len(light_rows)
    shared, shared_k = base.shape[0] == 1, k.shape[0] == 1
    alpha, ior, metallic, f_avg, e1_avg = lobes[0], lobes[1], lobes[2], lobes[3], lobes[4]
    metal = metallic > 0.0
    f = np.empty((v, 3))
    pdf = np.empty(v)
    for n in range(v):
        i = light_rows[n]
        j = 0 if shared else i
        jk = 0 if shared_k else i
        s = -1.0 if wo[i, 2] < 0.0 else 1.0  # two-sided: a view from below mirrored above, with its light
        oz = wo[i, 2] * s
        b0, b1, b2 = base[j, 0], base[j, 1], base[j, 2]
        scale, diffuse, s0, s1, s2, p = principled_view(
            curve_at(e_curve, oz), curve_at(e1_curve, oz), e1_avg, f_avg, metallic, b0, b1, b2, metal
        )
        f[n, 0], f[n, 1], f[n, 2], pdf[n] = principled_eval(
            light_wi[n, 0], light_wi[n, 1], light_wi[n, 2] * s, wo[i, 0], wo[i, 1], oz, alpha, ior, metallic,
            b0, b1, b2, k[jk, 0], k[jk, 1], k[jk, 2], scale, diffuse, s0, s1, s2, p, metal,
        )  # fmt: skip
    return f, pdf


@njit(**_JIT)
def _principled_samples(base, k, lobes, e_curve, e1_curve, wo, u_lobe, u):
    n = len(wo)
    shared, shared_k = base.shape[0] == 1, k.shape[0] == 1
    alpha, ior, metallic, f_avg, e1_avg = lobes[0], lobes[1], lobes[2], lobes[3], lobes[4]
    metal = metallic > 0.0
    wi = np.empty((n, 3))
    weight = np.empty((n, 3))
    pdf = np.empty(n)
    delta = np.empty(n, dtype=np.bool_)
    valid = np.empty(n, dtype=np.bool_)
    for i in range(n):
        j = 0 if shared else i
        jk = 0 if shared_k else i
        s = -1.0 if wo[i, 2] < 0.0 else 1.0
        oz = wo[i, 2] * s
        b0, b1, b2 = base[j, 0], base[j, 1], base[j, 2]
        scale, diffuse, s0, s1, s2, p = principled_view(
            curve_at(e_curve, oz), curve_at(e1_curve, oz), e1_avg, f_avg, metallic, b0, b1, b2, metal
        )
        x, y, z, w0, w1, w2, q, is_delta, ok = principled_sample(
            wo[i, 0], wo[i, 1], oz, u_lobe[i], u[i, 0], u[i, 1], alpha, ior, metallic,
            b0, b1, b2, k[jk, 0], k[jk, 1], k[jk, 2], scale, diffuse, s0, s1, s2, p, metal,
        )  # fmt: skip
        delta[i] = _keep_sample(wi, weight, pdf, valid, i, x, y, z * s, w0, w1, w2, q, ok) and is_delta
    return wi, weight, pdf, delta, valid


@njit(**_JIT)
def finish_proposals(wi, pdf, f):
    """A sample from proposed directions ``wi`` (N, 3), their density and the evaluated f (N, 3)
    (``render.shading.finish_sample``): weight f |cos| / pdf where the pdf is positive and wi above the
    horizon. Returns wi, weight, pdf, valid, zeroed where invalid."""
    n = len(wi)
    out_wi = np.empty((n, 3))
    weight = np.empty((n, 3))
    out_pdf = np.empty(n)
    valid = np.empty(n, dtype=np.bool_)
    for i in range(n):
        x, y, z, p = wi[i, 0], wi[i, 1], wi[i, 2], pdf[i]
        s = abs(z) / p
        ok = p > 0.0 and z > 0.0
        _keep_sample(out_wi, weight, out_pdf, valid, i, x, y, z, f[i, 0] * s, f[i, 1] * s, f[i, 2] * s, p, ok)
    return out_wi, weight, out_pdf, valid


# --- the sampling proxy (addon.core.neural.proxy) -----------------------------------------------


@njit(inline="always", **_JIT)
def _disk_mass(sigma):
    """Mass of the isotropic 2D Gaussian inside the unit disk: 1 - exp(-1 / (2 sigma^2))."""
    return -math.expm1(-0.5 / (sigma * sigma))


@njit(inline="always", **_JIT)
def _shared_disk_mass(sigma):
    """:func:`_disk_mass` of ``sigma[0]`` where ``sigma`` is one value that every row shares (a single latent's
    proxy), else 0 (unused: each row's is taken with it). Taken once before a loop: ``expm1`` for every row was
    0.7% of a demo render's samples."""
    return _disk_mass(sigma[0]) if len(sigma) == 1 else 0.0


@njit(inline="always", **_JIT)
def _proxy_pdf(ox, oy, oz, ix, iy, iz, s, mass, w):
    """The proxy's density at wi (ix, iy, iz) given wo (ox, oy, oz) for parameters (s, w) (``proxy_pdf``);
    ``mass``: :func:`_disk_mass` of s."""
    if not (oz > 0.0 and iz > 0.0):
        return 0.0
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    hn = max(_sqrt(hx * hx + hy * hy + hz * hz), 1e-12)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    p_disk = math.exp(-0.5 * (hx * hx + hy * hy) / (s * s)) / (2.0 * math.pi * s * s * mass)
    p_h = p_disk * max(hz, 0.0)
    wo_h = abs(ox * hx + oy * hy + oz * hz)
    p_gauss = p_h / (4.0 * wo_h) if wo_h > 1e-9 else 0.0
    return (1.0 - w) * p_gauss + w * max(iz, 0.0) / math.pi


@njit(**_JIT)
def proxy_pdf(wo, wi, sigma, w):
    """Solid-angle density (N,) of the proxy choosing ``wi`` given ``wo`` (``neural.proxy.pdf``), with
    per-row ``sigma`` (>= SIGMA_MIN) and cosine-lobe weight ``w`` (in [0, 1]); 0 below the horizon."""
    n = len(wo)
    out = np.empty(n)
    for i in range(n):
        s = sigma[i]
        out[i] = _proxy_pdf(wo[i, 0], wo[i, 1], wo[i, 2], wi[i, 0], wi[i, 1], wi[i, 2], s, _disk_mass(s), w[i])
    return out


@njit(inline="always", **_JIT)
def _proxy_direction(ox, oy, oz, s, mass, w, u0, u1, u2):
    """One direction of ``proxy_directions`` for wo (ox, oy, oz), parameters (s, w) and uniforms u0..u2;
    ``mass``: :func:`_disk_mass` of s."""
    c, s_phi = turn_cos_sin(u2)  # the azimuth 2 pi u2
    if u0 < w:
        rc = _sqrt(u1)
        x, y, z = rc * c, rc * s_phi, _sqrt(max(1.0 - u1, 0.0))
    else:
        r = min(s * _sqrt(-2.0 * math.log1p(-u1 * mass)), 1.0)
        hx, hy, hz = r * c, r * s_phi, _sqrt(max(1.0 - r * r, 0.0))
        x, y, z = reflected(ox, oy, oz, hx, hy, hz)
    norm = max(_sqrt(x * x + y * y + z * z), 1e-12)
    return x / norm, y / norm, z / norm


@njit(**_JIT)
def proxy_directions(wo, sigma, w, u):
    """Directions (N, 3) the proxy samples given ``wo`` (``neural.proxy.sample_directions``): u[:, 0]
    picks the lobe (the cosine lobe below ``w``), u[:, 1:] place the direction: the Gaussian lobe's
    half vector by a truncated Rayleigh radius in the projected disk (wo mirrored about it), the
    cosine lobe by Malley's method."""
    n = len(wo)
    out = np.empty((n, 3))
    for i in range(n):
        s = sigma[i]
        out[i, 0], out[i, 1], out[i, 2] = _proxy_direction(
            wo[i, 0], wo[i, 1], wo[i, 2], s, _disk_mass(s), w[i], u[i, 0], u[i, 1], u[i, 2]
        )
    return out


# --- the exact top coat of remainder decoders (addon.core.neural.top_lobe) -----------------------


@njit(**_JIT)
def top_lobe_eval_pdf(wi, wo, top):
    """f (N,) and the sampling density (N,) of the top interface's reflection (``top_lobe.eval_pdf_top``) at
    unit local directions: ``top`` (1, 2) one (alpha, ior) for every row, or (N, 2) per row; 0 where the
    interface is index-matched or a direction is at or below the horizon."""
    n = len(wi)
    f = np.zeros(n)
    p = np.zeros(n)
    shared = top.shape[0] == 1
    for i in range(n):
        j = 0 if shared else i
        f[i], p[i] = top_reflection(wi[i, 0], wi[i, 1], wi[i, 2], wo[i, 0], wo[i, 1], wo[i, 2], top[j, 0], top[j, 1])
    return f, p


@njit(forceinline=True, **_JIT)
def _alpha_cell(alpha_grid, a):
    """The transmittance table's cell of roughness ``a`` (its grid is geometric: ``top_lobe.TRANSMITTANCE_ALPHA``)."""
    return _segment_near(alpha_grid, a, _spacing_guess(alpha_grid, a, 1))


@njit(forceinline=True, **_JIT)
def _ior_cell(ior_grid, ior):
    """The transmittance table's cell of index ``ior`` (its grid is even: ``top_lobe.TRANSMITTANCE_IOR``)."""
    return _segment_near(ior_grid, ior, _spacing_guess(ior_grid, ior, 0))


@njit(forceinline=True, **_JIT)
def _coating_node(table, k, ia, fa, ii, fi):
    """The transmittance table (cos, alpha, ior) at its k-th cosine for a coating whose alpha and ior cells
    (ia, fa), (ii, fi) are found already: bilinear in alpha and ior."""
    low = table[k, ia, ii] * (1.0 - fi) + table[k, ia, ii + 1] * fi
    high = table[k, ia + 1, ii] * (1.0 - fi) + table[k, ia + 1, ii + 1] * fi
    return low * (1.0 - fa) + high * fa


@njit(forceinline=True, **_JIT)
def _between_nodes(cos_grid, c):
    """The cosine cell (k, weight) of ``c`` in the transmittance table, or k = -1 at and below the horizon."""
    if not c > 0.0:
        return -1, 0.0
    return _segment_near(cos_grid, c, _spacing_guess(cos_grid, c, 2))


@njit(inline="always", **_JIT)
def _between_clipped(low, high, t):
    """The transmittance between two cosine nodes' values, weight ``t`` on the second, clipped to [0, 1]."""
    return min(max(low * (1.0 - t) + high * t, 0.0), 1.0)


@njit(forceinline=True, **_JIT)
def _transmission(table, cos_grid, c, ia, fa, ii, fi):
    """The top interface's transmittance at cosine ``c`` (``top_lobe.transmission``): trilinear in ``table``
    (cos, alpha, ior) with the coating's alpha and ior cells (ia, fa), (ii, fi) found already, clipped to
    [0, 1]; 0 at and below the horizon."""
    k, t = _between_nodes(cos_grid, c)
    if k < 0:
        return 0.0
    return _between_clipped(_coating_node(table, k, ia, fa, ii, fi), _coating_node(table, k + 1, ia, fa, ii, fi), t)


@njit(forceinline=True, **_JIT)
def _transmission_column(table, alpha_grid, ior_grid, a, ior):
    """One coating's (a, ior) transmittance at every cosine of the table's grid (:func:`_coating_node`): for a
    material's rows, which share their coating, so that each row reads two of them (:func:`_column_transmission`)
    where :func:`_transmission` reads eight corners of the table."""
    ia, fa = _alpha_cell(alpha_grid, a)
    ii, fi = _ior_cell(ior_grid, ior)
    out = np.empty(table.shape[0])
    for k in range(table.shape[0]):
        out[k] = _coating_node(table, k, ia, fa, ii, fi)
    return out


@njit(forceinline=True, **_JIT)
def _column_transmission(column, cos_grid, c):
    """:func:`_transmission` at cosine ``c`` from the coating's :func:`_transmission_column` (the same numbers)."""
    k, t = _between_nodes(cos_grid, c)
    if k < 0:
        return 0.0
    return _between_clipped(column[k], column[k + 1], t)


@njit(**_JIT)
def transmission_rows(top, cos, table, cos_grid, alpha_grid, ior_grid):
    """(N,) ``top_lobe.transmission``: the share of the light arriving from ``cos`` (N,) that the top coatings
    ``top`` ((1, 2) shared or (N, 2)) let into the coat; 1 for an index-matched row (no top interface)."""
    n = len(cos)
    out = np.empty(n)
    shared = top.shape[0] == 1
    for i in range(n):
        j = 0 if shared else i
        if abs(top[j, 1] - 1.0) < INDEX_MATCHED_TOL:
            out[i] = 1.0
            continue
        ia, fa = _alpha_cell(alpha_grid, top[j, 0])
        ii, fi = _ior_cell(ior_grid, top[j, 1])
        out[i] = _transmission(table, cos_grid, cos[i], ia, fa, ii, fi)
    return out


# ``decoded_brdf``'s ``hit_of_row`` where row i reads row i
EVERY_ROW = np.zeros(0, dtype=I8)


@njit(**_JIT)
def decoded_brdf(out, wi, wo, calibration, top, transmittance, scale, add_lobe, hit_of_row):
    """A decoder's ``out`` (N, 3) float32 made the material's f, in place, in one pass (``ModelSet.eval_brdf``):
    times the albedo calibration's factor at the cosines and the relative azimuth (``calibration`` as
    ``RowCalibration.arrays`` gives it;
    no table: none); then, for a remainder decoder's top coat (``top`` (1, 2) shared or per row; no rows: none),
    with ``scale`` times the transmission factor T(cos theta_i) T(cos theta_o) (``transmission_rows``) and with
    ``add_lobe`` plus the top lobe's f (``top_lobe_eval_pdf``). Returns the top lobe's sampling density (N,)
    (0 without a top coat). Unit local directions.

    ``hit_of_row`` (N,): the row of ``top`` and of the calibration's choice of table that row i reads (a latent
    texture's hits, each queried at its next-event and its proposed direction); empty: row i."""
    grid, tables, which = calibration
    table, cos_grid, alpha_grid, ior_grid = transmittance
    n = len(wi)
    p = np.zeros(n)
    calibrated = tables.shape[0] > 0
    coated = top.shape[0] > 0
    shared = top.shape[0] == 1
    column = _transmission_column(table, alpha_grid, ior_grid, top[0, 0], top[0, 1]) if shared else np.empty(0)
    # per-hit coatings: a row's cells are the row before's when its coating is (a latent texture's hits inside
    # one texel, or a hit's next-event and proposal rows)
    last_a, last_ior, ia, fa, ii, fi = -1.0, -1.0, 0, 0.0, 0, 0.0
    indexed = len(hit_of_row) > 0
    for i in range(n):
        h = hit_of_row[i] if indexed else i
        if calibrated:
            x, y = min(max(wi[i, 2], 0.0), 1.0), min(max(wo[i, 2], 0.0), 1.0)
            cos_phi = _cos_relative_azimuth(wi[i, 0], wi[i, 1], wo[i, 0], wo[i, 1])
            _scale_row(out, i, x, y, cos_phi, grid, tables, which[h] if len(which) else 0)
        if not coated:
            continue
        j = 0 if shared else h
        a, ior = top[j, 0], top[j, 1]
        if abs(ior - 1.0) < INDEX_MATCHED_TOL:
            continue
        if scale:
            if shared:
                s = _column_transmission(column, cos_grid, wi[i, 2]) * _column_transmission(column, cos_grid, wo[i, 2])
            else:
                if a != last_a or ior != last_ior:
                    ia, fa = _alpha_cell(alpha_grid, a)
                    ii, fi = _ior_cell(ior_grid, ior)
                    last_a, last_ior = a, ior
                s = _transmission(table, cos_grid, wi[i, 2], ia, fa, ii, fi) * _transmission(
                    table, cos_grid, wo[i, 2], ia, fa, ii, fi
                )
            s = np.float32(s)
            for c in range(3):
                out[i, c] = out[i, c] * s
        f, p[i] = top_reflection(wi[i, 0], wi[i, 1], wi[i, 2], wo[i, 0], wo[i, 1], wo[i, 2], a, ior)
        if add_lobe and f != 0.0:
            for c in range(3):
                out[i, c] = out[i, c] + np.float32(f)
    return p


@njit(**_JIT)
def propose_with_top(wo, u_lobe, u, sigma, w, top):
    """The sampler of a remainder decoder's material (``render.neural_material``): at each row the top lobe
    with probability ``top_lobe.top_share`` of wo (the mirror of wo about a GGX visible normal, as
    ``top_lobe.sample_top_directions``), else the proxy (``proxy_directions``, its lobe chosen by u_lobe
    rescaled past the share). ``top`` is (1, 2) or (N, 2) as in ``top_lobe_eval_pdf``; ``sigma``, ``w`` (N,).
    Returns the directions (N, 3), the share (N,) and the rows whose top-lobe sample failed (below the
    horizon: zero-weight samples). ``sigma`` and ``w`` may be (1,), shared, as ``top`` may."""
    n = len(wo)
    wi = np.empty((n, 3))
    share = np.empty(n)
    missed = np.zeros(n, dtype=np.bool_)
    shared = top.shape[0] == 1
    one_proxy = len(sigma) == 1
    mass0 = _shared_disk_mass(sigma)
    for i in range(n):
        j = 0 if shared else i
        k = 0 if one_proxy else i
        a, ior = top[j, 0], top[j, 1]
        ox, oy, oz = wo[i, 0], wo[i, 1], wo[i, 2]
        sh = top_share_cos(oz, a, ior)
        share[i] = sh
        if u_lobe[i] < sh:
            mx, my, mz = visible_normal(ox, oy, oz, max(a, MIN_ALPHA), u[i, 0], u[i, 1])
            x, y, z = reflected(ox, oy, oz, mx, my, mz)
            missed[i] = not (oz > 0.0 and z > 0.0)
        else:
            v = min(max((u_lobe[i] - sh) / (1.0 - sh), 0.0), 1.0 - 1e-12)
            mass = mass0 if one_proxy else _disk_mass(sigma[k])
            x, y, z = _proxy_direction(ox, oy, oz, sigma[k], mass, w[k], v, u[i, 0], u[i, 1])
        wi[i, 0], wi[i, 1], wi[i, 2] = x, y, z
    return wi, share, missed


@njit(inline="always", **_JIT)
def _mixture_row(wo, wi, i, sigma, mass0, w, j, share, p_top):
    """The mixture's density at row i (:func:`mixture_pdf`), the proxy's parameters and share of hit j
    (``mass0``: :func:`_shared_disk_mass` of ``sigma``)."""
    one_proxy = len(sigma) == 1
    k = 0 if one_proxy else j
    mass = mass0 if one_proxy else _disk_mass(sigma[k])
    p = _proxy_pdf(wo[i, 0], wo[i, 1], wo[i, 2], wi[i, 0], wi[i, 1], wi[i, 2], sigma[k], mass, w[k])
    return (1.0 - share[j]) * p + share[j] * p_top[i]


@njit(**_JIT)
def mixture_pdf(wo, wi, sigma, w, share, p_top):
    """The density of ``propose_with_top`` at wi: the proxy's (``proxy_pdf``) mixed with the top lobe's
    ``p_top`` by ``share``, all per row (N,); ``sigma`` and ``w`` (1,) shared, or per row."""
    n = len(wo)
    out = np.empty(n)
    mass0 = _shared_disk_mass(sigma)
    for i in range(n):
        out[i] = _mixture_row(wo, wi, i, sigma, mass0, w, i, share, p_top)
    return out


@njit(**_JIT)
def neural_shading(f, p_top, wi, wo, rows, v, sigma, w, share, missed, need_pdf):
    """A remainder decoder's answer to a bounce after its one decoder batch (``render.neural_material``): rows
    [0, v) are next-event directions, the rest the hits' proposals (``propose_with_top``) in hit order, with
    ``f`` (V + N, 3) float32 and ``p_top`` the decoder's f and the top lobe's density there
    (``ModelSet.eval_brdf``), ``rows`` (V + N,) each row's hit. ``sigma``, ``w`` (1,) shared or per hit;
    ``share`` and ``missed`` per hit, as ``propose_with_top`` returns them.

    Returns f (V, 3) and the mixture's density (V,) at the next-event directions (zeros unless ``need_pdf``),
    and the hits' samples as ``finish_proposals`` makes them (wi, weight, pdf, valid): the density of a
    proposal whose top-lobe sample missed is 0."""
    n = len(wi) - v
    f_light = np.empty((v, 3))
    pdf_light = np.zeros(v)
    s_wi, weight, s_pdf = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    valid = np.empty(n, dtype=np.bool_)
    mass0 = _shared_disk_mass(sigma)
    for i in range(v):
        for c in range(3):
            f_light[i, c] = f[i, c]
        if need_pdf:
            pdf_light[i] = _mixture_row(wo, wi, i, sigma, mass0, w, rows[i], share, p_top)
    for k in range(n):
        i = v + k
        p = 0.0 if missed[k] else _mixture_row(wo, wi, i, sigma, mass0, w, k, share, p_top)
        x, y, z = wi[i, 0], wi[i, 1], wi[i, 2]
        s = abs(z) / p
        ok = p > 0.0 and z > 0.0
        _keep_sample(s_wi, weight, s_pdf, valid, k, x, y, z, f[i, 0] * s, f[i, 1] * s, f[i, 2] * s, p, ok)
    return f_light, pdf_light, s_wi, weight, s_pdf, valid


# --- the albedo calibration (addon.core.neural.calibrate) ---------------------------------------


@njit(forceinline=True, **_JIT)
def _segment_near(grid, x, guess):
    """Index i and weight t of ``x`` between ``grid[i]`` and ``grid[i + 1]`` (``grid`` increasing), constant beyond
    its ends: walked from a guess of the index (a float) to the cell that holds ``x``. The cell and the weight do
    not depend on the guess; where it comes from the grid's own spacing (:func:`_spacing_guess`) the walk takes a
    step or two, cheaper than a binary search's unpredictable branches (the exact top coat 25-35% faster, the
    calibration's tables 15%)."""
    last = len(grid) - 1
    x = min(max(x, grid[0]), grid[last])
    i = min(max(int(guess), 0), last - 1)
    while i > 0 and grid[i] > x:
        i -= 1
    while i < last - 1 and grid[i + 1] <= x:
        i += 1
    return i, (x - grid[i]) / (grid[i + 1] - grid[i])


@njit(forceinline=True, **_JIT)
def _spacing_guess(grid, x, spacing):
    """Where ``x`` falls in ``grid`` (a fractional index) if the grid is spaced as ``spacing`` says: 0 evenly, 1
    geometrically, 2 quadratically from its first node (``top_lobe``'s transmittance grids: ior, alpha, cosine)."""
    last = len(grid) - 1
    g0, g1 = grid[0], grid[last]
    if not (x > g0):
        return 0.0
    if spacing == 1:
        return last * math.log(x / g0) / math.log(g1 / g0)
    t = (x - g0) / (g1 - g0)
    return last * (_sqrt(t) if spacing == 2 else t)


@njit(**_JIT)
def scale_by_table(f, x, y, grid, tables, which, cos_phi=None):
    """``f`` (N, C) times ``tables[which[n]]`` (T, K, K * P, C) at (``x``, ``y``, ``cos_phi``) (N,) each: the cosines
    of the two elevations, bilinear between the increasing abscissae ``grid`` (K,) on both axes, constant beyond
    them, and the cosine of the relative azimuth, linear in the azimuth between P nodes (:func:`_scale_row`); in
    place. An empty ``which`` means table 0 for every row. ``cos_phi`` may be left out for tables of one azimuth
    node (P = 1: elevation only)."""
    if cos_phi is None and tables.shape[2] != len(grid):
        raise ValueError("tables with azimuth nodes need the rows' cos_phi")
    for n in range(len(f)):
        c = 1.0 if cos_phi is None else cos_phi[n]
        _scale_row(f, n, x[n], y[n], c, grid, tables, which[n] if len(which) else 0)


@njit(**_JIT)
def relative_azimuth_cosines(wi, wo):
    """(N,) the cosine of the relative azimuth of each row's directions ``wi``, ``wo`` (N, 3), as the calibration's
    tables read it (:func:`_cos_relative_azimuth`)."""
    out = np.empty(len(wi))
    for n in range(len(wi)):
        out[n] = _cos_relative_azimuth(wi[n, 0], wi[n, 1], wo[n, 0], wo[n, 1])
    return out


@njit(forceinline=True, **_JIT)
def _cos_relative_azimuth(ax, ay, bx, by):
    """cos(phi_a - phi_b) of two directions from their tangent components; 1 where either is along the normal
    (where the tables do not depend on the azimuth: ``calibrate.solve_azimuth``)."""
    d = (ax * ax + ay * ay) * (bx * bx + by * by)
    if not (d > 1e-30):
        return 1.0
    return min(max((ax * bx + ay * by) / _sqrt(d), -1.0), 1.0)


@njit(forceinline=True, **_JIT)
def _azimuth_cell(cos_phi, nodes):
    """Index q and weight w of the relative azimuth phi = acos(``cos_phi``) between nodes q and q + 1 of ``nodes``
    evenly spaced on [0, pi] (``neural.calibration_formulas.azimuth_cell``, which ``calibrate`` runs on arrays);
    (0, 0) for one node."""
    if nodes < 2:
        return 0, 0.0
    return azimuth_cell(cos_phi, nodes)


@njit(forceinline=True, **_JIT)
def _table_at(tables, m, i, s, j, t, node, c):
    """``tables[m]``'s channel c, bilinear at the cosines' cells (i, s) and (j, t), at azimuth node ``node`` (the
    columns j * P + node)."""
    p = tables.shape[2] // tables.shape[1]
    a, b = j * p + node, (j + 1) * p + node
    low = tables[m, i, a, c] * (1.0 - s) + tables[m, i + 1, a, c] * s
    high = tables[m, i, b, c] * (1.0 - s) + tables[m, i + 1, b, c] * s
    return low * (1.0 - t) + high * t


@njit(forceinline=True, **_JIT)
def _scale_row(f, n, x, y, cos_phi, grid, tables, m):
    """``f[n]`` times ``tables[m]`` (K, K * P, C) at (x, y, cos_phi) (:func:`scale_by_table`): bilinear in the two
    cosines, linear in the relative azimuth between its P nodes (``tables[m, i, j * P + q]``: cosines i and j,
    azimuth node q). The table is indexed, not sliced: a slice is an array whose reference count a loop would raise
    and drop for every row."""
    # the calibration's cosines are close to quadratic: guesses within two cells
    i, s = _segment_near(grid, x, _spacing_guess(grid, x, 2))
    j, t = _segment_near(grid, y, _spacing_guess(grid, y, 2))
    q, w = _azimuth_cell(cos_phi, tables.shape[2] // len(grid))
    for c in range(f.shape[1]):
        v = _table_at(tables, m, i, s, j, t, q, c)
        if w > 0.0:
            v = v * (1.0 - w) + _table_at(tables, m, i, s, j, t, q + 1, c) * w
        f[n, c] *= v


@njit(fastmath={"reassoc", "contract"}, **_JIT)
def nearest_rows(x, centres):
    """Index (N,) of the row of ``centres`` (T, D) nearest each row of ``x`` (N, D), in squared distance (float32
    both, C-contiguous: a latent texture's hits and its calibration's centroids, ``textures.calibration``). A
    loop, not a matrix product: a BLAS product called from the render's threads starts BLAS's own threads
    beside them and, on two cores, made a textured render 20-35% slower. The sums may be reassociated (so
    that they vectorise: 4x here); a row halfway between two centroids may then take either."""
    n, t, dim = x.shape[0], centres.shape[0], x.shape[1]
    out = np.zeros(n, dtype=np.int64)
    for i in range(n):
        best = np.inf
        for j in range(t):
            s = np.float32(0.0)
            for k in range(dim):
                e = x[i, k] - centres[j, k]
                s += e * e
            if s < best:
                best, out[i] = s, j
    return out


# --- the camera ----------------------------------------------------------------------------------


# What ``camera_rays`` writes (``out``, a row per pixel): origins, directions, the ray cones' spreads, the rays'
# lengths to the far clipping plane and their origins' distances from the camera (on the near plane).
CAMERA_RAYS_OUT = ((3, F8), (3, F8), (0, F8), (0, F8), (0, F8))


@njit(**_JIT)
def camera_rays(
    out, px, py, jitter, matrix, width, height, tan_x, tan_y, shift_x, shift_y, pixel_spread, clip_start, clip_end
):
    """World rays of a pinhole camera (``render.scene.Camera``) through pixels (px, py) (row 0 at the
    top; integers or floats) offset by ``jitter`` (N, 2) in [0, 1)^2: origins and unit directions (N, 3), and each
    ray cone's spread (N,), each ray's length to the far clipping plane (N,) and its origin's distance from the
    camera (N,), into ``out``
    (:data:`CAMERA_RAYS_OUT`) and returned. The clipping planes are at depths ``clip_start`` and ``clip_end`` along
    the optical axis, as Blender's: each ray starts on the near one and ends on the far one (inf: none).
    ``matrix``: the camera's (4, 4)
    object-to-world without scale, looking along its local -z; ``shift``: Blender's lens shift in units of the larger
    image side. The spread is the angle the ray's pixel subtends: ``pixel_spread`` (the image centre's) times cos^1.5
    of the ray's angle to the optical axis (a pixel off the axis subtends cos^2 of it radially and cos across:
    their geometric mean), cos being 1 / the length of the camera-space direction (x, y, -1). One spread for every
    ray made a plane facing the camera look blurrier toward the corners: a texture at one texel a pixel took mip
    level 0.25 in a 40-degree view's corners, 1.2 in a 90-degree view's."""
    n = len(px)
    o, d, spread, tmax, near = out
    big = max(width, height)
    off_x = 2.0 * shift_x * tan_x * big / width
    off_y = 2.0 * shift_y * tan_y * big / height
    to_x, to_y = 2.0 / width, 2.0 / height  # multiplied, not divided, in the loop: 10 -> 7 ns a ray
    for i in range(n):
        x = ((px[i] + jitter[i, 0]) * to_x - 1.0) * tan_x + off_x
        y = (1.0 - (py[i] + jitter[i, 1]) * to_y) * tan_y + off_y
        dx = matrix[0, 0] * x + matrix[0, 1] * y - matrix[0, 2]
        dy = matrix[1, 0] * x + matrix[1, 1] * y - matrix[1, 2]
        dz = matrix[2, 0] * x + matrix[2, 1] * y - matrix[2, 2]
        length = _sqrt(dx * dx + dy * dy + dz * dz)  # a unit depth's distance along the ray
        inv = 1.0 / length
        d[i, 0], d[i, 1], d[i, 2] = dx * inv, dy * inv, dz * inv
        o[i, 0] = matrix[0, 3] + clip_start * dx  # on the near plane
        o[i, 1] = matrix[1, 3] + clip_start * dy
        o[i, 2] = matrix[2, 3] + clip_start * dz
        spread[i] = pixel_spread * inv * _sqrt(inv)
        tmax[i] = (clip_end - clip_start) * length
        near[i] = clip_start * length
    return o, d, spread, tmax, near


# --- the disk cache and the formulas compiled into the loops -------------------------------------

# The sources of the formulas (``addon.core.formula``) the loops above compile in, relative to this folder.
FORMULA_SOURCES = ("formula.py", "bsdf/*.py", "neural/top_formulas.py", "neural/calibration_formulas.py")
_FORMULA_STAMP = "kernels.formulas"


def formula_digest() -> str:
    """sha256 of the formula sources the loops compile in (``FORMULA_SOURCES``)."""
    import hashlib
    from pathlib import Path

    here = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for pattern in FORMULA_SOURCES:
        for path in sorted(here.glob(pattern)):
            h.update(path.relative_to(here).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def _drop_stale_cache() -> None:
    """numba keys a cached loop on this file's time stamp and the loop's own bytecode only, not on the
    formulas from other files compiled into it: after a formula changed, the cache would load the old
    machine code. So the formulas' digest is kept beside the cache, and when it differs every cached loop
    of this module is dropped (and compiled again on first use). Best effort: a cache folder that cannot be
    written is left as it is (numba then does not cache there either)."""
    from pathlib import Path

    try:
        cache = Path(surface_hits._cache.cache_path)
        stamp = cache / _FORMULA_STAMP
        digest = formula_digest()
        if stamp.is_file() and stamp.read_text() == digest:
            return
        for stale in cache.glob(f"{__name__.rsplit('.', 1)[-1]}.*.nb[ic]"):
            stale.unlink(missing_ok=True)
        cache.mkdir(parents=True, exist_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass


_drop_stale_cache()

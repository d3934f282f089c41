"""Compiled per-row loops of the renderer (numba, nopython, GIL released).

The wavefront renderer spends most of its time outside rays and networks in long chains of small
numpy operations per bounce: each one streams whole arrays through memory and allocates its
temporaries. The loops here do one pass over the rows for such a chain, with scalars in registers.
They hold only the renderer's own bookkeeping and geometry (texture taps, the surface at a hit, the
lights, path continuation); the BSDF formulas, which training and the reference share through the
array namespace (``addon.core.xp``), stay in ``addon.core.bsdf`` in numpy.

Every kernel:

- takes and returns numpy arrays (float64 unless said), never Python objects;
- releases the GIL (``nogil``), so the renderer's chunk threads run them at once;
- is compiled on first use and cached on disk beside this file (or in the user's cache folder
  where that is read-only), so a later process loads it in milliseconds;
- is the one implementation of what it computes: the numpy callers it replaced are gone.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(nogil=True, cache=True, error_model="numpy")


# --- mip chains --------------------------------------------------------------------------------


@njit(inline="always", **_JIT)
def _bilinear_add(flat, offset, h, w, c, u, v, weight, out_row):
    """Add ``weight`` times the bilinear tap (repeat addressing, v = 0 at the bottom row) of the level
    stored at ``flat[offset:]`` as (h, w, c) to ``out_row``, in float32."""
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5
    x0f = math.floor(x)
    y0f = math.floor(y)
    fx = np.float32(x - x0f)
    fy = np.float32(y - y0f)
    x0 = int(x0f) % w
    y0 = int(y0f) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    gx = np.float32(1.0) - fx
    top = np.float32(weight) * (np.float32(1.0) - fy)
    bottom = np.float32(weight) * fy
    a = offset + (y0 * w + x0) * c
    b = offset + (y0 * w + x1) * c
    d = offset + (y1 * w + x0) * c
    e = offset + (y1 * w + x1) * c
    for k in range(c):
        out_row[k] += (flat[a + k] * gx + flat[b + k] * fx) * top + (flat[d + k] * gx + flat[e + k] * fx) * bottom


@njit(**_JIT)
def trilinear(flat, offsets, heights, widths, channels, uv, lod, out):
    """Trilinear lookup into a mip chain packed in ``flat`` (float32; level k at ``offsets[k]``, shape
    (heights[k], widths[k], channels)): row i of ``out`` (float32, zeroed) gets levels floor(lod[i])
    and the next one (the last level: itself) blended by the fraction of lod[i]."""
    n_levels = len(offsets)
    for i in range(len(lod)):
        k = int(math.floor(lod[i]))
        t = lod[i] - k
        row = out[i]
        u, v = uv[i, 0], uv[i, 1]
        if k + 1 >= n_levels:
            _bilinear_add(flat, offsets[k], heights[k], widths[k], channels, u, v, 1.0, row)
        else:
            _bilinear_add(flat, offsets[k], heights[k], widths[k], channels, u, v, 1.0 - t, row)
            _bilinear_add(flat, offsets[k + 1], heights[k + 1], widths[k + 1], channels, u, v, t, row)


# --- surfaces ----------------------------------------------------------------------------------


@njit(**_JIT)
def texture_footprint(width, cos_o, tri_uv_scale):
    """Footprint in uv units of a ray cone of ``width`` (world units) hitting a surface at |cos|
    ``cos_o`` (floored at 0.05: grazing hits do not blow up) on triangles of uv scale
    ``tri_uv_scale``: the width stretched by 1 / sqrt(cos) (the mean of its two axes). Scalars or
    arrays."""
    return width / np.sqrt(np.maximum(np.abs(cos_o), 0.05)) * tri_uv_scale


@njit(**_JIT)
def surface_hits(corners, face_normals, uv_scale, prim, bu, bv, d, t, width, spread):
    """The surface where rays ``d`` (unit, world) land on triangles ``prim`` at barycentrics (bu, bv)
    and distance ``t``: position, geometric and shading normals, uv, the ray cone's width there
    (``width + spread * t``) and its footprint in uv units.

    ``corners`` (T, 3, 8): each corner's position, normal and uv. The shading normal is the
    interpolated one, normalised; where it is zero or disagrees with the geometric normal, the
    geometric one. Both are turned toward the viewer, and a shading normal the viewer sees at
    grazing (cos <= 1e-6) falls back to the geometric one.
    Returns p, ng, ns (N, 3), uv (N, 2), width, footprint (N,)."""
    n = len(prim)
    p = np.empty((n, 3))
    ng = np.empty((n, 3))
    ns = np.empty((n, 3))
    uv = np.empty((n, 2))
    width_out = np.empty(n)
    footprint = np.empty(n)
    for i in range(n):
        k = prim[i]
        b1, b2 = bu[i], bv[i]
        b0 = 1.0 - b1 - b2
        c0, c1, c2 = corners[k, 0], corners[k, 1], corners[k, 2]
        for j in range(3):
            p[i, j] = b0 * c0[j] + b1 * c1[j] + b2 * c2[j]
        uv[i, 0] = b0 * c0[6] + b1 * c1[6] + b2 * c2[6]
        uv[i, 1] = b0 * c0[7] + b1 * c1[7] + b2 * c2[7]
        sx = b0 * c0[3] + b1 * c1[3] + b2 * c2[3]
        sy = b0 * c0[4] + b1 * c1[4] + b2 * c2[4]
        sz = b0 * c0[5] + b1 * c1[5] + b2 * c2[5]
        gx, gy, gz = face_normals[k, 0], face_normals[k, 1], face_normals[k, 2]
        length = math.sqrt(sx * sx + sy * sy + sz * sz)
        if length > 0.0:
            sx, sy, sz = sx / length, sy / length, sz / length
        if not (sx * gx + sy * gy + sz * gz > 0.0):  # inconsistent or zero: the geometric normal
            sx, sy, sz = gx, gy, gz
        ox, oy, oz = -d[i, 0], -d[i, 1], -d[i, 2]
        cos_g = gx * ox + gy * oy + gz * oz
        if cos_g < 0.0:  # turned toward the viewer
            gx, gy, gz, sx, sy, sz, cos_g = -gx, -gy, -gz, -sx, -sy, -sz, -cos_g
        if not (sx * ox + sy * oy + sz * oz > 1e-6):  # grazing: the geometric normal
            sx, sy, sz = gx, gy, gz
        ng[i, 0], ng[i, 1], ng[i, 2] = gx, gy, gz
        ns[i, 0], ns[i, 1], ns[i, 2] = sx, sy, sz
        w = width[i] + spread[i] * t[i]
        width_out[i] = w
        footprint[i] = texture_footprint(w, cos_g, uv_scale[k])
    return p, ng, ns, uv, width_out, footprint

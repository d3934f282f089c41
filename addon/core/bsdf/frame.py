"""Directions and shading frames.

All functions take direction arrays of shape ``(N, 3)`` (a single ``(3,)`` vector also works
where noted) and work row by row. The local shading frame has the normal at +z. ``reflected``,
``refracted`` and ``basis`` are the formulas (``addon.core.formula``) the compiled loops share.
"""

from __future__ import annotations

import numpy as np

from ..formula import copysign, formula, maximum, sqrt, where
from ..xp import namespace


def cos_theta(w: np.ndarray) -> np.ndarray:
    """Cosine to the local normal (+z): the z component, shape (N,)."""
    return w[..., 2]


def same_hemisphere(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """True where ``a`` and ``b`` lie strictly on the same side of the local surface."""
    return a[..., 2] * b[..., 2] > 0.0


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product, shape (N,): the elementwise product, then its three columns added (twice as
    fast as ``einsum`` on (N, 3) rows, whose reduction over rows of three runs a loop per row)."""
    p = a * b
    return p[..., 0] + p[..., 1] + p[..., 2]


def max_component(v: np.ndarray) -> np.ndarray:
    """The largest of the three components of each row, shape (N,): two elementwise maxima, 3x faster
    than ``v.max(axis=1)``, whose reduction over rows of three runs a loop per row."""
    xp = namespace(v)
    return xp.maximum(xp.maximum(v[..., 0], v[..., 1]), v[..., 2])


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along ``v``; zero-length rows stay zero (never NaN)."""
    xp = namespace(v)
    v = xp.asarray(v, dtype=xp.float64)
    n = xp.sqrt(dot(v, v))[..., None]
    with xp.errstate(invalid="ignore", divide="ignore"):
        out = v / n
    return xp.where(n > 0.0, out, 0.0)


@formula
def reflected(wx, wy, wz, nx, ny, nz):
    """(x, y, z): the formula of :func:`reflect` on components."""
    d = 2.0 * (wx * nx + wy * ny + wz * nz)
    return d * nx - wx, d * ny - wy, d * nz - wz


def reflect(w: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror ``w`` about ``n``: both point away from the surface, ``2 (w.n) n - w``."""
    x, y, z = reflected(w[..., 0], w[..., 1], w[..., 2], n[..., 0], n[..., 1], n[..., 2])
    return namespace(w, n).stack([x, y, z], axis=-1)


@formula
def refracted(wx, wy, wz, nx, ny, nz, eta):
    """(tx, ty, tz, valid): the formula of :func:`refract` on components."""
    c = wx * nx + wy * ny + wz * nz
    flip = c < 0.0
    e = where(flip, 1.0 / eta, eta)
    s = where(flip, -1.0, 1.0)
    c = abs(c)
    sin2_t = maximum(0.0, 1.0 - c * c) / (e * e)
    valid = sin2_t < 1.0
    k = c / e - sqrt(maximum(0.0, 1.0 - sin2_t))
    tx = -wx / e + k * nx * s
    ty = -wy / e + k * ny * s
    tz = -wz / e + k * nz * s
    return where(valid, tx, 0.0), where(valid, ty, 0.0), where(valid, tz, 0.0), valid


def refract(w: np.ndarray, n: np.ndarray, eta) -> tuple[np.ndarray, np.ndarray]:
    """Refract ``w`` (pointing away from the surface) through the interface with normal ``n``.

    ``eta`` is the relative index n_t / n_i for light on the side ``n`` points to; where
    ``w`` lies on the other side (w.n < 0) the interface is seen from below, so ``eta`` is
    inverted and ``n`` flipped, as pbrt-v4's ``Refract``. Returns ``(wt, valid)``: the
    transmitted direction (pointing away on the other side) and False under total internal
    reflection (there ``wt`` is 0).
    """
    xp = namespace(w, n, eta)
    eta = xp.asarray(eta, dtype=xp.float64)
    with xp.errstate(invalid="ignore", divide="ignore"):
        tx, ty, tz, valid = refracted(w[..., 0], w[..., 1], w[..., 2], n[..., 0], n[..., 1], n[..., 2], eta)
    return xp.stack([tx, ty, tz], axis=-1), valid


@formula
def basis(nx, ny, nz):
    """(sx, sy, sz, tx, ty, tz): the tangents of :func:`coordinate_system` for the unit normal n."""
    sign = copysign(1.0, nz)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    return 1.0 + sign * nx * nx * a, sign * b, -sign * nx, b, sign + ny * ny * a, -ny


def coordinate_system(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal tangents ``(s, t)`` with ``s x t = n`` for unit normals ``n``.

    Branchless construction of Duff et al. 2017, "Building an Orthonormal Basis, Revisited".
    """
    xp = namespace(n)
    n = xp.asarray(n, dtype=xp.float64)
    sx, sy, sz, tx, ty, tz = basis(n[..., 0], n[..., 1], n[..., 2])
    return xp.stack([sx, sy, sz], axis=-1), xp.stack([tx, ty, tz], axis=-1)


def to_local(v: np.ndarray, s: np.ndarray, t: np.ndarray, n: np.ndarray) -> np.ndarray:
    """World vector ``v`` in the frame (s, t, n): components (v.s, v.t, v.n)."""
    return namespace(v, s, t, n).stack([dot(v, s), dot(v, t), dot(v, n)], axis=-1)


def to_world(v: np.ndarray, s: np.ndarray, t: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Local vector ``v`` of the frame (s, t, n) in world space: v.x s + v.y t + v.z n."""
    return v[..., 0:1] * s + v[..., 1:2] * t + v[..., 2:3] * n

"""Simple triangle meshes (sphere, quad, box) for tests, benchmarks and the demo scene."""

from __future__ import annotations

import math

import numpy as np

from .scene import Mesh


def uv_sphere(
    center=(0.0, 0.0, 0.0),
    radius: float = 1.0,
    segments: int = 32,
    rings: int = 16,
    material: int = 0,
    smooth: bool = True,
) -> Mesh:
    """A UV sphere with smooth (or flat) normals and equirectangular uvs."""
    j, i = np.meshgrid(np.arange(rings + 1), np.arange(segments + 1), indexing="ij")
    theta = j / rings * math.pi  # polar angle from +z
    phi = i / segments * 2 * math.pi
    nrm = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)
    pos = np.asarray(center, dtype=np.float64) + radius * nrm
    uv = np.stack([i / segments, 1 - j / rings], axis=-1)
    a = (slice(0, rings), slice(0, segments))
    b = (slice(0, rings), slice(1, segments + 1))
    c = (slice(1, rings + 1), slice(1, segments + 1))
    d = (slice(1, rings + 1), slice(0, segments))
    tris = []
    for arr in (pos, nrm, uv):
        t1 = np.stack([arr[a], arr[d], arr[c]], axis=2).reshape(-1, 3, arr.shape[-1])
        t2 = np.stack([arr[a], arr[c], arr[b]], axis=2).reshape(-1, 3, arr.shape[-1])
        tris.append(np.concatenate([t1, t2]))
    p, n, u = tris
    mesh_normals = n if smooth else None
    return Mesh(p, mesh_normals, u, np.full(len(p), material))


def quad(center, u_half, v_half, material: int = 0) -> Mesh:
    """A rectangle centre +- u_half +- v_half; its normal is u x v; uvs span [0, 1]^2."""
    c, u, v = (np.asarray(x, dtype=np.float64) for x in (center, u_half, v_half))
    corners = np.array([c - u - v, c + u - v, c + u + v, c - u + v])
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
    idx = np.array([[0, 1, 2], [0, 2, 3]])
    return Mesh(corners[idx], None, uvs[idx], np.full(2, material))


def box(center, half_size, material: int = 0) -> Mesh:
    """An axis-aligned box with flat faces pointing outward."""
    c = np.asarray(center, dtype=np.float64)
    h = np.broadcast_to(np.asarray(half_size, dtype=np.float64), (3,))
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            a = np.zeros(3)
            a[(axis + 1) % 3] = h[(axis + 1) % 3]
            b = np.zeros(3)
            b[(axis + 2) % 3] = h[(axis + 2) % 3]
            if sign < 0:
                a, b = b, a
            faces.append(quad(c + n * h, a, b, material))
    return Mesh.concatenate(faces)

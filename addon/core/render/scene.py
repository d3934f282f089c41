"""The scene as plain arrays: what the renderer needs, with no Blender types.

Units and frames: world space, metres, right-handed with +z up (Blender's). Images are
(H, W, 3) float32 linear Rec.709 RGB with row 0 at the top.

Scene export (``addon/blender/scene_export.py``) fills these from an evaluated depsgraph;
tests and scripts build them directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import kernels
from .lights import AreaLight, Environment, PointLight, SpotLight, SunLight

Light = PointLight | SpotLight | SunLight | AreaLight


@dataclass
class Camera:
    """A pinhole camera.

    ``matrix`` is camera-to-world (4, 4) without scale: the camera looks down its local -z with
    +y up (Blender's convention). ``tan_half_fov`` is (tan of half the horizontal field of view,
    tan of half the vertical one); ``shift`` is Blender's lens shift in units of the larger
    image side; ``clip`` the depths of the near and far clipping planes along the optical axis (Blender's
    *Clip Start* and *End*: nothing nearer or farther is seen, the world beyond the far one is).
    """

    matrix: np.ndarray
    width: int
    height: int
    tan_half_fov: tuple[float, float]
    shift: tuple[float, float] = (0.0, 0.0)
    clip: tuple[float, float] = (0.0, math.inf)

    def __post_init__(self):
        self.matrix = np.asarray(self.matrix, dtype=np.float64).reshape(4, 4)
        if not np.isfinite(self.matrix).all():
            raise ValueError(f"camera matrix must be finite, got {self.matrix.tolist()}")
        self.width, self.height = int(self.width), int(self.height)
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be at least 1 x 1, got {self.width} x {self.height}")
        tx, ty = (float(v) for v in self.tan_half_fov)
        if not (tx > 0 and ty > 0 and math.isfinite(tx) and math.isfinite(ty)):
            raise ValueError(f"tan_half_fov must be two positive numbers, got {self.tan_half_fov}")
        self.tan_half_fov = (tx, ty)
        near, far = (float(v) for v in self.clip)
        if not (0.0 <= near < far and math.isfinite(near)):
            raise ValueError(f"clip must be two depths 0 <= start < end, got {self.clip}")
        self.clip = (near, far)
        # Orthonormalise the rotation so a scaled camera object still gives unit directions.
        r = self.matrix[:3, :3]
        u, _, vt = np.linalg.svd(r)
        self.matrix = self.matrix.copy()
        self.matrix[:3, :3] = u @ vt

    @classmethod
    def look_at(
        cls, eye, target, up=(0.0, 0.0, 1.0), fov_deg: float = 40.0, width: int = 64, height: int = 64
    ) -> "Camera":
        """A camera at ``eye`` looking at ``target``; ``fov_deg`` spans the larger image side."""
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise ValueError(f"image size must be at least 1 x 1, got {width} x {height}")
        fov = float(fov_deg)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180) degrees, got {fov_deg!r}")
        eye, target, up = (np.asarray(v, dtype=np.float64).reshape(3) for v in (eye, target, up))
        for name, v in (("eye", eye), ("target", target), ("up", up)):
            if not np.isfinite(v).all():
                raise ValueError(f"camera {name} must be finite, got {v.tolist()}")
        back = eye - target
        if np.linalg.norm(back) == 0:
            raise ValueError("camera eye and target must differ")
        back /= np.linalg.norm(back)
        right = np.cross(up, back)
        if np.linalg.norm(right) < 1e-9:
            right = np.cross((0.0, 1.0, 0.0), back)
        right /= np.linalg.norm(right)
        true_up = np.cross(back, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, back, eye
        t = math.tan(math.radians(fov) / 2)
        aspect = width / height
        tan = (t, t / aspect) if width >= height else (t * aspect, t)
        return cls(m, width, height, tan)

    @property
    def position(self) -> np.ndarray:
        return self.matrix[:3, 3]

    @property
    def axis(self) -> np.ndarray:
        """(3,) the unit direction the camera looks in (its local -z in world space): depths are measured along it."""
        return np.ascontiguousarray(-self.matrix[:3, 2])

    @property
    def pixel_spread(self) -> float:
        """Angle (radians) one pixel subtends at the image centre: the ray cone's spread."""
        return 2.0 * self.tan_half_fov[1] / self.height

    def generate_rays(self, px: np.ndarray, py: np.ndarray, jitter: np.ndarray, out=None):
        """World-space rays through pixel (px, py) (row 0 at the top) offset by jitter in [0, 1)^2.

        Returns origins (N, 3) and unit directions (N, 3), float64: ``out`` (two such arrays) when given.
        """
        n = len(out[0]) if out is not None else 0
        return self.rays(px, py, jitter, None if out is None else (*out, *(np.empty(n) for _ in range(3))))[:2]

    def rays(self, px: np.ndarray, py: np.ndarray, jitter: np.ndarray, out=None):
        """:meth:`generate_rays`' origins and directions, each ray cone's spread (N,), the angle its pixel
        subtends, each ray's length to the far clipping plane (N,) and its origin's distance from the camera (N,)
        (``kernels.camera_rays``): ``out`` (``kernels.CAMERA_RAYS_OUT``) when given."""
        px, py = np.asarray(px), np.asarray(py)
        integers = px.dtype.kind in "iu" and py.dtype.kind in "iu"  # read as they are; anything else as float64
        px, py = (np.ascontiguousarray(a, dtype=np.int64 if integers else np.float64) for a in (px, py))
        return kernels.camera_rays(
            kernels.rows_of(kernels.CAMERA_RAYS_OUT, len(px)) if out is None else out,
            px,
            py,
            np.ascontiguousarray(jitter, dtype=np.float64),
            self.matrix,
            self.width,
            self.height,
            *self.tan_half_fov,
            *(float(v) for v in self.shift),
            self.pixel_spread,
            *self.clip,
        )


@dataclass
class Mesh:
    """Triangles in world space.

    positions (T, 3, 3) corners; normals (T, 3, 3) per-corner shading normals (flat shading
    repeats the face normal); uvs (T, 3, 2) or None; material_index (T,) into Scene.materials.
    Degenerate triangles (zero area or non-finite corners) are dropped on construction.
    """

    positions: np.ndarray
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    material_index: np.ndarray | None = None
    dropped: int = 0

    def __post_init__(self):
        p = np.asarray(self.positions, dtype=np.float32).reshape(-1, 3, 3)
        t = p.shape[0]
        n = None if self.normals is None else np.asarray(self.normals, dtype=np.float32).reshape(-1, 3, 3)
        uv = None if self.uvs is None else np.asarray(self.uvs, dtype=np.float32).reshape(-1, 3, 2)
        mi = (
            np.zeros(t, dtype=np.int32)
            if self.material_index is None
            else np.asarray(self.material_index, dtype=np.int32).reshape(-1)
        )
        for name, arr in (("normals", n), ("uvs", uv), ("material_index", mi)):
            if arr is not None and arr.shape[0] != t:
                raise ValueError(f"Mesh.{name} has {arr.shape[0]} triangles, positions have {t}")
        # In float64 from the float32 corners: their differences and products are exact or nearly, so a triangle
        # of collinear corners has a cross product of about 0, whatever its size.
        p64 = p.astype(np.float64)
        e1, e2 = p64[:, 1] - p64[:, 0], p64[:, 2] - p64[:, 0]
        face_n = np.cross(e1, e2)
        area2 = np.linalg.norm(face_n, axis=1)
        # Degenerate relative to its size: a small object's real triangles are kept (an absolute 1e-12 dropped a
        # tenth of a 0.1 mm sphere's, and every triangle of a 0.01 mm one).
        longest2 = np.maximum(np.maximum(np.sum(e1 * e1, axis=1), np.sum(e2 * e2, axis=1)), np.sum((e2 - e1) ** 2, 1))
        with np.errstate(invalid="ignore", over="ignore"):
            keep = np.isfinite(p).all(axis=(1, 2)) & (area2 > 1e-12 * longest2) & (area2 > 0.0)
        self.dropped = int(t - keep.sum())
        p, mi, face_n, area2 = p[keep], mi[keep], face_n[keep], area2[keep]
        face_n = face_n / np.maximum(area2, 1e-30)[:, None]
        if n is None:
            n = np.repeat(face_n[:, None, :], 3, axis=1).astype(np.float32)
        else:
            n = n[keep].astype(np.float64)
            length = np.linalg.norm(n, axis=2, keepdims=True)
            bad = ~np.isfinite(length) | (length < 1e-12)
            n = np.where(bad, face_n[:, None, :], n / np.where(bad, 1.0, length)).astype(np.float32)
        if uv is not None:
            uv = np.nan_to_num(uv[keep], nan=0.0, posinf=0.0, neginf=0.0)
        self.positions, self.normals, self.uvs, self.material_index = p, n, uv, mi
        self.face_normals = face_n.astype(np.float32)
        self.areas = (0.5 * area2).astype(np.float64)

    @property
    def triangle_count(self) -> int:
        return int(self.positions.shape[0])

    @classmethod
    def concatenate(cls, meshes: list["Mesh"]) -> "Mesh":
        """One mesh from many (material indices are kept as they are)."""
        meshes = [m for m in meshes if m.triangle_count]
        if not meshes:
            return cls(np.zeros((0, 3, 3), np.float32))
        has_uv = any(m.uvs is not None for m in meshes)
        uvs = None
        if has_uv:
            uvs = np.concatenate(
                [m.uvs if m.uvs is not None else np.zeros((m.triangle_count, 3, 2), np.float32) for m in meshes]
            )
        return cls(
            np.concatenate([m.positions for m in meshes]),
            np.concatenate([m.normals for m in meshes]),
            uvs,
            np.concatenate([m.material_index for m in meshes]),
        )


@dataclass
class Scene:
    """Everything the integrator needs.

    ``materials`` holds, per material index, a renderer material (see ``materials.py``), a
    :class:`addon.core.stack.Stack` (resolved to a neural or reference material by the render
    mode) or a :class:`materials.LayeredSpec` (a stack plus an optional latent texture). A
    triangle whose index has no entry renders as a grey Lambertian.
    """

    camera: Camera
    mesh: Mesh = field(default_factory=lambda: Mesh(np.zeros((0, 3, 3), np.float32)))
    materials: list[Any] = field(default_factory=list)
    lights: list[Light] = field(default_factory=list)
    environment: Environment | None = None
    material_names: list[str] = field(default_factory=list)

    def __post_init__(self):
        if self.mesh.triangle_count:
            top = int(self.mesh.material_index.max())
            low = int(self.mesh.material_index.min())
            if low < 0:
                raise ValueError(f"material_index must be >= 0, got {low}")
            del top  # indices past the list fall back to a grey Lambertian
        for i, light in enumerate(self.lights):
            if not isinstance(light, (PointLight, SpotLight, SunLight, AreaLight)):
                raise ValueError(
                    f"lights[{i}] must be a PointLight, SpotLight, SunLight or AreaLight, got {type(light).__name__}"
                )

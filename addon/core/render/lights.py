"""Lights and the environment, each with vectorised sampling for next-event estimation.

Blender's units, converted once here:

- point and spot: ``power`` in watts, radiant intensity I = power / (4 pi) W/sr per colour
  channel (a spot is a point light masked to its cone, as in Blender);
- sun: ``strength`` is the irradiance in W/m^2 on a surface facing it;
- area: ``power`` in watts leaves one side (the light's local -z) as a Lambertian emitter,
  radiance L = power / (pi * area).

Every ``sample(p, u)`` returns a :class:`LightSample` of world directions *toward* the light,
the distance to it (inf for the sun and the environment), the arriving radiance (for delta
lights the irradiance-like quantity that the BRDF and cosine multiply) and the solid-angle
pdf (1 for delta lights).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..bsdf import frame

INF = np.inf


@dataclass
class LightSample:
    wi: np.ndarray  # (N, 3) unit, toward the light
    dist: np.ndarray  # (N,)
    radiance: np.ndarray  # (N, 3)
    pdf: np.ndarray  # (N,) solid angle; 1 for delta lights
    delta: bool


def _rgb(value, name: str) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()
    if not np.isfinite(v).all() or (v < 0).any():
        raise ValueError(f"{name} must be three finite non-negative numbers, got {value!r}")
    return v


def _unit(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"{name} must be a non-zero finite vector, got {v.tolist()}")
    return v / n


def _point(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.size != 3 or not np.isfinite(v).all():
        raise ValueError(f"{name} must be three finite numbers, got {np.asarray(value).tolist()!r}")
    return v.reshape(3)


def _power(value, name: str) -> float:
    v = float(value)
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
    return v


@dataclass
class PointLight:
    position: np.ndarray
    power: float = 1000.0
    color: tuple = (1.0, 1.0, 1.0)

    def __post_init__(self):
        self.position = _point(self.position, f"{type(self).__name__}.position")
        self.power = _power(self.power, "PointLight.power")
        self.color = _rgb(self.color, "PointLight.color")

    @property
    def intensity(self) -> np.ndarray:
        return self.color * self.power / (4 * math.pi)

    def _mask(self, wi: np.ndarray) -> np.ndarray:
        return np.ones(len(wi))

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        d = self.position - p
        dist = np.linalg.norm(d, axis=1)
        safe = np.maximum(dist, 1e-9)
        wi = d / safe[:, None]
        rad = self.intensity[None, :] * (self._mask(wi) / np.maximum(safe, 1e-4) ** 2)[:, None]
        return LightSample(wi, dist, rad, np.ones(len(p)), True)

    def estimated_power(self) -> float:
        return float(self.power * self.color.mean())


@dataclass
class SpotLight(PointLight):
    """A point light masked to a cone around ``direction`` (where the light points).

    ``spot_size`` is the full cone angle in radians, ``blend`` in [0, 1] softens its edge with
    Blender's smoothstep.
    """

    direction: np.ndarray = (0.0, 0.0, -1.0)
    spot_size: float = math.radians(45.0)
    blend: float = 0.15

    def __post_init__(self):
        super().__post_init__()
        self.direction = _unit(self.direction, "SpotLight.direction")
        if not (0 < self.spot_size <= math.pi):
            raise ValueError(f"SpotLight.spot_size must be in (0, pi] radians, got {self.spot_size}")
        if not (0 <= self.blend <= 1):
            raise ValueError(f"SpotLight.blend must be in [0, 1], got {self.blend}")

    def _mask(self, wi: np.ndarray) -> np.ndarray:
        cos_edge = math.cos(self.spot_size / 2)
        c = -frame.dot(wi, self.direction)
        smooth = (1 - cos_edge) * self.blend
        if smooth <= 0:
            return (c > cos_edge).astype(np.float64)
        t = np.clip((c - cos_edge) / smooth, 0.0, 1.0)
        return t * t * (3 - 2 * t)


@dataclass
class SunLight:
    """A distant light: ``direction`` is where the light travels, ``strength`` the irradiance."""

    direction: np.ndarray
    strength: float = 1.0
    color: tuple = (1.0, 1.0, 1.0)

    def __post_init__(self):
        self.direction = _unit(self.direction, "SunLight.direction")
        self.strength = _power(self.strength, "SunLight.strength")
        self.color = _rgb(self.color, "SunLight.color")

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        n = len(p)
        wi = np.broadcast_to(-self.direction, (n, 3)).copy()
        rad = np.broadcast_to(self.color * self.strength, (n, 3)).copy()
        return LightSample(wi, np.full(n, INF), rad, np.ones(n), True)

    def estimated_power(self) -> float:
        return float(self.strength * self.color.mean() * 10.0)


@dataclass
class AreaLight:
    """A one-sided Lambertian emitter: a rectangle or an ellipse.

    ``matrix`` is the light's object-to-world (4, 4) (it emits along its local -z); the shape
    spans ``size`` x ``size_y`` in local x and y (Blender's SQUARE/RECTANGLE/DISK/ELLIPSE; for a
    disk size is the diameter). Local scale in ``matrix`` scales the shape.
    """

    matrix: np.ndarray
    power: float = 100.0
    color: tuple = (1.0, 1.0, 1.0)
    size: float = 1.0
    size_y: float | None = None
    ellipse: bool = False

    def __post_init__(self):
        m = np.asarray(self.matrix, dtype=np.float64).reshape(4, 4)
        if not np.isfinite(m).all():
            raise ValueError(f"AreaLight.matrix must be finite, got {m.tolist()}")
        self.power = _power(self.power, "AreaLight.power")
        self.color = _rgb(self.color, "AreaLight.color")
        sy = self.size if self.size_y is None else self.size_y
        if not (self.size > 0 and sy > 0):
            raise ValueError(f"AreaLight size must be > 0, got {self.size} x {sy}")
        self.center = m[:3, 3].copy()
        self.axis_u = m[:3, 0] * self.size / 2  # half-extent vectors in world space
        self.axis_v = m[:3, 1] * sy / 2
        n = np.cross(self.axis_u, self.axis_v)
        if np.linalg.norm(n) < 1e-20 or not np.isfinite(n).all():
            raise ValueError("AreaLight matrix collapses the light to zero area")
        self.normal = -n / np.linalg.norm(n)  # emits along local -z
        full = 4 * np.linalg.norm(n)
        self.area = full * (math.pi / 4 if self.ellipse else 1.0)
        self.radiance = self.color * self.power / (math.pi * self.area)

    def _point(self, u: np.ndarray) -> np.ndarray:
        a = 2 * u[:, 0] - 1
        b = 2 * u[:, 1] - 1
        if self.ellipse:  # concentric square-to-disk map (uniform area density)
            swap = np.abs(a) > np.abs(b)
            r = np.where(swap, a, b)
            phi = np.where(
                swap,
                (math.pi / 4) * b / np.where(a == 0, 1, a),
                math.pi / 2 - (math.pi / 4) * a / np.where(b == 0, 1, b),
            )
            a, b = r * np.cos(phi), r * np.sin(phi)
        return self.center + a[:, None] * self.axis_u + b[:, None] * self.axis_v

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        q = self._point(u)
        d = q - p
        dist = np.linalg.norm(d, axis=1)
        safe = np.maximum(dist, 1e-9)
        wi = d / safe[:, None]
        cos_l = -frame.dot(wi, self.normal)
        ok = cos_l > 1e-8
        pdf = np.where(ok, safe**2 / (np.where(ok, cos_l, 1.0) * self.area), 0.0)
        rad = np.where(ok[:, None], self.radiance[None, :], 0.0)
        return LightSample(wi, dist, rad, pdf, False)

    def intersect(self, o: np.ndarray, d: np.ndarray):
        """Distance along unit rays to the emitting side (inf where missed) and the solid-angle pdf."""
        n = len(o)
        t_out, pdf_out = np.full(n, INF), np.zeros(n)
        denom = frame.dot(d, self.normal)
        height = frame.dot(self.center - o, self.normal)
        # Only rays arriving against the emitting normal, from its lit side, can hit it.
        idx = np.nonzero((denom < -1e-12) & (height < 0))[0]
        if len(idx) == 0:
            return t_out, pdf_out
        t = height[idx] / denom[idx]
        q = o[idx] + t[:, None] * d[idx] - self.center
        a = frame.dot(q, self.axis_u) / (self.axis_u @ self.axis_u)
        b = frame.dot(q, self.axis_v) / (self.axis_v @ self.axis_v)
        inside = (a * a + b * b <= 1) if self.ellipse else ((np.abs(a) <= 1) & (np.abs(b) <= 1))
        hit = inside & (t > 1e-6)
        idx, t = idx[hit], t[hit]
        t_out[idx] = t
        pdf_out[idx] = t * t / (-denom[idx] * self.area)
        return t_out, pdf_out

    def estimated_power(self) -> float:
        return float(self.power * self.color.mean())


def direction_to_equirect(d: np.ndarray) -> np.ndarray:
    """Blender's equirectangular mapping: world direction -> (u, v) in [0, 1]^2, v = 1 at +z."""
    u = -np.arctan2(d[:, 1], d[:, 0]) / (2 * math.pi) + 0.5
    v = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])) / math.pi + 0.5
    return np.stack([u, v], axis=1)


def equirect_to_direction(uv: np.ndarray) -> np.ndarray:
    phi = -(uv[:, 0] - 0.5) * 2 * math.pi
    el = (uv[:, 1] - 0.5) * math.pi
    c = np.cos(el)
    return np.stack([c * np.cos(phi), c * np.sin(phi), np.sin(el)], axis=1)


class Environment:
    """World lighting: a constant colour or an equirectangular image (row 0 = top = +z).

    The image is importance-sampled by a piecewise-constant distribution over its pixels with
    density proportional to luminance times sin(polar angle), so the solid-angle pdf is
    p_pixel * W * H / (2 pi^2 sin(theta)) (uniform in (u, v) inside the chosen pixel).
    """

    def __init__(self, color=(0.0, 0.0, 0.0), image: np.ndarray | None = None, strength: float = 1.0):
        self.strength = _power(strength, "Environment.strength")
        self.color = _rgb(color, "Environment.color")
        self.image = None
        if image is not None:
            img = np.asarray(image, dtype=np.float64)
            if img.ndim != 3 or img.shape[2] < 3 or img.shape[0] < 1 or img.shape[1] < 1:
                raise ValueError(f"environment image must be (H, W, 3), got shape {img.shape}")
            img = np.nan_to_num(np.maximum(img[:, :, :3], 0.0), nan=0.0, posinf=0.0)
            self.image = img * self.strength
            h, w, _ = img.shape
            lum = self.image @ np.array([0.2126, 0.7152, 0.0722])
            theta = (np.arange(h) + 0.5) / h * math.pi  # polar angle of each row's centre
            weight = lum * np.sin(theta)[:, None]
            total = weight.sum()
            if total <= 0:
                weight = np.ones((h, w)) * np.sin(theta)[:, None]
                total = weight.sum()
            self.pixel_p = (weight / total).ravel()
            self.cdf = np.cumsum(self.pixel_p)
            self.cdf /= self.cdf[-1]
        self.constant = self.color * self.strength

    @property
    def is_black(self) -> bool:
        if self.image is not None:
            return not (self.image > 0).any()
        return not (self.constant > 0).any()

    def _pixel(self, d: np.ndarray):
        h, w, _ = self.image.shape
        uv = direction_to_equirect(d)
        x = np.clip((uv[:, 0] * w).astype(np.int64), 0, w - 1)
        y = np.clip(((1 - uv[:, 1]) * h).astype(np.int64), 0, h - 1)
        return y, x

    def radiance(self, d: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) arriving from world directions d (pointing away from the scene)."""
        return self.radiance_and_pdf(d)[0]

    def pdf(self, d: np.ndarray) -> np.ndarray:
        return self.radiance_and_pdf(d)[1]

    def radiance_and_pdf(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radiance (N, 3) from world directions d and the solid-angle pdf (N,) of :meth:`sample`
        choosing them, from one pixel lookup."""
        if self.image is None:
            return np.broadcast_to(self.constant, (len(d), 3)).copy(), np.full(len(d), 1 / (4 * math.pi))
        y, x = self._pixel(d)
        return self.image[y, x], self._pdf_at(y, x, d)

    def _pdf_at(self, y: np.ndarray, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        h, w, _ = self.image.shape
        sin_t = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-8)
        return self.pixel_p[y * w + x] * (w * h) / (2 * math.pi**2 * sin_t)

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        n = len(p)
        if self.image is None:
            z = 1 - 2 * u[:, 0]
            r = np.sqrt(np.maximum(0.0, 1 - z * z))
            phi = 2 * math.pi * u[:, 1]
            wi = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
            rad, pdf = self.radiance_and_pdf(wi)
        else:
            h, w, _ = self.image.shape
            # One uniform picks the pixel through the cdf; the second jitters inside it.
            idx = np.minimum(np.searchsorted(self.cdf, u[:, 0], side="right"), h * w - 1)
            lo = np.where(idx > 0, self.cdf[idx - 1], 0.0)
            width = np.maximum(self.cdf[idx] - lo, 1e-300)
            fx = np.clip((u[:, 0] - lo) / width, 0.0, 1.0 - 1e-9)
            y, x = np.divmod(idx, w)
            uv = np.stack([(x + fx) / w, 1 - (y + u[:, 1]) / h], axis=1)
            wi = equirect_to_direction(uv)
            # The direction lies inside the chosen pixel: its radiance and density are that pixel's.
            rad, pdf = self.image[y, x], self._pdf_at(y, x, wi)
        return LightSample(wi, np.full(n, INF), rad, pdf, False)

    def estimated_power(self) -> float:
        if self.image is None:
            return float(self.constant.mean() * math.pi * 10.0)
        return float(self.image.mean() * math.pi * 10.0)

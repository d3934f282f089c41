"""Lights and the environment, each with vectorised sampling for next-event estimation.

Blender's units, converted once here:

- point and spot: ``power`` in watts, radiant intensity I = power / (4 pi) W/sr per colour
  channel (a spot is a point light masked to its cone, as in Blender); of a ``radius`` (Blender's Radius), as in
  Cycles, a sphere (Soft Falloff off) or a disk facing the point it lights (Soft Falloff on, Blender's default) of
  radiance L = I / (pi r^2), sampled by the solid angle of the sphere's cone or evenly over the disk's area, a spot's
  cone applied to the direction each point of it shines in;
- sun: ``strength`` is the irradiance in W/m^2 on a surface facing it; of an ``angle`` (Blender's Angle) a disk of
  the sky of that diameter, of radiance strength / (pi sin^2(angle / 2)), sampled evenly in its solid angle;
- *Normalize* off (point, spot, sun, area): Cycles' power over pi (a point or spot of no radius: intensity power /
  pi), a sun's strength the radiance of its disk;
- area: ``power`` in watts leaves one side (the light's local -z) as a Lambertian emitter,
  radiance L = power / (pi * area) (L = power / pi where Blender's *Normalize* is off), shaped by Blender's
  *Spread* (Cycles' soft-box grid, which keeps the power: ``spread_factor``); a rectangle is sampled by the
  solid angle it fills (within a spread's cone: ``kernels._rect_window``), an ellipse evenly in area.

Every ``sample(p, u)`` returns a :class:`LightSample` of world directions *toward* the light,
the distance to it (inf for the sun and the environment), the arriving radiance (for delta
lights the irradiance-like quantity that the BRDF and cosine multiply) and the solid-angle
pdf (1 for delta lights). Rays hit the lights that are not delta lights (``kernels.add_emission``), and camera rays
see them where ``camera_visible``. ``max_bounces`` (Cycles' per-light Max Bounces): the deepest bounce at whose hits
next-event estimation samples the light (0: the camera rays' hits only), as Cycles' does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .. import kernels
from ..formula import LUMINANCE
from ..kernels import N_PARAMS

INF = np.inf
# The environment arrays the kernels take for lights other than the environment, and for a scene without one
# (``Environment.image_arrays``' types, so that the kernels compile once): placeholders the loops never read.
NO_IMAGE = (
    np.zeros((1, 1, 3)),
    np.ones(1),
    np.ones(1),
    np.zeros(1, dtype=np.int64),
    np.array([1.0, -1.0]),
    np.zeros(1, dtype=np.int64),
    np.array([[-1.0, 0.0], [-1.0, 0.0]]),
    np.zeros(1, dtype=np.int64),
)
# Bins of the lookup's first guesses (``kernels._env_pixel``) per image row and per image column.
GUESS_BINS = 16


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


def _shadowed(row: np.ndarray, light) -> np.ndarray:
    """``row`` with the parameters of every light's row: :data:`kernels.NO_SHADOW`, 1 where ``light`` casts no shadow,
    and its :data:`kernels.MAX_BOUNCES`."""
    row[kernels.NO_SHADOW] = 0.0 if light.casts_shadow else 1.0
    row[kernels.MAX_BOUNCES] = light.max_bounces
    return row


def _max_bounces(value, name: str) -> int:
    if isinstance(value, bool) or int(value) != value or value < 0:
        raise ValueError(f"{name} must be a whole number >= 0, got {value!r}")
    return int(value)


# Cycles' default per-light Max Bounces (no limit a render reaches)
MAX_BOUNCES = 1024


@dataclass
class PointLight:
    """A point light; of a ``radius`` > 0 a sphere (``soft_falloff`` False) or a disk facing each point it lights
    (``soft_falloff`` True, Blender's default), as Cycles' (the module's notes)."""

    position: np.ndarray
    power: float = 1000.0
    color: tuple = (1.0, 1.0, 1.0)
    casts_shadow: bool = field(default=True, kw_only=True)  # Blender's Cast Shadow: off, surfaces do not block it
    radius: float = field(default=0.0, kw_only=True)
    soft_falloff: bool = field(default=True, kw_only=True)
    normalize: bool = field(default=True, kw_only=True)
    camera_visible: bool = field(default=True, kw_only=True)
    max_bounces: int = field(default=MAX_BOUNCES, kw_only=True)

    def __post_init__(self):
        name = type(self).__name__
        self.position = _point(self.position, f"{name}.position")
        self.power = _power(self.power, f"{name}.power")
        self.color = _rgb(self.color, f"{name}.color")
        self.radius = _power(self.radius, f"{name}.radius")
        self.max_bounces = _max_bounces(self.max_bounces, f"{name}.max_bounces")

    @property
    def intensity(self) -> np.ndarray:
        """The radiant intensity (W/sr) of the light of no radius: Cycles' power over pi and the area 4 it gives a
        point, power / (4 pi); power / pi with *Normalize* off."""
        return self.color * self.power / (4 * math.pi if self.normalize else math.pi)

    @property
    def radiance(self) -> np.ndarray:
        """The radiance of the sphere or disk of a light of a radius: power / (4 pi r^2 pi), Cycles' power over the
        sphere's area and pi (I / (pi r^2): its irradiance far off is a point's); power / pi, *Normalize* off."""
        area = 4.0 * math.pi * self.radius**2 if self.normalize else 1.0
        return self.color * self.power / (area * math.pi)

    def table_row(self) -> tuple[int, np.ndarray]:
        row = np.zeros(N_PARAMS)
        row[0:3] = self.position
        if not self.radius > 0.0:
            row[3:6] = self.intensity
            return kernels.POINT, _shadowed(row, self)
        row[3:6] = self.radiance
        row[6:15] = np.eye(3).ravel()  # the spot cone's frame and an edge nothing is beyond: no cone
        row[15] = -2.0
        row[kernels.RADIUS] = self.radius
        row[kernels.CAMERA_VISIBLE] = 1.0 if self.camera_visible else 0.0
        return (kernels.FACING_DISK if self.soft_falloff else kernels.SPHERE), _shadowed(row, self)

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        return _sample(self, p, u)

    def intersect(self, o: np.ndarray, d: np.ndarray):
        """Distance (inf where missed), solid-angle pdf and share of the radiance (0: missed) along unit rays of a
        light of a radius (``kernels.intersect_soft``)."""
        return _intersect_soft(self, o, d)

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
    axes: np.ndarray | None = None

    def __post_init__(self):
        """``axes``: the light object's local x, y and z axes in world space (the columns of its (3, 3) matrix),
        scale included; the cone is tested in the light's own frame, as Blender's is, so a light scaled unevenly
        casts an elliptical cone and one flattened along its z a wider one. None: an unscaled light pointing
        along ``direction``."""
        super().__post_init__()
        if self.axes is None:
            self.direction = _unit(self.direction, "SpotLight.direction")
            z = -self.direction
            x = np.cross((0.0, 0.0, 1.0) if abs(z[2]) < 0.9 else (1.0, 0.0, 0.0), z)
            x /= np.linalg.norm(x)
            self.axes = np.stack([x, np.cross(z, x), z], axis=1)
        else:
            axes = np.asarray(self.axes, dtype=np.float64).reshape(3, 3)
            if not (np.isfinite(axes).all() and abs(np.linalg.det(axes)) > 1e-30):
                raise ValueError(f"SpotLight.axes must be three finite independent axes, got {axes.tolist()}")
            self.axes = axes
            self.direction = _unit(-axes[:, 2], "SpotLight.axes' z")
        if not (0 < self.spot_size <= math.pi):
            raise ValueError(f"SpotLight.spot_size must be in (0, pi] radians, got {self.spot_size}")
        if not (0 <= self.blend <= 1):
            raise ValueError(f"SpotLight.blend must be in [0, 1], got {self.blend}")

    def table_row(self) -> tuple[int, np.ndarray]:
        kind, row = super().table_row()
        cos_edge = math.cos(self.spot_size / 2)
        row[6:15] = np.linalg.inv(self.axes).ravel()  # world -> the light's frame: a direction's local (x, y, z)
        row[15], row[16] = cos_edge, (1 - cos_edge) * self.blend
        return (kernels.SPOT if kind == kernels.POINT else kind), row


@dataclass
class SunLight:
    """A distant light: ``direction`` is where the light travels, ``strength`` the irradiance; of an ``angle`` > 0
    (radians, the disk's diameter, up to pi) a disk of the sky (the module's notes)."""

    direction: np.ndarray
    strength: float = 1.0
    color: tuple = (1.0, 1.0, 1.0)
    casts_shadow: bool = field(default=True, kw_only=True)
    angle: float = field(default=0.0, kw_only=True)
    normalize: bool = field(default=True, kw_only=True)
    camera_visible: bool = field(default=True, kw_only=True)
    max_bounces: int = field(default=MAX_BOUNCES, kw_only=True)

    def __post_init__(self):
        self.direction = _unit(self.direction, "SunLight.direction")
        self.strength = _power(self.strength, "SunLight.strength")
        self.color = _rgb(self.color, "SunLight.color")
        self.angle = _power(self.angle, "SunLight.angle")
        if self.angle > math.pi:
            raise ValueError(f"SunLight.angle must be in [0, pi] radians, got {self.angle!r}")
        self.max_bounces = _max_bounces(self.max_bounces, "SunLight.max_bounces")

    def table_row(self) -> tuple[int, np.ndarray]:
        row = np.zeros(N_PARAMS)
        row[0:3], row[3:6] = -self.direction, self.color * self.strength
        if not self.angle > 0.0:
            return kernels.SUN, _shadowed(row, self)
        half = self.angle / 2
        if self.normalize:  # Cycles' strength over the disk's area pi sin^2: the irradiance facing it is the strength
            row[3:6] /= math.pi * math.sin(half) ** 2
        row[6], row[7] = math.cos(half), 2.0 * math.sin(half / 2) ** 2  # cos and 1 - cos of the half angle
        row[kernels.CAMERA_VISIBLE] = 1.0 if self.camera_visible else 0.0
        return kernels.SUN_DISK, _shadowed(row, self)

    def intersect(self, o: np.ndarray, d: np.ndarray):
        """Distance (inf), solid-angle pdf and share of the radiance (0: missed) along unit rays of a sun of an
        angle (``kernels.intersect_soft``)."""
        return _intersect_soft(self, o, d)

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        return _sample(self, p, u)

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
    normalize: bool = True
    spread: float = math.pi
    camera_visible: bool = True
    casts_shadow: bool = field(default=True, kw_only=True)
    solid_angle: bool = field(default=True, kw_only=True)
    max_bounces: int = field(default=MAX_BOUNCES, kw_only=True)

    def __post_init__(self):
        """``normalize``: Blender's *Normalize* (the power spread over the light's area; off, the radiance is
        power / pi whatever the size). ``spread``: Blender's *Spread* in radians, [0, pi]: the light leaves within
        that cone of its normal (``spread_factor``). ``camera_visible``: whether camera rays see the light itself
        (the object's *Camera* ray visibility), as Cycles draws it; it lights the scene either way. ``solid_angle``:
        a rectangle is sampled by the solid angle it fills (``kernels._rect_window``); False samples it by area, as
        before (``benchmarks/bench_light_sampling.py`` compares the two)."""
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
        # emits along its local -z: the side of the plane -m[:3, 2] points to (a mirroring scale turns u x v over)
        self.normal = n / np.linalg.norm(n) * (-1.0 if np.dot(n, m[:3, 2]) >= 0.0 else 1.0)
        full = 4 * np.linalg.norm(n)
        self.area = full * (math.pi / 4 if self.ellipse else 1.0)
        self.radiance = self.color * self.power / (math.pi * (self.area if self.normalize else 1.0))
        self.spread = float(self.spread)
        if not 0.0 <= self.spread <= math.pi:
            raise ValueError(f"AreaLight.spread must be in [0, pi] radians, got {self.spread!r}")
        self.max_bounces = _max_bounces(self.max_bounces, "AreaLight.max_bounces")

    def table_row(self) -> tuple[int, np.ndarray]:
        row = np.zeros(N_PARAMS)
        row[0:3], row[3:6], row[6:9] = self.center, self.axis_u, self.axis_v
        row[9:12], row[12:15], row[15] = self.normal, self.radiance, self.area
        row[16] = self._bounding_radius2()
        row[17], row[18] = spread_table(self.spread)
        row[kernels.CAMERA_VISIBLE] = 1.0 if self.camera_visible else 0.0
        row[kernels.BY_AREA] = 0.0 if self.solid_angle else 1.0
        return (kernels.AREA_ELLIPSE if self.ellipse else kernels.AREA_RECT), _shadowed(row, self)

    def _bounding_radius2(self) -> float:
        """The squared radius about the centre, 0.1% wider, of a sphere that holds the light: the points a u + b v,
        |a|, |b| <= 1, which both the sampling and the intersection take (an oblique u and v, a sheared light,
        included). The intersection's first test."""
        u, v = self.axis_u, self.axis_v
        return float(max(np.sum((u + v) ** 2), np.sum((u - v) ** 2)) * 1.001)

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        return _sample(self, p, u)

    def intersect(self, o: np.ndarray, d: np.ndarray):
        """Distance along unit rays to the emitting side (inf where missed) and the solid-angle pdf."""
        _, row = self.table_row()
        return kernels.intersect_area(row, self.ellipse, _rows(o), _rows(d))

    def estimated_power(self) -> float:
        return float(self.power * self.color.mean())


def spread_table(spread: float) -> tuple[float, float]:
    """An area light's *Spread* (radians) as the light table holds it: the tangent of its half angle (inf for
    180 degrees: no grid) and the factor that keeps the light's power (``kernels.spread_factor``). Cycles'
    soft-box grid: a direction at angle a to the normal passes (tan(s/2) - tan a) / tan(s/2) of the light, and
    the integral of cos a sin a over the cone is (tan(s/2) - s/2) / tan(s/2) of the hemisphere's; at half angles
    below 0.05 the difference loses its digits, and its series' first term takes its place."""
    half = 0.5 * spread
    if spread >= math.pi:
        return math.inf, 1.0
    if half <= 0.0:
        return 0.0, 0.0
    tan_half = math.tan(half)
    return tan_half, (1.0 / (tan_half - half) if half > 0.05 else 3.0 / half**3)


def _pixel_guesses(z_edges: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tables ``kernels._env_pixel`` guesses from: the row at the middle of each of ``GUESS_BINS`` * H even
    bins of z (from +1 down), the columns' W + 1 edge directions (x, y) and the column at the middle of each of
    ``GUESS_BINS`` * W even bins of ``kernels._pseudo_angle``. A guess only starts the comparisons with the
    edges, which decide."""
    h = len(z_edges) - 1
    nz = GUESS_BINS * h
    z = 1.0 - 2.0 * (np.arange(nz) + 0.5) / nz
    row_of_bin = np.clip(np.searchsorted(-z_edges, -z, side="left") - 1, 0, h - 1).astype(np.int64)
    u = np.arange(w + 1) / w
    edges = np.ascontiguousarray(kernels.equirect_direction(np.stack([u, np.full(w + 1, 0.5)], axis=1))[:, :2])
    na = GUESS_BINS * w
    a = 4.0 * (np.arange(na) + 0.5) / na  # the diamond's point at each bin's middle, quadrant by quadrant
    q = np.floor(a)
    f = a - q
    x = np.select([q == 0, q == 1, q == 2], [1.0 - f, -f, f - 1.0], f)
    y = np.select([q == 0, q == 1, q == 2], [f, 1.0 - f, -f], f - 1.0)
    col = kernels.equirect_uv(np.stack([x, y, np.zeros(na)], axis=1))[:, 0]
    column_of_bin = np.clip((col * w).astype(np.int64), 0, w - 1)
    return row_of_bin, edges, column_of_bin


def direction_to_equirect(d: np.ndarray) -> np.ndarray:
    """Blender's equirectangular mapping: world direction -> (u, v) in [0, 1]^2, v = 1 at +z."""
    return kernels.equirect_uv(_rows(d))


def equirect_to_direction(uv: np.ndarray) -> np.ndarray:
    return kernels.equirect_direction(_rows(uv, 2))


def _rows(a, columns: int = 3) -> np.ndarray:
    """``a`` as contiguous float64 rows of ``columns`` (the kernels' layout); a clear error otherwise."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != columns:
        raise ValueError(f"expected an (N, {columns}) array, got shape {a.shape}")
    return a


def _intersect_soft(light, o: np.ndarray, d: np.ndarray):
    """``light.intersect`` of a light of a radius or an angle: the kernels' intersection of its row."""
    kind, row = light.table_row()
    if kernels.is_delta(kind):
        raise ValueError(f"{type(light).__name__} of no radius or angle: rays cannot hit it")
    return kernels.intersect_soft(kind, row, _rows(o), _rows(d))


def _sample(light, p: np.ndarray, u: np.ndarray) -> LightSample:
    """``light.sample``: the light table's sampling loop on this one light."""
    kind, row = light.table_row()
    env = light.image_arrays() if isinstance(light, Environment) else NO_IMAGE
    p, u = _rows(p), _rows(u, 2)
    if len(u) != len(p):
        raise ValueError(f"one pair of uniforms per point: got {len(u)} for {len(p)}")
    wi, dist, rad, pdf = kernels.sample_light(kind, row, env, p, u)
    return LightSample(wi, dist, rad, pdf, bool(kernels.is_delta(kind)))


class Environment:
    """World lighting: a constant colour or an equirectangular image (row 0 = top = +z).

    The image is importance-sampled by a piecewise-constant distribution over its pixels with
    probability proportional to luminance times the pixel's solid angle, and inside the chosen pixel
    evenly in solid angle (evenly in azimuth and in z): the solid-angle pdf is p_pixel / (the pixel's
    solid angle), one number per pixel (``pixel_pdf``), which the lookup of a direction reads with the
    pixel's radiance.
    """

    def __init__(self, color=(0.0, 0.0, 0.0), image: np.ndarray | None = None, strength: float = 1.0):
        self.strength = _power(strength, "Environment.strength")
        self.color = _rgb(color, "Environment.color")
        self.constant = self.color * self.strength
        self.image = None
        if image is not None:
            # Blender's pixels as they are, contiguous: one compiled loop for every caller, the warm-up's too (the
            # export's RGB of RGBA pixels is a strided view, which compiled a loop of its own on the first F12)
            src = np.ascontiguousarray(image, dtype=np.float32)
            if src.ndim != 3 or src.shape[2] < 3 or src.shape[0] < 1 or src.shape[1] < 1:
                raise ValueError(f"environment image must be (H, W, 3), got shape {src.shape}")
            # float32, as Blender's pixels are: an 8K image is 403 MB where it was 805, and on this kind of machine
            # its pages took longer to fault in than all the work on them
            self.image = np.empty(src.shape[:2] + (3,), dtype=np.float32)
            lum = np.empty(src.shape[:2])
            kernels.clean_environment(src, self.strength, self.image, lum)
        # The kernels read one kind of environment: a constant colour is an image of one pixel.
        pixels = self.image if self.image is not None else self.constant.reshape(1, 1, 3).astype(np.float32)
        h, w, _ = pixels.shape
        if self.image is None:
            lum = pixels @ np.array(LUMINANCE)
        # The rows' edge heights and the columns' edge directions, from the mapping itself.
        v = 1.0 - np.arange(h + 1) / h
        z_edges = kernels.equirect_direction(np.stack([np.full(h + 1, 0.5), v], axis=1))[:, 2]
        z_edges[0], z_edges[h] = 1.0, -1.0
        solid = (2.0 * math.pi / w) * (z_edges[:-1] - z_edges[1:])  # (H,) each pixel's solid angle, by row
        weight = lum
        weight *= solid[:, None]  # in place: an 8K image's arrays are 268 MB each
        total = weight.sum()
        if not total > 0:
            weight = np.ones((h, w)) * solid[:, None]
            total = weight.sum()
        self._solid = solid
        weight /= total  # each pixel's probability
        self.pixel_pdf = np.ascontiguousarray((weight / solid[:, None]).ravel())
        self.alias_p, self.alias_i = kernels.alias_table(weight.ravel())
        self._arrays = (np.ascontiguousarray(pixels), self.pixel_pdf, self.alias_p, self.alias_i, z_edges)
        self._arrays += _pixel_guesses(z_edges, w)

    @property
    def pixel_p(self) -> np.ndarray:
        """(H * W,) each pixel's probability of being sampled (computed from ``pixel_pdf``; not kept, since an
        HDRI's would be as large as its density)."""
        return (self.pixel_pdf.reshape(len(self._solid), -1) * self._solid[:, None]).ravel()

    @property
    def is_black(self) -> bool:
        if self.image is not None:
            return not (self.image > 0).any()
        return not (self.constant > 0).any()

    def table_row(self) -> tuple[int, np.ndarray]:
        """The light table's row: the kind and no parameters but no bounce limit (the environment is all in
        :meth:`image_arrays`)."""
        row = np.zeros(N_PARAMS)
        row[kernels.MAX_BOUNCES] = INF
        return kernels.ENVIRONMENT, row

    def image_arrays(self) -> tuple:
        """The ``env`` tuple the kernels read (``kernels``, "lights"): the image (one pixel for a constant colour),
        each pixel's solid-angle pdf, the alias table (``kernels.alias_table``), the rows' edge heights and the
        lookup's guesses."""
        return self._arrays

    def radiance(self, d: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) arriving from world directions d (pointing away from the scene)."""
        return self.radiance_and_pdf(d)[0]

    def pdf(self, d: np.ndarray) -> np.ndarray:
        return self.radiance_and_pdf(d)[1]

    def radiance_and_pdf(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radiance (N, 3) from world directions d and the solid-angle pdf (N,) of :meth:`sample`
        choosing them, from one pixel lookup."""
        d = _rows(d)
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)  # the lookup reads unit directions
        return kernels.environment_radiance(self._arrays, d)

    def sample(self, p: np.ndarray, u: np.ndarray) -> LightSample:
        return _sample(self, p, u)

    def estimated_power(self) -> float:
        if self.image is None:
            return float(self.constant.mean() * math.pi * 10.0)
        return float(self.image.mean() * math.pi * 10.0)

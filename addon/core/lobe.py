"""Lobe images: f(wi, wo) cos(theta_o) on a regular grid of the projected outgoing hemisphere.

This is the measurement of docs/architecture.md, Measurement and what the lobe preview shows. A pixel (x, y)
of the unit disk maps to wo = (x, y, sqrt(1 - x^2 - y^2)); pixels outside the disk are 0.
The incident direction lies in the x-z plane at ``theta_i`` degrees from the normal, on the
-x side, so the mirror direction appears at +x.

Because the grid is uniform in the projected disk, dA = cos(theta_o) d(omega): the
directional albedo is simply the sum of f over the disk times the pixel area.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

BrdfFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

INCIDENT_ANGLES_DEG = (0.0, 30.0, 60.0, 75.0)


def incident_direction(theta_i_deg: float) -> np.ndarray:
    """Unit wi (toward the light) at theta_i degrees from the normal, in the x-z plane."""
    t = np.radians(theta_i_deg)
    return np.array([-np.sin(t), 0.0, np.cos(t)], dtype=np.float64)


def lobe_grid(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Outgoing directions of a res x res lobe image and the mask of pixels on the disk.

    Returns ``wo`` of shape (res*res, 3) (rows top to bottom = +y to -y, columns -x to +x;
    off-disk rows hold (0, 0, 1) so they are valid directions) and ``mask`` (res*res,).
    """
    if res < 2:
        raise ValueError(f"lobe resolution must be >= 2, got {res}")
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)
    r2 = x * x + y * y
    mask = r2 < 1.0
    z = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    wo = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    m = mask.reshape(-1)
    wo[~m] = (0.0, 0.0, 1.0)
    return wo, m


def lobe_image(brdf: BrdfFn, theta_i_deg: float, res: int = 64) -> np.ndarray:
    """(res, res, 3) image of f(wi, wo) cos(theta_o); ``brdf(wi, wo) -> (N, 3)`` is one batch call."""
    wo, mask = lobe_grid(res)
    wi = np.broadcast_to(incident_direction(theta_i_deg), wo.shape).copy()
    f = np.asarray(brdf(wi[mask], wo[mask]), dtype=np.float64)
    img = np.zeros((res * res, 3))
    img[mask] = f * wo[mask, 2:3]
    return img.reshape(res, res, 3)


def albedo_from_lobe(lobe: np.ndarray) -> np.ndarray:
    """Directional albedo (..., 3) from lobe images (..., R, R, 3): sum of f over the disk times the pixel area."""
    res = lobe.shape[-2]
    wo, mask = lobe_grid(res)
    f = lobe.reshape(*lobe.shape[:-3], res * res, 3)[..., mask, :] / wo[mask, 2:3]
    return f.sum(axis=-2) * (2.0 / res) ** 2


def relative_rmse(estimate: np.ndarray, reference: np.ndarray, image_axes: int | None = None):
    """||estimate - reference|| / ||reference|| over all pixels and channels (0 if both vanish).

    With ``image_axes=k`` the last k axes are one image and the result is an array over the leading
    axes (e.g. k = 3 for (stacks, angles, R, R, 3) lobe images); without it, one float over everything.
    """
    e = np.asarray(estimate, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    if e.shape != r.shape:
        raise ValueError(f"shapes differ: estimate {e.shape} vs reference {r.shape}")
    axes = None if image_axes is None else tuple(range(e.ndim - image_axes, e.ndim))
    num = np.sqrt(np.mean((e - r) ** 2, axis=axes))
    den = np.sqrt(np.mean(r**2, axis=axes))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(den > 0.0, num / np.where(den > 0.0, den, 1.0), np.where(num == 0.0, 0.0, np.inf))
    return float(out) if image_axes is None else out


def to_display(img: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear HDR -> sRGB-encoded [0, 1] for PNG previews (simple clamp tone map)."""
    x = np.clip(np.nan_to_num(img * exposure, nan=0.0, posinf=1.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)

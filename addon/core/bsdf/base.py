"""The shared BSDF interface: sample record, constants, and parameter/direction validation.

Every BSDF in this package is a small class over per-row parameters with

    eval(wi, wo, mode="radiance") -> (N, 3)   f without the cosine, 1/sr; 0 where impossible
    pdf(wi, wo, mode="radiance")  -> (N,)     solid-angle density of sample() choosing wi
    sample(wo, u_lobe, u, mode="radiance") -> BSDFSample

in the local frame (normal +z), with ``wi`` (toward the light) and ``wo`` (toward the viewer)
both pointing away from the surface. Parameters are scalars or per-row arrays: ``(N,)`` for
scalars, ``(N, 3)`` or ``(3,)`` for RGB. Results are float64.

Each method takes ``check=True``: it validates directions (shape, finite, unit length) and
random numbers. Hot internal loops that build their inputs themselves pass ``check=False``
to skip the finiteness/length scans (shapes are still checked).

Arrays may come from numpy, CuPy or torch (:mod:`addon.core.xp`): each method works in the
array library of its inputs and parameters (numpy in, numpy out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..formula import formula, isfinite, minimum
from ..xp import namespace, to_numpy
from .frame import dot

SMOOTH_ALPHA = 1e-3
RADIANCE = "radiance"
IMPORTANCE = "importance"
MODES = (RADIANCE, IMPORTANCE)

UNIT_TOLERANCE = 1e-3


@dataclass
class BSDFSample:
    """Result of ``sample``.

    ``wi`` (N, 3) sampled direction (0 on invalid rows); ``weight`` (N, 3) = f |cos wi| / pdf
    (for delta lobes the event's weight); ``pdf`` (N,) solid-angle density, or for delta lobes
    the discrete probability of the chosen event; ``delta``, ``transmission``, ``valid`` (N,)
    bool. Invalid rows have weight 0 and pdf 0.
    """

    wi: np.ndarray
    weight: np.ndarray
    pdf: np.ndarray
    delta: np.ndarray
    transmission: np.ndarray
    valid: np.ndarray

    @classmethod
    def build(cls, wi, weight, pdf, delta, transmission, valid) -> "BSDFSample":
        """Assemble a sample, zeroing every row that is invalid or not finite (:func:`sample_ok`)."""
        xp = namespace(wi, weight, pdf)
        valid = sample_ok(
            valid, pdf, weight[..., 0], weight[..., 1], weight[..., 2], wi[..., 0], wi[..., 1], wi[..., 2]
        )
        v3 = valid[:, None]
        return cls(
            wi=xp.where(v3, wi, 0.0),
            weight=xp.where(v3, weight, 0.0),
            pdf=xp.where(valid, pdf, 0.0),
            delta=delta & valid,
            transmission=transmission & valid,
            valid=valid,
        )


@formula
def sample_ok(valid, pdf, w0, w1, w2, x, y, z):
    """Whether a sample (direction x, y, z; weight w0..w2; pdf) counts: ``valid`` and a positive finite pdf,
    a finite direction and a finite non-negative weight. Sums stand for the finiteness of each entry (inf -
    inf and nan + x are nan), short of overflow, which a unit direction or a sample weight does not reach."""
    return (
        valid
        & (pdf > 0.0)
        & isfinite(pdf)
        & isfinite(w0 + w1 + w2)
        & isfinite(x + y + z)
        & (minimum(minimum(w0, w1), w2) >= 0.0)
    )


# ----------------------------------------------------------------------------- validation


def check_mode(mode) -> str:
    if mode not in MODES:
        raise ValueError(f"mode must be {RADIANCE!r} or {IMPORTANCE!r}, got {mode!r}")
    return mode


def as_directions(w, name: str, check: bool = True, xp=None) -> np.ndarray:
    """``w`` as a float64 (N, 3) array of unit directions; a single (3,) vector becomes (1, 3).

    With ``check`` it must be finite and of unit length (within ``UNIT_TOLERANCE``). ``xp``:
    the array namespace to return (default: ``w``'s own).
    """
    xp = namespace(w) if xp is None else xp
    try:
        a = xp.asarray(w, dtype=xp.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an (N, 3) array of directions, got {type(w).__name__}") from None
    if a.ndim == 1 and a.shape[0] == 3:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(a.shape)}")
    if check:
        _check_directions(to_numpy(a), name)
    return a


def _check_directions(a: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(a), axis=1))[0])
        raise ValueError(f"{name} must be finite, row {bad} is {a[bad].tolist()}")
    n = dot(a, a)
    off = np.abs(n - 1.0) > 2.0 * UNIT_TOLERANCE
    if np.any(off):
        bad = int(np.flatnonzero(off)[0])
        raise ValueError(f"{name} must be unit vectors, row {bad} = {a[bad].tolist()} has length {np.sqrt(n[bad]):.6g}")


def as_uniform(u, name: str, n: int, dims: int, check: bool = True, xp=None) -> np.ndarray:
    """Uniform random numbers: shape (n,) for ``dims == 1`` or (n, dims), in [0, 1]."""
    xp = namespace(u) if xp is None else xp
    a = xp.asarray(u, dtype=xp.float64)
    want = (n,) if dims == 1 else (n, dims)
    if tuple(a.shape) != want:
        raise ValueError(f"{name} must have shape {want} to match {n} directions, got {tuple(a.shape)}")
    if check and not (xp.all(a >= 0.0) and xp.all(a <= 1.0)):
        a = to_numpy(a)
        raise ValueError(f"{name} must hold numbers in [0, 1), got values in [{np.nanmin(a)}, {np.nanmax(a)}]")
    return a


def same_rows(name_a: str, a, name_b: str, b) -> int:
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{name_a} has {a.shape[0]} rows but {name_b} has {b.shape[0]}")
    return a.shape[0]


def as_param(
    value, name: str, *, lo: float = -np.inf, hi: float = np.inf, lo_open: bool = False, rgb: bool = False
) -> np.ndarray:
    """A BSDF parameter as float64: scalars -> (1,) or (N,); RGB -> (1, 3) or (N, 3).

    Raises ValueError naming the parameter, the bad value and the valid range. Stays in the
    array library of ``value`` (numpy for scalars and lists).
    """
    xp = namespace(value)
    try:
        a = xp.array(value, dtype=xp.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or an array of numbers, got {value!r}") from None
    if rgb:
        if a.ndim == 0:
            a = xp.full((1, 3), float(a))
        elif a.ndim == 1 and a.shape[0] == 3:
            a = a[None, :]
        elif not (a.ndim == 2 and a.shape[1] == 3):
            raise ValueError(
                f"{name} must be a scalar, an RGB triple (3,) or per-row (N, 3), got shape {tuple(a.shape)}"
            )
    else:
        if a.ndim == 0:
            a = a[None]
        elif a.ndim != 1:
            raise ValueError(f"{name} must be a scalar or a per-row (N,) array, got shape {tuple(a.shape)}")
    if math.prod(a.shape) == 0 or a.shape[0] == 0:
        raise ValueError(f"{name} must not be empty")
    if not xp.all(xp.isfinite(a)):
        a = to_numpy(a)
        raise ValueError(f"{name} must be finite, got {_show(a[~np.isfinite(a)])}")
    below = (a <= lo) if lo_open else (a < lo)
    if xp.any(below) or xp.any(a > hi):
        a, below = to_numpy(a), to_numpy(below)
        bad = a[below | (a > hi)]
        lb = "(" if lo_open else "["
        raise ValueError(f"{name} = {_show(bad)} is outside the valid range {lb}{lo}, {hi}]")
    return a


def _show(a: np.ndarray) -> str:
    a = np.unique(np.ravel(a))
    return repr(float(a[0])) if a.size == 1 else f"{a[:4].tolist()}{'...' if a.size > 4 else ''}"


def rows(param, n: int, name: str, xp=np):
    """Broadcast a stored parameter ((1,...) or (N,...)) to ``n`` rows, or raise ValueError;
    moved to the array namespace ``xp`` if it is not there yet."""
    if param.shape[0] != 1 and param.shape[0] != n:
        raise ValueError(f"{name} has {param.shape[0]} rows but the batch has {n} directions")
    return xp.broadcast_to(xp.asarray(param), (n,) + tuple(param.shape[1:]))


class BSDF:
    """Common machinery: per-row parameters listed in ``_params`` and ``take``."""

    _params: tuple[str, ...] = ()

    @property
    def batch_rows(self) -> int | None:
        """Number of rows of the per-row parameters, or None if all are shared."""
        n = [getattr(self, p).shape[0] for p in self._params if getattr(self, p).shape[0] != 1]
        return max(n) if n else None

    def take(self, index) -> "BSDF":
        """The same BSDF restricted to rows ``index`` (bool mask or integer indices) of its
        per-row parameters; shared parameters are kept. For batches that shrink as paths die."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        for p in self._params:
            v = getattr(self, p)
            if v.shape[0] != 1:
                setattr(out, p, v[index])
        return out

    def _xp(self, *arrays):
        """The array namespace of the inputs and the parameters."""
        return namespace(*arrays, *(getattr(self, p) for p in self._params))

    def _inputs(self, wi, wo, mode, check):
        """Validated ``(wi, wo, xp)``."""
        check_mode(mode)
        xp = self._xp(wi, wo)
        wi = as_directions(wi, "wi", check, xp)
        wo = as_directions(wo, "wo", check, xp)
        same_rows("wi", wi, "wo", wo)
        return wi, wo, xp

    def _sample_inputs(self, wo, u_lobe, u, mode, check):
        """Validated ``(wo, u_lobe, u, xp)``."""
        check_mode(mode)
        xp = self._xp(wo, u_lobe, u)
        wo = as_directions(wo, "wo", check, xp)
        n = wo.shape[0]
        return wo, as_uniform(u_lobe, "u_lobe", n, 1, check, xp), as_uniform(u, "u", n, 2, check, xp), xp

"""A numpy-named namespace over torch tensors on one device (see :mod:`addon.core.xp`).

Only the subset the analytic BSDFs and the reference walk use. Defaults follow numpy, not
torch: new float arrays are float64, Python scalars become float64/int64/bool 0-d tensors
(torch would make float32), ``axis`` instead of ``dim``. torch is imported when a namespace is
created, never at module level.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np


class _TorchGenerator:
    def __init__(self, torch, device, seed: int):
        self.torch, self.device = torch, device
        self.gen = torch.Generator(device=device)
        self.gen.manual_seed(seed)

    def random(self, shape):
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        return self.torch.rand(shape, generator=self.gen, dtype=self.torch.float64, device=self.device)


class TorchNamespace:
    name = "torch"
    pi = math.pi
    inf = math.inf
    nan = math.nan

    def __init__(self, device):
        import torch

        self.torch = torch
        self.device = torch.device(device)
        self.float64 = torch.float64
        self.float32 = torch.float32
        self.int64 = torch.int64
        self.bool_ = torch.bool
        self.ndarray = torch.Tensor
        self._consts = {}
        self._dtypes = {
            bool: torch.bool,
            float: torch.float64,
            int: torch.int64,
            np.bool_: torch.bool,
            np.float64: torch.float64,
            np.float32: torch.float32,
            np.int64: torch.int64,
        }

    # ---------------------------------------------------------------- conversion and creation

    def _dt(self, dtype):
        if dtype is None or isinstance(dtype, self.torch.dtype):
            return dtype
        if isinstance(dtype, np.dtype):
            dtype = dtype.type
        return self._dtypes[dtype]

    def _t(self, x):
        """``x`` as a tensor on this device (numpy-typed: Python floats become float64)."""
        if isinstance(x, self.torch.Tensor):
            return x if x.device == self.device else x.to(self.device)
        if isinstance(x, (float, int)) and x == x:
            # Python scalars recur (0.0, 1.0, inf, ...): one 0-d tensor each, never written to
            key = (type(x), x)
            t = self._consts.get(key)
            if t is None:
                t = self.torch.as_tensor(np.asarray(x), device=self.device)
                if len(self._consts) < 4096:
                    self._consts[key] = t
            return t
        if type(x).__module__.startswith("cupy"):
            x = x.get()
        return self.torch.as_tensor(np.asarray(x), device=self.device)

    def asarray(self, x, dtype=None):
        t = self._t(x) if isinstance(x, self.torch.Tensor) else self._t(np.asarray(x))
        dt = self._dt(dtype)
        return t if dt is None or t.dtype == dt else t.to(dt)

    def array(self, x, dtype=None):
        return self.asarray(x, dtype).clone()

    def copy(self, x):
        return self._t(x).clone()

    def _fill_dtype(self, value, dtype):
        if dtype is not None:
            return self._dt(dtype)
        if isinstance(value, bool):
            return self.torch.bool
        if isinstance(value, int):
            return self.torch.int64
        return self.torch.float64

    def zeros(self, shape, dtype=None):
        return self.torch.zeros(shape, dtype=self._dt(dtype) or self.torch.float64, device=self.device)

    def ones(self, shape, dtype=None):
        return self.torch.ones(shape, dtype=self._dt(dtype) or self.torch.float64, device=self.device)

    def full(self, shape, value, dtype=None):
        return self.torch.full(
            (shape,) if isinstance(shape, int) else tuple(shape),
            value,
            dtype=self._fill_dtype(value, dtype),
            device=self.device,
        )

    def zeros_like(self, a, dtype=None):
        return self.torch.zeros_like(a, dtype=self._dt(dtype))

    def ones_like(self, a, dtype=None):
        return self.torch.ones_like(a, dtype=self._dt(dtype))

    def full_like(self, a, value, dtype=None):
        return self.torch.full_like(a, value, dtype=self._dt(dtype))

    def arange(self, start, stop=None, step=1, dtype=None):
        if stop is None:
            start, stop = 0, start
        return self.torch.arange(start, stop, step, dtype=self._dt(dtype) or self.torch.int64, device=self.device)

    def default_rng(self, seed: int):
        return _TorchGenerator(self.torch, self.device, seed)

    # ---------------------------------------------------------------- elementwise

    def where(self, cond, a, b):
        return self.torch.where(self._t(cond), self._t(a), self._t(b))

    def abs(self, x):
        return self.torch.abs(self._t(x))

    def sqrt(self, x):
        return self.torch.sqrt(self._t(x))

    def exp(self, x):
        return self.torch.exp(self._t(x))

    def log(self, x):
        return self.torch.log(self._t(x))

    def log1p(self, x):
        return self.torch.log1p(self._t(x))

    def sin(self, x):
        return self.torch.sin(self._t(x))

    def cos(self, x):
        return self.torch.cos(self._t(x))

    def arccos(self, x):
        return self.torch.arccos(self._t(x))

    def isfinite(self, x):
        return self.torch.isfinite(self._t(x))

    def maximum(self, a, b):
        return self.torch.maximum(self._t(a), self._t(b))

    def minimum(self, a, b):
        return self.torch.minimum(self._t(a), self._t(b))

    def clip(self, x, lo, hi):
        return self.torch.clamp(self._t(x), lo, hi)

    def copysign(self, a, b):
        b = self._t(b)
        return self.torch.copysign(self._t(a).to(b.dtype).expand_as(b), b)

    def nan_to_num(self, x, nan=0.0, posinf=None, neginf=None):
        return self.torch.nan_to_num(self._t(x), nan=nan, posinf=posinf, neginf=neginf)

    @staticmethod
    def errstate(**kwargs):
        """numpy's floating-point warning control; torch raises none, so a no-op."""
        return contextlib.nullcontext()

    # ---------------------------------------------------------------- shapes and reductions

    def einsum(self, spec, *ops):
        return self.torch.einsum(spec, *[self._t(o) for o in ops])

    def stack(self, arrays, axis=0):
        return self.torch.stack([self._t(a) for a in arrays], dim=axis)

    def concatenate(self, arrays, axis=0):
        return self.torch.cat([self._t(a) for a in arrays], dim=axis)

    def repeat(self, a, repeats, axis=None):
        a = self._t(a)
        if axis is None:
            return a.reshape(-1).repeat_interleave(repeats)
        return a.repeat_interleave(repeats, dim=axis)

    def tile(self, a, reps):
        return self._t(a).repeat(reps)

    def broadcast_to(self, a, shape):
        return self.torch.broadcast_to(self._t(a), tuple(shape))

    def all(self, x, axis=None):
        x = self._t(x)
        return self.torch.all(x) if axis is None else self.torch.all(x, dim=axis)

    def any(self, x, axis=None):
        x = self._t(x)
        return self.torch.any(x) if axis is None else self.torch.any(x, dim=axis)

    def max(self, x, axis=None):
        x = self._t(x)
        return self.torch.amax(x) if axis is None else self.torch.amax(x, dim=axis)

    def min(self, x, axis=None):
        x = self._t(x)
        return self.torch.amin(x) if axis is None else self.torch.amin(x, dim=axis)

    def flatnonzero(self, x):
        return self.torch.nonzero(self._t(x).reshape(-1), as_tuple=True)[0]

    def nonzero(self, x):
        return self.torch.nonzero(self._t(x), as_tuple=True)

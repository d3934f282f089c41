"""Array namespaces: one source for numpy and GPU array libraries (CuPy, torch).

The analytic BSDFs and the reference walk are written against an array namespace ``xp`` with
numpy's names (``xp.where``, ``xp.zeros``, ...), resolved from their inputs by
:func:`namespace`: numpy arrays and Python scalars give the ``numpy`` module itself (so the
numpy path is the plain numpy code), CuPy arrays give CuPy (which mirrors numpy's API), torch
tensors give a small shim (:mod:`addon.core.xp_torch`) with the numpy-named subset the code uses.
Nothing here imports torch or CuPy at module level; they are imported when first needed.

:class:`Rng` draws float64 uniforms on the namespace's device, so the walk never calls numpy's
random generator directly; :class:`HostRng` draws them with numpy and moves them to the device,
so that runs on different backends consume identical random numbers (for tests).
"""

from __future__ import annotations

import contextlib

import numpy as np

BACKENDS = ("numpy", "torch", "cupy")

_TORCH = {}
_CUPY = None


def _kind(a) -> str:
    mod = type(a).__module__
    if mod.startswith("torch"):
        return "torch"
    if mod.startswith("cupy"):
        return "cupy"
    return "numpy"


def namespace(*arrays):
    """The array namespace of ``arrays``: numpy unless one of them is a torch tensor or a CuPy
    array (numpy arrays and scalars mixed with those are converted by ``xp.asarray``)."""
    for a in arrays:
        k = _kind(a)
        if k == "torch":
            return _torch_ns(a.device)
        if k == "cupy":
            return _cupy_ns()
    return np


def get(backend: str | None = None, device: str | None = None):
    """The namespace of a backend by name: ``"numpy"`` (device must be None or "cpu"),
    ``"torch"`` (device "cpu" by default, or "cuda", "cuda:1", ...) or ``"cupy"`` (the current
    CUDA device; ``device`` "cuda" or "cuda:N" selects one)."""
    if backend is None or backend == "numpy":
        if device not in (None, "cpu"):
            raise ValueError(f"backend 'numpy' runs on the CPU only, got device {device!r}")
        return np
    if backend == "torch":
        return _torch_ns(device or "cpu")
    if backend == "cupy":
        ns = _cupy_ns()
        if device not in (None, "cuda") and not str(device).startswith("cuda:"):
            raise ValueError(f"backend 'cupy' needs a CUDA device ('cuda' or 'cuda:N'), got {device!r}")
        if device is not None and ":" in str(device):
            ns.cp.cuda.Device(int(str(device).split(":")[1])).use()
        return ns
    raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def name(xp) -> str:
    """``"numpy"``, ``"torch"`` or ``"cupy"``."""
    return "numpy" if xp is np else xp.name


def to_numpy(a) -> np.ndarray:
    """A host numpy copy (or the array itself if it is numpy already)."""
    k = _kind(a)
    if k == "torch":
        return a.detach().cpu().numpy()
    if k == "cupy":
        return a.get()
    return np.asarray(a)


def index_add(xp, target, index, values) -> None:
    """``target[index[i]] += values[i]`` in place, repeated indices accumulating."""
    if xp is not np and xp.name == "torch":
        target.index_add_(0, index, values)
    else:  # numpy, and CuPy's ufunc.at (CuPy 13 and later: its older cupyx.scatter_add is deprecated)
        xp.add.at(target, index, values)


def _torch_ns(device):
    key = str(device)
    ns = _TORCH.get(key)
    if ns is None:
        from .xp_torch import TorchNamespace

        ns = _TORCH[key] = TorchNamespace(device)
    return ns


class _CupyNamespace:
    """CuPy itself, plus the few numpy names the code uses that CuPy lacks (``errstate``:
    GPU arithmetic raises no floating-point warnings, so it is a no-op)."""

    name = "cupy"

    def __init__(self):
        import cupy

        self.cp = cupy

    def __getattr__(self, attr):
        return getattr(self.cp, attr)

    @staticmethod
    def errstate(**kwargs):
        return contextlib.nullcontext()

    def default_rng(self, seed):
        return self.cp.random.default_rng(seed)


def _cupy_ns():
    global _CUPY
    if _CUPY is None:
        _CUPY = _CupyNamespace()
    return _CUPY


class Rng:
    """Uniform float64 random numbers on ``xp``'s device: ``rng.random(shape)``.

    ``seed`` is an integer or a numpy Generator. On numpy the Generator itself draws (the same
    stream as before backends existed); elsewhere the library's own generator is seeded with
    the integer, or with a number drawn from the given numpy Generator.
    """

    def __init__(self, xp, seed):
        self.xp = xp
        if isinstance(seed, np.random.Generator):
            if xp is np:
                self.random = seed.random
                return
            seed = int(seed.integers(2**62))
        if xp is np:
            self.random = np.random.default_rng(int(seed)).random
        else:
            self.random = xp.default_rng(int(seed)).random


class HostRng(Rng):
    """Draws with a numpy Generator on the host and moves the numbers to ``xp``: backends fed
    from equal seeds consume identical random numbers (slow on a GPU; for tests)."""

    def __init__(self, xp, seed):
        self.xp = xp
        self.gen = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(int(seed))

    def random(self, shape):
        u = self.gen.random(shape)
        return u if self.xp is np else self.xp.asarray(u)

"""Formulas written once for numpy arrays, torch tensors and the renderer's compiled loops.

A function decorated with :func:`formula` is plain Python over components (the x, y, z of a
direction, a cosine, a roughness), built from arithmetic and the few operations of this module:

    @formula
    def ndf_cos(cz, alpha):
        a2 = alpha * alpha
        d = cz * cz * (a2 - 1.0) + 1.0
        return where(cz > 0.0, a2 / (math.pi * d * d), 0.0)

- called with numpy arrays (or CuPy arrays, or torch tensors) it works elementwise on whole
  columns, in the array library of its inputs (``addon.core.xp``): that is how the BSDF classes,
  the reference walk and training run it;
- called from a compiled loop of ``addon.core.kernels`` it is compiled by numba with scalars, into
  that loop (``numba.extending.register_jitable``); the operations below then mean their scalar
  versions (``where(c, a, b)`` is ``a if c else b``).

So a formula is one implementation whichever runs it. What it may use: arithmetic, comparisons
combined with ``&``, ``|`` and :func:`negate` (never ``and``/``or``/``not``, which arrays do not support,
nor ``~``, which is -2 for Python's True), the
built-in ``abs``, ``math`` constants, and the operations here. Both sides of a ``where`` are
evaluated on arrays, so each must stay harmless where it is not selected (a division may give
inf or nan there; array callers silence numpy's warnings with ``np.errstate``, and the compiled
loops use numpy's error model). A formula returns a number or a tuple of numbers, never an array
it builds itself, so that the compiled loops allocate nothing.
"""

from __future__ import annotations

import math

import numpy as np
from numba.extending import overload, register_jitable

from .xp import namespace


def formula(fn):
    """Mark ``fn`` as a formula: unchanged for arrays and tensors, and compiled into the loops that
    call it (see the module docstring)."""
    return register_jitable(fn)


def where(c, a, b):
    """``a`` where ``c`` holds, else ``b`` (elementwise)."""
    return namespace(c, a, b).where(c, a, b)


def negate(c):
    """Logical not, elementwise (Python's ``~True`` is -2, so formulas use this, never ``~``)."""
    xp = namespace(c)
    return xp.logical_not(c) if xp is np else ~c


def sqrt(x):
    return namespace(x).sqrt(x)


def maximum(a, b):
    return namespace(a, b).maximum(a, b)


def minimum(a, b):
    return namespace(a, b).minimum(a, b)


def clip(x, lo, hi):
    return namespace(x).clip(x, lo, hi)


def cos(x):
    return namespace(x).cos(x)


def sin(x):
    return namespace(x).sin(x)


def isfinite(x):
    return namespace(x).isfinite(x)


def copysign(a, b):
    return namespace(a, b).copysign(a, b)


# --- the same operations on scalars, inside compiled loops -----------------------------------------


@overload(where)
def _where_scalar(c, a, b):
    return lambda c, a, b: a if c else b


@overload(negate)
def _negate_scalar(c):
    return lambda c: not c


@overload(sqrt)
def _sqrt_scalar(x):
    return lambda x: math.sqrt(x) if x >= 0.0 else math.nan


@overload(maximum)
def _maximum_scalar(a, b):  # numpy's: nan if either is nan
    return lambda a, b: a if (a >= b or a != a) else b


@overload(minimum)
def _minimum_scalar(a, b):
    return lambda a, b: a if (a <= b or a != a) else b


@overload(clip)
def _clip_scalar(x, lo, hi):
    return lambda x, lo, hi: lo if x < lo else (hi if x > hi else x)


@overload(cos)
def _cos_scalar(x):
    return lambda x: math.cos(x)


@overload(sin)
def _sin_scalar(x):
    return lambda x: math.sin(x)


@overload(isfinite)
def _isfinite_scalar(x):
    return lambda x: math.isfinite(x)


@overload(copysign)
def _copysign_scalar(a, b):
    return lambda a, b: math.copysign(a, b)

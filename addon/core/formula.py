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

# Rec. 709 luminance weights of linear R, G, B (Blender's scene-linear space): the sky's importance, and the grey
# value of a colour image driving a single-valued parameter (as Blender converts a colour to a number).
LUMINANCE = (0.2126, 0.7152, 0.0722)


def formula(fn=None, *, inline: bool = False):
    """Mark ``fn`` as a formula: unchanged for arrays and tensors, and compiled into the loops that
    call it (see the module docstring). LLVM decides whether a loop calls it or copies it in; with ``inline``
    numba copies it into every loop that calls it, before LLVM sees it: for a large formula that a hot loop
    called (``rough_dielectric_eval_pdf`` in ``kernels.decoded_brdf``: 105-110 ns a row in seven one-thread
    splits, where the call took 116-129 in six of seven and 105 in one; the add-on's first compile of every loop
    22.0 -> 23.3 s)."""
    if fn is None:
        return lambda f: formula(f, inline=inline)
    return register_jitable(inline="always")(fn) if inline else register_jitable(fn)


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


def arccos(x):
    return namespace(x).arccos(x)


def quarter_cos_sin(a):
    """(cos a, sin a) of an angle |a| <= pi / 4 (compiled: the Taylor series, no call into the C library)."""
    xp = namespace(a)
    return xp.cos(a), xp.sin(a)


def turn_cos_sin(u):
    """(cos, sin) of the angle 2 pi u (compiled: reduced to a quarter turn exactly, then the Taylor series)."""
    xp = namespace(u)
    phi = 2.0 * math.pi * u
    return xp.cos(phi), xp.sin(phi)


def isfinite(x):
    return namespace(x).isfinite(x)


def copysign(a, b):
    return namespace(a, b).copysign(a, b)


def node_below(x, last):
    """The integer node of an evenly spaced table at or below ``x`` >= 0 (in node units), at most ``last``; 0 for
    ``x`` below 0 or nan (elementwise: int64 for numpy or CuPy arrays, whose fancy indexing reads the table; an int
    inside the compiled loops)."""
    xp = namespace(x)
    return xp.where(x >= 0.0, xp.minimum(x, last), 0.0).astype(np.int64)  # x >= 0: truncation is floor


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


@overload(arccos)
def _arccos_scalar(x):
    return lambda x: math.acos(x)


# The Taylor series of cos and sin to a^16 / 16! and a^15 / 15! (the latter over a): at |a| <= pi / 4 the first
# terms left out are below 1.1e-15 (a^18 / 18!, a^17 / 17!), so the sums are within a few units in the last place.
_COS_TERMS = tuple((-1.0) ** k / math.factorial(2 * k) for k in range(9))
_SIN_TERMS = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(8))


@register_jitable
def _series_cos_sin(a):
    """cos and sin of |a| <= pi / 4 by :data:`_COS_TERMS` and :data:`_SIN_TERMS`, two chains of multiply-adds. The
    C library's ``sincos`` reduces its angle first, whatever it is: in the sky's light samples that call took 31
    of the 71 ns a sample took (``kernels._sample_environment``)."""
    a2 = a * a
    c = _COS_TERMS[8]
    for k in range(7, -1, -1):
        c = c * a2 + _COS_TERMS[k]
    s = _SIN_TERMS[7]
    for k in range(6, -1, -1):
        s = s * a2 + _SIN_TERMS[k]
    return c, a * s


@overload(quarter_cos_sin)
def _quarter_cos_sin_scalar(a):
    return lambda a: _series_cos_sin(a)


@register_jitable
def _turn_cos_sin(u):
    t = 4.0 * (u - math.floor(u))  # quarter turns, in [0, 4): exact
    q = math.floor(t)
    f = t - q  # exact, in [0, 1)
    upper = f > 0.5  # past the eighth: the series at the quarter's far end, cos and sin exchanged
    c, s = _series_cos_sin((1.0 - f if upper else f) * (math.pi / 2.0))
    if upper:
        c, s = s, c
    if q == 0.0:
        return c, s
    if q == 1.0:
        return -s, c
    if q == 2.0:
        return -c, -s
    return s, -c


@overload(turn_cos_sin)
def _turn_cos_sin_scalar(u):
    return lambda u: _turn_cos_sin(u)


@overload(isfinite)
def _isfinite_scalar(x):
    return lambda x: math.isfinite(x)


@overload(copysign)
def _copysign_scalar(a, b):
    return lambda a, b: math.copysign(a, b)


@overload(node_below)
def _node_below_scalar(x, last):  # nan fails both tests: node 0, never an index from int(nan)
    return lambda x, last: last if x >= last else (int(x) if x >= 0.0 else 0)

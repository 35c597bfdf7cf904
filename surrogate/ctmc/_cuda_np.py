"""The ``np`` the CUDA SSA's generated code sees: the scalar functions and constants that
:mod:`surrogate.ctmc.kinetics` and :mod:`surrogate.ctmc.events` emit as ``np.<name>``, mapped to
their ``math`` counterparts, which numba-cuda compiles in device code (it has no NumPy scalar
ufuncs there). Generated CPU and CUDA code thus come from one expression tree and one code
generator; only this namespace differs."""

from __future__ import annotations

import builtins
import math

import numpy
from numba import cuda

nan = math.nan
inf = math.inf
exp = math.exp
log = math.log
log10 = math.log10
log1p = math.log1p
sqrt = math.sqrt
sin = math.sin
cos = math.cos
tan = math.tan
arcsin = math.asin
arccos = math.acos
arctan = math.atan
sinh = math.sinh
cosh = math.cosh
tanh = math.tanh
abs = builtins.abs  # numba-cuda compiles the builtin for floats


#: from 2**52 on every float is a whole number (and ``math.floor``'s int64 would overflow
#: past 2**63): floor and ceil are the value itself there, NaN and the infinities included
WHOLE_FROM = 4503599627370496.0


@cuda.jit(device=True, inline=True)
def floor(x):
    """``np.floor``: a float, as NumPy's (``math.floor`` returns an int)."""
    return float(math.floor(x)) if abs(x) < WHOLE_FROM else x


@cuda.jit(device=True, inline=True)
def ceil(x):
    """``np.ceil``: a float, as NumPy's."""
    return float(math.ceil(x)) if abs(x) < WHOLE_FROM else x


# the dtypes the kernel template names (``np.float64`` ...)
float64 = numpy.float64
int64 = numpy.int64
bool_ = numpy.bool_

"""Scalar formulas written once, run over tensors and compiled per cell.

A formula is a plain Python function of scalars: arithmetic, comparisons, ``if``/``for`` on
plain ints and bools, calls of other formulas and of the primitives of this module (``exp``,
``log``, ``log1p``, ``expm1``, ``cos``, ``sin``, ``sigmoid``, ``where``, ``clamp``,
``clamp_min``, ``maximum``, ``minimum``, ``remainder``, ``to64``, ``f32``, ``flag``,
``choose``, ``complement_product``), taken
as globals. Its module imports the primitives from here, so its functions *are* the torch
versions (elementwise over tensors, Python floats as constants). :func:`numba_formulas`
re-binds the same code objects to the numba primitives and ``numba.njit``-s them (inlined into
the kernel that calls them): one source, two loops, the same operations in the same order.

The precision rule of both is torch's: a float32 tensor combined with a Python float stays
float32 (the float is rounded first). In numba a Python float literal is float64 and would
promote a float32 value, so a formula writes a literal that meets float32 values as
``f32(1.0)`` (a Python float in torch, ``np.float32`` in numba) and takes its constants as
arguments (the kernel passes them from a float32 array; torch callers pass Python floats).
Literals of float64 code (motor rates) and in comparisons may be written plainly.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import types
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import (
    Tensor,
    clamp,
    clamp_min,
    cos,
    exp,
    expm1,
    log,
    log1p,
    maximum,
    minimum,
    remainder,
    sigmoid,
    sin,
    where,
)

__all__ = [
    "choose",
    "clamp",
    "clamp_min",
    "complement_product",
    "cos",
    "exp",
    "expm1",
    "f32",
    "flag",
    "log",
    "log1p",
    "maximum",
    "minimum",
    "numba_formulas",
    "numba_primitives",
    "remainder",
    "renew_with",
    "sigmoid",
    "sin",
    "to64",
    "where",
]


# -- the torch primitives (the formulas' own globals): torch's, and these three ----------------
def to64(x: Tensor) -> Tensor:
    """``x`` in float64."""
    return x.to(torch.float64)


def f32(value: float) -> float:
    """A literal that meets float32 values (a Python float: torch rounds it to the tensor's
    dtype; numba's ``np.float32``)."""
    return value


def flag(condition: Tensor) -> Tensor:
    """A condition as float32 0/1."""
    return condition.to(torch.float32)


def complement_product(u: Tensor, lo: int, hi: int) -> Tensor:
    """The product of ``1 - u[j]`` for rows ``j`` from ``lo`` to ``hi - 1`` (at least one),
    in row order (torch's reduction along the rows is sequential, as numba's loop)."""
    return torch.prod(1.0 - u[lo:hi], dim=0)


def choose(index: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """``a``, ``b`` or ``c`` where ``index`` (float 0., 1., 2.; ``a``, ``b``, ``c`` broadcast
    along its first dimension) is 0, 1 or 2: a gather from the stacked choices eagerly (about
    twice as fast), ``where`` blends when compiled (SIMD lanes); the same values."""
    if torch.compiler.is_compiling():
        return torch.where(index == 0, a, torch.where(index == 1, b, c))
    return torch.stack([a, b, c]).gather(0, index.long())


PRIMITIVES = ("exp", "log", "log1p", "expm1", "cos", "sin", "sigmoid", "where", "clamp",
              "clamp_min", "maximum", "minimum", "remainder", "to64", "f32", "flag", "choose",
              "complement_product")  # fmt: skip

#: numba options of the compiled formulas (those of the kernels that inline them)
JIT_OPTIONS: dict[str, Any] = {"nogil": True, "fastmath": False, "error_model": "numpy"}


@functools.cache
def numba_primitives() -> dict[str, Any]:
    """The primitives as numba functions: the scalar code the per-cell kernels always had
    (float32 in, float32 out where the argument is float32)."""
    import numba

    jit = numba.njit(inline="always", **JIT_OPTIONS)

    def sigmoid(x):  # 1 / (1 + exp(-x)): float32
        return np.float32(1.0) / (np.float32(1.0) + np.exp(-x))

    def where(condition, a, b):
        return a if condition else b

    def clamp(value, lo, hi):  # torch.clamp: NaN passes through
        if value < lo:
            return lo
        if value > hi:
            return hi
        return value

    def clamp_min(value, lo):
        return max(value, lo)

    def maximum(a, b):
        return max(a, b)

    def minimum(a, b):
        return min(a, b)

    def remainder(a, b):  # torch.remainder for b > 0: fmod, then into [0, b)
        mod = np.fmod(a, b)
        return mod + b if mod < 0 else mod

    def flag(condition):
        return np.float32(1.0) if condition else np.float32(0.0)

    def complement_product(u, lo, hi):
        prod = np.float32(1.0) - u[lo]
        for j in range(lo + 1, hi):
            prod = prod * (np.float32(1.0) - u[j])
        return prod

    def choose(index, a, b, c):
        return a if index == 0 else (b if index == 1 else c)

    jitted = {f.__name__: jit(f) for f in (sigmoid, where, clamp, clamp_min, maximum, minimum,
                                           remainder, flag, choose, complement_product)}  # fmt: skip
    return {
        "exp": np.exp, "log": np.log, "log1p": np.log1p, "expm1": np.expm1, "cos": np.cos,
        "sin": np.sin, "to64": np.float64, "f32": np.float32, **jitted,
    }  # fmt: skip


def numba_formulas(
    functions: Iterable[Callable[..., Any]], constants: Mapping[str, Any] | None = None
) -> types.ModuleType:
    """``numba.njit``-ed (inlined) copies of ``functions`` (formulas of one module, callees
    before callers), each bound to the numba primitives, ``constants`` (ints, floats: the
    module's index names) and the other copies, in place of its module's globals; returned
    as a module (which numba code reads as ``module.name``)."""
    import numba

    functions = list(functions)
    namespace: dict[str, Any] = {"__name__": functions[0].__module__, **dict(constants or {})}
    namespace |= numba_primitives()
    jit = numba.njit(inline="always", **JIT_OPTIONS)
    out = {}
    for f in functions:
        code = types.FunctionType(f.__code__, namespace, f.__name__, f.__defaults__, f.__closure__)
        namespace[f.__name__] = out[f.__name__] = jit(code)
    module = types.ModuleType(f"{namespace['__name__']}[numba]")
    module.__dict__.update(out)
    return module


def renew_with(dispatchers: Iterable[Any], modules: Iterable[types.ModuleType]) -> None:
    """Make numba's on-disk cache of ``dispatchers`` (``cache=True`` functions) stale when
    the source of ``modules`` changes, as it is when their own file changes: numba stamps a
    cached function with its own file only, not with the files of the formulas it inlines.
    (Where numba's cache internals differ, nothing is done.)"""
    digest = hashlib.sha256(b"".join(Path(inspect.getfile(m)).read_bytes() for m in modules))
    for dispatcher in dispatchers:
        try:
            cache_file = dispatcher._cache._cache_file
            cache_file._source_stamp = (cache_file._source_stamp, digest.hexdigest())
        except AttributeError:
            pass

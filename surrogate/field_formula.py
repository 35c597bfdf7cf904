"""Field formulas: L(x, y, t) as a validated expression tree, compiled to torch and to numba.

A formula is SBML Level 3 infix text (``"0.1 * exp(-0.5 * ((x - 1)^2 + y^2) / 3)"``) read by
:func:`surrogate.sbml.formula.parse_formula` into the same whitelisted
:class:`~surrogate.ctmc.kinetics.Expr` trees as the SBML kinetics, over the variables ``x``,
``y`` (mm), ``t`` (s), the field's peak ``peak_x``, ``peak_y`` (mm) and its named parameters;
beyond SBML's functions it may call ``hypot(a, b)`` (the norm of (a, b), as torch's
``vector_norm``). From the one tree we generate

* a torch function ``field(position (n, 2) float32, t, params) -> (n,) float32`` and
* scalar numba code of ``x``, ``y`` (float32), ``t`` and ``row`` (the float64 parameters,
  ``row[1 + k]`` the ``k``-th of :attr:`FieldFormula.parameters`) -> float32, one branch of
  a generated dispatcher on the row's formula index (:func:`dispatcher_source`).

Both keep one precision rule, the torch fields' own: a subtree of the parameters and ``t``
only is computed in float64 (Python floats in torch, float64 in numba) and rounded to float32
where it meets a subtree of the position, which is float32 throughout (as a float32 tensor
times a Python float). So a built-in field written in the same operation order as its torch
code computes exactly the same numbers on the torch path. (One difference: a division by
zero or an overflow in such a scalar subtree raises in Python, where numba gives inf or nan.)
No ``eval``/``exec``: the source
holds only our templates, indices and ``repr`` of floats (see :mod:`surrogate.ctmc.codegen`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache

from torch import Tensor

from surrogate.ctmc.expr import (
    BOOL,
    OPERATORS,
    Expr,
    combine_scalar,
    const,
    input_ref,
    substitute,
)
from surrogate.errors import ConfigError

__all__ = ["VARIABLES", "FieldFormula", "dispatcher_source", "field_formula"]

#: the formula's variables: position (mm) and time (s)
VARIABLES = ("x", "y", "t")
#: parameters every formula has: the field's peak (mm)
PEAK_PARAMETERS = ("peak_x", "peak_y")
#: functions a formula may call beyond SBML's, as operators of the kinetics whitelist
EXTRA_FUNCTIONS = {"hypot": "hypot"}

_X, _Y, _T, _FIRST_PARAMETER = 0, 1, 2, 3
_MATH = {  # torch-side scalars are Python floats: the math module's names of the unary ops
    "exp": "math.exp", "ln": "math.log", "log10": "math.log10", "sqrt": "math.sqrt",
    "abs": "abs", "floor": "math.floor", "ceiling": "math.ceil", "sin": "math.sin",
    "cos": "math.cos", "tan": "math.tan", "arcsin": "math.asin", "arccos": "math.acos",
    "arctan": "math.atan", "sinh": "math.sinh", "cosh": "math.cosh", "tanh": "math.tanh",
}  # fmt: skip


def _is_cell(e: Expr) -> bool:
    """Whether ``e`` reads the position (x or y): a per-cell float32 value."""
    return bool({_X, _Y} & e.inputs_used())


# -- scalar code: parameters p<k> and time p2, float64 -------------------------------------------
def _scalar(e: Expr, lib: str) -> str:
    """Scalar code of a subtree without x, y; ``lib`` ``"math"`` (Python floats, the torch
    function) or ``"np"`` (numba float64)."""
    if e.op == "const":
        if e.kind == BOOL:
            return "True" if e.value else "False"
        value = float(e.value)
        if math.isnan(value) or math.isinf(value):
            name = "nan" if math.isnan(value) else "inf"
            return f"({'-' if value < 0 else ''}{lib}.{name})"
        return repr(value)
    if e.op == "input":
        return f"p{e.index}"
    args = [_scalar(a, lib) for a in e.args]
    spec = OPERATORS[e.op]
    combined = combine_scalar(e.op, args)
    if combined is not None:
        return combined
    if e.op == "hypot":
        return f"{lib}.sqrt({args[0]} * {args[0]} + {args[1]} * {args[1]})"
    if e.op in _MATH:
        return f"{_MATH[e.op]}({args[0]})" if lib == "math" else spec.numba.format(*args)
    return spec.numba.format(*args)


# -- per-cell code: float32 ----------------------------------------------------------------------
_BINARY = {"plus": "+", "times": "*", "minus": "-", "divide": "/"}
_COMPARE = {"lt": "<", "leq": "<=", "gt": ">", "geq": ">=", "eq": "==", "neq": "!="}
#: exponents torch's pow computes by multiplication or sqrt (pow_tensor_scalar_optimized)
_NUMBA_POWERS = {2.0: "({0} * {0})", 3.0: "({0} * {0} * {0})", 0.5: "np.sqrt({0})",
                 -1.0: "(np.float32(1.0) / {0})", -2.0: "(np.float32(1.0) / ({0} * {0}))",
                 -0.5: "(np.float32(1.0) / np.sqrt({0}))"}  # fmt: skip


def _is_plus_zero(e: Expr) -> bool:
    if not e.is_const or e.kind == BOOL or e.value != 0.0:
        return False
    return math.copysign(1.0, float(e.value)) > 0


@dataclass(frozen=True)
class _Code:
    """Code of a subtree for one target: per cell (float32 tensor / scalar) or float64."""

    text: str
    cell: bool
    kind: str  # "real" or "bool"


class _Emitter:
    """Emits the code of a tree for ``target`` ``"torch"`` or ``"numba"``."""

    def __init__(self, target: str) -> None:
        self.target = target
        self.lib = "math" if target == "torch" else "np"

    def full(self, code: _Code) -> str:
        """``code`` as per-cell code (a float64 scalar rounded to float32, or a full tensor)."""
        if code.cell:
            return code.text
        if self.target == "numba":
            return code.text if code.kind == BOOL else f"np.float32({code.text})"
        dtype = "torch.bool" if code.kind == BOOL else "x.dtype"
        return f"torch.full(x.shape, {code.text}, dtype={dtype}, device=x.device)"

    def operand(self, code: _Code) -> str:
        """An operand of an arithmetic operator beside a per-cell one."""
        if code.cell or code.kind == BOOL:
            return code.text
        return f"float({code.text})" if self.target == "torch" else f"np.float32({code.text})"

    def emit(self, e: Expr) -> _Code:  # noqa: C901  # one branch per node kind
        if not _is_cell(e):
            return _Code(_scalar(e, self.lib), False, e.kind)
        if e.op == "input":
            return _Code("x" if e.index == _X else "y", True, e.kind)
        args = [self.emit(a) for a in e.args]
        torch = self.target == "torch"
        if e.op in _BINARY or e.op in _COMPARE:  # left to right, as Python evaluates a + b + c
            symbol = _BINARY.get(e.op) or _COMPARE[e.op]
            code = args[0]
            for arg, tree in zip(args[1:], e.args[1:], strict=True):
                if e.op == "minus" and code.cell and _is_plus_zero(tree):
                    continue  # a - (+0.0) is a, bit for bit (the peak at the origin)
                if code.cell or arg.cell:
                    text = f"({self.operand(code)} {symbol} {self.operand(arg)})"
                    code = _Code(text, True, e.kind)
                else:
                    code = _Code(f"({code.text} {symbol} {arg.text})", False, e.kind)
            return code
        if e.op == "negate":
            return _Code(f"(-{args[0].text})", True, e.kind)
        if e.op == "power":
            base, exponent = args
            if not exponent.cell and e.args[1].is_const:
                value = float(e.args[1].value)
                if torch:  # the constant's code: inf and nan are not Python names
                    return _Code(f"({base.text} ** {_scalar(e.args[1], 'math')})", True, e.kind)
                if value in _NUMBA_POWERS:
                    return _Code(_NUMBA_POWERS[value].format(base.text), True, e.kind)
            if torch and not base.cell:
                return _Code(f"torch.pow({base.text}, {exponent.text})", True, e.kind)
            return _Code(f"({self.operand(base)} ** {self.operand(exponent)})", True, e.kind)
        if e.op in ("min", "max"):
            code = args[0]
            for arg in args[1:]:
                code = self._extremum(e.op, code, arg)
            return code
        if e.op == "hypot":
            a, b = (self.full(arg) for arg in args)
            if torch:
                text = f"torch.linalg.vector_norm(torch.stack([{a}, {b}], -1), dim=-1)"
            else:
                text = f"_hypot({a}, {b})"
            return _Code(text, True, e.kind)
        if e.op in ("and", "or", "xor"):
            if torch:
                text = self.full(args[0])
                for arg in args[1:]:
                    text = f"torch.logical_{e.op}({text}, {self.full(arg)})"
                return _Code(text, True, e.kind)
            symbol = "!=" if e.op == "xor" else e.op
            return _Code("(" + f" {symbol} ".join(a.text for a in args) + ")", True, e.kind)
        if e.op == "not":
            text = f"torch.logical_not({args[0].text})" if torch else f"(not {args[0].text})"
            return _Code(text, True, e.kind)
        if e.op == "piecewise":
            text = self.full(args[-1])
            for k in range(len(args) - 3, -1, -2):
                then, cond = self.full(args[k]), args[k + 1]
                if torch:
                    text = f"torch.where({self.full(cond)}, {then}, {text})"
                else:
                    text = f"({then} if {cond.text} else {text})"
            return _Code(text, True, e.kind)
        # a unary function: torch.<fn>(a) / np.<fn>(a), float32 in and out
        spec = OPERATORS[e.op]
        return _Code((spec.torch if torch else spec.numba).format(args[0].text), True, e.kind)

    def _extremum(self, op: str, a: _Code, b: _Code) -> _Code:
        if not (a.cell or b.cell):
            return _Code(f"{op}({a.text}, {b.text})", False, a.kind)
        if self.target == "numba":
            return _Code(f"{op}({self.operand(a)}, {self.operand(b)})", True, a.kind)
        if a.cell and b.cell:
            return _Code(f"torch.{op}imum({a.text}, {b.text})", True, a.kind)
        cell, scalar = (a, b) if a.cell else (b, a)  # clamp, as Tensor.clamp_min(floor)
        bound = "clamp_min" if op == "max" else "clamp_max"
        return _Code(f"torch.{bound}({cell.text}, float({scalar.text}))", True, a.kind)


@dataclass(frozen=True, eq=False)
class FieldFormula:
    """A field's formula, parsed and checked; its generated code.

    Attributes:
        text: The formula as written.
        parameters: Names of its parameters in row order: ``peak_x``, ``peak_y``, then the
            field's named parameters.
        expr: The validated tree: inputs 0, 1, 2 are x, y, t; input ``3 + k`` parameter ``k``.
    """

    text: str
    parameters: tuple[str, ...]
    expr: Expr
    _cache: dict = field(default_factory=dict, repr=False)

    def _prologue(self, lib: str, expr: Expr) -> list[str]:
        used = sorted(expr.inputs_used() - {_X, _Y})
        read = {_T: "t"}
        for k in range(len(self.parameters)):
            read[_FIRST_PARAMETER + k] = f"params[{k}]" if lib == "math" else f"row[{1 + k}]"
        return [f"    p{j} = {read[j]}" for j in used]

    def torch_source(self, at_origin: bool = False) -> str:
        """Source of ``field(position, t, params)``: (n, 2) float32 positions, the time (s)
        and the parameter values (floats, in the order of :attr:`parameters`) -> (n,).
        ``at_origin``: for a peak at (0, 0) (``x - peak_x`` is ``x``: two operations less)."""
        expr = self.expr
        if at_origin:
            expr = substitute(expr, {name: const(0.0) for name in PEAK_PARAMETERS})
        emitter = _Emitter("torch")
        lines = [
            "def field(position, t, params):",
            "    x = position[..., 0]",
            "    y = position[..., 1]",
            *self._prologue("math", expr),
            f"    return {emitter.full(emitter.emit(expr))}",
            "",
        ]
        return "\n".join(lines)

    def numba_lines(self, indent: str = "    ") -> list[str]:
        """Body of a scalar numba function of ``x``, ``y`` (float32), ``t`` (float64) and the
        packed float64 ``row`` (``row[1 + k]`` parameter ``k``) returning L (float32)."""
        emitter = _Emitter("numba")
        lines = [line.strip() for line in self._prologue("np", self.expr)]
        lines.append(f"return {emitter.full(emitter.emit(self.expr))}")
        return [indent + line for line in lines]

    def numba_source(self, name: str) -> str:
        """Source of a standalone ``name(x, y, t, row)`` (see :meth:`numba_lines`)."""
        return "\n".join([f"def {name}(x, y, t, row):", *self.numba_lines(), ""])

    def torch_function(
        self, at_origin: bool = False
    ) -> Callable[[Tensor, float, Sequence[float]], Tensor]:
        """The generated torch function of :meth:`torch_source` (loaded once)."""
        fn = self._cache.get(at_origin)
        if fn is None:
            from surrogate.ctmc.codegen import load_generated

            source = "import math\n\nimport torch\n\n\n" + self.torch_source(at_origin)
            fn = self._cache[at_origin] = load_generated(source, prefix="field").field
        return fn


@lru_cache(maxsize=256)
def field_formula(
    text: str, parameters: tuple[str, ...] = (), where: str = "field.expression"
) -> FieldFormula:
    """Parse ``text`` over x, y, t, ``peak_x``, ``peak_y`` and ``parameters``.

    Raises:
        ConfigError: unparsable text, an unknown name or function (named), a condition where
            a number is needed, or a parameter named like a variable.
    """
    from surrogate.sbml.formula import parse_formula

    names = (*PEAK_PARAMETERS, *parameters)
    clash = sorted(set(parameters) & {*VARIABLES, *PEAK_PARAMETERS})
    if clash or len(set(names)) != len(names):
        raise ConfigError(
            f"{where}: parameter names must be unique and not {[*VARIABLES, *PEAK_PARAMETERS]}"
            f", got {list(parameters)}"
        )
    symbols = {name: input_ref(k, name) for k, name in enumerate(VARIABLES)}
    symbols |= {name: input_ref(_FIRST_PARAMETER + k, name) for k, name in enumerate(names)}
    expr = parse_formula(
        text, symbols, where, "real", what="variable or parameter", operators=EXTRA_FUNCTIONS
    )
    return FieldFormula(text=text, parameters=names, expr=expr)


def dispatcher_source(formulas: Sequence[FieldFormula], jit_options: str) -> str:
    """Source of a module with ``field(fields, row, x, y, t)``: formula ``int(row[0])`` at
    ``x``, ``y`` (float32), ``t`` (float64), float32; a plain function (the implementation of
    :func:`surrogate.field_kernel.field_value`, which numba compiles into the kernel, inlined),
    every formula's code in one branch of it."""
    lines = [
        "import numba",
        "import numpy as np",
        "",
        f"_JIT = {jit_options}",
        "",
        "",
        "@numba.njit(inline='always', **_JIT)",
        "def _hypot(a, b):",
        "    return np.sqrt(a * a + b * b)",
        "",
        "",
        "def field(fields, row, x, y, t):",
        "    k = int(row[0])",
    ]
    for k, formula in enumerate(formulas[:-1]):
        lines += [f"    if k == {k}:", *formula.numba_lines("        ")]
    lines += [*formulas[-1].numba_lines("    "), ""]
    return "\n".join(lines)

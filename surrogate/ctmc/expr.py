"""Expressions of general kinetics: validated trees, folded as built, compiled twice.

The trees of :mod:`surrogate.ctmc.kinetics` (one per propensity, rule or event): built only from
the operators in ``OPERATORS``, every node type-checked (real or boolean), constant subtrees
folded; from one tree we generate a torch function (vectorised over cells, any device) and
scalar numba code for the compiled SSA. See :mod:`surrogate.ctmc.kinetics` for why the tree is
hand-written.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from torch import Tensor

__all__ = [
    "OPERATORS",
    "Expr",
    "call",
    "combine_scalar",
    "const",
    "input_ref",
    "scalar_code",
    "scalar_locals",
    "species_ref",
    "substitute",
    "time_ref",
    "torch_function",
]


REAL, BOOL = "real", "bool"


@dataclass(frozen=True)
class _Op:
    """One operator: arity (``None``: variadic, at least ``min_args``), argument / result types,
    the folding function on float64 scalars and the torch / numba code templates."""

    min_args: int
    max_args: int | None
    arg_kind: str  # REAL, BOOL or "any" (comparisons of reals; piecewise checks itself)
    kind: str
    fold: Callable[..., float | bool]
    torch: str  # format string over {0}, {1}, ... or a special name
    numba: str


def _np1(fn: Callable[[np.float64], np.float64]) -> Callable[[float], float]:
    def folded(x: float) -> float:
        with np.errstate(all="ignore"):
            return float(fn(np.float64(x)))

    return folded


def _pow(a: float, b: float) -> float:
    with np.errstate(all="ignore"):
        return float(np.power(np.float64(a), np.float64(b)))


def _div(a: float, b: float) -> float:
    with np.errstate(all="ignore"):
        return float(np.float64(a) / np.float64(b))


_UNARY_NP = {
    "exp": np.exp,
    "ln": np.log,
    "log10": np.log10,
    "sqrt": np.sqrt,
    "abs": np.abs,
    "floor": np.floor,
    "ceiling": np.ceil,
    "sin": np.sin,
    "cos": np.cos,
    "tan": np.tan,
    "arcsin": np.arcsin,
    "arccos": np.arccos,
    "arctan": np.arctan,
    "sinh": np.sinh,
    "cosh": np.cosh,
    "tanh": np.tanh,
}
_UNARY_TORCH = {
    "exp": "exp",
    "ln": "log",
    "log10": "log10",
    "sqrt": "sqrt",
    "abs": "abs",
    "floor": "floor",
    "ceiling": "ceil",
    "sin": "sin",
    "cos": "cos",
    "tan": "tan",
    "arcsin": "asin",
    "arccos": "acos",
    "arctan": "atan",
    "sinh": "sinh",
    "cosh": "cosh",
    "tanh": "tanh",
}
_UNARY_NUMBA = {
    "exp": "exp",
    "ln": "log",
    "log10": "log10",
    "sqrt": "sqrt",
    "abs": "abs",
    "floor": "floor",
    "ceiling": "ceil",
    "sin": "sin",
    "cos": "cos",
    "tan": "tan",
    "arcsin": "arcsin",
    "arccos": "arccos",
    "arctan": "arctan",
    "sinh": "sinh",
    "cosh": "cosh",
    "tanh": "tanh",
}

OPERATORS: dict[str, _Op] = {
    "plus": _Op(1, None, REAL, REAL, lambda *a: math.fsum(a), "+", "+"),
    "times": _Op(1, None, REAL, REAL, lambda *a: math.prod(a), "*", "*"),
    "minus": _Op(2, 2, REAL, REAL, lambda a, b: a - b, "({0} - {1})", "({0} - {1})"),
    "negate": _Op(1, 1, REAL, REAL, lambda a: -a, "(-{0})", "(-{0})"),
    "divide": _Op(2, 2, REAL, REAL, _div, "({0} / {1})", "({0} / {1})"),
    "power": _Op(2, 2, REAL, REAL, _pow, "({0} ** {1})", "({0} ** {1})"),
    "min": _Op(1, None, REAL, REAL, min, "minimum", "min"),
    "max": _Op(1, None, REAL, REAL, max, "maximum", "max"),
    **{
        name: _Op(
            1,
            1,
            REAL,
            REAL,
            _np1(fn),
            f"torch.{_UNARY_TORCH[name]}({{0}})",
            f"np.{_UNARY_NUMBA[name]}({{0}})",
        )
        for name, fn in _UNARY_NP.items()
    },
    # the Euclidean norm of (a, b), as torch's vector_norm of the pair (the fields' distance)
    "hypot": _Op(
        2,
        2,
        REAL,
        REAL,
        lambda a, b: float(np.sqrt(np.float64(a) * a + np.float64(b) * b)),
        "torch.linalg.vector_norm(torch.stack([{0}, {1}], -1), dim=-1)",
        "np.sqrt({0} * {0} + {1} * {1})",
    ),
    "lt": _Op(2, 2, REAL, BOOL, lambda a, b: a < b, "({0} < {1})", "({0} < {1})"),
    "leq": _Op(2, 2, REAL, BOOL, lambda a, b: a <= b, "({0} <= {1})", "({0} <= {1})"),
    "gt": _Op(2, 2, REAL, BOOL, lambda a, b: a > b, "({0} > {1})", "({0} > {1})"),
    "geq": _Op(2, 2, REAL, BOOL, lambda a, b: a >= b, "({0} >= {1})", "({0} >= {1})"),
    "eq": _Op(2, 2, REAL, BOOL, lambda a, b: a == b, "({0} == {1})", "({0} == {1})"),
    "neq": _Op(2, 2, REAL, BOOL, lambda a, b: a != b, "({0} != {1})", "({0} != {1})"),
    "and": _Op(1, None, BOOL, BOOL, lambda *a: all(a), "logical_and", "and"),
    "or": _Op(1, None, BOOL, BOOL, lambda *a: any(a), "logical_or", "or"),
    "xor": _Op(1, None, BOOL, BOOL, lambda *a: sum(a) % 2 == 1, "logical_xor", "!="),
    "not": _Op(1, 1, BOOL, BOOL, lambda a: not a, "torch.logical_not({0})", "(not {0})"),
    # piecewise(v1, c1, v2, c2, ..., otherwise): args checked by ``call`` itself.
    "piecewise": _Op(1, None, "any", REAL, lambda *a: math.nan, "piecewise", "piecewise"),
}


@dataclass(frozen=True)
class Expr:
    """A node of a propensity expression. Build with :func:`const`, :func:`species_ref`,
    :func:`input_ref` and :func:`call` (which check and fold), not directly.

    Attributes:
        op: ``"const"``, ``"species"``, ``"input"``, ``"time"`` or a key of ``OPERATORS``.
        args: Child nodes (operators only).
        value: The value of a constant (a bool for boolean constants).
        index: Column of a species (in the state) or an input (in the inputs).
        name: Species or input name (for messages and readable code).
        kind: ``"real"`` or ``"bool"``.
    """

    op: str
    args: tuple[Expr, ...] = ()
    value: float | bool = 0.0
    index: int = -1
    name: str = ""
    kind: str = REAL

    @property
    def is_const(self) -> bool:
        """True for a constant leaf (every constant subtree is folded into one)."""
        return self.op == "const"

    def evaluate(
        self, species: Sequence[float], inputs: Sequence[float], time: float = math.nan
    ) -> float | bool:
        """Evaluate at one state (and ``time``, for the time leaf) with plain float64 scalar
        arithmetic (a reference, not fast)."""
        if self.op == "const":
            return self.value
        if self.op == "species":
            return float(species[self.index])
        if self.op == "input":
            return float(inputs[self.index])
        if self.op == "time":
            return float(time)
        if self.op == "piecewise":
            pieces = self.args
            for k in range(0, len(pieces) - 1, 2):
                if pieces[k + 1].evaluate(species, inputs, time):
                    return pieces[k].evaluate(species, inputs, time)
            return pieces[-1].evaluate(species, inputs, time) if len(pieces) % 2 else math.nan
        values = [arg.evaluate(species, inputs, time) for arg in self.args]
        return OPERATORS[self.op].fold(*values)

    def uses_time(self) -> bool:
        """True if the time leaf occurs in this expression."""
        return self.op == "time" or any(arg.uses_time() for arg in self.args)

    def species_used(self) -> set[int]:
        """Columns of the species this expression reads."""
        if self.op == "species":
            return {self.index}
        return set().union(*(arg.species_used() for arg in self.args)) if self.args else set()

    def inputs_used(self) -> set[int]:
        """Columns of the inputs this expression reads."""
        if self.op == "input":
            return {self.index}
        return set().union(*(arg.inputs_used() for arg in self.args)) if self.args else set()


def const(value: float | bool) -> Expr:
    """A real (or, for a Python bool, boolean) constant."""
    if isinstance(value, (bool, np.bool_)):
        return Expr("const", value=bool(value), kind=BOOL)
    return Expr("const", value=float(value))


def species_ref(index: int, name: str) -> Expr:
    """The count of species ``name`` (state column ``index``), as a real number."""
    if index < 0:
        raise ValueError(f"species {name!r}: column must be >= 0, got {index}")
    return Expr("species", index=index, name=name)


def input_ref(index: int, name: str) -> Expr:
    """The per-cell input ``name`` (inputs column ``index``)."""
    if index < 0:
        raise ValueError(f"input {name!r}: column must be >= 0, got {index}")
    return Expr("input", index=index, name=name)


def time_ref() -> Expr:
    """The network's time (a cell's own clock; only event triggers may use it, in comparisons
    with expressions free of time, see :mod:`surrogate.ctmc.events`)."""
    return Expr("time", name="time")


def call(op: str, *args: Expr) -> Expr:  # noqa: C901  # one branch per operator family
    """Apply operator ``op`` (a key of ``OPERATORS``) to ``args``; type-checks and folds.

    Raises:
        ValueError: unknown operator, wrong number of arguments, or an argument of the wrong
            kind (e.g. a boolean added to a number); the message names the operator.
    """
    spec = OPERATORS.get(op)
    if spec is None:
        raise ValueError(f"unknown operator {op!r}; known: {sorted(OPERATORS)}")
    n = len(args)
    if n < spec.min_args or (spec.max_args is not None and n > spec.max_args):
        most = "any number of" if spec.max_args is None else f"at most {spec.max_args}"
        raise ValueError(
            f"operator {op!r} takes at least {spec.min_args} and {most} arguments, got {n}"
        )
    if op == "piecewise":
        for k, arg in enumerate(args):
            want = BOOL if (k % 2 == 1 and not (n % 2 == 1 and k == n - 1)) else REAL
            if arg.kind != want:
                raise ValueError(f"piecewise argument {k} must be {want}, got {arg.kind}")
        return _fold_piecewise(args)
    if spec.arg_kind != "any":
        for k, arg in enumerate(args):
            if arg.kind != spec.arg_kind:
                raise ValueError(
                    f"operator {op!r} argument {k} must be {spec.arg_kind}, got {arg.kind}"
                )
    if all(arg.is_const for arg in args):
        return const(spec.fold(*(arg.value for arg in args)))
    if op in ("and", "or"):
        absorbing = op == "or"  # True absorbs 'or', False absorbs 'and'
        rest = []
        for arg in args:
            if arg.is_const:
                if arg.value == absorbing:
                    return const(absorbing)
                continue  # the neutral constant drops out
            rest.append(arg)
        if len(rest) == 1:
            return rest[0]
        args = tuple(rest)
    if n == 1 and op in ("plus", "times", "min", "max"):
        return args[0]
    return Expr(op, args=tuple(args), kind=spec.kind)


def _fold_piecewise(args: Sequence[Expr]) -> Expr:
    """Drop pieces whose condition is constant False; stop at the first constant True."""
    pieces: list[Expr] = []
    otherwise = args[-1] if len(args) % 2 == 1 else const(math.nan)
    for k in range(0, len(args) - 1, 2):
        value, cond = args[k], args[k + 1]
        if cond.is_const:
            if cond.value:
                otherwise = value
                break
            continue
        pieces += [value, cond]
    if not pieces:
        return otherwise
    return Expr("piecewise", args=(*pieces, otherwise), kind=REAL)


# ----------------------------------------------------------------------------------------------
# code generation


def _float_literal(value: float) -> str:
    """Python source for a float constant, NaN and +-inf included (``repr`` gives the bare
    names ``nan`` and ``inf``, which are not defined in generated code)."""
    if math.isnan(value):
        return "float('nan')"
    if math.isinf(value):
        return "float('inf')" if value > 0 else "(-float('inf'))"
    return repr(value)


def _torch_code(e: Expr, tensor: bool = False) -> str:
    """Torch expression over ``x`` (n, S) float64 and ``p`` (n, P) float64; ``_z`` is an
    (n,) float64 zero vector used to turn constants into tensors where torch needs one."""
    if e.op == "const":
        if e.kind == BOOL:
            return "(_z == 0)" if e.value else "(_z != 0)"
        text = _float_literal(float(e.value))
        return f"(_z + {text})" if tensor else f"({text})"
    if e.op == "species":
        return f"x[:, {e.index}]"
    if e.op == "input":
        return f"p[:, {e.index}]"
    if e.op == "time":
        return "t"
    spec = OPERATORS[e.op]
    if e.op in ("plus", "times"):
        return "(" + f" {spec.torch} ".join(_torch_code(a) for a in e.args) + ")"
    if e.op in ("min", "max", "and", "or", "xor"):
        code = _torch_code(e.args[0], tensor=True)
        for arg in e.args[1:]:
            code = f"torch.{spec.torch}({code}, {_torch_code(arg, tensor=True)})"
        return code
    if e.op == "piecewise":
        code = _torch_code(e.args[-1], tensor=True)
        for k in range(len(e.args) - 3, -1, -2):
            value = _torch_code(e.args[k], tensor=True)
            code = f"torch.where({_torch_code(e.args[k + 1], tensor=True)}, {value}, {code})"
        return code
    return spec.torch.format(
        *(_torch_code(a, tensor=spec.torch.startswith("torch.")) for a in e.args)
    )


def _numba_code(e: Expr) -> str:
    """Scalar numba expression over locals ``s<j>`` (species, float) and ``p<j>`` (inputs)."""
    if e.op == "const":
        if e.kind == BOOL:
            return "True" if e.value else "False"
        value = float(e.value)
        if math.isnan(value):
            return "np.nan"
        if math.isinf(value):
            return "np.inf" if value > 0 else "(-np.inf)"
        return repr(value)
    if e.op == "species":
        return f"s{e.index}"
    if e.op == "input":
        return f"p{e.index}"
    if e.op == "time":
        return "t"
    args = [_numba_code(a) for a in e.args]
    combined = combine_scalar(e.op, args)
    return combined if combined is not None else OPERATORS[e.op].numba.format(*args)


def combine_scalar(op: str, args: Sequence[str]) -> str | None:
    """Scalar code of the n-ary operators (``plus``, ``times``, ``and``, ``or``, ``xor``,
    ``min``, ``max``, ``piecewise``) over their arguments' code; None for the others (their
    ``OPERATORS[op].numba`` template). One place for every scalar code generator."""
    spec = OPERATORS[op]
    if op in ("plus", "times", "and", "or", "xor"):
        return "(" + f" {spec.numba} ".join(args) + ")"
    if op in ("min", "max"):
        code = args[0]
        for arg in args[1:]:
            code = f"{spec.numba}({code}, {arg})"
        return code
    if op == "piecewise":
        code = args[-1]
        for k in range(len(args) - 3, -1, -2):
            code = f"({args[k]} if {args[k + 1]} else {code})"
        return code
    return None


def torch_source(exprs: Sequence[Expr], name: str = "propensities", time: bool = False) -> str:
    lines = [
        f"def {name}(state, inputs{', t' if time else ''}):",
        "    x = state.to(torch.float64)",
        "    p = inputs.to(device=state.device, dtype=torch.float64)",
        "    _z = torch.zeros(state.shape[0], dtype=torch.float64, device=state.device)",
        "    return torch.stack([",
    ]
    lines += [f"        {_torch_code(e, tensor=True)}," for e in exprs]
    lines += ["    ], dim=1)", ""]
    return "\n".join(lines)


def scalar_code(e: Expr) -> str:
    """Scalar numba code of ``e`` over the locals of :func:`scalar_locals` (and ``t``, the
    time)."""
    return _numba_code(e)


def scalar_locals(exprs: Sequence[Expr], indent: str = "    ") -> list[str]:
    """Lines binding the locals ``s<j> = float(x[j])`` and ``p<j> = p[j]`` that ``exprs`` read
    (``x`` one cell's counts, ``p`` its inputs), for :func:`scalar_code`."""
    used_s = sorted(set().union(set(), *(e.species_used() for e in exprs)))
    used_p = sorted(set().union(set(), *(e.inputs_used() for e in exprs)))
    lines = [f"{indent}s{j} = float(x[{j}])" for j in used_s]
    return lines + [f"{indent}p{j} = p[{j}]" for j in used_p]


def numba_source(exprs: Sequence[Expr], name: str = "propensities") -> str:
    lines = [f"def {name}(x, p, a):", *scalar_locals(exprs)]
    lines += [f"    a[{r}] = {_numba_code(e)}" for r, e in enumerate(exprs)]
    lines += ["", ""]
    return "\n".join(lines)


def substitute(e: Expr, bindings: Mapping[str, Expr]) -> Expr:
    """Replace every input leaf whose name is in ``bindings`` (re-folding on the way up)."""
    if e.op == "input":
        return bindings.get(e.name, e)
    if not e.args:
        return e
    return call(e.op, *(substitute(a, bindings) for a in e.args))


def torch_function(exprs: Sequence[Expr], time: bool = False) -> Callable[..., Tensor]:
    """``f(state (n, S), inputs (n, P)) -> (n, K)``: the values of ``exprs`` per cell.

    The same code generation as the propensities (from the validated trees only; no ``eval``),
    for expressions of one kind: real ones give float64 columns, conditions (e.g. a lump
    property over species counts) bool columns. Loaded once per distinct source.

    Args:
        exprs: ``K`` expressions over species columns of ``state`` and inputs columns.
        time: The expressions may read the time leaf: ``f(state, inputs, t)`` with ``t`` the
            ``(n,)`` float64 time of each cell.

    Example:
        >>> from surrogate.ctmc.kinetics import call, const, species_ref, torch_function
        >>> run = call("geq", species_ref(1, "N"), const(2.0))
        >>> torch_function([run])(torch.tensor([[0, 3], [1, 1]]), torch.zeros(2, 0))[:, 0]
        tensor([ True, False])
    """
    exprs = tuple(exprs)
    kinds = {e.kind for e in exprs}
    if not exprs or len(kinds) != 1:
        raise ValueError(f"need one or more expressions of one kind, got kinds {sorted(kinds)}")
    from surrogate.ctmc.codegen import load_generated

    if not time and any(e.uses_time() for e in exprs):
        raise ValueError("an expression reads the time; build the function with time=True")
    source = "import torch\n\n\n" + torch_source(exprs, "columns", time)
    return load_generated(source, prefix="columns").columns

"""libsbml MathML ASTs -> validated :class:`~surrogate.ctmc.kinetics.Expr` trees.

Every node type is mapped explicitly; any other node (delay, time, rateOf, factorial of a
variable, quotient/rem, lambda outside a function definition, distribution functions, ...)
raises :class:`~surrogate.sbml.errors.SbmlError` naming the construct and the element.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import libsbml

from surrogate.ctmc.kinetics import Expr, call, const
from surrogate.sbml.errors import SbmlError

__all__ = ["AVOGADRO", "Resolver", "convert"]

# libsbml's value of the avogadro csymbol (the 2019 SI exact value).
AVOGADRO = 6.02214076e23

# Names resolve to an expression via the caller (species, parameters, inputs, ...).
Resolver = Callable[[str], Expr]

_UNARY = {
    libsbml.AST_FUNCTION_EXP: "exp",
    libsbml.AST_FUNCTION_LN: "ln",
    libsbml.AST_FUNCTION_ABS: "abs",
    libsbml.AST_FUNCTION_FLOOR: "floor",
    libsbml.AST_FUNCTION_CEILING: "ceiling",
    libsbml.AST_FUNCTION_SIN: "sin",
    libsbml.AST_FUNCTION_COS: "cos",
    libsbml.AST_FUNCTION_TAN: "tan",
    libsbml.AST_FUNCTION_ARCSIN: "arcsin",
    libsbml.AST_FUNCTION_ARCCOS: "arccos",
    libsbml.AST_FUNCTION_ARCTAN: "arctan",
    libsbml.AST_FUNCTION_SINH: "sinh",
    libsbml.AST_FUNCTION_COSH: "cosh",
    libsbml.AST_FUNCTION_TANH: "tanh",
}
_RELATIONAL = {
    libsbml.AST_RELATIONAL_LT: "lt",
    libsbml.AST_RELATIONAL_LEQ: "leq",
    libsbml.AST_RELATIONAL_GT: "gt",
    libsbml.AST_RELATIONAL_GEQ: "geq",
    libsbml.AST_RELATIONAL_EQ: "eq",
    libsbml.AST_RELATIONAL_NEQ: "neq",
}
_LOGICAL = {
    libsbml.AST_LOGICAL_AND: "and",
    libsbml.AST_LOGICAL_OR: "or",
    libsbml.AST_LOGICAL_XOR: "xor",
}
_VARIADIC = {
    libsbml.AST_PLUS: "plus",
    libsbml.AST_TIMES: "times",
    libsbml.AST_FUNCTION_MIN: "min",
    libsbml.AST_FUNCTION_MAX: "max",
}
_NAMED_UNSUPPORTED = {
    libsbml.AST_NAME_TIME: "the time csymbol (time-dependent propensities)",
    libsbml.AST_FUNCTION_DELAY: "the delay csymbol",
    libsbml.AST_FUNCTION_RATE_OF: "the rateOf csymbol",
    libsbml.AST_LAMBDA: "a lambda outside a function definition",
    libsbml.AST_FUNCTION_QUOTIENT: "quotient",
    libsbml.AST_FUNCTION_REM: "rem",
    libsbml.AST_LOGICAL_IMPLIES: "implies",
    libsbml.AST_CSYMBOL_FUNCTION: "a csymbol function",
}

_MAX_DEPTH = 200


def _formula(node: libsbml.ASTNode) -> str:
    text = libsbml.formulaToL3String(node)
    return text if text else "?"


def convert(  # noqa: C901  # one branch per MathML node type
    node: libsbml.ASTNode | None,
    resolve: Resolver,
    functions: Mapping[str, libsbml.FunctionDefinition],
    where: str,
    _bound: Mapping[str, Expr] | None = None,
    _depth: int = 0,
    operators: Mapping[str, str] | None = None,
    time: Expr | None = None,
) -> Expr:
    """Convert one MathML AST to an :class:`Expr`.

    Args:
        node: The libsbml AST (``None`` means the element has no math: an error).
        resolve: Maps a name (species, compartment, parameter, ...) to its expression; it
            raises :class:`SbmlError` for names it cannot resolve.
        functions: The model's function definitions by id, inlined at each call.
        where: The element being converted, e.g. ``"kinetic law of reaction 'R1'"`` (used in
            every error message).
        operators: Function names the text may call beyond SBML's, each an operator of
            :data:`~surrogate.ctmc.kinetics.OPERATORS` (e.g. ``{"hypot": "hypot"}``).
        time: What the time csymbol reads (e.g. :func:`~surrogate.ctmc.kinetics.time_ref` in
            an event trigger); None refuses it.

    Raises:
        SbmlError: an unsupported construct or an ill-typed expression, naming ``where``.
    """
    if node is None:
        raise SbmlError(f"{where}: no math (missing or unparsable MathML)")
    if _depth > _MAX_DEPTH:
        raise SbmlError(
            f"{where}: expression nested deeper than {_MAX_DEPTH} (recursive function?)"
        )
    bound = _bound or {}
    t = node.getType()
    n = node.getNumChildren()

    def child(i: int, names: Mapping[str, Expr] | None = None) -> Expr:
        return convert(
            node.getChild(i),
            resolve,
            functions,
            where,
            bound if names is None else names,
            _depth + 1,
            operators,
            time,
        )

    def apply(op: str, *args: Expr) -> Expr:
        try:
            return call(op, *args)
        except ValueError as error:
            raise SbmlError(f"{where}: {error} in {_formula(node)!r}") from None

    if t == libsbml.AST_INTEGER:
        return const(float(node.getInteger()))
    if t in (libsbml.AST_REAL, libsbml.AST_REAL_E, libsbml.AST_RATIONAL):
        return const(float(node.getReal()))
    if t == libsbml.AST_CONSTANT_E:
        return const(math.e)
    if t == libsbml.AST_CONSTANT_PI:
        return const(math.pi)
    if t == libsbml.AST_CONSTANT_TRUE:
        return const(True)
    if t == libsbml.AST_CONSTANT_FALSE:
        return const(False)
    if t == libsbml.AST_NAME_AVOGADRO:
        return const(AVOGADRO)
    if t == libsbml.AST_NAME:
        name = node.getName()
        if name in bound:
            return bound[name]
        return resolve(name)
    if t == libsbml.AST_NAME_TIME and time is not None:
        return time
    if t in _NAMED_UNSUPPORTED:
        raise SbmlError(
            f"{where}: unsupported construct: {_NAMED_UNSUPPORTED[t]} in {_formula(node)!r}"
        )
    if t in _VARIADIC:
        if n == 0:
            if t in (libsbml.AST_PLUS, libsbml.AST_TIMES):
                return const(0.0 if t == libsbml.AST_PLUS else 1.0)
            raise SbmlError(f"{where}: {node.getName()} needs at least one argument")
        return apply(_VARIADIC[t], *(child(i) for i in range(n)))
    if t == libsbml.AST_MINUS:
        if n == 1:
            return apply("negate", child(0))
        return apply("minus", *(child(i) for i in range(n)))
    if t == libsbml.AST_DIVIDE:
        return apply("divide", *(child(i) for i in range(n)))
    if t in (libsbml.AST_POWER, libsbml.AST_FUNCTION_POWER):
        return apply("power", *(child(i) for i in range(n)))
    if t in _UNARY:
        return apply(_UNARY[t], *(child(i) for i in range(n)))
    if t == libsbml.AST_FUNCTION_LOG:
        if n == 1:
            return apply("log10", child(0))
        if n == 2:
            base, x = child(0), child(1)
            if base.is_const and base.value == 10.0:
                return apply("log10", x)
            return apply("divide", apply("ln", x), apply("ln", base))
    if t == libsbml.AST_FUNCTION_ROOT:
        if n == 1:
            return apply("sqrt", child(0))
        if n == 2:
            degree, x = child(0), child(1)
            if degree.is_const and degree.value == 2.0:
                return apply("sqrt", x)
            return apply("power", x, apply("divide", const(1.0), degree))
    if t == libsbml.AST_FUNCTION_FACTORIAL and n == 1:
        x = child(0)
        if x.is_const and x.value >= 0 and float(x.value).is_integer():
            return const(float(math.factorial(int(x.value))))
        raise SbmlError(
            f"{where}: unsupported construct: factorial of a non-constant in {_formula(node)!r}"
        )
    if t in _RELATIONAL:
        if n < 2:
            raise SbmlError(f"{where}: relational {node.getName()} needs two or more arguments")
        args = [child(i) for i in range(n)]
        pairs = [apply(_RELATIONAL[t], args[i], args[i + 1]) for i in range(n - 1)]
        return pairs[0] if len(pairs) == 1 else apply("and", *pairs)
    if t in _LOGICAL:
        if n == 0:
            return const(t == libsbml.AST_LOGICAL_AND)
        return apply(_LOGICAL[t], *(child(i) for i in range(n)))
    if t == libsbml.AST_LOGICAL_NOT:
        return apply("not", *(child(i) for i in range(n)))
    if t == libsbml.AST_FUNCTION_PIECEWISE:
        if n == 0:
            raise SbmlError(f"{where}: empty piecewise")
        return apply("piecewise", *(child(i) for i in range(n)))
    if t == libsbml.AST_FUNCTION:
        name = node.getName()
        definition = functions.get(name)
        if definition is None and operators and name in operators:
            return apply(operators[name], *(child(i) for i in range(n)))
        if definition is None:
            raise SbmlError(f"{where}: call of unknown function {name!r} in {_formula(node)!r}")
        return _inline(definition, [child(i) for i in range(n)], resolve, functions, where, _depth)
    kind = node.getName() or f"AST type {t}"
    raise SbmlError(f"{where}: unsupported MathML construct {kind!r} in {_formula(node)!r}")


def _inline(
    definition: libsbml.FunctionDefinition,
    args: list[Expr],
    resolve: Resolver,
    functions: Mapping[str, libsbml.FunctionDefinition],
    where: str,
    depth: int,
) -> Expr:
    """Inline a function definition: its body with the bound variables replaced by ``args``."""
    fid = definition.getId()
    lam = definition.getMath()
    if lam is None or lam.getType() != libsbml.AST_LAMBDA:
        raise SbmlError(f"function definition {fid!r}: math is not a lambda")
    n_bvar = lam.getNumBvars()
    if len(args) != n_bvar:
        raise SbmlError(
            f"{where}: function {fid!r} takes {n_bvar} arguments, called with {len(args)}"
        )
    names = {lam.getChild(i).getName(): args[i] for i in range(n_bvar)}
    body = lam.getChild(lam.getNumChildren() - 1)

    def no_free_names(name: str) -> Expr:
        raise SbmlError(
            f"function definition {fid!r}: its body uses {name!r}, which is not one of its "
            "arguments (SBML function bodies may only use their arguments)"
        )

    return convert(
        body, no_free_names, functions, f"{where} (in function {fid!r})", names, depth + 1
    )

"""Whether a reversible reaction's kinetic law is a net rate (forward minus backward), read as a
signed sum of products (its expansion, never built); the rule is in :mod:`surrogate.sbml.reader`'s
docstring."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from surrogate.ctmc.kinetics import Expr


@dataclass(frozen=True)
class _Terms:
    """A law read as a signed sum of products (its expansion, not built): whether some term is
    positive / negative, and the species (by column) found in positive / negative terms."""

    positive: bool
    negative: bool
    in_positive: frozenset[int] = frozenset()
    in_negative: frozenset[int] = frozenset()

    def flipped(self) -> _Terms:
        return _Terms(self.negative, self.positive, self.in_negative, self.in_positive)

    def __add__(self, other: _Terms) -> _Terms:
        return _Terms(
            self.positive or other.positive,
            self.negative or other.negative,
            self.in_positive | other.in_positive,
            self.in_negative | other.in_negative,
        )

    def __mul__(self, other: _Terms) -> _Terms:
        # a term of the product is one term of each factor: negative where their signs differ
        a, b = self, other
        in_positive: frozenset[int] = frozenset()
        in_negative: frozenset[int] = frozenset()
        for mine, theirs in ((a, b), (b, a)):
            if theirs.positive:
                in_positive |= mine.in_positive
                in_negative |= mine.in_negative
            if theirs.negative:
                in_positive |= mine.in_negative
                in_negative |= mine.in_positive
        return _Terms(
            (a.positive and b.positive) or (a.negative and b.negative),
            (a.positive and b.negative) or (a.negative and b.positive),
            in_positive,
            in_negative,
        )


#: functions whose sign is their argument's (the argument's terms are the value's terms)
_SIGN_OF_ARGUMENT = frozenset({"sinh", "tanh", "arcsin", "arctan", "floor", "ceiling"})


def _positive_factor(expr: Expr) -> _Terms:
    """A factor read as one positive term holding every species it reads (a function's value,
    a power's exponent): a minus inside it subtracts no term from the law."""
    return _Terms(True, False, frozenset(n.index for n in _leaves(expr) if n.op == "species"))


def _terms(expr: Expr) -> _Terms:  # noqa: C901  # one branch per expression node kind
    """The signed terms of ``expr`` (see :class:`_Terms` and the module docstring): through
    sums, differences, negations, products, quotients, a power's base, min / max, the values
    of a piecewise (its conditions a positive factor) and sign-keeping functions; every other
    function (``exp``, ``sqrt``, ``abs``, ``ln``, ...) and a power's exponent is a positive
    factor, and so is an even integer power."""
    op, args = expr.op, expr.args
    if op == "const":
        return _Terms(not expr.value < 0, expr.value < 0)
    if op == "species":
        return _Terms(True, False, frozenset({expr.index}))
    if op in ("input", "time"):
        return _Terms(True, False)
    if op in ("plus", "min", "max"):
        out = _terms(args[0])
        for arg in args[1:]:
            out = out + _terms(arg)
        return out
    if op == "minus":
        return _terms(args[0]) + _terms(args[1]).flipped()
    if op == "negate":
        return _terms(args[0]).flipped()
    if op in ("times", "divide"):  # 1 / b has the sign of b
        out = _terms(args[0])
        for arg in args[1:]:
            out = out * _terms(arg)
        return out
    if op == "power":
        base, exponent = args
        if exponent.is_const and float(exponent.value) % 2 == 0:
            return _positive_factor(expr)
        return _terms(base) * _positive_factor(exponent)
    if op in _SIGN_OF_ARGUMENT:
        return _terms(args[0])
    if op == "piecewise":
        values = [*args[0:-1:2], *([args[-1]] if len(args) % 2 else [])]
        conditions = args[1::2]
        out = _terms(values[0])
        for value in values[1:]:
            out = out + _terms(value)
        for condition in conditions:
            out = out * _positive_factor(condition)
        return out
    return _positive_factor(expr)


def net_rate_products(expr: Expr, products: set[int]) -> list[str]:
    """The products (by name) that some negative term of a reversible reaction's law depends
    on: a non-empty list marks the law a net rate (forward minus backward). See the module
    docstring."""
    names = {n.index: repr(n.name) for n in _leaves(expr) if n.op == "species"}
    return [names[i] for i in sorted(_terms(expr).in_negative & products)]


def _leaves(expr: Expr) -> Iterable[Expr]:
    if not expr.args:
        yield expr
    for arg in expr.args:
        yield from _leaves(arg)


__all__ = ["net_rate_products"]

"""Formulas written by hand (a lump property, an input's formula) read with libsbml's parser.

A formula is SBML Level 3 infix text (``"N >= 2 && S == 0"``, ``"1 / (1 + exp(F))"``), parsed
by ``libsbml.parseL3FormulaWithSettings`` and converted by :func:`surrogate.sbml.math.convert`
into a validated :class:`~surrogate.ctmc.kinetics.Expr` tree: nothing in it is evaluated as
Python, and every name must be one of the symbols the caller offers (else an error naming the
unknown name and the known ones). For readability ``and``, ``or`` and ``not`` may be written as
words (``"N >= 2 and S == 0"``); ``not`` binds tighter than a comparison, as SBML's ``!``, so
write ``not (S == 0)``. ``log(x)`` is refused as ambiguous: write ``ln(x)`` or ``log10(x)``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import libsbml

from surrogate.ctmc.kinetics import Expr
from surrogate.sbml.errors import SbmlError
from surrogate.sbml.math import convert

__all__ = ["parse_formula"]

_WORDS = {"and": "&&", "or": "||", "not": "!"}
#: the words as operators; followed directly by "(" they are SBML's functions and(a, b), ...
_WORD = re.compile(r"(?<![\w.])(and|or|not)(?![\w.(])")


def _settings() -> libsbml.L3ParserSettings:
    settings = libsbml.L3ParserSettings()
    settings.setParseUnits(False)  # "2 S" is not a number with a unit here
    settings.setParseLog(libsbml.L3P_PARSE_LOG_AS_ERROR)
    return settings


def parse_formula(
    text: str,
    symbols: Mapping[str, Expr],
    where: str,
    kind: str | None = None,
    what: str = "name",
    operators: Mapping[str, str] | None = None,
) -> Expr:
    """Parse ``text`` into an expression over ``symbols``.

    Args:
        text: SBML L3 infix formula (``&&``/``and``, ``||``/``or``, ``!``/``not``, comparisons,
            arithmetic, ``exp``, ``ln``, ``piecewise``, ...).
        symbols: the names the formula may use and what each stands for (e.g. species counts).
        where: the setting being parsed, named in every error (e.g. ``"model.lump"``).
        kind: ``"bool"`` (a condition) or ``"real"`` (a value) to require; None accepts both.
        what: what the symbols are, for the message on an unknown name (e.g. ``"species"``).
        operators: function names beyond SBML's the text may call, each naming an operator of
            :data:`~surrogate.ctmc.kinetics.OPERATORS` (e.g. ``{"hypot": "hypot"}``).

    Returns:
        The validated expression (constants folded).

    Raises:
        SbmlError: unparsable text, an unknown name, an ill-typed expression or the wrong kind.

    Example:
        >>> from surrogate.ctmc.kinetics import species_ref
        >>> names = {"S": species_ref(0, "S"), "N": species_ref(2, "N")}
        >>> parse_formula("N >= 2 and S == 0", names, "model.lump", kind="bool").op
        'and'
    """
    if not isinstance(text, str) or not text.strip():
        raise SbmlError(f"{where}: expected a formula (text), got {text!r}")
    source = _WORD.sub(lambda m: _WORDS[m.group(1)], text)
    ast = libsbml.parseL3FormulaWithSettings(source, _settings())
    if ast is None:
        detail = libsbml.getLastParseL3Error().strip().splitlines()
        raise SbmlError(f"{where}: cannot parse {text!r}: {detail[-1] if detail else 'syntax'}")

    def resolve(name: str) -> Expr:
        if name in symbols:
            return symbols[name]
        raise SbmlError(f"{where}: unknown {what} {name!r} in {text!r}; known: {sorted(symbols)}")

    expr = convert(ast, resolve, {}, f"{where} {text!r}", operators=operators)
    if kind is not None and expr.kind != kind:
        want = "a condition (e.g. N >= 2 and S == 0)" if kind == "bool" else "a number"
        raise SbmlError(f"{where}: {text!r} must be {want}")
    return expr

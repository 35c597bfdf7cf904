"""Fields inside a compiled (numba) kernel: generated scalar code, chosen by a field index.

A kernel evaluates a cell's field as ``field_value(field_set, row, x, y, t)``: ``row`` is the
field's packed float64 row (:func:`pack_field`: its formula's index in the set, then its
parameters) and ``field_set`` a :class:`FieldSet`, the formulas the kernel may meet. Numba
types a field set by the generated module that holds its formulas' scalar functions and their
dispatcher (:func:`surrogate.field_formula.dispatcher_source`; a content-addressed file), so
the kernel is compiled, and cached on disk, once per distinct set of formulas: the built-in
fields' set (:data:`BUILTIN_FORMULAS`, the precompiled one) or that set followed by the
formulas of the simulation's :class:`~surrogate.fields.ExpressionField` s. The dispatcher is
inlined, as one ``if`` per formula.

A coupled field (:class:`~surrogate.grid.CoupledField`: the agents change it every step) has no
formula: its row says :data:`READ_OUTSIDE`, and the simulator reads it before each one-step call
of the kernel and hands the values over in the cells' inputs (:func:`pack_fields`).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np
from numba.core import types
from numba.extending import NativeValue, models, overload, register_model, typeof_impl, unbox

from surrogate.errors import KernelUnsupported
from surrogate.field_formula import FieldFormula, dispatcher_source
from surrogate.fields import BUILTIN_FIELDS, Field, FormulaField
from surrogate.grid.coupled import is_coupled

__all__ = [
    "BUILTIN_FORMULAS",
    "READ_OUTSIDE",
    "FieldSet",
    "field_set",
    "field_value",
    "pack_field",
    "pack_fields",
]

#: numba options of the generated scalar functions (inlined into the kernel that calls them)
_JIT_OPTIONS = '{"nogil": True, "fastmath": False, "error_model": "numpy"}'
#: the least row width (columns), so rows of the built-in fields fit without padding
MIN_COLUMNS = 8
#: a row's formula index for a field read outside the kernel (a coupled field: its state
#: changes every step, so the kernel takes one step per call and reads the inputs it is given)
READ_OUTSIDE = -1


class FieldSet:
    """The formulas a kernel may meet, in index order, and their generated module."""

    def __init__(self, formulas: Sequence[FieldFormula]) -> None:
        from surrogate.ctmc.codegen import load_generated

        self.formulas = tuple(formulas)
        source = dispatcher_source(self.formulas, _JIT_OPTIONS)
        self.module = load_generated(source, prefix="fields").__name__
        self._index = {_key(f): k for k, f in enumerate(self.formulas)}
        self.columns = max(MIN_COLUMNS, 1 + max(len(f.parameters) for f in self.formulas))

    def index(self, formula: FieldFormula) -> int:
        """The index of ``formula`` (equal text and parameter names) in this set."""
        return self._index[_key(formula)]

    def __contains__(self, formula: FieldFormula) -> bool:
        return _key(formula) in self._index


def _key(formula: FieldFormula) -> tuple[str, tuple[str, ...]]:
    return formula.text, formula.parameters


def _builtin_formulas() -> tuple[FieldFormula, ...]:
    return tuple(cls().formula for cls in BUILTIN_FIELDS.values())  # type: ignore[attr-defined]


#: the built-in fields' formulas (constant, gaussian, linear, dynamic, exponential)
BUILTIN_FORMULAS = _builtin_formulas()
_SETS: dict[tuple, FieldSet] = {}


def _formula_of(field: Field) -> FieldFormula:
    """The formula the kernel computes for ``field``, or KernelUnsupported naming the field."""
    if not isinstance(field, FormulaField) or type(field).__call__ is not FormulaField.__call__:
        raise KernelUnsupported(
            f"field {type(field).__name__} (a Python field: the kernel runs formula fields, "
            "the built-in ones and surrogate.fields.ExpressionField)"
        )
    return field.formula


def field_set(fields: Sequence[Field]) -> FieldSet:
    """The set of the built-in formulas and those of ``fields`` (in first-seen order).

    Raises:
        KernelUnsupported: a field that is not a formula (a Python ``__call__``).
    """
    formulas = list(BUILTIN_FORMULAS)
    for formula in map(_formula_of, fields):
        if all(_key(formula) != _key(f) for f in formulas):
            formulas.append(formula)
    key = tuple(map(_key, formulas))
    if key not in _SETS:
        _SETS[key] = FieldSet(formulas)
    return _SETS[key]


def pack_field(field: Field, fields: FieldSet) -> np.ndarray:
    """``field`` as a float64 row of ``fields.columns``: its formula's index in ``fields``,
    then its parameters (the peak first), zeros after."""
    formula = _formula_of(field)
    values = field.packed_parameters()  # type: ignore[attr-defined]
    row = np.zeros(fields.columns, dtype=np.float64)
    row[0] = fields.index(formula)
    row[1 : 1 + len(values)] = values
    return row


def pack_fields(fields: Sequence[Field]) -> tuple[FieldSet, np.ndarray]:
    """The field set of ``fields``' formulas and their packed rows (``len(fields) x
    columns`` float64): a coupled field's row is :data:`READ_OUTSIDE` (its values come from
    the simulator's read before each step), every other field's :func:`pack_field`.

    Raises:
        KernelUnsupported: a given field that is not a formula (a Python ``__call__``).
    """
    fields_set = field_set([f for f in fields if not is_coupled(f)])
    rows = np.zeros((len(fields), fields_set.columns), dtype=np.float64)
    for row, field in zip(rows, fields, strict=True):
        if is_coupled(field):
            row[0] = READ_OUTSIDE
        else:
            row[:] = pack_field(field, fields_set)
    return fields_set, rows


# -- numba: a FieldSet is typed by its generated module (no data at run time) -----------------
class FieldSetType(types.Dummy):
    """Numba type of a :class:`FieldSet`: its module's name (a content address)."""

    def __init__(self, module: str) -> None:
        self.module = module
        super().__init__(name=f"FieldSet({module})")


@typeof_impl.register(FieldSet)
def _typeof_field_set(value: FieldSet, context: object) -> FieldSetType:
    return FieldSetType(value.module)


register_model(FieldSetType)(models.OpaqueModel)


@unbox(FieldSetType)
def _unbox_field_set(typ: FieldSetType, obj: object, c: object) -> NativeValue:
    return NativeValue(c.context.get_dummy_value())  # type: ignore[attr-defined]


def field_value(fields: FieldSet, row: np.ndarray, x: float, y: float, t: float) -> float:
    """L of the field ``row`` (float32) at ``x``, ``y`` (float32 mm), ``t`` (float64 s):
    callable from numba-compiled code only."""
    raise NotImplementedError("field_value is compiled into numba kernels only")


@overload(field_value, inline="always")
def _field_value(fields, row, x, y, t):
    if not isinstance(fields, FieldSetType):
        return None
    return sys.modules[fields.module].field

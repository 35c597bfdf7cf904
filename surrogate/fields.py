"""Spatio-temporal ligand fields L(r, t) in mM, positions in mm, time in s.

The paper's three fields (peak 0.1 mM at the origin):

* ``GaussianField`` (L1): 0.1 exp(-0.5 r' S^-1 r), S = 3 I
* ``LinearField`` (L2): max(1e-5, 0.1 - 0.05 |A r|), A = diag(1/5, 1/2)
* ``DynamicGaussianField`` (L3): 0.1 exp(-0.5 r' S(t)^-1 r), S(t) = 3 (t/50 + 1) I

A user-defined field is any subclass of :class:`Field` (or any object with the same
``__call__(position, t)`` and ``peak``), selected through Hydra's ``_target_``::

    # conf/field/my_field.yaml
    _target_: mypackage.fields.MyField
    name: my_field
    some_parameter: 1.0

A field can also be a formula, with no Python at all (:class:`ExpressionField`)::

    # conf/field/ridge.yaml
    _target_: surrogate.fields.ExpressionField
    expression: "amplitude * exp(-0.5 * (x - peak_x)^2 / width^2)"
    parameters: {amplitude: 0.1, width: 1.0}
    peak: [0.0, 0.0]

The built-in fields are formulas too (each class's ``expression``): their torch code and the
compiled kernels' scalar code are generated from the one formula
(:mod:`surrogate.field_formula`), so a formula field runs wherever a built-in one does.

All fields are vectorised over cells: ``position`` is ``(n_cells, 2)``, the result ``(n_cells,)``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.field_formula import FieldFormula, field_formula


class Field:
    """Base class: a ligand concentration L(r, t) >= 0 with a peak location for distances."""

    name: str = "field"

    def __init__(self, peak: Sequence[float] = (0.0, 0.0)) -> None:
        if len(peak) != 2:
            raise ConfigError(f"field.peak must have two coordinates (mm), got {list(peak)!r}")
        self.peak: tuple[float, float] = (float(peak[0]), float(peak[1]))

    def __call__(self, position: Tensor, t: float) -> Tensor:
        """Ligand concentration (mM) at ``position`` (n, 2) and time ``t`` (s)."""
        raise NotImplementedError

    def offset(self, position: Tensor) -> Tensor:
        """Position relative to the peak, (n, 2)."""
        if self.peak == (0.0, 0.0):
            return position
        return position - position.new_tensor(self.peak)

    def distance_from_peak(self, position: Tensor) -> Tensor:
        """Euclidean distance (mm) from the field's peak, (n,)."""
        return torch.linalg.vector_norm(self.offset(position), dim=-1)

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if not k.startswith("_"))
        return f"{type(self).__name__}({params})"


class FormulaField(Field):
    """A field whose L(x, y, t) is the formula ``expression`` (SBML infix text over x, y in mm,
    t in s, ``peak_x``, ``peak_y`` and ``parameter_names``, whose values
    :meth:`parameter_values` gives in that order).

    The torch step and the compiled kernels both run code generated from the formula, so a
    subclass only states its formula and parameters; one that overrides ``__call__`` is a
    Python field (the torch step only). The formula is parsed once per class (per instance
    for :class:`ExpressionField`) and its code loaded at construction, so a call is only the
    generated torch code (nothing for ``torch.compile`` to break its graph on).
    """

    expression: str = ""
    parameter_names: tuple[str, ...] = ()
    _formula: FieldFormula | None = None

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        if "expression" in cls.__dict__:  # a class with a formula of its own
            cls._formula = field_formula(cls.expression, cls.parameter_names)

    def __init__(self, peak: Sequence[float] = (0.0, 0.0)) -> None:
        super().__init__(peak)
        if self._formula is not None:
            self._formula.torch_function(self.peak == (0.0, 0.0))  # generate and load it now

    @property
    def formula(self) -> FieldFormula:
        """The parsed formula."""
        if self._formula is None:
            raise ConfigError(f"{type(self).__name__} has no expression")
        return self._formula

    def parameter_values(self) -> dict[str, float]:
        """The values of ``parameter_names``, in that order."""
        return {}

    def packed_parameters(self) -> tuple[float, ...]:
        """The values of :attr:`FieldFormula.parameters`, in its order (the peak first)."""
        return (*self.peak, *self.parameter_values().values())

    def __call__(self, position: Tensor, t: float) -> Tensor:
        at_origin = self.peak == (0.0, 0.0)
        return self.formula.torch_function(at_origin)(position, t, self.packed_parameters())


class ExpressionField(FormulaField):
    """A field given as a formula, e.g. from yaml (see the module docstring).

    Args:
        expression: L(x, y, t) in mM, SBML L3 infix: ``+ - * / ^``, ``exp``, ``ln``,
            ``sqrt``, ``min``, ``max``, ``piecewise``, comparisons, ..., and ``hypot(a, b)``
            (the norm of (a, b)); over ``x``, ``y`` (mm), ``t`` (s), ``peak_x``, ``peak_y``
            and the names of ``parameters``.
        parameters: Named constants of the formula.
        peak: Where the field peaks (mm): the distances of the fidelity report are from it.

    Raises:
        ConfigError: an unparsable formula, an unknown name or function (named), or a
            non-finite parameter.

    Example:
        >>> ridge = ExpressionField("a * exp(-0.5 * (x - 1)^2)", {"a": 0.1}, peak=(1.0, 0.0))
        >>> ridge(torch.tensor([[1.0, 5.0]]), 0.0)
        tensor([0.1000])
    """

    name = "expression"

    def __init__(
        self,
        expression: str,
        parameters: Mapping[str, float] | None = None,
        peak: Sequence[float] = (0.0, 0.0),
    ) -> None:
        self.expression = expression
        self.parameters = {str(k): float(v) for k, v in dict(parameters or {}).items()}
        for key, value in self.parameters.items():
            if not math.isfinite(value):
                raise ConfigError(f"field.parameters.{key} must be finite, got {value!r}")
        self._formula = field_formula(expression, tuple(self.parameters))
        super().__init__(peak)

    @property
    def parameter_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(self.parameters)

    def parameter_values(self) -> dict[str, float]:
        return dict(self.parameters)

    def __getstate__(self) -> dict:
        """Picklable: the formula's text, not its generated code (parsed again on loading)."""
        return {k: v for k, v in self.__dict__.items() if k != "_formula"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._formula = field_formula(self.expression, tuple(self.parameters))


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"field.{name} must be a positive number, got {value!r}")
    return value


class ConstantField(FormulaField):
    """Uniform, static concentration (``value = 0`` is the zero field used as a control)."""

    name = "constant"
    parameter_names = ("value",)
    expression = "value"

    def __init__(self, value: float = 0.0, peak: Sequence[float] = (0.0, 0.0)) -> None:
        super().__init__(peak)
        if not (math.isfinite(float(value)) and float(value) >= 0):
            raise ConfigError(f"field.value must be a non-negative number, got {value!r}")
        self.value = float(value)

    def parameter_values(self) -> dict[str, float]:
        return {"value": self.value}


class GaussianField(FormulaField):
    """L1: ``amplitude * exp(-0.5 |r - peak|^2 / variance)``."""

    name = "gaussian"
    parameter_names = ("amplitude", "variance")
    expression = "amplitude * exp(((x - peak_x)^2 + (y - peak_y)^2) * (-0.5 / variance))"

    def __init__(
        self, amplitude: float = 0.1, variance: float = 3.0, peak: Sequence[float] = (0.0, 0.0)
    ) -> None:
        super().__init__(peak)
        self.amplitude = _positive("amplitude", amplitude)
        self.variance = _positive("variance", variance)

    def parameter_values(self) -> dict[str, float]:
        return {"amplitude": self.amplitude, "variance": self.variance}


class LinearField(FormulaField):
    """L2: ``max(floor, amplitude - slope * |A (r - peak)|)``, ``A = diag(scale_x, scale_y)``."""

    name = "linear"
    parameter_names = ("amplitude", "slope", "scale_x", "scale_y", "floor")
    expression = (
        "max(amplitude - slope * hypot((x - peak_x) * scale_x, (y - peak_y) * scale_y), floor)"
    )

    def __init__(
        self,
        amplitude: float = 0.1,
        slope: float = 0.05,
        scale: Sequence[float] = (0.2, 0.5),
        floor: float = 1e-5,
        peak: Sequence[float] = (0.0, 0.0),
    ) -> None:
        super().__init__(peak)
        self.amplitude = _positive("amplitude", amplitude)
        self.slope = _positive("slope", slope)
        if len(scale) != 2:
            raise ConfigError(
                f"field.scale must have two entries (diagonal of A), got {list(scale)!r}"
            )
        self.scale = (_positive("scale", scale[0]), _positive("scale", scale[1]))
        self.floor = float(floor)
        if not (math.isfinite(self.floor) and 0 <= self.floor < self.amplitude):
            raise ConfigError(f"field.floor must lie in [0, amplitude), got {floor!r}")

    def parameter_values(self) -> dict[str, float]:
        return {"amplitude": self.amplitude, "slope": self.slope, "scale_x": self.scale[0],
                "scale_y": self.scale[1], "floor": self.floor}  # fmt: skip


class DynamicGaussianField(FormulaField):
    """L3: a Gaussian whose variance grows in time, ``variance * (t / spread_time + 1)``."""

    name = "dynamic"
    parameter_names = ("amplitude", "variance", "spread_time")
    expression = (
        "amplitude * exp(((x - peak_x)^2 + (y - peak_y)^2)"
        " * (-0.5 / (variance * (t / spread_time + 1))))"
    )

    def __init__(
        self,
        amplitude: float = 0.1,
        variance: float = 3.0,
        spread_time: float = 50.0,
        peak: Sequence[float] = (0.0, 0.0),
    ) -> None:
        super().__init__(peak)
        self.amplitude = _positive("amplitude", amplitude)
        self.variance = _positive("variance", variance)
        self.spread_time = _positive("spread_time", spread_time)

    def variance_at(self, t: float) -> float:
        """Variance of the Gaussian (mm^2) at time ``t``."""
        return self.variance * (t / self.spread_time + 1.0)

    def parameter_values(self) -> dict[str, float]:
        return {"amplitude": self.amplitude, "variance": self.variance,
                "spread_time": self.spread_time}  # fmt: skip


class ExponentialField(FormulaField):
    """A cone in log L: ``amplitude * exp(-|r - peak| / length)`` (constant d ln L / dr, so the
    cells see the same relative gradient everywhere; not one of the paper's fields)."""

    name = "exponential"
    parameter_names = ("amplitude", "length")
    expression = "amplitude * exp(hypot(x - peak_x, y - peak_y) * (-1 / length))"

    def __init__(
        self, amplitude: float = 0.1, length: float = 1.0, peak: Sequence[float] = (0.0, 0.0)
    ) -> None:
        super().__init__(peak)
        self.amplitude = _positive("amplitude", amplitude)
        self.length = _positive("length", length)

    def parameter_values(self) -> dict[str, float]:
        return {"amplitude": self.amplitude, "length": self.length}


class FieldBatch(Field):
    """Several fields side by side for a population simulated as consecutive blocks of cells
    (replicates in one batch): block i of ``sizes[i]`` cells sees ``fields[i]``.

    Blocks that share one field object are evaluated in one call over all their cells (gathered,
    then put back in block order), so a batch costs one call per distinct field, not per block.

    Example:
        >>> batch = FieldBatch([GaussianField(), LinearField()], [100, 100])
        >>> batch(torch.zeros(200, 2), 0.0).shape
        torch.Size([200])
    """

    name = "batch"

    def __init__(self, fields: Sequence[Field], sizes: Sequence[int]) -> None:
        if len(fields) != len(sizes) or not fields:
            raise ValueError("FieldBatch needs one size per field")
        super().__init__(fields[0].peak)
        self.fields = list(fields)
        self.sizes = [int(n) for n in sizes]
        distinct = {id(f): f for f in self.fields}
        self.distinct = list(distinct.values())
        self._cells: list[Tensor] | None = None  # per distinct field, its cells (block order)
        self._order: Tensor | None = None  # position of each cell in the concatenated results
        if len(self.distinct) < len(self.fields):
            starts = [0, *itertools.accumulate(self.sizes)][:-1]
            cells: dict[int, list[Tensor]] = {k: [] for k in distinct}
            for f, a, n in zip(self.fields, starts, self.sizes, strict=True):
                cells[id(f)].append(torch.arange(a, a + n))
            self._cells = [torch.cat(c) for c in cells.values()]
            self._order = torch.argsort(torch.cat(self._cells))
        self._device: torch.device | None = None

    def _on(self, device: torch.device) -> None:
        if self._cells is not None and self._device != device:
            self._cells = [c.to(device) for c in self._cells]
            self._order = self._order.to(device)  # type: ignore[union-attr]
            self._device = device

    def _apply(self, method: str, position: Tensor, *args: float) -> Tensor:
        if self._cells is None:  # every block its own field: split, evaluate, join
            parts = torch.split(position, self.sizes, dim=0)
            return torch.cat([getattr(f, method)(p, *args)
                              for f, p in zip(self.fields, parts, strict=True)])  # fmt: skip
        self._on(position.device)
        out = torch.cat([getattr(f, method)(position[c], *args)
                         for f, c in zip(self.distinct, self._cells, strict=True)])  # fmt: skip
        return out[self._order]

    def __call__(self, position: Tensor, t: float) -> Tensor:
        return self._apply("__call__", position, t)

    def distance_from_peak(self, position: Tensor) -> Tensor:
        """Each block's distance from its own field's peak."""
        return self._apply("distance_from_peak", position)


BUILTIN_FIELDS: dict[str, type[Field]] = {
    cls.name: cls
    for cls in (ConstantField, GaussianField, LinearField, DynamicGaussianField, ExponentialField)
}

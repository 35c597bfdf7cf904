"""The species of a grid field and their exchange with the agents (uptake, secretion).

A species is declared in the field's yaml by name::

    species:
      serine:
        diffusion: 8.0e-4      # mm^2/s
        decay: 0.0             # 1/s, first-order
        initial: 0.1           # mM: a number, or a formula over x, y (mm)
        source: 0.0            # mM/s, constant in time: a number, or a formula over x, y
        parameters: {}         # named constants of the formulas
        uptake: {vmax: 1.6e5, km: 0.01}          # per cell: molecules/s, mM
        secretion: {rate_on: 0.0, rate_off: 0.0}  # per cell, molecules/s when phi = 1 / 0

Formulas are the field formulas of :class:`~surrogate.fields.ExpressionField` (``x``, ``y`` in
mm, ``t`` = 0, the grid's centre as ``peak_x``, ``peak_y``), evaluated once at the cell centres.

Uptake is Michaelis-Menten in the concentration at the agent, ``vmax c / (km + c)``, taken over
the step (forward Euler in the exchange, first order in dt) and capped so that no grid cell
gives more than it holds: each agent's demand is deposited on the grid (the adjoint
interpolation), every cell whose demand exceeds its content scales its demand down to its
content, and each agent takes its demand times the interpolated scale, so what the agents take
is exactly what the grid loses (the ledger sums it on the grid, ``sum_j wanted_j scale_j``:
the same total by the deposit's adjointness, without a second pass over the agents; the
demand's read and deposit are one fused pass on the CPU, :mod:`surrogate.grid.kernels`).
Secretion is ``rate_on`` (phi = 1) or ``rate_off`` (phi = 0)
per agent, deposited the same way. Amounts are kept in nmol (1 mM x 1 mm^3 = 1 nmol) and
float64: a cell's share per step (~1e-11 nmol) beside a grid cell's content (~1e-5 nmol) is
below float32's resolution.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.fields import ExpressionField
from surrogate.grid.geometry import Grid, Stencil
from surrogate.validation import known_keys

__all__ = ["MOLECULES_PER_NMOL", "Secretion", "Species", "Uptake", "cap_uptake"]

#: Avogadro's number per nmol: molecules/s per cell -> nmol/s
MOLECULES_PER_NMOL = 6.02214076e14

_KEYS = ("diffusion", "decay", "initial", "source", "parameters", "uptake", "secretion")


def _number(value: Any, where: str, positive: bool = False) -> float:
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    value = float(value) if ok else value
    if not ok or not math.isfinite(value) or value < 0 or (positive and value == 0):
        want = "a positive number" if positive else "a non-negative number"
        raise ConfigError(f"{where} must be {want}, got {value!r}")
    return value


@dataclass(frozen=True)
class Uptake:
    """Michaelis-Menten uptake per agent: ``vmax`` (molecules/s) and ``km`` (mM)."""

    vmax: float
    km: float

    def take(self, c: Tensor, stencil: Stencil, dt: float, volume: float) -> tuple[Tensor, Tensor]:
        """The step's uptake from the grid ``c`` (``(n_x, n_y)``, mM) by the agents of
        ``stencil``, capped by what each grid cell holds (module docstring).

        Returns:
            The grid's concentration loss ``(n_x, n_y)`` (mM) and the agents' total uptake
            (nmol, a float64 scalar). The total is summed over the grid's cells: by the
            adjointness of the deposit, ``sum_a demand_a interpolate(scale)_a = sum_j
            wanted_j scale_j``, and the grid's side is the very amount the grid loses (and
            needs no second pass over the agents).
        """
        wanted = stencil.saturating_deposit(c, self.vmax / MOLECULES_PER_NMOL * dt, self.km)
        return cap_uptake(wanted, c, volume)


def cap_uptake(wanted: Tensor, c: Tensor, volume: float) -> tuple[Tensor, Tensor]:
    """The agents' deposited demand ``wanted`` (``(n_x, n_y)`` nmol) capped by what each grid
    cell of ``c`` (mM) holds: the concentration loss (mM) and the total taken (nmol), as
    :meth:`Uptake.take` returns them (shared with :mod:`surrogate.grid.fused`)."""
    held = c.clamp_min(0.0) * volume  # nmol per grid cell
    scale = torch.where(wanted > held, held / wanted.clamp_min(1e-300), torch.ones_like(held))
    taken = wanted * scale
    return taken / volume, taken.sum()


@dataclass(frozen=True)
class Secretion:
    """Secretion per agent (molecules/s): ``rate_on`` while phi = 1, ``rate_off`` while 0."""

    rate_on: float
    rate_off: float

    def give(self, phi: Tensor, dt: float) -> Tensor:
        """Each agent's secretion over the step, ``(n,)`` nmol float64, from its phi after the
        step's window (``(n,)`` bool or 0/1)."""
        on = phi.to(torch.float64)
        rate = self.rate_off + (self.rate_on - self.rate_off) * on
        return rate * (dt / MOLECULES_PER_NMOL)


@dataclass(frozen=True)
class Species:
    """One species of a grid field (module docstring)."""

    name: str
    diffusion: float
    decay: float
    initial: float | str
    source: float | str
    parameters: dict[str, float] = field(default_factory=dict)
    uptake: Uptake | None = None
    secretion: Secretion | None = None

    @classmethod
    def from_config(cls, name: str, spec: Any, where: str = "field.species") -> Species:
        """A checked species from its yaml mapping (unknown keys, negative rates and a
        non-positive ``km`` are refused, named ``<where>.<name>.<key>``)."""
        at = f"{where}.{name}"
        s = known_keys(spec, _KEYS, at)
        if "diffusion" not in s:
            raise ConfigError(f"{at}.diffusion is required (mm^2/s; 0 for a species that does "
                              "not diffuse)")  # fmt: skip
        params = s.get("parameters") or {}
        if not isinstance(params, Mapping):
            raise ConfigError(f"{at}.parameters must be a mapping of names to numbers")
        parameters = {str(k): float(_finite(v, f"{at}.parameters.{k}")) for k, v in params.items()}
        profiles = {key: _profile(s.get(key, 0.0), f"{at}.{key}") for key in ("initial", "source")}
        uptake = secretion = None
        if s.get("uptake") is not None:
            u = known_keys(s["uptake"], ("vmax", "km"), f"{at}.uptake", required=("vmax", "km"))
            if set(u) != {"vmax", "km"}:
                raise ConfigError(f"{at}.uptake needs vmax (molecules/s per cell) and km (mM)")
            uptake = Uptake(_number(u["vmax"], f"{at}.uptake.vmax"),
                            _number(u["km"], f"{at}.uptake.km", positive=True))  # fmt: skip
        if s.get("secretion") is not None:
            r = known_keys(s["secretion"], ("rate_on", "rate_off"), f"{at}.secretion")
            secretion = Secretion(_number(r.get("rate_on", 0.0), f"{at}.secretion.rate_on"),
                                  _number(r.get("rate_off", 0.0), f"{at}.secretion.rate_off"))  # fmt: skip
        return cls(
            name,
            _number(s["diffusion"], f"{at}.diffusion"),
            _number(s.get("decay", 0.0), f"{at}.decay"),
            profiles["initial"],
            profiles["source"],
            parameters,
            uptake,
            secretion,
        )

    def profile(self, key: str, grid: Grid, device: torch.device | str = "cpu") -> Tensor:
        """The ``initial`` or ``source`` profile on the grid, ``(n_x, n_y)`` float64 (a
        formula is evaluated at the cell centres at t = 0).

        Raises:
            ConfigError: a formula with unknown names, or non-finite or negative values.
        """
        value = getattr(self, key)
        where = f"field.species.{self.name}.{key}"
        if not isinstance(value, str):
            return torch.full(grid.shape, float(value), dtype=torch.float64, device=device)
        out = _formula(value, self.parameters, grid, where)(grid.centres(device))
        if not bool(torch.isfinite(out).all()) or bool((out < 0).any()):
            raise ConfigError(f"{where}={value!r} must be finite and non-negative on the grid "
                              f"(lowest {float(out.min()):.3g})")  # fmt: skip
        return out

    def check_formulas(self, grid: Grid) -> None:
        """Parse the formulas now (unknown names are refused before any run)."""
        for key in ("initial", "source"):
            value = getattr(self, key)
            if isinstance(value, str):
                _formula(value, self.parameters, grid, f"field.species.{self.name}.{key}")


def _finite(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def _profile(value: Any, where: str) -> float | str:
    if isinstance(value, str):
        return value
    return _number(value, where)


def _formula(
    text: str, parameters: Mapping[str, float], grid: Grid, where: str
) -> Callable[[Tensor], Tensor]:
    """A function ``centres (n_x, n_y, 2) -> (n_x, n_y)`` float64 evaluating ``text``."""
    peak = tuple((a + b) / 2 for a, b in zip(grid.lower, grid.upper, strict=True))
    try:
        formula = ExpressionField(text, parameters, peak=peak)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None

    def evaluate(centres: Tensor) -> Tensor:
        flat = centres.reshape(-1, 2).to(torch.float32)
        return formula(flat, 0.0).to(torch.float64).reshape(centres.shape[:-1])

    return evaluate

"""The inputs the fields give (the inspection's item 2) and the grid of fixed inputs over
their range (items 3, 4 and 6): a short full-model population in each field, within a budget of
estimated simulation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.config import seed_everything
from surrogate.diagnosis.cost import STEP_SECONDS, cost_seconds, step_seconds
from surrogate.diagnosis.options import InspectOptions
from surrogate.models.base import Model
from surrogate.models.network import NetworkInternalModel
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import record_occupancy

#: cells per grid point below which a settling run stops rather than thins its cells (and the
#: fewest a population gets)
MIN_CELLS = 16
#: network states sampled for the sensitivities
MAX_STATES_SAMPLED = 2000
#: population records per cell (item 2)
RECORDS_PER_CELL = 50


@dataclass(frozen=True)
class Runs:
    """The full-model runs the inspection measures: what reproduce would run, as plain values.

    Attributes:
        model: the model.
        dt: its step (s).
        seed: the run's seed (each population is seeded with it).
        device: where the runs go.
        fields: the fields' names, in order.
        field_of: the field of a name (built on demand, in the order of ``fields``).
        start: ``(2,)`` where the cells start.
        t_end: the run's length (s).
        equilibration_time: the settling before records (s).
    """

    model: Model
    dt: float
    seed: int
    device: torch.device
    fields: tuple[str, ...]
    field_of: Callable[[str], Any]
    start: Sequence[float]
    t_end: float
    equilibration_time: float


@dataclass
class Population:
    """The inputs a short full-model population sees in each field (item 2).

    Attributes:
        x: ``rows x d`` the body's inputs, every field's records pooled.
        kinetic: ``rows x P`` the network's input parameters computed from them (networks).
        states: ``m x S`` network states at the runs' ends (networks).
        fields: per field: cells, duration, quantiles of every input, the share of phi = 1.
        notes: what was reduced to fit the budget.
        cost: the estimated seconds of simulation.
    """

    x: np.ndarray
    kinetic: np.ndarray | None
    states: Tensor | None
    fields: dict[str, dict[str, Any]]
    notes: list[str]
    cost: float


def network_of(model: Model) -> NetworkInternalModel | None:
    internal = model.internal
    return internal if isinstance(internal, NetworkInternalModel) else None


def population_inputs(runs: Runs, options: InspectOptions, seconds: float) -> Population:
    """Item 2: a full-model population in each field of ``runs.fields``, within ``seconds``
    of estimated simulation (the loop's measured cost per step and the model's per cell-step,
    as every stage's budget)."""
    o = options
    model, dt = runs.model, runs.dt
    network = network_of(model)
    names = tuple(model.internal.input_names)
    kinetic_names = network.kinetics.input_names if network is not None else ()
    step_cost = model.cell_step_seconds(dt, device=runs.device)
    burn_in = network.burn_in if network is not None and network.state_space is None else 0.0
    share = seconds / len(runs.fields)
    xs, kins, states, per_field, notes, spent = [], [], [], {}, [], 0.0
    equilibration = float(runs.equilibration_time)

    fixed = STEP_SECONDS  # the loop's cost per step in the field at hand (measured)

    def estimate(cells: int, span: float) -> float:
        steps = (span + equilibration + burn_in) / dt
        return cost_seconds(steps, cells, fixed, step_cost)

    for name in runs.fields:
        fixed = step_seconds(model, runs.field_of(name), dt, "full", runs.device)
        cells, span = int(o.population_cells), o.population_share * float(runs.t_end)
        if estimate(cells, span) > share:
            full = (cells, span)
            steps = (span + equilibration + burn_in) / dt
            cells = max(MIN_CELLS, int((share / steps - fixed) / step_cost))
            cells = min(cells, full[0])
            if estimate(cells, span) > share:  # even the fewest cells: a shorter run
                per_step = fixed + cells * step_cost
                span = max(10 * dt, share / per_step * dt - equilibration - burn_in)
            notes.append(f"{name}: {cells} cells for {span:.3g} s (not {full[0]} for "
                         f"{full[1]:.3g} s), within the budget")  # fmt: skip
        spent += estimate(cells, span)
        field = runs.field_of(name)
        seed_everything(runs.seed)
        simulator = Simulator(model, FullDecision(model.internal), field, dt, runs.device,
                              backend="auto")  # fmt: skip
        steps = max(1, round(span / dt))
        table = record_occupancy(simulator, cells, span, torch.tensor(runs.start),
                                 max(1, steps // RECORDS_PER_CELL), equilibration)  # fmt: skip
        x = table[list(names)].to_numpy(np.float64)
        xs.append(x)
        summary: dict[str, Any] = {"cells": cells, "seconds": span,
                                   "phi_share": float(table["phi"].mean()), "inputs": {}}  # fmt: skip
        columns = {n: x[:, i] for i, n in enumerate(names)}
        if network is not None:
            kin = network.kinetic_inputs(torch.tensor(x, dtype=torch.float32)).numpy()
            kins.append(kin)
            columns.update({n: kin[:, j] for j, n in enumerate(kinetic_names) if n not in columns})
            states.append(simulator.decision.fused_state()[0].cpu())
        q = o.quantiles
        for n, v in columns.items():
            summary["inputs"][n] = {"low": float(np.quantile(v, q[0])),
                                    "median": float(np.median(v)),
                                    "high": float(np.quantile(v, q[1])),
                                    "min": float(v.min()), "max": float(v.max())}  # fmt: skip
        per_field[name] = summary
    pooled_states = None
    if states:
        pooled_states = torch.cat(states)
        if pooled_states.shape[0] > MAX_STATES_SAMPLED:
            gen = torch.Generator().manual_seed(runs.seed)
            pick = torch.randperm(pooled_states.shape[0], generator=gen)[:MAX_STATES_SAMPLED]
            pooled_states = pooled_states[pick]
    return Population(np.concatenate(xs), np.concatenate(kins) if kins else None,
                      pooled_states, per_field, notes, spent)  # fmt: skip


@dataclass
class Grid:
    """Fixed inputs: row 0 every input at its median, then ``points`` values of each input
    from its low to its high quantile with the others at their median (an input whose range
    is one value gets none).

    Attributes:
        names: the body's inputs (columns of ``x``).
        x: ``G x d`` the grid points.
        axis: ``(G,)`` the input varied at each point (-1: the median point).
        low, median, high: ``(d,)`` the range of each input.
    """

    names: tuple[str, ...]
    x: np.ndarray
    axis: np.ndarray
    low: np.ndarray
    median: np.ndarray
    high: np.ndarray

    @classmethod
    def from_inputs(
        cls, x: np.ndarray, names: Sequence[str], quantiles: Sequence[float], points: int
    ) -> Grid:
        """The grid over the range of the pooled inputs ``x`` (``rows x d``)."""
        low, high = np.quantile(x, quantiles[0], axis=0), np.quantile(x, quantiles[1], axis=0)
        median = np.median(x, axis=0)
        rows, axis = [median], [-1]
        for i in range(x.shape[1]):
            if not high[i] > low[i]:
                continue
            for value in np.linspace(low[i], high[i], points):
                point = median.copy()
                point[i] = value
                rows.append(point)
                axis.append(i)
        return cls(tuple(names), np.stack(rows), np.array(axis), low, median, high)

    def ends(self) -> list[int]:
        """The points at the ends of each input's range (its lowest and highest value, the
        others at their median): where a period measured at the median is likeliest to differ
        most."""
        out: list[int] = []
        for i in range(self.x.shape[1]):
            on = np.flatnonzero(self.axis == i)
            if on.size:
                out += [int(on[np.argmin(self.x[on, i])]), int(on[np.argmax(self.x[on, i])])]
        return out

    def describe(self, g: int) -> str:
        """``L = 0.05`` (the input varied) or ``median``."""
        i = int(self.axis[g])
        return "median" if i < 0 else f"{self.names[i]} = {self.x[g, i]:.4g}"


__all__ = [
    "MAX_STATES_SAMPLED",
    "MIN_CELLS",
    "RECORDS_PER_CELL",
    "Grid",
    "Population",
    "Runs",
    "network_of",
    "population_inputs",
]

"""The inspect stage: a model measured before any collection, and an abstraction recommended.

``python3 scripts/inspect_model.py model=sbml model.spec=examples/toggle_switch/model.yaml``
writes ``report.md``, ``inspect.json`` and figures under ``data/inspect/<settings>/`` in about a
minute for a small network. Every figure is a measurement (the definitions are here and in
:mod:`surrogate.evaluate.dynamics`):

1. **The network** (internal models that are reaction networks): species and initial counts,
   global and reaction-local parameters, and for each input parameter the reactions whose
   propensities it enters and its *sensitivity*: for reaction r,
   ``S_r = sum_s |a_r(s, p_hi) - a_r(s, p_lo)| / sum_s (a_r(s, p_lo) + a_r(s, p_hi)) / 2``
   over network states s sampled from the population runs (item 2), with the input at the low
   and the high quantile of the values the fields give it and every other input at its median
   (``a_r`` the kinetics' own generated propensity function; 0 where the reaction never fires
   in those states). An input that enters no reaction, or moves no propensity by more than
   ``inspect.effect_threshold``, is flagged; so is one whose range is a single value.
2. **The inputs the fields give**: the inputs the body hands the internal model (and the
   network's input parameters computed from them) in a full-model population of
   ``inspect.population_cells`` cells for ``inspect.population_share`` of ``t_end`` in each field
   of ``fields``, from reproduce's ``start`` after its ``equilibration_time`` (fewer cells, then
   a shorter run, where the model's estimated cost exceeds a quarter of ``inspect.max_seconds``).
3. **phi's occupancy across that range**: at a grid of inputs (``inspect.grid_points`` values of
   each input from the low to the high quantile, the others at their median, and the point
   where every input is at its median), the stationary P(phi = 1): exactly, from the generator,
   where the state space has at most ``inspect.exact_max_states`` states; else the mean over
   ``inspect.n_cells`` cells at fixed inputs of each cell's average over the samples of the
   second half of a run from the file's counts (item 4), with its standard error across cells.
   A lump whose occupancy is below ``inspect.min_occupancy`` (or above 1 minus it) at every grid
   point is refused (ConfigError) once the report is written.
4. **Settling and relaxation**: from the file's initial counts at each grid point, the settling
   time of each species' mean count and of phi's occupancy
   (:func:`~surrogate.evaluate.dynamics.settling_time`: the time after which the mean stays
   within ``inspect.settle_tolerance`` of its final value or within the noise); simulated runs
   double their horizon from ``inspect.min_time`` until every grid point has settled in the
   first half (or ``inspect.max_time``, or the budget). The lump's relaxation time at the
   median inputs: ``1 / spectral gap`` of the generator where enumerable, else the decay time
   of phi's autocorrelation over ``inspect.record_windows`` windows of dt at stationarity
   (:func:`~surrogate.evaluate.dynamics.relaxation_from_series`). Where phi oscillates (its
   autocorrelation dips below ``-inspect.oscillation_depth`` beyond its noise,
   :func:`~surrogate.evaluate.dynamics.oscillation_from_acf`; exact where enumerable) the
   period and the decay of the oscillation's envelope are reported beside it: an exponential
   decay describes only the autocorrelation's first fall there. ``model.burn_in`` is compared
   with ``inspect.burn_in_factor`` x the settling time.
5. **Cost**: SSA events per window (the model's estimate from the file's initial state, which
   the stages' budgets use, and the mean at stationarity), the estimated cost of each stage of
   ``scripts/reproduce.py`` with the same settings (:mod:`surrogate.stages.budget`, at both
   rates), and the collection the switching implies: ``inspect.min_switches`` switches from
   each origin at the measured switching probability per window.
6. **A recommended abstraction**: at the median inputs at stationarity, the hazard of leaving
   phi against the time since phi last changed (exact from the lumped chain where enumerable,
   :func:`~surrogate.ctmc.lumped.lumped_age_psi`; else
   :func:`~surrogate.evaluate.dynamics.switch_hazards` with a chi-square test). A constant
   hazard: the two-state chain (``gp=svgp``; the default ``gp=auto`` where no classes are declared). One that depends on the age by more
   than ``inspect.memory_effect`` (and significantly): classes over bins of the species when
   the lump is a threshold on one species count (``gp=classes`` with ``classes: {species: P,
   edges: [...]}``, edges at the species' stationary quantiles on each side of the threshold;
   with ``gp.class_moves=relaxation`` for a network that settles over
   :data:`SLOW_SETTLING_WINDOWS` windows or more, :func:`settling_estimate`: where the run
   stopped before settling, at least half the run and ln(1 / tolerance) x phi's relaxation
   time), else the switch clock (``gp=clock`` with ``gp.max_age`` where the hazard flattens). A lump
   that oscillates (item 4) gets the switch clock whatever the lump: its memory is the cycle's
   phase, which the time since phi last changed measures (:func:`oscillation_advice`:
   ``gp.max_age`` the longest period, or 90th percentile of the segments' durations, over the
   range the fields give: exactly at every grid point, simulated at the ends of each input's
   range as well as the median).

Models whose internal model is not a network (``model=ecoli``) get items 2, 3, 4 (relaxation),
5 and 6 by simulation from their own initial state (their stationary law).

Before item 2, a network burned in from the file's counts (its state space not enumerated) is
probed (:func:`cost_probe`): a few cells from the file's counts at the file's input values, run
over the burn-in within a tenth of ``inspect.max_seconds``, their SSA calls capped in events.
Every estimate starts from the events at the file's counts; a network whose windows outgrow
them by orders of magnitude (a count growing without bound) is refused in seconds with the rate
it reached, instead of burning in for hours.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.config import seed_everything, to_dict
from surrogate.ctmc.lumped import (
    lumped_age_psi,
    lumped_psi,
    relaxation_time,
    stationary_distribution,
)
from surrogate.errors import ConfigError
from surrogate.evaluate.dynamics import (
    Oscillation,
    oscillation_from_acf,
    relaxation_from_series,
    segment_durations,
    settling_from_cells,
    settling_time,
    switch_hazards,
)
from surrogate.gp.class_relaxation import CELLS_PER_BIN, relaxation_cells
from surrogate.io import make_once, save_figure, write_json, write_manifest, write_text
from surrogate.models.base import Model
from surrogate.models.capabilities import lump_expr_of, lump_formula_of, signal_bounds_of
from surrogate.models.count_classes import threshold_of
from surrogate.models.network import NetworkInternalModel
from surrogate.sbml import SbmlModel
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import record_occupancy
from surrogate.stages import budget
from surrogate.stages import probe as network_probe
from surrogate.stages.artefacts import (
    INPUT_OCCUPANCY_FIGURE,
    INSPECTION,
    MEMORY_FIGURE,
    REPORT,
    SETTLING_FIGURE,
)
from surrogate.stages.inspection_report import (
    plot_memory,
    plot_occupancy,
    plot_settling,
    relaxation_text,
    report_markdown,
    settling_text,
)
from surrogate.stages.probe import counter_species
from surrogate.stages.settings import CollectSettings, InspectSettings

log = logging.getLogger(__name__)

#: shares of ``inspect.max_seconds``: the population runs (item 2) at most this ...
POPULATION_BUDGET = 0.25
#: ... and the settling runs at most this of what is left (the stationary record gets the rest)
SETTLING_BUDGET = 0.7
#: samples per doubling of a settling run's horizon
SAMPLES = 64
#: cells per grid point below which a settling run stops rather than thins its cells
MIN_CELLS = 16
#: network states sampled for the sensitivities
MAX_STATES_SAMPLED = 2000
#: population records per cell (item 2)
RECORDS_PER_CELL = 50
#: share of the stationary record's budget kept for the range's ends (simulated networks),
#: spent only where phi oscillates at the median inputs: the period there sets gp.max_age
RANGE_SHARE = 0.25
#: the cost probe's share of ``inspect.max_seconds`` (:func:`cost_probe`; its cells, calls and
#: growth rule: :mod:`surrogate.stages.probe`)
PROBE_BUDGET = 0.1


def validate(cfg: Mapping[str, Any]) -> InspectSettings:
    """The inspection's settings (the model built and checked), before any simulation."""
    settings = InspectSettings.from_config(cfg)
    log.info("inspect: at most ~%s of simulation (inspect.max_seconds=%g)",
             budget.duration(settings.options["max_seconds"]),
             settings.options["max_seconds"])  # fmt: skip
    return settings


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Inspect the model of ``cfg`` (or reuse the report); return the report's directory."""
    return inspect(validate(cfg), config=to_dict(cfg), force=force)


def inspect(
    settings: InspectSettings, config: Mapping[str, Any] | None = None, force: bool = False
) -> Path:
    """Run (or reuse) the inspection of ``settings``; log where its report is."""
    out = settings.directory
    make_once(out, settings.identity(), settings.command(),
              lambda _: _inspect(settings, out, config), what="inspection", force=force)  # fmt: skip
    log.info("inspection report: %s", out / REPORT)
    return out


# ----------------------------------------------------------------------------------------------
# before item 2: what a window of the network costs where it starts


def cost_probe(settings: InspectSettings) -> dict[str, Any] | None:
    """The network's cost measured before anything is run on the estimate from the file's
    counts (:func:`surrogate.stages.probe.cost_probe`), within :data:`PROBE_BUDGET` of
    ``inspect.max_seconds``: a network whose rate is still growing when that runs out is
    refused (ConfigError) with what was measured, the burn-in's and collect's cost at that
    rate and what to do. Returns what it measured (``None`` where it does not apply)."""
    max_seconds = float(settings.options["max_seconds"])
    naming = network_probe.Naming(
        stage="inspect",
        outgrew="the inspection",
        budget=f"{PROBE_BUDGET:.0%} of inspect.max_seconds={max_seconds:g}",
        remedy="a larger inspect.max_seconds (the probe gets a tenth of it)",
        collect=lambda cell_step: _collect_at(settings, cell_step),
    )
    setup = settings.setup
    return network_probe.cost_probe(setup.model, setup.dt, setup.seed, settings.job.device,
                                    PROBE_BUDGET * max_seconds, naming)  # fmt: skip


def _collect_source(settings: InspectSettings) -> CollectSettings | None:
    """The collection the inspected run would make (reproduce's training source), or None
    where its settings are not given or it trains on an external table."""
    try:
        source = settings.reproduce.train.source
    except ConfigError:
        return None
    return source if isinstance(source, CollectSettings) else None


def _collect_at(settings: InspectSettings, cell_step: float) -> tuple[float, str] | None:
    """Collect's estimated seconds at the full model's ``cell_step`` (s per cell-step) and
    the settings behind it; None where the collection's settings are not given."""
    source = _collect_source(settings)
    return None if source is None else network_probe.collect_cost(source, cell_step)


# ----------------------------------------------------------------------------------------------
# item 2: the inputs the fields give


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


def _network(model: Model) -> NetworkInternalModel | None:
    internal = model.internal
    return internal if isinstance(internal, NetworkInternalModel) else None


def population_inputs(settings: InspectSettings, seconds: float) -> Population:
    """Item 2: a full-model population in each field of ``settings.fields``, within ``seconds``
    of estimated simulation (the loop's measured cost per step and the model's per cell-step,
    as every stage's budget)."""
    setup, o, run_ = settings.setup, settings.options, settings.run
    model, dt = setup.model, setup.dt
    network = _network(model)
    names = tuple(model.internal.input_names)
    kinetic_names = network.kinetics.input_names if network is not None else ()
    step_cost = model.cell_step_seconds(dt)
    burn_in = network.burn_in if network is not None and network.state_space is None else 0.0
    share = seconds / len(settings.fields)
    xs, kins, states, per_field, notes, spent = [], [], [], {}, [], 0.0
    equilibration = float(run_["equilibration_time"])

    fixed = budget.STEP_SECONDS  # the loop's cost per step in the field at hand (measured)

    def estimate(cells: int, span: float) -> float:
        steps = (span + equilibration + burn_in) / dt
        return budget.cost_seconds(steps, cells, fixed, step_cost)

    for name in settings.fields:
        fixed = budget.step_seconds(model, settings.field_setup(name).field, dt, "full",
                                    settings.job.device)  # fmt: skip
        cells, span = int(o["population_cells"]), o["population_share"] * float(run_["t_end"])
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
        fsetup = settings.field_setup(name)
        seed_everything(setup.seed)
        simulator = Simulator(model, FullDecision(model.internal), fsetup.field, dt,
                              settings.job.device, backend="auto")  # fmt: skip
        steps = max(1, round(span / dt))
        table = record_occupancy(simulator, cells, span, torch.tensor(run_["start"]),
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
        q = o["quantiles"]
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
            gen = torch.Generator().manual_seed(setup.seed)
            pick = torch.randperm(pooled_states.shape[0], generator=gen)[:MAX_STATES_SAMPLED]
            pooled_states = pooled_states[pick]
    return Population(np.concatenate(xs), np.concatenate(kins) if kins else None,
                      pooled_states, per_field, notes, spent)  # fmt: skip


# ----------------------------------------------------------------------------------------------
# the grid of fixed inputs (items 3, 4, 6)


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


# ----------------------------------------------------------------------------------------------
# item 1: the network


def propensity_change(kinetics: Any, states: Tensor, low: Tensor, high: Tensor) -> np.ndarray:
    """The sensitivity of every reaction's propensity to a change of the inputs from ``low``
    to ``high`` (``(P,)`` each), over ``states`` (``m x S`` counts):
    ``sum_s |a_r(s, high) - a_r(s, low)| / sum_s (a_r(s, low) + a_r(s, high)) / 2``, 0 where the
    reaction never fires in those states. ``(R,)``."""
    m = states.shape[0]
    a_low = kinetics.torch_propensity(states, low.reshape(1, -1).expand(m, -1))
    a_high = kinetics.torch_propensity(states, high.reshape(1, -1).expand(m, -1))
    change = (a_high - a_low).abs().sum(0)
    mean = ((a_low + a_high) / 2).sum(0)
    return torch.where(mean > 0, change / mean.clamp_min(1e-300), 0.0).numpy()


def _fires(
    kinetics: Any, states: Tensor, low: Tensor, high: Tensor, enters: list[str],
    reactions: tuple[str, ...],
) -> bool:  # fmt: skip
    """Whether some reaction of ``enters`` has a positive propensity in some of ``states`` at
    ``low`` or ``high`` inputs."""
    m = states.shape[0]
    columns = [reactions.index(r) for r in enters]
    both = [kinetics.torch_propensity(states, x.reshape(1, -1).expand(m, -1))[:, columns]
            for x in (low, high)]  # fmt: skip
    return bool(any((a > 0).any() for a in both))


def describe_network(
    network: NetworkInternalModel, population: Population, grid: Grid, options: Mapping[str, Any]
) -> dict[str, Any]:
    """Item 1: species, parameters, and what each input feeds and whether it has an effect."""
    kinetics = network.kinetics
    reactions = network.reactions.reaction_names
    sbml = network.network if isinstance(network.network, SbmlModel) else None
    initial = network.initial_counts.tolist()
    out: dict[str, Any] = {
        "species": {s: int(c) for s, c in zip(network.species, initial, strict=True)},
        "reactions": list(reactions),
        "global_parameters": dict(sbml.parameters) if sbml else {},
        "local_parameters": dict(sbml.local_parameters) if sbml else {},
        "file_inputs": bool(sbml),
    }
    states = population.states
    assert states is not None and population.kinetic is not None
    kin = population.kinetic
    q = options["quantiles"]
    low, high = np.quantile(kin, q[0], axis=0), np.quantile(kin, q[1], axis=0)
    median = np.median(kin, axis=0)
    as_tensor = lambda v: torch.as_tensor(v, dtype=torch.float64)  # noqa: E731
    inputs = []
    for j, name in enumerate(kinetics.input_names):
        enters = [reactions[r] for r, e in enumerate(kinetics.propensity_exprs)
                  if j in e.inputs_used()]  # fmt: skip
        lo, hi = median.copy(), median.copy()
        lo[j], hi[j] = low[j], high[j]
        sens = propensity_change(kinetics, states, as_tensor(lo), as_tensor(hi))
        effect = {reactions[r]: float(sens[r]) for r in range(len(reactions))
                  if reactions[r] in enters}  # fmt: skip
        flags = []
        if not enters:
            flags.append("feeds no reaction")
        elif not high[j] > low[j]:
            flags.append("one value over the fields' range")
        elif not _fires(kinetics, states, as_tensor(lo), as_tensor(hi), enters, reactions):
            which = "its reactions never fire" if len(enters) > 1 else "its reaction never fires"
            flags.append(
                f"no effect seen: {which} in the states sampled (propensity 0 at "
                "both ends of the range: a species it needs is absent or used up)"
            )
        elif max(effect.values()) < options["effect_threshold"]:
            flags.append("no effect on its reactions' propensities in the states sampled")
        inputs.append({"name": name, "low": float(low[j]), "median": float(median[j]),
                       "high": float(high[j]), "reactions": enters, "sensitivity": effect,
                       "flags": flags})  # fmt: skip
    out["inputs"] = inputs
    # the body's inputs, through the model's features and input formulas
    body = []
    for i, name in enumerate(grid.names):
        xl, xh = grid.median.copy(), grid.median.copy()
        xl[i], xh[i] = grid.low[i], grid.high[i]
        both = network.kinetic_inputs(torch.as_tensor(np.stack([xl, xh]), dtype=torch.float32))
        sens = propensity_change(kinetics, states, both[0], both[1])
        body.append({"name": name, "low": float(grid.low[i]), "high": float(grid.high[i]),
                     "sensitivity": {reactions[r]: float(sens[r]) for r in range(len(reactions))
                                     if sens[r] > 0},
                     "effect": float(sens.max()) if sens.size else 0.0})  # fmt: skip
    out["body_inputs"] = body
    return out


# ----------------------------------------------------------------------------------------------
# items 3, 4 and 6 at fixed inputs

#: :attr:`FixedInputs.method`: measured on the network's generator, or on simulated cells (the
#: inspection's words; ``exact`` here is no decision=exact layer, issue 40)
EXACT_METHOD, SIMULATED_METHOD = "exact", "simulated"


@dataclass
class FixedInputs:
    """Occupancy, settling, relaxation and memory of phi at the grid's fixed inputs.

    Attributes:
        method: :data:`EXACT_METHOD` (the generator) or :data:`SIMULATED_METHOD`.
        occupancy, occupancy_se: ``(G,)`` the stationary P(phi = 1) at each grid point.
        settled: ``(G,)`` whether the point settled within the horizon.
        settle_phi: ``(G,)`` the settling time of phi's occupancy (s).
        settle_network: ``(G,)`` the largest settling time of a species' mean count (s).
        species_settle: per species, its settling time at the median point (s).
        curves: the median point's mean counts and occupancy over time (for the figure).
        horizon: the run's (or the exact curve's) length (s).
        relaxation: the lump's relaxation time at the median point (s) and how it was
            measured.
        hazards: per origin, the hazard of leaving it against the time since phi changed.
        memory: whether phi's switching has memory at the median point (None: it never
            switches there).
        switch: ``(2,)`` P(phi changes over a window | phi = 0, 1) at the median point.
        events: mean SSA events per window at stationarity at the median point (networks).
        species_law: per species, its stationary values and weights at the median point.
        stopped: the stationary share of the median point's cells (or probability, exactly)
            in a state where no reaction can fire (networks; None otherwise): near 1, the
            network runs down to an absorbing state (a closed system that consumes its
            substrate, a decay with no source) and phi stops changing.
        stopped_state: the most frequent such state (``{species: count}``), for the message.
        oscillation: whether phi oscillates at the median point (:func:`oscillation_dict`:
            its autocorrelation's negative lobe, period and, simulated, the durations of its
            segments); None where not measured.
        cells: cells per grid point (simulated).
        notes: what the budget cut.
        cost: estimated seconds of simulation.
    """

    method: str
    occupancy: np.ndarray
    occupancy_se: np.ndarray
    settled: np.ndarray
    settle_phi: np.ndarray
    settle_network: np.ndarray | None
    species_settle: dict[str, float]
    curves: dict[str, Any]
    horizon: float
    relaxation: dict[str, Any]
    hazards: list[dict[str, Any] | None]
    memory: bool | None
    switch: np.ndarray
    events: float | None
    species_law: dict[str, tuple[np.ndarray, np.ndarray]]
    stopped: float | None = None
    stopped_state: dict[str, int] | None = None
    oscillation: dict[str, Any] | None = None
    cells: int = 0
    notes: list[str] = field(default_factory=list)
    cost: float = 0.0

    @property
    def exact(self) -> bool:
        """Whether it was measured on the generator (:data:`EXACT_METHOD`), not on cells."""
        return self.method == EXACT_METHOD

    @property
    def settling_curves(self) -> bool:
        """Whether the median point's curves over time were kept (the settling figure): phi's
        curve, which every kept set of curves has."""
        return self.curves.get("phi") is not None


def _hazard_dict(h: Any, dt: float) -> dict[str, Any] | None:
    if h is None:
        return None
    return {"age_s": (h.edges * dt).tolist(), "rows": h.rows.tolist(),
            "hazard": h.hazard.tolist(), "se": h.se.tolist(), "pooled": h.pooled,
            "chi2": h.chi2, "df": h.df, "p_value": h.p_value, "effect": h.effect,
            "flat_from_s": h.flat_from * dt}  # fmt: skip


def oscillation_dict(
    found: Oscillation, dt: float, segments: Sequence[np.ndarray] | None = None
) -> dict[str, Any]:
    """An :class:`~surrogate.evaluate.dynamics.Oscillation` for inspect.json, with each lump's
    complete segments (:func:`~surrogate.evaluate.dynamics.segment_durations`, windows):
    their number, mean (s), coefficient of variation (1 for a memoryless lump's exponential
    durations; below 1 where the hazard rises with the age) and 90th percentile (s)."""
    out: dict[str, Any] = {k: (None if isinstance(v, float) and math.isnan(v) else v)
                           for k, v in vars(found).items()}  # fmt: skip
    out["segments"] = None
    if segments is not None:
        out["segments"] = [
            {"count": int(d.size), "mean_s": float(d.mean() * dt),
             "cv": float(d.std() / d.mean()), "q90_s": float(np.quantile(d, 0.9) * dt)}
            if d.size >= 2 else None for d in segments
        ]  # fmt: skip
    return out


def exact_fixed_inputs(
    network: NetworkInternalModel, grid: Grid, options: Mapping[str, Any], dt: float
) -> FixedInputs:
    """Items 3, 4 and 6 from the generator of an enumerable network (no simulation)."""
    space = network.state_space
    assert space is not None
    q = network.generator(torch.as_tensor(grid.x, dtype=torch.float32))  # (G, K, K)
    pi = stationary_distribution(q)
    states = space.states.to(torch.float64)
    lump = network.phi((space.states,)).to(torch.float64)
    occupancy = (pi @ lump).numpy()
    tau = relaxation_time(q).numpy()
    # settling from the file's counts: the law p0 exp(Q t) on a grid of times, doubled
    g_count, k = pi.shape
    rel = options["settle_tolerance"]
    finite = tau[np.isfinite(tau)]
    horizon = min(max(8 * float(finite.max()) if finite.size else 0.0, options["min_time"]),
                  options["max_time"])  # fmt: skip
    while True:
        steps = 512
        step = torch.linalg.matrix_exp(q * (horizon / steps))
        law = torch.zeros(g_count, k, dtype=torch.float64)
        law[:, 0] = 1.0  # states[0] is the initial state
        laws = [law]
        for _ in range(steps):
            law = torch.einsum("gk,gkj->gj", law, step)
            laws.append(law)
        laws_t = torch.stack(laws)  # (T, G, K)
        means = (laws_t @ states).numpy()  # (T, G, S)
        phi = (laws_t @ lump).numpy()  # (T, G)
        final_means, final_phi = (pi @ states).numpy(), occupancy
        times = np.linspace(0.0, horizon, steps + 1)
        zero = np.zeros(times.size)
        settle_phi = np.array([settling_time(times, phi[:, g], zero, final_phi[g], rel_tol=rel)
                               for g in range(g_count)])  # fmt: skip
        settle_species = np.array([[settling_time(times, means[:, g, s], zero,
                                                  final_means[g, s], rel_tol=rel)
                                    for s in range(states.shape[1])]
                                   for g in range(g_count)])  # fmt: skip
        settled = np.maximum(settle_phi, settle_species.max(1)) <= horizon / 2
        if settled.all() or horizon >= options["max_time"]:
            break
        horizon = min(2 * horizon, options["max_time"])
    # memory at the median inputs: the exact hazard against the age
    q0 = q[:1]
    tau0 = float(tau[0]) if math.isfinite(tau[0]) else dt
    ages = int(min(max(math.ceil(5 * tau0 / dt), 16), 2000))
    age_psi = lumped_age_psi(q0, lump > 0, dt, ages)[0].numpy()  # (2, A + 1)
    psi = lumped_psi(q0, lump > 0, dt)[0].numpy()
    hazards: list[dict[str, Any] | None] = []
    effects = []
    for v in (0, 1):
        h = age_psi[v] if v == 0 else 1.0 - age_psi[v]
        pooled = psi[v] if v == 0 else 1.0 - psi[v]
        mass = occupancy[0] if v == 1 else 1.0 - occupancy[0]
        if not (mass > 0 and pooled > 0 and np.isfinite(h).all()):
            hazards.append(None)
            continue
        effect = float(np.abs(h - pooled).max() / pooled)
        flat = settling_time(np.arange(h.size), h, np.zeros(h.size), float(h[-1]), rel_tol=rel)
        effects.append(effect)
        hazards.append({"age_s": (np.arange(h.size) * dt).tolist(), "rows": None,
                        "hazard": h.tolist(), "se": None, "pooled": float(pooled),
                        "chi2": None, "df": None, "p_value": None, "effect": effect,
                        "flat_from_s": float(flat) * dt})  # fmt: skip
    memory = None if len(effects) < 2 else max(effects) > options["memory_effect"]
    # phi's exact autocorrelation at lags 0..ages windows: cov(l) = sum pi f P^l f
    one = torch.linalg.matrix_exp(q0[0] * dt)
    f = lump - float(occupancy[0])
    ahead, cov = f.clone(), []
    for _ in range(ages + 1):
        cov.append(float((pi[0] * f * ahead).sum()))
        ahead = one @ ahead
    oscillation = None
    if cov[0] > 0:
        rho = np.asarray(cov) / cov[0]
        oscillation = oscillation_dict(
            oscillation_from_acf(rho, None, dt, options["oscillation_depth"]), dt
        )
        if oscillation["detected"] and g_count > 1:
            oscillation["over_range"] = [
                _exact_period(q[g], pi[g], lump, float(occupancy[g]), float(tau[g]), dt,
                              options["oscillation_depth"]) | {"at": grid.describe(g)}
                for g in range(1, g_count)
            ]  # fmt: skip
    switch = np.array([psi[0], 1.0 - psi[1]])
    median_inputs = network.kinetic_inputs(torch.as_tensor(grid.x[:1], dtype=torch.float32))
    a0 = network.kinetics.torch_propensity(space.states, median_inputs.expand(k, -1)).sum(1)
    events = float((pi[0] * a0).sum()) * dt
    dead = a0 <= 0
    stopped = float(pi[0][dead].sum())
    stopped_state = None
    if bool(dead.any()):
        where = int(torch.argmax(torch.where(dead, pi[0], -1.0)))
        stopped_state = dict(zip(network.species, space.states[where].tolist(), strict=True))
    species_law = {s: (space.states[:, j].numpy(), pi[0].numpy())
                   for j, s in enumerate(network.species)}  # fmt: skip
    curves = {"times": times.tolist(), "species": {s: means[:, 0, j].tolist()
                                                   for j, s in enumerate(network.species)},
              "final": {s: float(final_means[0, j]) for j, s in enumerate(network.species)},
              "phi": phi[:, 0].tolist(), "phi_final": float(final_phi[0])}  # fmt: skip
    relaxation = {"tau_s": float(tau[0]), "se": 0.0, "bound": "",
                  "method": "1 / spectral gap of the generator"}  # fmt: skip
    return FixedInputs(EXACT_METHOD, occupancy, np.zeros_like(occupancy), settled, settle_phi,
                       settle_species.max(1),
                       {s: float(settle_species[0, j]) for j, s in enumerate(network.species)},
                       curves, horizon, relaxation, hazards, memory, switch, events,
                       species_law, stopped, stopped_state, oscillation)  # fmt: skip


def _exact_period(
    q: Tensor, pi: Tensor, lump: Tensor, occupancy: float, tau: float, dt: float, depth: float
) -> dict[str, Any]:  # fmt: skip
    """Whether phi oscillates at one point of the grid and its period, from the generator
    ``q`` (``K x K``) and its stationary law ``pi``: the exact autocorrelation over the lags
    :func:`exact_fixed_inputs` takes at the median (five relaxation times, 16 to 2,000)."""
    ages = int(min(max(math.ceil(5 * (tau if math.isfinite(tau) else dt) / dt), 16), 2000))
    one = torch.linalg.matrix_exp(q * dt)
    f = lump - occupancy
    ahead, cov = f.clone(), []
    for _ in range(ages + 1):
        cov.append(float((pi * f * ahead).sum()))
        ahead = one @ ahead
    if not cov[0] > 0:
        return {"detected": False, "period_s": None, "q90_s": None}
    found = oscillation_from_acf(np.asarray(cov) / cov[0], None, dt, depth)
    period = float(found.period_s)
    return {"detected": bool(found.detected),
            "period_s": period if math.isfinite(period) else None, "q90_s": None}  # fmt: skip


def _range_periods(
    series: np.ndarray, group: np.ndarray, points: Sequence[int], grid: Grid, dt: float,
    depth: float,
) -> list[dict[str, Any]]:  # fmt: skip
    """Whether phi oscillates at each of ``points`` and its period and segments' 90th
    percentile, from each point's rows of ``series`` (cells x windows, at stationarity)."""
    out = []
    for g in points:
        rows = series[group == g]
        item: dict[str, Any] = {"at": grid.describe(g), "detected": False, "period_s": None,
                                "q90_s": None, "cells": int(rows.shape[0])}  # fmt: skip
        if rows.shape[0] >= 2:
            relax = relaxation_from_series(rows, dt, max_lag=max(1, (rows.shape[1] - 1) // 4))
            if np.isfinite(relax.rho[0]):
                found = oscillation_from_acf(relax.rho, relax.rho_se, dt, depth)
                durations = [d for d in segment_durations(rows) if d.size >= 2]
                period = float(found.period_s)
                item.update(detected=bool(found.detected),
                            period_s=period if math.isfinite(period) else None,
                            q90_s=max((float(np.quantile(d, 0.9) * dt) for d in durations),
                                      default=None))  # fmt: skip
        out.append(item)
    return out


def _take(state: tuple[Tensor, ...], index: Tensor) -> tuple[Tensor, ...]:
    return tuple(t.index_select(0, index.to(t.device)) for t in state)


def simulate_fixed_inputs(
    model: Model, grid: Grid, options: Mapping[str, Any], dt: float, device: torch.device,
    seconds: float,
) -> FixedInputs:  # fmt: skip
    """Items 3, 4 and 6 by simulation: ``inspect.n_cells`` cells at each grid point from the
    file's counts (a network) or the model's own initial state, run with a horizon doubled
    until every point has settled, then the median point's cells window by window at
    stationarity; within ``seconds`` of estimated simulation."""
    internal = model.internal
    network = _network(model)
    g_count, n = grid.x.shape[0], int(options["n_cells"])
    rel, alpha = options["settle_tolerance"], options["markov_alpha"]
    notes: list[str] = []
    x_grid = torch.as_tensor(grid.x, dtype=torch.float32, device=device)
    group = torch.arange(g_count).repeat_interleave(n)
    x = x_grid[group.to(device)]
    kin = network.kinetic_inputs(x) if network is not None else None
    state = network.start_state(x.shape[0], device, kin) if network is not None else \
        internal.initial_state(x)  # fmt: skip
    step_cost = model.cell_step_seconds(dt)

    def cost(state: tuple[Tensor, ...], kin: Tensor | None, cells: int, span: float) -> float:
        """Estimated seconds of advancing ``cells`` cells by ``span`` (the events expected at
        the cells' current states, at the model's cost per event)."""
        if network is None:
            return cells * span / dt * step_cost
        assert kin is not None  # a network's kinetic inputs
        a0 = network.kinetics.torch_propensity(state[0], kin).sum(1)
        return cells * network.cell_step_seconds(span, float(a0.mean()) * span)

    def sample(state: tuple[Tensor, ...]) -> tuple[np.ndarray, np.ndarray | None]:
        phi = internal.phi(state).cpu().numpy()
        counts = state[0].cpu().numpy().astype(np.float64) if network is not None else None
        return phi, counts

    budget_settle = SETTLING_BUDGET * seconds
    counters = counter_species(network) if network is not None else []
    if counters:
        assert network is not None
        names = ", ".join(network.species[j] for j in counters)
        notes.append(f"not waited for: {names}, made and never consumed nor read (counters "
                     "of events: their means grow for ever and change nothing else)")  # fmt: skip
    times, phis, counts = [0.0], [], []
    p, c = sample(state)
    phis.append(p)
    counts.append(c)
    t, horizon, spent = 0.0, max(options["min_time"], SAMPLES * dt), 0.0
    wall = time.perf_counter()
    while True:
        span = (horizon - t) / SAMPLES
        projected = SAMPLES * cost(state, kin, group.numel(), span)
        # a network's state holds its cells in rows (another model's is opaque: never thinned)
        while spent + projected > budget_settle and n // 2 >= MIN_CELLS and network is not None:
            old, n = n, n // 2  # thin every grid point's cells, keep the horizon growing
            keep = torch.cat([torch.arange(g * old, g * old + n) for g in range(g_count)])
            state, x = _take(state, keep), x[keep.to(device)]
            kin = kin[keep.to(device)] if kin is not None else None
            group = group[keep]
            phis = [v[keep.numpy()] for v in phis]
            counts = [v[keep.numpy()] if v is not None else None for v in counts]
            projected *= n / old
            notes.append(f"{n} cells per grid point from {t:g} s on (inspect.max_seconds)")
        if spent + projected > budget_settle:
            if t > 0:
                notes.append(f"the settling run stopped at {t:g} s (inspect.max_seconds)")
                break
            # not even the first horizon fits: a shorter one (the settling is then a bound)
            horizon = max(2 * dt, horizon * budget_settle / projected)
            span = horizon / SAMPLES
            notes.append(f"a first horizon of {horizon:g} s (inspect.max_seconds)")
        for _ in range(SAMPLES):
            spent += cost(state, kin, group.numel(), span)
            state = internal.advance(state, x, span)
            t += span
            p, c = sample(state)
            times.append(t)
            phis.append(p)
            counts.append(c)
        settle = _settling(np.array(times), np.stack(phis, 1), counts, group.numpy(), g_count,
                           rel, counters)  # fmt: skip
        if settle["settled"].all() or horizon >= options["max_time"]:
            if not settle["settled"].all():
                notes.append(f"not settled by inspect.max_time={options['max_time']:g} s")
            break
        horizon = min(2 * horizon, options["max_time"])
    settle_wall = time.perf_counter() - wall
    # the stationary record at the median point, window by window (a network's median cells
    # alone; another model's whole population, its state being opaque)
    median = (group == 0).nonzero().squeeze(1)
    windows = int(options["record_windows"])
    left = max(seconds - spent, 0.0)
    ends = grid.ends()
    rows: slice | np.ndarray
    if network is not None:
        assert kin is not None  # a network's kinetic inputs
        state_m, x_m, kin_m = _take(state, median), x[median.to(device)], kin[median.to(device)]
        per_window = cost(state_m, kin_m, 1, dt)
        # a share is kept for the range's ends, recorded where phi oscillates (the period)
        share = 1.0 - RANGE_SHARE if ends else 1.0
        affordable = share * left / max(per_window * windows, 1e-300)
        cells_m = int(min(median.numel(), max(affordable, MIN_CELLS)))
        state_m, x_m = _take(state_m, torch.arange(cells_m)), x_m[:cells_m]
        rows = slice(None)
    else:
        state_m, x_m, kin_m = state, x, None
        per_window = cost(state, None, 1, dt)
        cells_m, rows = group.numel(), median.numpy()
    if cells_m * per_window * windows > left:
        windows = max(200, int(left / max(cells_m * per_window, 1e-300)))
        notes.append(f"{windows} windows recorded at stationarity (inspect.max_seconds)")
    series = np.empty((median.numel() if network is None else cells_m, windows + 1), np.int8)
    # another model's whole population runs (its state opaque): every point's phi is kept
    everyone = np.empty((group.numel(), windows + 1), np.int8) if network is None else None
    phi_now = internal.phi(state_m).cpu().numpy()
    series[:, 0] = phi_now[rows]
    if everyone is not None:
        everyone[:, 0] = phi_now
    snapshots = []
    every = max(1, windows // 8)
    for k in range(1, windows + 1):
        state_m = internal.advance(state_m, x_m, dt)
        phi_now = internal.phi(state_m).cpu().numpy()
        series[:, k] = phi_now[rows]
        if everyone is not None:
            everyone[:, k] = phi_now
        if network is not None and k % every == 0:
            snapshots.append(state_m[0].cpu())
    spent += cells_m * windows * per_window
    cells_m = series.shape[0]
    relax = relaxation_from_series(series, dt, max_lag=max(1, windows // 4))
    hz = switch_hazards(series, alpha)
    hazards = [_hazard_dict(h, dt) for h in hz]
    oscillation = None
    depth = options["oscillation_depth"]
    if np.isfinite(relax.rho[0]):
        found = oscillation_from_acf(relax.rho, relax.rho_se, dt, depth)
        oscillation = oscillation_dict(found, dt, segment_durations(series))
    if oscillation is not None and oscillation["detected"] and ends:
        if everyone is not None:
            oscillation["over_range"] = _range_periods(everyone, group.numpy(), ends, grid,
                                                       dt, depth)  # fmt: skip
        else:
            assert kin is not None
            left = max(seconds - spent, 0.0)
            pick = torch.cat([(group == g).nonzero().squeeze(1) for g in ends])
            state_e, x_e, kin_e = _take(state, pick), x[pick.to(device)], kin[pick.to(device)]
            per_cell = cost(state_e, kin_e, 1, dt) * (windows + 1)
            cells_e = int(min(n, left / max(len(ends) * per_cell, 1e-300)))
            if cells_e >= MIN_CELLS // 2:
                keep = torch.cat([torch.arange(j * n, j * n + cells_e) for j in range(len(ends))])
                state_e, x_e = _take(state_e, keep), x_e[keep.to(device)]
                group_e = np.repeat(np.asarray(ends), cells_e)
                record = np.empty((group_e.size, windows + 1), np.int8)
                record[:, 0] = internal.phi(state_e).cpu().numpy()
                for k in range(1, windows + 1):
                    state_e = internal.advance(state_e, x_e, dt)
                    record[:, k] = internal.phi(state_e).cpu().numpy()
                spent += len(ends) * cells_e * per_cell
                oscillation["over_range"] = _range_periods(record, group_e, ends, grid, dt,
                                                           depth)  # fmt: skip
            else:
                notes.append("phi's period at the range's ends not measured "
                             "(inspect.max_seconds): gp.max_age from the median inputs'")  # fmt: skip
    memory = None
    if hz[0] is not None and hz[1] is not None:
        memory = any(h.p_value < alpha and h.effect > options["memory_effect"]
                     for h in (hz[0], hz[1]))  # fmt: skip
    before, after = series[:, :-1], series[:, 1:]
    switch = np.array([(after[before == v] != v).mean() if (before == v).any() else np.nan
                       for v in (0, 1)])  # fmt: skip
    events, species_law = None, {}
    stopped, stopped_state = None, None
    if network is not None:
        pooled = torch.cat(snapshots) if snapshots else state_m[0].cpu()
        assert kin_m is not None
        a0 = network.kinetics.torch_propensity(pooled, kin_m[:1].expand(pooled.shape[0], -1))
        events = float(a0.sum(1).mean()) * dt
        dead = a0.sum(1) <= 0
        stopped = float(dead.double().mean())
        if bool(dead.any()):
            values, counts = torch.unique(pooled[dead], dim=0, return_counts=True)
            state_row = values[int(torch.argmax(counts))].tolist()
            stopped_state = dict(zip(network.species, state_row, strict=True))
        weights = np.full(pooled.shape[0], 1.0 / pooled.shape[0])
        species_law = {s: (pooled[:, j].numpy(), weights) for j, s in enumerate(network.species)}
    relaxation = {"tau_s": relax.tau, "se": relax.tau_se, "amplitude": relax.amplitude,
                  "bound": relax.bound,
                  "lags": relax.lags, "acf": relax.rho.tolist(), "acf_se": relax.rho_se.tolist(),
                  "max_lag_s": (relax.rho.size - 1) * dt, "acf_at_max_lag": float(relax.rho[-1]),
                  "method": f"decay of phi's autocorrelation over {windows} windows of "
                            f"{cells_m} cells"}  # fmt: skip
    curves, species_settle = settle["curves"], {}
    if network is not None:
        species_settle = {s: r.time for s, r in zip(network.species, settle["species"],
                                                     strict=True)}  # fmt: skip
        curves["species"] = {s: np.asarray(curves["species"])[j].tolist()
                             for j, s in enumerate(network.species)}  # fmt: skip
        curves["final"] = dict(zip(network.species, curves["final"], strict=True))
    result = FixedInputs(
        SIMULATED_METHOD, settle["occupancy"], settle["occupancy_se"], settle["settled"],
        settle["phi"], settle["network"], species_settle, curves, t, relaxation,
        hazards, memory, switch, events, species_law, stopped, stopped_state, oscillation,
        int(n), notes, spent,
    )  # fmt: skip
    result.curves["wall_s"] = settle_wall
    return result


def _settling(
    times: np.ndarray,
    phi: np.ndarray,
    counts: list[np.ndarray | None],
    group: np.ndarray,
    g_count: int,
    rel: float,
    counters: list[int] | None = None,
) -> dict[str, Any]:
    """Settling and occupancy of every grid point from a run's samples (``phi``: cells x T).
    The noise bands share a family-wise level of 5 % over every curve tested (each point's phi
    and species), so that a run at its plateau is not taken for a drifting one by chance.
    ``counters``: species columns reported but not waited for (:func:`counter_species`)."""
    skip = set(counters or ())
    has_counts = counts[0] is not None
    c = np.stack([k for k in counts if k is not None], 2) if has_counts else None  # (cells, S, T)
    alpha = 0.05 / (g_count * (1 + (c.shape[1] if c is not None else 0)))
    out: dict[str, Any] = {k: np.zeros(g_count) for k in
                           ("occupancy", "occupancy_se", "phi", "network")}  # fmt: skip
    out["settled"] = np.zeros(g_count, dtype=bool)
    out["species"], out["curves"] = {}, {}
    for g in range(g_count):
        rows = group == g
        s_phi = settling_from_cells(times, phi[rows], rel, alpha)
        out["occupancy"][g], out["occupancy_se"][g] = s_phi.final, s_phi.final_se
        out["phi"][g] = s_phi.time
        settled = s_phi.settled
        worst = 0.0
        if c is not None:
            per_species = [
                settling_from_cells(times, c[rows, s], rel, alpha) for s in range(c.shape[1])
            ]
            waited = [r for j, r in enumerate(per_species) if j not in skip]
            worst = max((r.time for r in waited), default=0.0)
            settled = settled and all(r.settled for r in waited)
            if g == 0:
                out["species"] = per_species
                out["curves"] = {"times": times.tolist(),
                                 "species": c[rows].mean(0).tolist(),
                                 "final": [s.final for s in per_species],
                                 "phi": phi[rows].mean(0).tolist(), "phi_final": s_phi.final}  # fmt: skip
        elif g == 0:
            out["curves"] = {"times": times.tolist(), "phi": phi[rows].mean(0).tolist(),
                             "phi_final": s_phi.final}  # fmt: skip
        out["network"][g] = worst
        out["settled"][g] = settled
    if not has_counts:
        out["network"] = None
    return out


# ----------------------------------------------------------------------------------------------
# item 5: cost


def stage_costs(settings: InspectSettings, measured_step: float) -> dict[str, Any]:
    """The estimated cost of every stage of ``scripts/reproduce.py`` with the same settings,
    artefacts that exist counted as well (:mod:`surrogate.stages.budget`): at the model's cost
    per cell-step (what the stages' budgets say) and at ``measured_step`` (the events
    measured at stationarity); the full-model works only change."""
    try:
        rs = settings.reproduce
    except ConfigError as error:
        return {"rows": [], "note": f"not estimated: {error}"}
    source = rs.train.source
    collect = budget.collect_work(source, reuse=False) if isinstance(source, CollectSettings) \
        else []  # fmt: skip
    train = budget.train_work(rs.train, reuse=False)[len(collect) :]
    runs = [w for r in rs.runs() for w in budget.run_work(r, reuse=False)]
    rows: dict[tuple, dict[str, Any]] = {}  # identical works (one per field) counted once
    for stage, works in (("collect", collect), ("train", train), ("simulate", runs)):
        for w in works:
            at = replace(w, cell_step_seconds=measured_step) if w.full else w
            key = (stage, w.what, w.cells, w.steps, w.cell_step_seconds)
            row = rows.setdefault(key, {"stage": stage, "what": w.what, "count": 0,
                                        "cells": w.cells, "steps": w.steps,
                                        "estimate_s": w.seconds, "at_measured_s": at.seconds,
                                        "settings": w.settings})  # fmt: skip
            row["count"] += 1
    return {"rows": list(rows.values()), "note": ""}


def collection_budget(
    settings: InspectSettings,
    fixed: FixedInputs,
    population: Population,
    measured_step: float,
) -> dict[str, Any]:
    """The rows per origin that give ``inspect.min_switches`` switches from each origin at the
    switching probability per window measured at the median inputs, what collecting them
    costs, and the simulated time it takes at the population's occupancy of each lump."""
    o = settings.options
    source = _collect_source(settings)
    if source is None:
        return {}
    c, dt = source.options, settings.setup.dt
    needed = [math.ceil(o["min_switches"] / p) if p > 0 else math.inf for p in fixed.switch]
    rows = max(needed)
    out: dict[str, Any] = {"switch_per_window": fixed.switch.tolist(), "rows_needed": needed,
                           "n_per_state": int(c["n_per_state"])}  # fmt: skip
    if not math.isfinite(rows):
        return out
    out["recommended_n_per_state"] = max(int(rows), int(c["n_per_state"]))
    more = replace(source, options={**c, "n_per_state": out["recommended_n_per_state"]})
    work = budget.collect_work(more, reuse=False)
    out["cost_s"] = sum(replace(w, cell_step_seconds=measured_step).seconds for w in work)
    field = settings.setup.field_name
    share1 = population.fields.get(field, next(iter(population.fields.values())))["phi_share"]
    times = []
    for share in (1.0 - share1, share1):
        rate = int(c["n_cells"]) * share / (int(c["record_every"]) * dt)  # rows per second
        times.append(float(c["equilibration_time"]) + out["recommended_n_per_state"] / rate
                     if rate > 0 else math.inf)  # fmt: skip
    out["seconds_needed"] = times
    out["max_time"] = float(c["max_time"])
    longest, eq = max(times), float(c["equilibration_time"])
    if math.isfinite(longest) and longest > out["max_time"]:
        # either setting alone gives the rows in time: a longer run, or more cells (rows per
        # second grow with the cells)
        out["max_time_needed"] = _round_up(longest)
        if out["max_time"] > eq:
            out["n_cells_needed"] = math.ceil(int(c["n_cells"]) * (longest - eq)
                                              / (out["max_time"] - eq))  # fmt: skip
    return out


def collection_overrides(collection: Mapping[str, Any]) -> list[list[str]]:
    """The collection advice (:func:`collection_budget`) as override sets: the rows per origin,
    with the longer run or (else) the more cells it needs where ``collect.max_time`` is too
    short; empty where nothing is advised."""
    if not collection.get("recommended_n_per_state"):
        return []
    rows = f"collect.n_per_state={collection['recommended_n_per_state']}"
    if "max_time_needed" not in collection:
        return [[rows]]
    out = [[rows, f"collect.max_time={collection['max_time_needed']:g}"]]
    if "n_cells_needed" in collection:
        out.append([rows, f"collect.n_cells={collection['n_cells_needed']}"])
    return out


def check_printed(
    config: Mapping[str, Any] | None,
    advice: dict[str, Any],
    burn: dict[str, Any],
    collection: dict[str, Any],
    yaml_model: bool,
    balanced: dict[str, Any] | None = None,
) -> list[str]:
    """Every setting the report will print, checked by the stages' own settings checks
    (:func:`~surrogate.stages.advice_check.check_advice`) against the inspected ``config``;
    one refused is marked (``refused``: why) and printed as not advised. Returns the refusals.
    ``yaml_model``: the model is a yaml (its keys can be given as ``++model.<key>``);
    ``balanced``: the offered threshold (:func:`balanced_threshold`), a key of the yaml."""
    from surrogate.stages.advice_check import checked

    refusals = []

    def mark(target: dict[str, Any], overrides: list[str], what: str, yaml: str = "") -> None:
        reason = checked(config, overrides, what, yaml if yaml_model else "")
        if reason is not None:
            target["refused"] = reason
            refusals.append(f"{what}: {reason}")

    if advice.get("abstraction"):
        mark(advice, list(advice.get("overrides") or []), "the abstraction",
             advice.get("yaml", ""))  # fmt: skip
    if advice.get("alternative"):
        alternative = advice["alternative"]
        mark(alternative, list(alternative["overrides"]), "the declared classes",
             alternative["yaml"])  # fmt: skip
    if balanced and yaml_model:
        mark(balanced, [], "the balanced threshold", f'lump: "{balanced["lump"]}"')
    if advice.get("signal_bounds") and yaml_model:
        bounds: dict[str, Any] = {}
        mark(bounds, [], "signal_bounds", advice["signal_bounds"])
        if "refused" in bounds:
            del advice["signal_bounds"]
    if burn.get("applies") and burn.get("enough") is False and yaml_model:
        mark(burn, [], "the burn-in", f"burn_in: {burn['needed_s']:g}")
    sets = collection_overrides(collection)
    kept = []
    for overrides in sets:
        reason = checked(config, overrides, "the collection")
        if reason is None:
            kept.append(overrides)
        else:
            refusals.append(f"the collection ({' '.join(overrides)}): {reason}")
            collection.setdefault("refused", reason)  # the report says why where none runs
    if sets:
        collection["advised"] = kept
    return refusals


# ----------------------------------------------------------------------------------------------
# item 6: the abstraction


def signal_bounds_advice(
    internal: Any, fixed: FixedInputs, ranges: Mapping[str, tuple[float, float]]
) -> str | None:
    """The yaml's ``signal_bounds`` over the inputs' range the fields give, for an enumerable
    network that declares none (its exact chain, the method's limit, is then a table rather
    than exp(Q dt) per cell and step); else None."""
    if not fixed.exact or not ranges or signal_bounds_of(internal) is not None:
        return None
    listed = ", ".join(f"{n}: [{lo!r}, {hi!r}]" for n, (lo, hi) in ranges.items())
    return f"signal_bounds: {{{listed}}}"


#: outside this band of phi's occupancy at the median inputs the report offers a threshold
#: that balances the lumps there (one lump then gives few windows to learn its switching from)
BALANCE_BAND = (0.1, 0.9)


def balanced_threshold(internal: Any, fixed: FixedInputs) -> dict[str, Any] | None:
    """For a threshold lump whose occupancy at the median inputs lies outside
    :data:`BALANCE_BAND`: the threshold on the same species, at its stationary law there, that
    puts phi = 1 nearest 1/2 (``{"lump": "P2 >= 87", "occupancy": 0.49, "now": 0.0033}``);
    else None."""
    threshold = threshold_lump(internal)
    now = float(fixed.occupancy[0])
    if threshold is None or BALANCE_BAND[0] <= now <= BALANCE_BAND[1]:
        return None
    species, _, upper = threshold
    if species not in fixed.species_law:
        return None
    values, weights = (np.asarray(a, float) for a in fixed.species_law[species])
    if weights.sum() <= 0:
        return None
    levels = np.unique(values)
    # P(count >= v) at each level v
    at_least = np.array([weights[values >= v].sum() for v in levels]) / weights.sum()
    share = at_least if upper else 1.0 - at_least
    best = int(np.argmin(np.abs(share - 0.5)))
    edge = int(levels[best])
    return {
        "lump": f"{species} {'>=' if upper else '<'} {edge}",
        "occupancy": float(share[best]),
        "now": now,
    }


def threshold_lump(internal: Any) -> tuple[str, int, bool] | None:
    """``(species, edge, upper)`` where the lump is a threshold on one species count: phi = 1
    iff ``count >= edge`` (``upper``) or ``count < edge``; None for any other lump."""
    return threshold_of(lump_expr_of(internal))


def _weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    return float(values[order][min(np.searchsorted(cum, q * cum[-1]), values.size - 1)])


def class_edges(values: np.ndarray, weights: np.ndarray, edge: int, per_side: int) -> list[int]:
    """Bins of a species count for K lumps: the threshold ``edge`` and, on each side, edges at
    the ``j / per_side`` quantiles of the species' stationary law there (integers strictly
    inside the side; a side without mass gets none)."""
    edges = {int(edge)}
    below = values < edge
    for low in (True, False):
        w = weights * (below if low else ~below)
        if not w.sum() > 0:
            continue
        for j in range(1, per_side):
            cut = math.ceil(_weighted_quantile(values, w, j / per_side))
            if (low and 0 < cut < edge) or (not low and cut > edge):
                edges.add(cut)
    return sorted(e for e in edges if e > 0)


def input_ranges(
    network: NetworkInternalModel | None, population: Population
) -> dict[str, tuple[float, float]]:
    """Each kinetic input's range over the fields (the lowest low and highest high quantile of
    :attr:`Population.fields`), widened outward to two significant digits; inputs the fields
    leave at one value are left out."""
    if network is None:
        return {}
    out = {}
    for name in network.kinetics.input_names:
        spans = [f["inputs"][name] for f in population.fields.values() if name in f["inputs"]]
        if not spans:
            continue
        lo, hi = min(s["low"] for s in spans), max(s["high"] for s in spans)
        if hi > lo:
            out[name] = (_round_sig(lo, math.floor), _round_sig(hi, math.ceil))
    return out


def _round_sig(value: float, to: Callable[[float], int], digits: int = 2) -> float:
    """``value`` rounded with ``to`` (floor / ceil) at ``digits`` significant digits."""
    if value == 0:
        return 0.0
    scale = 10 ** (digits - 1 - math.floor(math.log10(abs(value))))
    return to(value * scale) / scale


def recommend(
    model: Model,
    fixed: FixedInputs,
    options: Mapping[str, Any],
    dt: float,
    input_ranges: Mapping[str, tuple[float, float]] | None = None,
) -> dict[str, Any]:
    """Item 6: the abstraction the memory measured at the median inputs calls for.

    ``input_ranges``: the network's kinetic inputs' range the fields give (:func:`input_ranges`):
    ``classes: auto`` then chooses its bins over that range, not at the file's values alone."""
    internal = model.internal
    hazards = fixed.hazards
    if fixed.memory is None:
        return {"abstraction": None, "command": "", "yaml": "",
                "reason": "phi does not switch both ways at the median inputs, so its memory "
                          "cannot be measured there"}  # fmt: skip
    exact = fixed.exact

    def describe(h: dict[str, Any], v: int) -> str:
        name = internal.lump_names[v]
        first = h["hazard"][0]
        if exact:
            test = f", departing from it by up to {h['effect']:.0%} with the age"
        else:
            departs = (f"age bins departing by up to {h['effect']:.0%} (beyond 3 standard "
                       f"errors)" if h["effect"] > 0 else "no age bin beyond 3 standard "
                       "errors")  # fmt: skip
            test = f", {departs}, chi-square p = {h['p_value']:.2g} over {h['df'] + 1} bins"
        return (f"leaving {name}: {first:.3g} per window at age 0 against {h['pooled']:.3g} "
                f"overall{test}")  # fmt: skip

    facts = "; ".join(describe(h, v) for v, h in enumerate(hazards) if h is not None)
    if not fixed.memory:
        return {"abstraction": "two-state", "command": "gp=svgp (what the default, gp=auto, runs for a model without classes)", "yaml": "",
                "overrides": ["gp=svgp"],
                "reason": f"the hazard of leaving each lump does not depend on the time since "
                          f"phi last changed ({facts}): phi's switching is Markov in the "
                          f"current input, as the two-state chain assumes"}  # fmt: skip
    threshold = threshold_lump(internal)
    if fixed.oscillation is not None and fixed.oscillation["detected"]:
        species = threshold[0] if threshold is not None else None
        return oscillation_advice(fixed.oscillation, internal.lump_names, facts, dt, species)
    if threshold is not None and threshold[0] in fixed.species_law:
        species, edge, upper = threshold
        values, weights = fixed.species_law[species]
        edges = class_edges(np.asarray(values, float), np.asarray(weights, float), edge,
                            int(options["classes_per_side"]))  # fmt: skip
        # each lump's bins on its own side of the threshold (model.classes' edges by lump)
        below, above = [e for e in edges if e < edge], [e for e in edges if e > edge]
        by_lump = dict(zip(internal.lump_names, (below, above) if upper else (above, below),
                           strict=True))  # fmt: skip
        # quoted: YAML reads bare off/on/yes/no as booleans
        listed = ", ".join(f'"{n}": [{", ".join(str(e) for e in v)}]' for n, v in by_lump.items())
        declared = f"classes: {{species: {species}, edges: {{{listed}}}}}"
        # a network can let the toolkit choose the count by measurement (the slow count that
        # holds the memory need not be the lump's species): model.classes=auto
        auto = isinstance(internal, NetworkInternalModel)
        over = ", ".join(f"{n}: [{lo!r}, {hi!r}]" for n, (lo, hi) in (input_ranges or {}).items())
        # a count that settles over many windows moves between bins too rarely per window to
        # learn, and its jitter across an edge reads as moves: its bins relax instead, finer
        est = settling_estimate(fixed, float(options["settle_tolerance"]))
        settling = est["seconds"]
        slow = auto and settling >= SLOW_SETTLING_WINDOWS * dt
        auto_options = [f"over: {{{over}}}"] if over else []
        if slow:
            # relaxation needs bins shared by both lumps: never the lump's own count's
            auto_options += [f"bins: {RELAXATION_BINS}", "shared: true"]
        yaml = (f"classes: {{auto: {{{', '.join(auto_options)}}}}}" if auto_options
                else "classes: auto") if auto else declared  # fmt: skip
        command = "gp=classes gp.class_moves=relaxation" if slow else "gp=classes"
        basis = f": {est['basis']}" if est["basis"] else ""
        relax = (f"; the network settles over {settling:.4g} s ({settling / dt:,.0f} windows"
                 f"{basis}), at least the {SLOW_SETTLING_WINDOWS:,} windows from which the bins "
                 f"move by relaxation to their stationary law (`gp.class_moves=relaxation`), "
                 f"not by a one-window law learned from rare, jittery crossings; "
                 f"{RELAXATION_BINS} bins per lump, the flips given each bin being learned from "
                 f"the windows, not from crossings, and the stationary sample "
                 f"{relaxation_cells(RELAXATION_BINS)} cells, {CELLS_PER_BIN} per bin" if slow else
                 f"; the network settles over {settling:.4g} s ({settling / dt:,.0f} windows"
                 f"{basis}), below the {SLOW_SETTLING_WINDOWS:,} windows from which bins relax "
                 f"(`gp.class_moves=relaxation`){est['caveat']}" if auto else "")  # fmt: skip
        # the lump's own species' bins, each lump's own: learned moves only (bins that relax
        # must hold both lumps), so offered beside auto with gp=classes alone
        alternative = {"overrides": ["gp=classes"], "yaml": declared,
                       "text": f"bins of the lump's own species at its stationary quantiles on "
                               f"each side of {edge}" + (", each lump's own (so learned moves, "
                               "not relaxation)" if slow else "")} if auto else None  # fmt: skip
        return {"abstraction": "classes", "command": command, "yaml": yaml,
                "overrides": command.split(),
                "settling_s": settling, "settling_basis": est["basis"],
                "declared": declared, "edges": edges, "edges_by_lump": by_lump,
                "species": species, "alternative": alternative,
                "reason": f"phi's switching has memory ({facts}) and the lump is a threshold on "
                          f"{species}: classes over bins of a count carry the hidden state"
                          + (" (`classes: auto` chooses the count whose bins best predict "
                             "the next phi, by a short seeded run"
                             + (" over the inputs' range the fields give" if over else "")
                             + ")" if auto else
                             f": bins of {species} at its stationary quantiles on each side of "
                             f"{edge}") + relax}  # fmt: skip
    flat = max(h["flat_from_s"] for h in hazards if h is not None)
    max_age = float(f"{max(flat, dt):.2g}")
    return {"abstraction": "clock", "command": f"gp=clock gp.max_age={max_age:g}", "yaml": "",
            "overrides": ["gp=clock", f"gp.max_age={max_age:g}"], "max_age": max_age,
            "reason": f"phi's switching has memory ({facts}); the lump is not a threshold on one "
                      f"species, so the switch clock carries it: the hazard is flat from "
                      f"{flat:.3g} s since the last change"}  # fmt: skip


def oscillation_advice(
    osc: Mapping[str, Any], lump_names: Sequence[str], facts: str, dt: float,
    species: str | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The switch clock for a lump that oscillates (:func:`oscillation_dict`), whatever the
    lump: the memory is the cycle's phase, which the time since phi last changed measures, not
    a count near a threshold that bins of it would hold. ``gp.max_age``: the largest of the
    period and the 90th percentile of either lump's segment durations (a cycle is one segment
    of each lump, so the clock covers the ages at which the segments end), at the median inputs
    and, where measured (``osc["over_range"]``: every grid point exactly, the ends of each
    input's range simulated), wherever phi oscillates over the range the fields give (a period
    that grows towards one end would outrun a cap from the median's), rounded up to two
    significant digits. ``species``: the threshold lump's species (the reason says why not
    classes over it)."""
    period = float(osc["period_s"])
    segments = [s for s in (osc.get("segments") or []) if s is not None]
    # the period (and the segments) wherever phi oscillates over the fields' range: the clock
    # must cover the longest cycle the population meets, not the median inputs' alone
    others = [p for p in (osc.get("over_range") or []) if p["detected"]]
    longest = max([period, dt] + [s["q90_s"] for s in segments]
                  + [p["period_s"] for p in others]
                  + [p["q90_s"] for p in others if p.get("q90_s") is not None])  # fmt: skip
    max_age = _round_up(longest)
    over = osc.get("over_range")
    if over:
        slowest = max(others, key=lambda p: p["period_s"], default=None)
        quiet = [p["at"] for p in over if not p["detected"]]
        across = (f"; over the range the fields give, the period is at most "
                  f"{slowest['period_s']:.3g} s ({slowest['at']})" if slowest is not None else
                  "; over the range the fields give it oscillates at the median alone")  # fmt: skip
        if quiet:
            across += f" (no oscillation found at {', '.join(quiet)})"
    else:
        across = ("; measured at the median inputs only (the range's ends not recorded, or "
                  "one value of each input)")  # fmt: skip
    trough = (f"its autocorrelation dips to {-osc['depth']:.2f}"
              + (f" +- {osc['depth_se']:.2g}" if osc["depth_se"] else "")
              + f" at a lag of {osc['trough_s']:.3g} s")  # fmt: skip
    if osc.get("crest") is not None:
        coherence = osc.get("coherence_s")
        forget = (f"; the cells forget their phase over ~{coherence:.3g} s" if coherence
                  is not None and math.isfinite(coherence) else "")  # fmt: skip
        trough += (f" and peaks again at {osc['crest']:.2f} at {period:.3g} s (the period"
                   f"{forget})")  # fmt: skip
    elif osc.get("bound"):
        trough += (f", the last lag measured (still falling: a period of at least "
                   f"{period:.3g} s; a longer record, `inspect.record_windows`, measures it)")  # fmt: skip
    else:
        trough += f" (no crest within the record: a period of about twice that, {period:.3g} s)"
    regular = ""
    if osc.get("segments"):
        parts = [f"{name} segments {s['mean_s']:.3g} s on average, coefficient of variation "
                 f"{s['cv']:.2f}, 90 % within {s['q90_s']:.3g} s"
                 for name, s in zip(lump_names, osc["segments"], strict=True) if s is not None]  # fmt: skip
        regular = (f"; {'; '.join(parts)} (a memoryless lump's durations are exponential, "
                   f"coefficient of variation 1)") if parts else ""  # fmt: skip
    why_not = (f". Classes over bins of {species} (the lump is a threshold on it) would hold "
               f"a count, not the phase" if species else "")  # fmt: skip
    return {"abstraction": "clock", "command": f"gp=clock gp.max_age={max_age:g}", "yaml": "",
            "overrides": ["gp=clock", f"gp.max_age={max_age:g}"],
            "max_age": max_age, "oscillation": True, "period_s": period,
            "reason": f"phi oscillates: {trough}, and no reversible network nor memoryless lump "
                      f"gives a negative autocorrelation (the check: below "
                      f"-{osc['depth_threshold']:g} and beyond {osc['z']:.1f} standard errors)"
                      f"{regular}. Its switching's memory ({facts}) is the cycle's phase, which "
                      f"the time since phi last changed measures: the switch clock carries it, "
                      f"its age capped at `gp.max_age={max_age:g}` s, the largest of the "
                      f"periods and the 90th percentiles of the segments' durations where the "
                      f"population lives{across}, so that it covers the ages at which both "
                      f"lumps' segments end{why_not}"}  # fmt: skip


def _round_up(value: float) -> float:
    """``value`` rounded up to two significant digits (a setting to recommend)."""
    if not (value > 0 and math.isfinite(value)):
        return value
    scale = 10 ** (math.floor(math.log10(value)) - 1)
    return math.ceil(value / scale - 1e-9) * scale


#: a network settling (from the file's counts) over at least this many windows gets classes
#: whose bins relax (:mod:`surrogate.gp.class_relaxation`). Set between the measured cases: the
#: auto-regulatory network settles over ~21,000 windows (1,060 s at dt 0.05) and its learned
#: moves between bins, ~1e-3 per window from 5-30 collected events each, mix the bins ~30x
#: too fast; a protein relaxing in 20 s settles over ~1,800
SLOW_SETTLING_WINDOWS = 10_000
#: bins per lump of ``classes: auto`` recommended where the bins relax: their flips are learned
#: from every window of the bin, not from rare crossings, so finer bins cost little data and
#: hold the count closer. The auto-regulatory network (docs/fidelity.md): 8 bins, 23 of 24
#: checks (a mean duration +3.009 %); 16 bins, 24 of 24 (durations -0.5 to +2.7 %)
RELAXATION_BINS = 16


def slowest_settling(fixed: FixedInputs) -> float:
    """The longest settling time (s) over the grid of the network's counts and phi (0 where
    none is finite)."""
    settle = fixed.settle_phi if fixed.settle_network is None else \
        np.maximum(fixed.settle_phi, fixed.settle_network)  # fmt: skip
    finite = settle[np.isfinite(settle)]
    return float(finite.max()) if finite.size else 0.0


def settling_estimate(fixed: FixedInputs, tolerance: float) -> dict[str, Any]:
    """The network's settling time (s) the inspection implies, for the rule of
    :data:`SLOW_SETTLING_WINDOWS`: ``{"seconds", "basis", "caveat"}``.

    Where every grid point settled: the longest settling over the grid
    (:func:`slowest_settling`; ``basis`` empty). Where the run stopped first (its budget,
    ``inspect.max_seconds``, or ``inspect.max_time``), the settling times measured are lower
    bounds that can fall far short: the auto-regulatory network at the default budget stopped
    at 640 s with 230 s measured, where 2,560 s of run measured 1,250 s. Then the larger of
    half the run (a point settles in the first half of its run) and ``ln(1 / tolerance)`` x
    phi's relaxation time at stationarity (a mean relaxing as ``exp(-t / tau)`` from a start
    as far from its plateau as the plateau is from 0 is within ``tolerance`` after that; the
    same network: 419 s, so ~1,250 s), each named in ``basis``; ``caveat`` says what would
    settle it."""
    measured = slowest_settling(fixed)
    if bool(fixed.settled.all()):
        return {"seconds": measured, "basis": "", "caveat": ""}
    half = fixed.horizon / 2
    parts = [f"not settled by the end of the inspector's {fixed.horizon:.3g}-s run: at least "
             f"{max(measured, half):.4g} s"]  # fmt: skip
    seconds = max(measured, half)
    tau = fixed.relaxation.get("tau_s")
    if tau is not None and math.isfinite(tau) and tau > 0:
        from_tau = math.log(1 / tolerance) * float(tau)
        se = fixed.relaxation.get("se")
        err = f" +- {se:.3g}" if se is not None and math.isfinite(se) and se > 0 else ""
        parts.append(f"phi's relaxation time at stationarity, {tau:.3g}{err} s, implies "
                     f"ln(1 / {tolerance:g}) x {tau:.3g} = {from_tau:.4g} s")  # fmt: skip
        seconds = max(seconds, from_tau)
    caveat = ("; the run did not settle, so a larger `inspect.max_seconds` (or "
              "`inspect.max_time`) would tell")  # fmt: skip
    return {"seconds": seconds, "basis": "; ".join(parts), "caveat": caveat}


def burn_in_advice(
    network: NetworkInternalModel | None,
    fixed: FixedInputs,
    factor: float,
    tolerance: float | None = None,
) -> dict[str, Any]:
    """``model.burn_in`` against ``factor`` x the network's settling time: the same estimate
    the recommendation states (:func:`settling_estimate` at ``tolerance``; without one, the
    longest settling over the grid, or half the run where it stopped first), with its
    ``basis`` and the grid points that did not settle. Where the run stopped before settling,
    that is a lower bound: a burn-in below it is too short, one above it is not known to be
    enough (``enough`` None), never told to shrink to it."""
    if network is None:
        return {"applies": False, "text": "the internal model draws its own initial state (no "
                                          "burn-in setting)"}  # fmt: skip
    if network.state_space is not None:
        return {"applies": False, "text": "not used: initial states are drawn from the exact "
                                          "stationary law (an enumerable network)"}  # fmt: skip
    settled = bool(fixed.settled.all())
    if tolerance is not None:
        est = settling_estimate(fixed, tolerance)
        worst, basis = float(est["seconds"]), str(est["basis"])
    else:
        worst = slowest_settling(fixed)
        worst, basis = (worst, "") if settled else (max(worst, fixed.horizon / 2), "")
    unsettled = [int(g) for g in np.flatnonzero(~np.asarray(fixed.settled, bool))]
    needed = _round_up(factor * worst)
    have = float(network.burn_in)
    return {"applies": True, "settling_s": worst, "settled": settled, "needed_s": needed,
            "burn_in_s": have, "enough": have >= needed if settled or have < needed else None,
            "basis": basis, "unsettled_points": unsettled, "text": ""}  # fmt: skip


# ----------------------------------------------------------------------------------------------
# the stage


def _inspect(settings: InspectSettings, out: Path, config: Mapping[str, Any] | None) -> None:
    """Measure, then write inspect.json, the figures, report.md and (last) the manifest; a
    lump (almost) never or always true is refused after the report is written."""
    t0 = time.perf_counter()
    setup, o = settings.setup, settings.options
    model, dt = setup.model, setup.dt
    internal, network = model.internal, _network(model)
    probe = cost_probe(settings)  # a runaway network refused in seconds, before any estimate
    seed_everything(setup.seed)
    population = population_inputs(settings, POPULATION_BUDGET * o["max_seconds"])
    grid = Grid.from_inputs(population.x, internal.input_names, o["quantiles"],
                            o["grid_points"])  # fmt: skip
    net = describe_network(network, population, grid, o) if network is not None else None
    seed_everything(setup.seed)
    space = network.state_space if network is not None else None
    left = max(o["max_seconds"] - population.cost, (1 - POPULATION_BUDGET) * o["max_seconds"])
    if network is not None and space is not None and space.n_states <= o["exact_max_states"]:
        fixed = exact_fixed_inputs(network, grid, o, dt)
    else:
        fixed = simulate_fixed_inputs(model, grid, o, dt, settings.job.device, left)
    model_events = network.events_per_window(dt) if network is not None else None
    step_model = model.cell_step_seconds(dt)
    step_measured = network.cell_step_seconds(dt, fixed.events) if network is not None \
        and fixed.events is not None else step_model  # fmt: skip
    costs = stage_costs(settings, step_measured)
    collection = collection_budget(settings, fixed, population, step_measured)
    burn = burn_in_advice(network, fixed, o["burn_in_factor"], o["settle_tolerance"])
    ranges = input_ranges(network, population)
    advice = recommend(model, fixed, o, dt, ranges)
    bounds = signal_bounds_advice(internal, fixed, ranges)
    if bounds:
        advice["signal_bounds"] = bounds
    balanced = balanced_threshold(internal, fixed)
    refused = check_printed(config if config is not None else settings.config, advice, burn,
                            collection, "spec" in (settings.config.get("model") or {}),
                            balanced)  # fmt: skip
    lump = lump_formula_of(internal) or "the model's own property"
    low = o["min_occupancy"]
    never, always = bool((fixed.occupancy < low).all()), bool((fixed.occupancy > 1 - low).all())
    stops = fixed.stopped is not None and fixed.stopped > 1 - low
    summary: dict[str, Any] = {
        "model": model.describe(), "command": settings.command(), "lump": lump,
        "settings": dict(o),
        "lump_names": list(internal.lump_names), "dt": dt, "fields": list(settings.fields),
        "network": net,
        "population": {"fields": population.fields, "notes": population.notes,
                       "estimated_s": population.cost},
        "grid": {"inputs": list(grid.names), "x": grid.x.tolist(), "axis": grid.axis.tolist(),
                 "low": grid.low.tolist(), "median": grid.median.tolist(),
                 "high": grid.high.tolist()},
        "occupancy": {"method": fixed.method, "value": fixed.occupancy.tolist(),
                      "se": fixed.occupancy_se.tolist(), "settled": fixed.settled.tolist(),
                      "never": never, "always": always, "threshold": low,
                      "balanced": balanced},
        "settling": {"horizon_s": fixed.horizon, "phi_s": fixed.settle_phi.tolist(),
                     "network_s": None if fixed.settle_network is None
                     else fixed.settle_network.tolist(),
                     "species_s_at_median": fixed.species_settle, "cells": fixed.cells,
                     "notes": fixed.notes, "estimated_s": fixed.cost},
        "relaxation": {k: v for k, v in fixed.relaxation.items() if k not in ("acf", "acf_se")},
        "burn_in": burn,
        "memory": {"memory": fixed.memory, "hazards": fixed.hazards},
        "oscillation": fixed.oscillation,
        "stopped": {"share": fixed.stopped, "state": fixed.stopped_state, "stops": stops},
        "cost": {"events_per_window_model": model_events,
                 "events_per_window_stationary": fixed.events,
                 "cell_step_s_model": step_model, "cell_step_s_measured": step_measured,
                 "probe": probe,
                 "stages": costs, "collection": collection},
        "recommendation": advice,
        "advice_refused": refused,
    }  # fmt: skip
    save_figure(out / INPUT_OCCUPANCY_FIGURE, plot_occupancy(grid, fixed, str(lump), low),
                crop=False)  # fmt: skip
    if fixed.settling_curves:
        burn_in = burn.get("burn_in_s") if burn.get("applies") else None
        save_figure(out / SETTLING_FIGURE, plot_settling(fixed, burn_in), crop=False)
    save_figure(out / MEMORY_FIGURE, plot_memory(fixed, dt, internal.lump_names), crop=False)
    # refused once measured at stationarity; a run cut short only warns
    refusal = _stopped(summary, fixed) if stops else (
        _refusal(summary, grid, fixed) if (never or always) else None)  # fmt: skip
    settled = bool(fixed.settled.all())
    summary["refused"] = refusal if settled else None
    summary["warning"] = None if settled or refusal is None else (
        f"{refusal}; measured at the end of a run that had not settled: it is refused if so "
        f"at stationarity (raise inspect.max_seconds to see)")  # fmt: skip
    summary["wall_time_s"] = time.perf_counter() - t0
    write_json(out / INSPECTION, summary)
    write_text(out / REPORT, report_markdown(summary, fixed))
    if summary["refused"] is not None:
        raise ConfigError(f"{refusal} (report: {out / REPORT})")
    write_manifest(out, stage="inspect", config=dict(config) if config is not None
                   else settings.identity(), seed=setup.seed, settings=settings.identity(),
                   device=str(settings.job.device), wall_time_s=summary["wall_time_s"],
                   occupancy=fixed.occupancy.tolist(), recommendation=advice["abstraction"])  # fmt: skip
    log.info("inspect: %s iff %s; occupancy %.3g-%.3g over the grid (%s); settling %s; "
             "relaxation %s; recommended: %s; %.1f s", internal.lump_names[1], lump,
             float(fixed.occupancy.min()), float(fixed.occupancy.max()), fixed.method,
             settling_text(summary), relaxation_text(summary["relaxation"]),
             advice["abstraction"], summary["wall_time_s"])  # fmt: skip


def _stopped(summary: dict[str, Any], fixed: FixedInputs) -> str:
    """The refusal of a network that runs down to a state where no reaction can fire: phi
    stops changing there whatever the lump, so no lump can be learned."""
    state = ", ".join(f"{k} = {v}" for k, v in (fixed.stopped_state or {}).items())
    exact = fixed.exact
    who = "of the stationary probability lies" if exact else "of the cells sit"
    return (
        f"the network stops: at stationarity at the median inputs, {fixed.stopped:.1%} "
        f"{who} in a state where no reaction can fire (e.g. {state}), so phi "
        f"(`{summary['lump']}`) never changes there, whatever the lump; collect could not see "
        "switches. The network runs down (a closed system that uses up its substrate, a decay "
        "with no source): a chain of phi needs a network that keeps switching at fixed "
        "inputs, e.g. one with a source reaction (an inflow, synthesis) that refills what the "
        "others consume"
    )


def _refusal(summary: dict[str, Any], grid: Grid, fixed: FixedInputs) -> str:
    """The refusal of a lump (almost) never or always true over the input range."""
    occ, se = fixed.occupancy, fixed.occupancy_se
    which = "never" if summary["occupancy"]["never"] else "always"
    worst = int(np.argmax(occ)) if which == "never" else int(np.argmin(occ))
    ranges = ", ".join(f"{n} in [{lo:.4g}, {hi:.4g}]" for n, lo, hi in
                       zip(grid.names, grid.low, grid.high, strict=True))  # fmt: skip
    return (f"the lump {summary['lump']!r} is (almost) {which} true over the input range the "
            f"fields give ({ranges}): P(phi = 1) = {occ[worst]:.3%} +- {se[worst]:.2%} at its "
            f"{'highest' if which == 'never' else 'lowest'} ({grid.describe(worst)}; "
            f"{fixed.method}), beyond inspect.min_occupancy="
            f"{summary['occupancy']['threshold']:g} at all {occ.size} grid points; collect "
            f"could not see both lumps. Choose a lump that holds part of the time (model.lump; "
            f"the report gives the stationary counts)")  # fmt: skip


__all__ = [
    "FixedInputs",
    "Grid",
    "Population",
    "burn_in_advice",
    "class_edges",
    "cost_probe",
    "describe_network",
    "exact_fixed_inputs",
    "inspect",
    "oscillation_advice",
    "oscillation_dict",
    "population_inputs",
    "propensity_change",
    "recommend",
    "run",
    "settling_estimate",
    "simulate_fixed_inputs",
    "stage_costs",
    "threshold_lump",
    "validate",
]

"""The cost probe: what a window of a network costs where its cells start, measured in seconds
before a stage spends its budget on the estimate from the file's counts.

Every estimate (the inspector's budget, each stage's :mod:`~surrogate.stages.budget`) starts
from the SSA events per window at the SBML file's counts. A network burned in from those counts
(its state space not enumerated) may outgrow them by orders of magnitude (a count growing
without bound, often a unit or volume slip), and then one cell's burn-in is one SSA call of
hours with no output. :func:`cost_probe` runs :data:`PROBE_CELLS` cells from the file's counts
at the file's input values over the burn-in within a wall-clock budget, each SSA call capped in
events, and refuses (a ConfigError) a network whose rate is still growing when the budget runs
out, naming what it measured and the remedies. The inspect stage gives it a tenth of
``inspect.max_seconds``, collect ``collect.probe_seconds`` (a :class:`Naming` says which, and
what else to do).

The probe draws on a fork of torch's generators (seeded with the run's seed): the run's random
stream is the same with and without it.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from surrogate.diagnosis.cost import cuda_devices, duration
from surrogate.errors import ConfigError, RunawayError
from surrogate.models.base import Model
from surrogate.models.network import NetworkInternalModel

log = logging.getLogger(__name__)


#: the probe's cells, the most SSA calls it makes over its horizon (longer windows than dt
#: beyond), the horizon where the network has no burn-in (windows of dt), the species its
#: refusal names
PROBE_CELLS = 4
PROBE_CALLS = 1000
PROBE_MIN_WINDOWS = 100
PROBE_SPECIES = 2
#: the share of the model time reached whose windows give the rate the collection records at
#: (``events_per_window_last``: their mean, after the burn-in where the probe completes)
PROBE_TAIL = 0.1
#: a probe out of budget is refused where its rate was still growing: the events per window it
#: reached (or the cap a window exceeded) at least this many times those at half its model time
#: (a steady, merely costly network goes on, with a warning: a wall-clock limit alone would
#: refuse it on a loaded machine)
PROBE_GROWTH = 10.0

#: the cost of a collection at a cell-step's cost (s per cell-step) -> (seconds, its settings)
CollectCost = Callable[[float], "tuple[float, str] | None"]


@dataclass(frozen=True)
class Naming:
    """What a stage's probe names: ``stage`` prefixes its log lines and refusal, ``outgrew``
    what the cost outgrew, ``budget`` where its seconds come from (in brackets after them),
    ``remedy`` the setting that gives it more, ``more`` a closing sentence (with its
    separator), ``collect`` collect's cost at the measured rate (None: not named) and
    ``collect_name`` what that collection is called."""

    stage: str
    outgrew: str
    budget: str
    remedy: str
    more: str = ""
    collect: CollectCost | None = None
    collect_name: str = "collect's default budget"


def probed_network(model: Model) -> NetworkInternalModel | None:
    """The network a probe runs: a network internal model whose state space is not
    enumerated (its cells start from the file's counts and a burn-in; an enumerated one is
    bounded) with input values of its own (SBML); else None."""
    network = model.internal
    if not isinstance(network, NetworkInternalModel) or network.state_space is not None:
        return None
    return network if network.file_inputs() is not None else None


def cost_probe(
    model: Model, dt: float, seed: int, device: Any, budget_s: float, naming: Naming
) -> dict[str, Any] | None:
    """The network's cost measured before anything is run on the estimate from the file's
    counts: :data:`PROBE_CELLS` cells from the file's counts at the file's input values (where
    :meth:`~surrogate.models.network.NetworkInternalModel.events_per_window` estimates it)
    advanced window by window over the burn-in (:data:`PROBE_MIN_WINDOWS` windows of dt where
    there is none; at most :data:`PROBE_CALLS` calls), within ``budget_s`` seconds: each call
    refuses more events per cell than what is left of that budget buys at the SSA's cost per
    event (``max_events``), and the wall clock is checked between calls. A network whose
    windows outgrow it is refused (ConfigError) with what was measured: the events per window
    it reached, and when, the species that grew most, the burn-in's and collect's cost at that
    rate, and what to do; where its rate was still growing (:data:`PROBE_GROWTH`), else a
    warning.

    Only networks of :func:`probed_network`. Returns what it measured (``None`` where it does
    not apply, or where the file's input values give rates the SSA refuses: the runs at the
    fields' inputs report those), among it ``events_per_window_last``: the mean events per
    window per cell over the last :data:`PROBE_TAIL` of the model time reached (after the
    burn-in where it ``completed``: what collect prices its windows at). Torch's generators
    are forked: the caller's stream is left as it was."""
    network = probed_network(model)
    if network is None:
        return None
    file_inputs = network.file_inputs()
    assert file_inputs is not None  # probed_network checked it
    device = torch.device(device)
    cells, stage = PROBE_CELLS, naming.stage
    horizon = network.burn_in if network.burn_in > 0 else PROBE_MIN_WINDOWS * dt
    span = max(dt, horizon / PROBE_CALLS)
    inputs = file_inputs.to(device).expand(cells, -1).clone()
    file_events = network.events_per_window(dt)
    per_event = network.event_seconds(device)
    network.prepare(device)  # the SSA's compile is not the network's cost

    def events(counts: Tensor) -> float:
        """Expected events per window of dt per cell at ``counts`` (the cells' mean)."""
        a0 = network.kinetics.torch_propensity(counts, inputs).clamp_min(0).sum(1)
        return float(a0.mean()) * dt

    with torch.random.fork_rng(devices=cuda_devices(device)):
        torch.manual_seed(seed)
        try:
            state = network.start_state(cells, device, inputs)
        except (ValueError, ConfigError) as error:
            log.debug("%s: no cost probe at the file's inputs (%s)", stage, error)
            return None
        t, times, rates, tripped = 0.0, [0.0], [events(state[0])], None
        wall = time.perf_counter()
        while t < horizon * (1 - 1e-12):
            left = budget_s - (time.perf_counter() - wall)
            if left <= 0:
                break
            cap = max(1, int(left / per_event / cells))
            step = min(span, horizon - t)
            try:
                state = network.advance_at(state, inputs, step, max_events=cap)
            except RunawayError:  # the cap: a window past the budget's events
                tripped = (cap, step)
                break
            except (ValueError, ConfigError) as error:
                log.debug("%s: the cost probe stopped at the file's inputs (%s)", stage, error)
                return None
            t += step
            times.append(t)
            rates.append(events(state[0]))
        wall_s = time.perf_counter() - wall
    counts = state[0].double().mean(0).cpu()
    # still growing: the rate reached (or the window the cap stopped) against half-way's
    reached = max(rates[-1], tripped[0] * dt / tripped[1] if tripped is not None else 0.0)
    earlier = rates[max(i for i, u in enumerate(times) if u <= t / 2)]
    growth = reached / earlier if earlier > 0 else (math.inf if reached > 0 else 1.0)
    # the rate where the collection records: the mean over the last windows (one at least)
    last = [r for u, r in zip(times, rates, strict=True) if u > 0 and u >= (1 - PROBE_TAIL) * t]
    probe = {"cells": cells, "horizon_s": horizon, "reached_s": t, "wall_s": wall_s,
             "budget_s": budget_s, "events_per_window_file": file_events,
             "events_per_window_end": rates[-1], "events_per_window_max": max(rates),
             "events_per_window_last": sum(last) / len(last) if last else rates[-1],
             "growth": growth, "burn_in_s": network.burn_in,
             "counts_end": dict(zip(network.species, counts.tolist(), strict=True)),
             "completed": t >= horizon * (1 - 1e-12)}  # fmt: skip
    log.info("%s: cost probe, %d cells from the file's counts for %.3g of %.3g s in %.2g "
             "s: %.3g events per window at the end (%.3g from the file's counts)", stage, cells,
             t, horizon, wall_s, rates[-1], file_events)  # fmt: skip
    if not probe["completed"]:
        if growth >= PROBE_GROWTH:
            raise ConfigError(refusal(network, dt, probe, tripped, naming))
        log.warning("%s: the cost probe ran out of its %.2g s at %.3g s of %.3g s with the "
                    "rate steady (%.3g events per window, %.2gx half-way's): the burn-ins cost "
                    "more than the estimates from the file's counts say", stage, budget_s, t,
                    horizon, rates[-1], growth)  # fmt: skip
    return probe


def refusal(
    network: NetworkInternalModel,
    dt: float,
    probe: dict[str, Any],
    tripped: tuple[int, float] | None,
    naming: Naming,
) -> str:
    """What the cost probe measured, what it costs at that rate, and what to do."""
    rate, file_rate = probe["events_per_window_end"], probe["events_per_window_file"]
    times = rate / file_rate if file_rate > 0 else math.inf
    start = network.initial_counts.double().tolist()
    end = probe["counts_end"]
    counters = {network.species[j] for j in counter_species(network)}  # they grow anyway
    growth = sorted((s for s in network.species if s not in counters),
                    key=lambda s: -(end[s] + 1) / (start[network.species.index(s)] + 1))  # fmt: skip
    grown = ", ".join(f"{s} = {end[s]:,.0f} from {start[network.species.index(s)]:,.0f}"
                      for s in growth[:PROBE_SPECIES]
                      if end[s] > start[network.species.index(s)])  # fmt: skip
    cell_step = network.cell_step_seconds(dt, rate)
    burn = network.burn_in / dt * cell_step if network.burn_in > 0 else 0.0
    values = network.file_inputs()
    inputs = ", ".join(f"{n} = {v:g}" for n, v in zip(
        network.kinetics.input_names, values.tolist() if values is not None else [],
        strict=False))  # fmt: skip
    horizon = "model.burn_in" if network.burn_in > 0 else f"{PROBE_MIN_WINDOWS} windows"
    text = (f"{naming.stage}: the network's cost outgrew {naming.outgrew}: {probe['cells']} "
            f"cells from the file's counts at the file's input values ({inputs}) ran out of "
            f"the cost probe's {probe['budget_s']:.2g} s ({naming.budget}) at model time "
            f"{probe['reached_s']:.3g} s of {probe['horizon_s']:.3g} s ({horizon}), after "
            f"{probe['wall_s']:.2g} s: there they fire ~{rate:,.0f} events per window of "
            f"dt={dt:g} s per cell, {times:,.0f} x the {file_rate:,.0f} estimated from the "
            "file's counts that every budget uses")  # fmt: skip
    if tripped is not None:
        text += (f"; the next {tripped[1]:.3g} s needed more than {tripped[0]:,} events "
                 "per cell")  # fmt: skip
    if grown:
        text += f". Fastest-growing: {grown}"
    costs = []
    if burn > 0:
        costs.append(f"one cell's burn-in of {network.burn_in:g} s would take "
                     f"~{duration(burn)} of CPU")  # fmt: skip
    collect = naming.collect(cell_step) if naming.collect is not None else None
    if collect is not None:
        costs.append(f"{naming.collect_name} ({collect[1]}) ~{duration(collect[0])}")
    if costs:
        text += f". At that rate (still growing: a bound) {', '.join(costs)}"
    return text + (
        ". A count that grows without bound is often a unit or volume slip: check the rates "
        "and units of the SBML file (substance units, compartment sizes, the rate constants, "
        f"model.substance_units); else a shorter model.burn_in, {naming.remedy}, or "
        f"device=cuda (the batched SSA){naming.more}"
    )


def counter_species(network: NetworkInternalModel) -> list[int]:
    """The columns of species that only count events: made by some reaction, consumed by
    none, read by no propensity, rule, event or the lump (a waste product such as StochSS's
    Brusselator's C and D). Their means grow for ever and change nothing else, so a settling
    run does not wait for them (nor does the probe name them as growing)."""
    kinetics = network.kinetics
    reactions = kinetics.network
    read: set[int] = set()
    for expr in kinetics.propensity_exprs:
        read |= expr.species_used()
    for rule in kinetics.rules:
        read |= rule.expr.species_used() | {rule.column}
    for event in kinetics.events:
        read |= event.trigger.species_used()
        for column, expr in event.assignments:
            read |= expr.species_used() | {column}
    if network.lump_expr is not None:
        read |= network.lump_expr.species_used()
    consumed = (reactions.reactants > 0).any(0).tolist()
    made = (reactions.products > 0).any(0).tolist()
    return [j for j in range(len(network.species))
            if made[j] and not consumed[j] and j not in read]  # fmt: skip


__all__ = [
    "PROBE_CELLS",
    "PROBE_GROWTH",
    "PROBE_TAIL",
    "Naming",
    "cost_probe",
    "counter_species",
    "probed_network",
    "refusal",
]

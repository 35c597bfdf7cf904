"""The inspect stage: a model measured before any collection, and its chain kind measured.

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
6. **The memory**: at the median inputs at stationarity, the hazard of leaving phi against the
   time since phi last changed (exact from the lumped chain where enumerable,
   :func:`~surrogate.ctmc.lumped.lumped_age_psi`; else
   :func:`~surrogate.evaluate.dynamics.switch_hazards` with a chi-square test): Markov where it
   is constant; with memory where it depends on the age by more than ``inspect.memory_effect``
   (and significantly), and then the switch clock's cap it suggests (where the hazard
   flattens; where phi oscillates, item 4, the longest cycle over the range the fields give,
   :func:`~surrogate.diagnosis.recommendation.oscillation_cap`). Facts, not a kind.
7. **The chain kind, measured** (:mod:`surrogate.stages.pilot`): ``gp=auto``'s measured choice
   made once at a small size (``inspect.pilot``): the candidates of ``gp.choice`` plus the
   clock at the cap of item 6, fitted by L-BFGS on a small collection and scored on a small
   held-out full-model run; priced first against ``inspect.max_seconds`` and shrunk to fit
   (else skipped, as where the transitions are an external table or
   ``inspect.pilot.enabled=false``). The report recommends keeping ``gp=auto`` (it measures
   the same at full size), shows the pilot's table, and where the pilot chose the added cap,
   ``gp.choice.max_ages=[..., X]`` so the full-size choice includes it; every override is
   checked (:func:`~surrogate.stages.advice_check.checked`) before it is printed.

Models whose internal model is not a network (``model=ecoli``) get items 2, 3, 4 (relaxation),
5, 6 and 7 by simulation from their own initial state (their stationary law).

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
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from surrogate.config import seed_everything, to_dict
from surrogate.diagnosis import probe as network_probe
from surrogate.diagnosis.cost import duration
from surrogate.diagnosis.exact import exact_fixed_inputs
from surrogate.diagnosis.fixed import FixedInputs
from surrogate.diagnosis.options import InspectOptions
from surrogate.diagnosis.population import Grid, Population, Runs, network_of, population_inputs
from surrogate.diagnosis.recommendation import (
    COLLECT_TIME_MARGIN,
    balanced_threshold,
    collection_overrides,
    input_ranges,
    memory_facts,
    signal_bounds_advice,
)
from surrogate.diagnosis.report import (
    INPUT_OCCUPANCY_FIGURE,
    MEMORY_FIGURE,
    SETTLING_FIGURE,
    plot_memory,
    plot_occupancy,
    plot_settling,
    relaxation_text,
    report_markdown,
    settling_text,
)
from surrogate.diagnosis.sensitivity import describe_network
from surrogate.diagnosis.settling import burn_in_advice, round_up
from surrogate.diagnosis.simulated import simulate_fixed_inputs
from surrogate.errors import ConfigError
from surrogate.io import make_once, save_figure, write_json, write_manifest, write_text
from surrogate.models.capabilities import lump_formula_of
from surrogate.simulate.transitions import recorded_share
from surrogate.stages import budget
from surrogate.stages.advice_check import checked
from surrogate.stages.artefacts import INSPECTION, REPORT
from surrogate.stages.pilot import pilot_advice, run_pilot
from surrogate.stages.settings import CollectSettings, InspectSettings, command_line
from surrogate.stages.settings.choice import collecting_pending

log = logging.getLogger(__name__)

#: the run the report advises next (as the README spells it)
NEXT_CMD = "python3 scripts/reproduce.py"

#: the population runs' (item 2) share of ``inspect.max_seconds`` at most
POPULATION_BUDGET = 0.25

#: the cost probe's share of ``inspect.max_seconds`` (:func:`cost_probe`; its cells, calls and
#: growth rule: :mod:`surrogate.diagnosis.probe`)
PROBE_BUDGET = 0.1


def validate(cfg: Mapping[str, Any]) -> InspectSettings:
    """The inspection's settings (the model built and checked), before any simulation."""
    with collecting_pending():  # the stages' costs: gp=auto's choice is made by train, later
        settings = InspectSettings.from_config(cfg)
    log.info("inspect: at most ~%s of simulation (inspect.max_seconds=%g)",
             duration(settings.options["max_seconds"]),
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


def cost_probe(settings: InspectSettings, options: InspectOptions) -> dict[str, Any] | None:
    """The network's cost measured before anything is run on the estimate from the file's
    counts (:func:`surrogate.diagnosis.probe.cost_probe`), within :data:`PROBE_BUDGET` of
    ``inspect.max_seconds``: a network whose rate is still growing when that runs out is
    refused (ConfigError) with what was measured, the burn-in's and collect's cost at that
    rate and what to do. Returns what it measured (``None`` where it does not apply)."""
    max_seconds = float(options.max_seconds)
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
    return None if source is None else budget.collect_cost(source, cell_step)


def runs_of(settings: InspectSettings) -> Runs:
    """The full-model runs of ``settings`` as plain values (the population's, item 2)."""
    setup, run_ = settings.setup, settings.run
    return Runs(setup.model, setup.dt, setup.seed, settings.job.device, tuple(settings.fields),
                lambda name: settings.field_setup(name).field, run_["start"],
                float(run_["t_end"]), float(run_["equilibration_time"]))  # fmt: skip


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


#: the simulation (s, at the measured events) recording every window must save before the
#: inspector advises it over collect's thinning (``collect.record_every=1``)
DENSE_SAVING_S = 300.0


def collection_budget(
    settings: InspectSettings,
    options: InspectOptions,
    fixed: FixedInputs,
    population: Population,
    measured_step: float,
    blackout: Sequence[str] = (),
) -> dict[str, Any]:
    """The rows per origin that give ``inspect.min_switches`` switches from each origin at the
    switching probability per window measured at the median inputs, what collecting them
    costs, and the simulated time it takes at the population's occupancy of each lump.

    Where collect keeps every switch (``collect.keep_switches``), a row counts the switches of
    the ``record_every`` windows it stands for. Where it thins them without (``record_every``
    k > 1) and recording every window would
    save more than :data:`DENSE_SAVING_S` of simulation, that is offered first (``dense``):
    the same rows, so the same switches, from 1/k of the simulated time (each window is one
    Bernoulli draw of psi whether or not its neighbours are kept; what thinning buys is rows
    spread over more of the inputs, which a slow-switching lump pays k times for).

    ``blackout``: the collect overrides the next command adds where the pilot's rows lagged a
    jump (``collect.blackout_time=20``, ``collect.perturb_rate=0.025``), timed with them: they
    leave fewer windows recordable, so the run the command makes is longer."""
    o = options
    source = _collect_source(settings)
    if source is None:
        return {}
    if blackout:
        keys = dict(item.split("=", 1) for item in blackout)
        source = replace(source, options={**source.options, **{
            key.removeprefix("collect."): float(value) for key, value in keys.items()}})  # fmt: skip
    c = source.options
    # keeping every switch (collect.keep_switches) a thinned row brings the switches of the
    # record_every windows it stands for
    per_row = int(c["record_every"]) if source.keep_switches else 1
    needed = [math.ceil(o.min_switches / (p * per_row)) if p > 0 else math.inf
              for p in fixed.switch]  # fmt: skip
    rows = max(needed)
    out: dict[str, Any] = {"switch_per_window": fixed.switch.tolist(), "rows_needed": needed,
                           "n_per_state": int(c["n_per_state"]),
                           "windows_per_row": per_row, "blackout": list(blackout)}  # fmt: skip
    if not math.isfinite(rows):
        return out
    out["recommended_n_per_state"] = max(int(rows), int(c["n_per_state"]))
    out.update(_collection_time(settings, source, population, measured_step,
                                out["recommended_n_per_state"], int(c["record_every"])))  # fmt: skip
    if int(c["record_every"]) > 1 and not source.keep_switches:  # else every switch is kept
        dense = _collection_time(settings, source, population, measured_step,
                                 out["recommended_n_per_state"], 1)  # fmt: skip
        if out["cost_s"] - dense["cost_s"] > DENSE_SAVING_S:
            out["dense"] = dense
    return out


def _collection_time(
    settings: InspectSettings,
    source: CollectSettings,
    population: Population,
    measured_step: float,
    n_per_state: int,
    record_every: int,
) -> dict[str, Any]:
    """The cost (s at the measured events) and simulated time of collecting ``n_per_state``
    rows per origin, one every ``record_every`` windows; the longer run or more cells it
    needs where ``collect.max_time`` is too short."""
    c, dt = source.options, settings.setup.dt
    more = replace(source, options={**c, "n_per_state": n_per_state, "record_every": record_every})
    work = budget.collect_work(more, reuse=False)
    out: dict[str, Any] = {"record_every": record_every,
                           "cost_s": sum(replace(w, cell_step_seconds=measured_step).seconds
                                         for w in work)}  # fmt: skip
    field = settings.setup.field_name
    share1 = population.fields.get(field, next(iter(population.fields.values())))["phi_share"]
    times = []
    recorded = recorded_share(float(c["perturb_rate"]), float(c["blackout_time"]))
    for share in (1.0 - share1, share1):
        rate = int(c["n_cells"]) * share * recorded / (record_every * dt)  # rows per second
        times.append(float(c["equilibration_time"]) + n_per_state / rate
                     if rate > 0 else math.inf)  # fmt: skip
    out["seconds_needed"] = times
    out["max_time"] = float(c["max_time"])
    eq = float(c["equilibration_time"])
    # the cap: the estimate's recorded time with its margin (collect stops once it has its rows)
    cap = eq + COLLECT_TIME_MARGIN * (max(times) - eq)
    if math.isfinite(cap) and cap > out["max_time"]:
        # either setting alone gives the rows in time: a longer run, or more cells (rows per
        # second grow with the cells)
        out["max_time_needed"] = round_up(cap)
        if out["max_time"] > eq:
            out["n_cells_needed"] = math.ceil(int(c["n_cells"]) * (cap - eq)
                                              / (out["max_time"] - eq))  # fmt: skip
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
    refusals = []

    def mark(target: dict[str, Any], overrides: list[str], what: str, yaml: str = "") -> None:
        reason = checked(config, overrides, what, yaml if yaml_model else "")
        if reason is not None:
            target["refused"] = reason
            refusals.append(f"{what}: {reason}")

    if advice.get("kind"):
        mark(advice, list(advice.get("overrides") or []), "the pilot's choice (gp=auto)")
        named: dict[str, Any] = {}
        mark(named, list(advice.get("named") or []), "the pilot's choice named outright")
        if "refused" in named:
            advice["named_refused"] = named["refused"]
    if balanced and yaml_model:
        mark(balanced, [], "the balanced threshold", f'lump: "{balanced["lump"]}"')
    if advice.get("signal_bounds") and yaml_model:
        bounds: dict[str, Any] = {}
        mark(bounds, [], "signal_bounds", advice["signal_bounds"])
        if "refused" in bounds:
            del advice["signal_bounds"]
    if _burn_in_short(burn, yaml_model):
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


def _burn_in_short(burn: Mapping[str, Any], yaml_model: bool) -> bool:
    """Whether the report advises a longer burn-in as a key of the model's yaml."""
    return bool(yaml_model and burn.get("applies") and burn.get("enough") is False)


def burn_in_overrides(burn: Mapping[str, Any], yaml_model: bool) -> list[str]:
    """The burn-in the report advises as an override (``++model.burn_in=480``): where the
    model's is too short, the model is a yaml (its keys can be given so) and the checks did
    not refuse it (:func:`check_printed`); else none."""
    if not _burn_in_short(burn, yaml_model) or burn.get("refused"):
        return []
    return [f"++model.burn_in={burn['needed_s']:g}"]


def next_command(
    config: Mapping[str, Any],
    setup_overrides: list[str],
    advice: Mapping[str, Any],
    collection: Mapping[str, Any],
    burn_in: Sequence[str] = (),
) -> dict[str, Any]:
    """The run the report advises next: ``scripts/reproduce.py`` with the inspected model,
    field, step and seed (``setup_overrides``), the burn-in it advises (``burn_in``,
    :func:`burn_in_overrides`), the first collection it advises (with the blackout collect
    advised where the pilot's rows lagged a jump) and the pilot's gp overrides (refused ones
    are not printed), checked as one command; where the stages' checks refuse the
    combination, the burn-in and collection are left out, then the gp overrides too
    (``dropped``: what was left out and why)."""
    # the burn-in, the collection's size, and where the pilot's rows lagged a jump, its blackout
    collect = [*burn_in, *(collection.get("advised") or [[]])[0],
               *(advice.get("blackout") or [])]  # fmt: skip
    gp = (
        list(advice.get("overrides") or [])
        if advice.get("kind") and not advice.get("refused")
        else []
    )
    dropped: list[str] = []
    for parts in ([*collect, *gp], gp):
        reason = checked(config, [*setup_overrides, *parts], "the next command") if parts else None
        if reason is None:
            return {"command": command_line(NEXT_CMD, setup_overrides, parts), "dropped": dropped}
        dropped.append(f"{' '.join(parts)}: {reason}")
    return {"command": command_line(NEXT_CMD, setup_overrides), "dropped": dropped}


# ----------------------------------------------------------------------------------------------
# the stage


def _inspect(settings: InspectSettings, out: Path, config: Mapping[str, Any] | None) -> None:
    """Measure, then write inspect.json, the figures, report.md and (last) the manifest; a
    lump (almost) never or always true is refused after the report is written."""
    t0 = time.perf_counter()
    setup, o = settings.setup, InspectOptions.from_mapping(settings.options)
    model, dt = setup.model, setup.dt
    internal, network = model.internal, network_of(model)
    probe = cost_probe(settings, o)  # a runaway network refused in seconds, before any estimate
    seed_everything(setup.seed)
    population = population_inputs(runs_of(settings), o, POPULATION_BUDGET * o.max_seconds)
    grid = Grid.from_inputs(population.x, internal.input_names, o.quantiles,
                            o.grid_points)  # fmt: skip
    net = describe_network(network, population, grid, o) if network is not None else None
    seed_everything(setup.seed)
    space = network.state_space if network is not None else None
    left = max(o.max_seconds - population.cost, (1 - POPULATION_BUDGET) * o.max_seconds)
    if network is not None and space is not None and space.n_states <= o.exact_max_states:
        fixed = exact_fixed_inputs(network, grid, o, dt)
    else:
        fixed = simulate_fixed_inputs(model, grid, o, dt, settings.job.device, left)
    model_events = network.events_per_window(dt) if network is not None else None
    step_model = model.cell_step_seconds(dt, device=settings.job.device)
    step_measured = network.cell_step_seconds(dt, fixed.events, settings.job.device) \
        if network is not None and fixed.events is not None else step_model  # fmt: skip
    costs = stage_costs(settings, step_measured)
    burn = burn_in_advice(network, fixed, o.burn_in_factor, o.settle_tolerance)
    ranges = input_ranges(network, population)
    low = o.min_occupancy
    never, always = bool((fixed.occupancy < low).all()), bool((fixed.occupancy > 1 - low).all())
    stops = fixed.stopped is not None and fixed.stopped > 1 - low
    facts = memory_facts(model, fixed, dt)
    if never or always or stops:  # refused below, once the report is written
        pilot = {"ran": False, "note": "skipped: the lump is refused (below)"}
    else:
        pilot = _pilot(settings, o, facts["max_age"], step_measured)
    advice = pilot_advice(settings.config, pilot)
    # timed as the next command collects: with the blackout it adds where the pilot's rows lag
    collection = collection_budget(settings, o, fixed, population, step_measured,
                                   advice.get("blackout") or ())  # fmt: skip
    bounds = signal_bounds_advice(internal, fixed, ranges)
    if bounds:
        advice["signal_bounds"] = bounds
    balanced = balanced_threshold(internal, fixed)
    checked_against = config if config is not None else settings.config
    yaml_model = "spec" in (settings.config.get("model") or {})
    refused = check_printed(checked_against, advice, burn, collection, yaml_model, balanced)
    advice["next"] = next_command(checked_against, settings.setup.overrides(), advice, collection,
                                  burn_in_overrides(burn, yaml_model))  # fmt: skip
    lump = lump_formula_of(internal) or "the model's own property"
    summary: dict[str, Any] = {
        "model": model.describe(), "command": settings.command(), "lump": lump,
        "settings": dict(settings.options),
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
        "memory": {"memory": fixed.memory, "hazards": fixed.hazards, "facts": facts},
        "pilot": pilot,
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
                   occupancy=fixed.occupancy.tolist(), recommendation=advice["kind"])  # fmt: skip
    log.info("inspect: %s iff %s; occupancy %.3g-%.3g over the grid (%s); settling %s; "
             "relaxation %s; the pilot's measured choice: %s; %.1f s", internal.lump_names[1], lump,
             float(fixed.occupancy.min()), float(fixed.occupancy.max()), fixed.method,
             settling_text(summary), relaxation_text(summary["relaxation"]),
             advice["kind"] or pilot["note"], summary["wall_time_s"])  # fmt: skip


def _pilot(
    settings: InspectSettings, o: InspectOptions, cap: float | None, cell_step: float
) -> dict[str, Any]:
    """The pilot's measured choice (:func:`~surrogate.stages.pilot.run_pilot`); a pilot whose
    settings or collection are refused (a lump collect cannot see, ...) is reported as not
    run, with why: the inspection's own measurements stand without it."""
    try:
        return run_pilot(settings.config, o.pilot, o.max_seconds, cap, cell_step)
    except ConfigError as error:
        log.warning("inspect: the pilot's measured choice could not run: %s", error)
        return {"ran": False, "note": f"could not run: {error}"}


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
    "POPULATION_BUDGET",
    "burn_in_overrides",
    "check_printed",
    "collection_budget",
    "cost_probe",
    "inspect",
    "next_command",
    "run",
    "runs_of",
    "stage_costs",
    "validate",
]

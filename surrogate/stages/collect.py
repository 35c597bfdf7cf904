"""The collect stage: perturbed micro-trajectories of the full model -> transitions table.

``python scripts/collect.py [model=...] [field=...] [collect.n_per_state=...]`` writes
``transitions.parquet`` (the model's inputs and features, ``phi``, ``phi_next``, ``cell``, ``t``,
``since_jump`` and, where the model gives it, the expected label ``phi_next_expected``), ``coverage.png`` and ``manifest.json`` into the settings' directory.

Before its first simulation a network burned in from the SBML file's counts is probed for
``collect.probe_seconds`` (:func:`cost_probe`): a runaway network is refused in seconds with
the rate it reached, instead of burning in its cells for hours with no output. Where it
passes, the collection's estimate is logged again at the events per window it measured after
the burn-in (:func:`measured_cost`), beside the one at the file's counts that ``validate``
checked, and refused past ``max_hours`` as that one is; the collection itself is unchanged.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from surrogate.config import seed_everything, to_dict
from surrogate.diagnosis import probe
from surrogate.diagnosis.cost import duration
from surrogate.diagnosis.jumps import (
    BLACKOUT_SHARE,
    after_jump_lag,
    blackout_advice,
    lag_message,
    lagging_window,
    settled_rows,
)
from surrogate.errors import ConfigError
from surrogate.gp.windows import origin_rows, origin_windows
from surrogate.io import MANIFEST, make_once, save_figure, write_manifest, write_parquet
from surrogate.models.base import Perturbation
from surrogate.models.capabilities import feature_names_of
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import CollectOptions, collect_transitions, recorded_share
from surrogate.stages import budget
from surrogate.stages.artefacts import COVERAGE_FIGURE, TRANSITIONS
from surrogate.stages.design import collect_in_rounds
from surrogate.stages.settings import CollectSettings, TrainSettings
from surrogate.stages.settings.inspection import INSPECT_CMD

log = logging.getLogger(__name__)


def validate(cfg: Mapping[str, Any]) -> CollectSettings:
    """All checks of a collect config and its estimated cost, before any work starts; the
    typed settings."""
    settings = CollectSettings.from_config(cfg, fits=TrainSettings.design_fits)
    budget.check(cfg, budget.collect_work(settings), "collect")
    return settings


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Run (or reuse) the collect stage of ``cfg``; return its artefact directory."""
    return collect(validate(cfg), config=to_dict(cfg), force=force)


def collect(
    settings: CollectSettings, config: Mapping[str, Any] | None = None, force: bool = False
) -> Path:
    """Run (or reuse) the collect stage described by ``settings``."""
    out = settings.directory
    return make_once(out, settings.identity(), settings.command(),
                     lambda _: _collect(settings, out, config), what="transitions", force=force)  # fmt: skip


def _collect(settings: CollectSettings, out: Path, config: Mapping[str, Any] | None) -> None:
    """Simulate, then write the table, the figure and (last) the manifest into ``out``."""
    setup, c, job = settings.setup, settings.options, settings.job
    # a runaway network refused in seconds, before any burn-in; else the estimate at its rate
    probed = cost_probe(settings)
    measured_cost(settings, probed, config or {})
    seed_everything(setup.seed)
    model = setup.model
    simulator = Simulator(model, FullDecision(model.internal), setup.field, setup.dt, job.device)
    perturbation = model.body.perturbation(setup.field, model.perturbation_options)
    t0 = time.perf_counter()
    options = CollectOptions(
        record_every=int(c["record_every"]),
        equilibration_time=float(c["equilibration_time"]),
        max_time=float(c["max_time"]),
        blackout=round(float(c.get("blackout_time", 0.0)) / setup.dt),
        expected=settings.expected_labels,
        keep_switches=settings.keep_switches,
    )
    arguments: dict[str, Any] = {
        "n_cells": int(c["n_cells"]),
        "perturb_rate": float(c["perturb_rate"]),
        "options": options,
    }
    design, topped = None, None
    lumps = model.internal.lump_names
    if settings.design is not None:  # rounds until the posterior meets the target
        table, design = collect_in_rounds(settings, simulator, perturbation, **arguments)
    else:
        table = collect_transitions(simulator, perturbation, n_per_state=int(c["n_per_state"]),
                                    progress=job.progress, **arguments)  # fmt: skip
    # matched on the signal psi reads by default (E. coli's dG, a network's inputs); measured
    # on the rows as first collected, before any top-up (whose rows are all settled)
    lag = after_jump_lag(table, model.internal.signal_names, setup.dt, lumps)
    if settings.design is None and c.get("top_up", "auto") == "auto":
        table, topped = top_up(settings, simulator, perturbation, table, lag, options,
                               time.perf_counter() - t0, config)  # fmt: skip
    wall = time.perf_counter() - t0
    # from here the directory reads as incomplete until the new manifest is written last
    (out / MANIFEST).unlink(missing_ok=True)
    write_parquet(out / TRANSITIONS, table)
    save_figure(out / COVERAGE_FIGURE, plot_coverage(table, model), crop=False)
    counts = {
        f"{lumps[phi]}_to_{lumps[nxt]}": int(
            ((table["phi"] == phi) & (table["phi_next"] == nxt)).sum()
        )
        for phi in (0, 1)
        for nxt in (0, 1)
    }
    columns = [*model.internal.input_names, *feature_names_of(model.internal)]
    blackout = float(settings.options["blackout_time"])
    done = topped is not None and "rows" in topped  # the blackout's rows, recorded already
    advice = () if done else blackout_advice(lag, blackout, float(settings.options["perturb_rate"]))
    refused = check_collection(settings, config, advice) if advice else None
    if lag is not None:
        lag["advice"] = [] if refused else list(advice)
    message = lag_message(lag, blackout, () if refused else advice, refused or "",
                          topped_up=_topped_text(topped) if done and topped else "")  # fmt: skip
    if message is not None:
        log.warning("collect: %s", message)
    write_manifest(
        out,
        stage="collect",
        config=dict(config) if config is not None else settings.identity(),
        seed=setup.seed,
        settings=settings.identity(),
        device=str(job.device),
        wall_time_s=wall,
        n_rows=len(table),
        counts_per_origin={lumps[p]: int((table["phi"] == p).sum()) for p in (0, 1)},
        counts=counts,
        lump_names=list(lumps),
        domain={n: [float(table[n].min()), float(table[n].max())] for n in columns},
        **({"design": design} if design is not None else {}),
        **_windows_record(table, lumps),
        **({"after_jump": lag} if lag is not None else {}),
        **({"top_up": topped} if topped is not None else {}),
        # the rate later stages price this model's full-model cells at (budget.train_work)
        **({"cost_probe": {k: probed[k] for k in PROBE_RECORD}} if probed is not None else {}),
    )
    log.info("collected %d transitions in %.1f s; artefacts in %s", len(table), wall, out)


def _windows_record(table: pd.DataFrame, lumps: Sequence[str]) -> dict[str, Any]:
    """The manifest's ``windows_per_origin`` where the rows keep every switch (the windows
    they stand for, :mod:`surrogate.gp.windows`); else nothing."""
    windows = origin_windows(table)
    if windows is None:
        return {}
    return {"windows_per_origin": {lumps[p]: float(windows[p]) for p in (0, 1)}}


def top_up(
    settings: CollectSettings,
    simulator: Simulator,
    perturbation: Perturbation,
    table: pd.DataFrame,
    lag: dict[str, Any] | None,
    options: CollectOptions,
    wall: float,
    config: Mapping[str, Any] | None,
) -> tuple[pd.DataFrame, dict[str, Any] | None]:
    """Where ``table``'s rows lag a jump and the lag ends within the measurement
    (:func:`~surrogate.diagnosis.jumps.lagging_window`), the rows train reads by default
    (``gp.jump_rows=auto``: those 20 s or more after a jump) topped up to ``n_per_state`` per
    origin: fresh cells collected with the blackout collect would advise
    (:func:`~surrogate.diagnosis.jumps.blackout_advice`: every row they record is settled),
    appended with their own cell numbers (``options``: the first pass's, its blackout moved).
    Returns the table and the record (None where nothing
    lagged or enough rows were settled; ``{"skipped": why}`` where the top-up was refused or
    stopped short: the table as collected, train's fallback then reads it).

    CERENA's gene-expression network (docs/choice.md): its default collection keeps 16 % of
    its rows settled, so every fit read a sixth of ``n_per_state``; topped up (36-43 s more),
    the issue's check over four training seeds passed 40 of 48, against 38 on the sixth and 42
    on the blackout's collection.
    """
    window = lagging_window(lag)
    c, dt = settings.options, settings.setup.dt
    if window is None or float(c["blackout_time"]) >= window:
        return table, None
    settled = settled_rows(table["since_jump"].to_numpy(), dt, window)
    # the settled rows per origin as the collection counts them (keeping switches: in thinned
    # rows, origin_rows)
    have = [round(v) for v in origin_rows(table[settled], int(c["record_every"]))]
    wanted = int(c["n_per_state"])
    need = wanted - min(have)
    if need <= 0:
        return table, None
    rate = min(float(c["perturb_rate"]), BLACKOUT_SHARE / window)
    overrides = (f"collect.blackout_time={window:g}", f"collect.perturb_rate={rate:g}")
    record: dict[str, Any] = {"window_s": window, "settled_before": have, "per_origin": need,
                              "blackout_time": window, "perturb_rate": rate}  # fmt: skip
    # priced at the first pass's pace: its share of windows recordable against the blackout's
    first = recorded_share(float(c["perturb_rate"]), float(c["blackout_time"]))
    estimate = wall * need / wanted * first / recorded_share(rate, window)
    limit = 3600.0 * budget.max_hours(config or {})
    lumps = settings.setup.model.internal.lump_names
    held = ", ".join(f"{lumps[p]} {have[p]:,}" for p in (0, 1))
    refused = check_collection(settings, config, overrides)
    if refused or estimate > limit:
        why = refused or f"~{duration(estimate)} estimated, above max_hours"
        log.warning("collect: rows lag a jump and only the settled ones are read (%s of %s per "
                    "origin); not topped up with `%s`: %s", held, f"{wanted:,}",
                    " ".join(overrides), why)  # fmt: skip
        return table, {**record, "skipped": why}
    log.info("collect: rows within %g s of a jump lag it and train reads only the settled ones "
             "(%s of %s per origin): recording %s more per origin with `%s` (~%s at the first "
             "pass's pace; collect.top_up=off keeps the table as collected)", window, held,
             f"{wanted:,}", f"{need:,}", " ".join(overrides), duration(estimate))  # fmt: skip
    settled_options = replace(options, blackout=math.ceil(window / dt - 1e-6))
    t0 = time.perf_counter()
    try:
        more = collect_transitions(simulator, perturbation, n_cells=int(c["n_cells"]),
                                   n_per_state=need, perturb_rate=rate, options=settled_options,
                                   progress=settings.job.progress)  # fmt: skip
    except ConfigError as error:  # short of rows by max_time: the first pass stands
        log.warning("collect: the top-up stopped short, the table is kept as collected: %s", error)
        return table, {**record, "skipped": str(error)}
    more["cell"] += int(table["cell"].max()) + 1  # fresh cells, their own numbers
    record.update(rows=len(more), wall_time_s=time.perf_counter() - t0)
    return pd.concat([table, more], ignore_index=True), record


def _topped_text(record: Mapping[str, Any]) -> str:
    """The log's words for a top-up that ran."""
    return (f"collect recorded {int(record['per_origin']):,} more settled rows per origin with "
            f"`collect.blackout_time={record['blackout_time']:g} "
            f"collect.perturb_rate={record['perturb_rate']:g}` (collect.top_up=auto), so each "
            f"origin has n_per_state settled rows")  # fmt: skip


def check_collection(
    settings: CollectSettings, config: Mapping[str, Any] | None, overrides: Sequence[str]
) -> str | None:
    """Why collect's own checks refuse ``overrides`` (``collect.`` keys) on the run's
    ``config`` (else on ``settings``' collect group), or None where they accept them."""
    from surrogate.stages.advice_check import apply_overrides

    base = config if config is not None else {"collect": settings.given or {}}
    try:
        cfg = apply_overrides(base, overrides)
        CollectSettings.from_config(cfg, setup=settings.setup, job=settings.job,
                                    fits=TrainSettings.design_fits)  # fmt: skip
    except (ConfigError, KeyError) as error:  # KeyError: a design's gp group not at hand
        return str(error)
    return None


#: what the collection's manifest keeps of its cost probe (``cost_probe``)
PROBE_RECORD = ("events_per_window_last", "events_per_window_file", "reached_s", "completed")


def cost_probe(settings: CollectSettings) -> dict[str, Any] | None:
    """The network's cost where its cells start, measured within ``collect.probe_seconds``
    (:func:`surrogate.diagnosis.probe.cost_probe`; 0: not measured) before the burn-ins: a rate
    still growing when they run out is refused (ConfigError) with the rate, its growth, this
    collection's cost at that rate and the remedies. Its draws are on a fork of torch's
    generators: the collection is the same with and without it. Returns what it measured
    (``None`` where it does not apply or is off)."""
    seconds = float(settings.options.get("probe_seconds", 0.0))
    if seconds <= 0:
        return None
    naming = probe.Naming(
        stage="collect",
        outgrew="collect's cost probe",
        budget=f"collect.probe_seconds={seconds:g}",
        remedy="a larger collect.probe_seconds (0 turns the probe off: the burn-ins then run at "
        "that rate)",
        more=f". `{INSPECT_CMD}` with the same model settings measures more (the probe over a "
        "tenth of inspect.max_seconds, then the network's settling, occupancy and costs)",
        collect=lambda cell_step: budget.collect_cost(settings, cell_step),
        collect_name="this collection",
    )
    setup = settings.setup
    return probe.cost_probe(setup.model, setup.dt, setup.seed, settings.job.device, seconds,
                            naming)  # fmt: skip


@dataclass(frozen=True)
class MeasuredCost:
    """Collect's estimate at the events per window its cost probe measured.

    Attributes:
        seconds: the estimated seconds of simulation at ``events`` (logged).
        file_seconds: the estimate at the file's counts (what ``validate`` logged and checked
            against ``max_hours``).
        events: SSA events per window of dt per cell, measured: the probe's mean over its last
            windows (:data:`~surrogate.diagnosis.probe.PROBE_TAIL` of the model time it reached).
        file_events: the events per window at the file's counts and input values.
        cell_step_seconds: the full model's cost per cell-step at ``events``.
        completed: whether the probe reached the end of its horizon (the burn-in); else
            ``events`` is the rate it reached, at ``reached_s``, when its budget ran out.
        reached_s: the model time the probe reached (s).
        horizon_s: the probe's horizon (s): the burn-in, or its windows where there is none.
    """

    seconds: float
    file_seconds: float
    events: float
    file_events: float
    cell_step_seconds: float
    completed: bool
    reached_s: float
    horizon_s: float


def measured_cost(
    settings: CollectSettings,
    measured: Mapping[str, Any] | None,
    cfg: Mapping[str, Any] | None = None,
) -> MeasuredCost | None:
    """Log collect's estimate (:func:`~surrogate.stages.budget.collect_work`: the windows and
    the burn-in) at the events per window its cost probe ``measured`` after the burn-in,
    instead of at the file's counts, naming both figures (a warning past
    :data:`~surrogate.stages.budget.WARN_SECONDS`); where the probe ran out of budget before
    the end of the burn-in (a steady rate: a growing one is refused), at the rate it reached,
    and saying so. With the stage's ``cfg``, past its ``max_hours`` (``validate`` checked the
    file's counts' estimate against it) it is refused, with both figures. Returns it; ``None`` where nothing was measured (the
    probe off, or no network of its kind), the estimate at the file's counts then standing
    alone."""
    setup = settings.setup
    network = probe.probed_network(setup.model)
    if measured is None or network is None or not measured["reached_s"] > 0:
        return None
    events, file_events = float(measured["events_per_window_last"]), float(
        measured["events_per_window_file"])  # fmt: skip
    cell_step = network.cell_step_seconds(setup.dt, events, settings.job.device)
    try:
        file_works = budget.collect_work(settings, reuse=False)
        works = budget.collect_work(settings, reuse=False, cell_step_seconds=cell_step)
    except ConfigError:  # the run reports it
        return None
    file_seconds = sum(w.seconds for w in file_works)
    reached, horizon = float(measured["reached_s"]), float(measured["horizon_s"])
    burn_in = float(measured.get("burn_in_s", 0.0)) > 0
    if measured["completed"]:
        span = "the burn-in" if burn_in else f"{horizon:.3g} s from the file's counts"
        at = f"at the events measured after {span}"
    else:
        span = f"the {horizon:.3g}-s burn-in" if burn_in else f"its {horizon:.3g} s"
        at = (f"at the steady rate the cost probe reached at {reached:.3g} s of {span}, when "
              f"collect.probe_seconds={float(measured['budget_s']):g} ran out")  # fmt: skip
    basis = (f"{at} ({_events(events)} per window per cell; the file's counts: "
             f"{_events(file_events)}, ~{duration(file_seconds)})")  # fmt: skip
    seconds = (budget.log_estimate(works, "collect", basis) if cfg is None
               else budget.check(cfg, works, "collect", basis))  # fmt: skip
    return MeasuredCost(seconds, file_seconds, events, file_events, cell_step,
                        bool(measured["completed"]), reached, horizon)  # fmt: skip


def _events(value: float) -> str:
    """``0.05``, ``6.6``, ``1,013``, ``7,100,000``: events per window as read."""
    return f"{value:,.0f}" if value >= 100 else f"{value:.3g}"


def plot_coverage(table: pd.DataFrame, model: Any) -> Any:
    """Where the collected transitions lie: the raw inputs (first two, coloured by the next
    phi) and the histogram of the signal by origin state."""
    from matplotlib.figure import Figure

    internal = model.internal
    lumps = internal.lump_names
    inputs = list(internal.input_names)
    signal = internal.signal_names[0]
    # margins fixed in inches (no layout engine: it measured every label once more)
    fig = Figure(figsize=(15, 4.2))
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.13, top=0.86, wspace=0.25)
    axes = fig.subplots(1, 3)
    for ax, phi in zip(axes[:2], (1, 0), strict=True):
        rows = table[table["phi"] == phi]
        rows = rows.sample(min(len(rows), 4000), random_state=0)
        x, y = (inputs[1], inputs[0]) if len(inputs) > 1 else (inputs[0], "t")
        for nxt, colour in ((1, "tab:blue"), (0, "tab:red")):
            pts = rows[rows["phi_next"] == nxt]
            ax.scatter(pts[x], pts[y], s=3, alpha=0.5, c=colour, label=f"next {lumps[nxt]}")
        ax.set_title(f"from {lumps[phi]} (n={int((table['phi'] == phi).sum())})")
        ax.set_xlabel(x)
        ax.set_ylabel(y)
        ax.legend(markerscale=3, fontsize=8)
    lo, hi = np.quantile(table[signal], [0.001, 0.999])
    for phi in (0, 1):
        values = table.loc[table["phi"] == phi, signal].to_numpy(float)
        axes[2].hist(values, bins=np.linspace(lo, hi, 80),
                     alpha=0.6, label=f"from {lumps[phi]}")  # fmt: skip
    axes[2].set_xlabel(f"signal {signal}")
    axes[2].set_ylabel("transitions")
    axes[2].legend(fontsize=8)
    fig.suptitle("Collected transitions")
    return fig

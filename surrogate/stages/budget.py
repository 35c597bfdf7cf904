"""What a stage will cost, estimated before it starts: steps x (the loop's fixed cost per step
+ cells x the model's cost per cell-step), for every simulation the stage would run (artefacts
that exist are reused, so they cost nothing).

Each stage's ``validate`` calls :func:`check`: the estimate is logged, a warning names the
settings that make it when it exceeds :data:`WARN_SECONDS`, and it is refused (a ConfigError
naming those settings) above the ``max_hours`` setting. The cost of one cell-step comes from
the model (:meth:`~surrogate.models.base.Model.cell_step_seconds`: for a network, its events
per window at the initial state times the measured cost of an SSA event), so ``dt=1e-9`` or
``collect.n_per_state=1e9`` is refused in milliseconds, not found out hours later. Collect,
once its cost probe has run, logs its estimate again at the events per window measured after
the burn-in (:func:`collect_work`'s ``cell_step_seconds``, :func:`log_estimate`): a network's
rate where its cells start may be orders of magnitude from where the collection records. The fixed
cost per step (Python and the step's many small tensor operations, the SSA's call: the same at
1 cell as at 1,000) is measured, not guessed: :func:`step_seconds` times a few steps of the
stage's own simulator (model, body, field, decision layer, device) at two small populations,
once per process; it dominates a population of a few hundred cells (the gene switch in a
walker: 0.5-1 ms per step against ~0.3 us per cell-step).

The cost model, the measured fixed cost per step and the :class:`~surrogate.diagnosis.cost.Work`
record live below the stages (:mod:`surrogate.diagnosis.cost`); here, each stage's works from
its settings. The estimate is a guard against runs of hours or years, not a forecast: it has no accuracy
guarantee (measured runs took 0.37x to 1.64x of it on the three shipped models, none bounds it
on others; docs/performance.md, "The cost estimate").

Example::

    settings = SimulateSettings.from_config(cfg)
    check(cfg, run_work(settings), "simulate")   # logs "simulate: estimated ~2.1 s of ..."
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from surrogate.diagnosis import probe
from surrogate.diagnosis.cost import Work, duration, step_seconds
from surrogate.errors import ArtefactError, ConfigError
from surrogate.io import MANIFEST, read_manifest
from surrogate.kinds import mode_kind
from surrogate.models.capabilities import burn_in_of
from surrogate.models.network import direct_exact_step_seconds
from surrogate.simulate.transitions import recorded_share
from surrogate.stages.settings import (
    CollectSettings,
    EvaluateSettings,
    ReproduceSettings,
    SimulateSettings,
    TrainSettings,
)

log = logging.getLogger(__name__)

#: estimates above this are logged as warnings, naming the settings that make them
WARN_SECONDS = 600.0


def _exists(directory: Any, reuse: bool = True) -> bool:
    return reuse and (directory / MANIFEST).exists()


def collect_work(
    settings: CollectSettings, reuse: bool = True, cell_step_seconds: float | None = None
) -> list[Work]:
    """The collection's windows, at least: the equilibration of every cell, then twice
    ``n_per_state`` recorded windows (both origins equally common), each every
    ``record_every``-th window of a cell outside the blackout after a jump
    (:func:`~surrogate.simulate.transitions.recorded_share` of them). ``reuse=False``: the
    cost even where the artefact exists (for every function here). ``cell_step_seconds``: the full model's cost
    per cell-step (its windows' and the burn-in's) instead of the model's estimate (collect's
    at the events its cost probe measured, :func:`surrogate.stages.collect.measured_cost`)."""
    if _exists(settings.directory, reuse):
        return []
    setup, c = settings.setup, settings.options
    n, every, cells = int(c["n_per_state"]), int(c["record_every"]), int(c["n_cells"])
    equilibration = float(c["equilibration_time"]) / setup.dt
    share = recorded_share(float(c["perturb_rate"]), float(c["blackout_time"]))
    steps = equilibration + 2.0 * n * every / (cells * share)
    where = (f"collect.n_per_state={n} per origin, every collect.record_every={every}th window "
             f"of collect.n_cells={cells} outside collect.blackout_time="
             f"{float(c['blackout_time']):g} s after a jump ({100 * share:.0f} % of windows), "
             f"collect.equilibration_time={float(c['equilibration_time']):g} s, "
             f"dt={setup.dt:g} s")  # fmt: skip
    fixed = step_seconds(setup.model, setup.field, setup.dt, "full", settings.job.device)
    device = settings.job.device
    cell_step = setup.model.cell_step_seconds(setup.dt, device=device) \
        if cell_step_seconds is None else cell_step_seconds  # fmt: skip
    return [Work("collect (at least)", cells, steps, cell_step, where, setup.model.name,
                 step_seconds=fixed),
            *burn_in_work(setup.model, cells, setup.dt, cell_step_seconds, device)]  # fmt: skip


def collect_cost(source: CollectSettings, cell_step: float) -> tuple[float, str] | None:
    """Collect's estimated seconds for ``source`` at the full model's ``cell_step`` (s per
    cell-step) and the settings behind it; None where they cannot be estimated."""
    try:
        works = collect_work(source, reuse=False, cell_step_seconds=cell_step)
    except ConfigError:
        return None
    return sum(w.seconds for w in works), works[0].settings if works else ""


def train_work(settings: TrainSettings, reuse: bool = True) -> list[Work]:
    """The collection it needs (if missing) and its diagnostic's full-model population (at
    the events per window its collection's cost probe measured, where it did:
    :func:`collected_cell_step`)."""
    works: list[Work] = []
    source = settings.source if isinstance(settings.source, CollectSettings) else None
    if source is not None:
        works += collect_work(source, reuse)
    occupancy = settings.occupancy()
    if not _exists(occupancy.directory, reuse):
        measured = collected_cell_step(source) if source is not None else None
        d, setup = occupancy.options, settings.setup
        span = float(d["t_end"]) + float(d["equilibration_time"])
        where = (f"gp.diagnostic.n_cells={d['n_cells']}, gp.diagnostic.t_end={d['t_end']:g} s "
                 f"+ gp.diagnostic.equilibration_time={d['equilibration_time']:g} s at "
                 f"dt={setup.dt:g} s")  # fmt: skip
        fixed = step_seconds(setup.model, setup.field, setup.dt, "full", settings.job.device)
        per_cell = setup.model.cell_step_seconds(setup.dt, device=settings.job.device) \
            if measured is None else measured  # fmt: skip
        works.append(Work("the train diagnostic's full-model population", int(d["n_cells"]),
                          span / setup.dt, per_cell, where, setup.model.name,
                          step_seconds=fixed))  # fmt: skip
        works += burn_in_work(setup.model, int(d["n_cells"]), setup.dt, measured,
                              device=settings.job.device)  # fmt: skip
    return works


def collected_cell_step(source: CollectSettings) -> float | None:
    """The full model's cost per cell-step on ``source``'s device at the events per window
    its collection's cost probe measured after the burn-in (``cost_probe`` in its manifest:
    where its cells live, which the file's counts may miss by orders of magnitude: Vilar's
    oscillator 2.5 events per window there, 213 after its 480-s burn-in); None where the
    collection is not made yet or measured nothing."""
    network = probe.probed_network(source.setup.model)
    if network is None or not (source.directory / MANIFEST).is_file():
        return None
    try:
        measured = read_manifest(source.directory).get("cost_probe")
    except ArtefactError:  # an estimate: an unreadable manifest is the train stage's to report
        return None
    if not isinstance(measured, dict) or not float(measured.get("reached_s", 0.0)) > 0:
        return None
    events = float(measured["events_per_window_last"])
    return network.cell_step_seconds(source.setup.dt, events, source.job.device)


def run_work(settings: SimulateSettings, reuse: bool = True) -> list[Work]:
    """One population run (if its artefact is missing)."""
    if _exists(settings.directory, reuse):
        return []
    setup, name, full = settings.setup, settings.decision.name, settings.decision.kind.full
    span = settings.t_end + settings.equilibration_time
    where = (f"t_end={settings.t_end:g} s + equilibration_time={settings.equilibration_time:g} s "
             f"at dt={setup.dt:g} s, n_cells={settings.n_cells}")  # fmt: skip
    label = {"full": "the full-model run", "abstract": "the abstraction's run",
             "exact": "the exact-psi chain's run"}.get(name, f"the {name} run")  # fmt: skip
    fixed = step_seconds(setup.model, setup.field, setup.dt, name, settings.job.device)
    per_cell = setup.model.cell_step_seconds(setup.dt, full, settings.job.device)
    mode = settings.decision.mode
    if settings.decision.kind.exact and mode is not None and not mode_kind(mode).table:
        # the exact law computed directly: exp(Q dt) per cell and step
        per_cell += direct_exact_step_seconds(setup.model.internal)
    return [Work(label, settings.n_cells, span / setup.dt, per_cell, where, setup.model.name,
                 name, fixed),
            *burn_in_work(setup.model, settings.n_cells, setup.dt, device=settings.job.device)]  # fmt: skip


def burn_in_work(
    model: Any,
    cells: int,
    dt: float,
    cell_step_seconds: float | None = None,
    device: torch.device | str = "cpu",
) -> list[Work]:
    """The full model's burn-in of ``cells`` initial states, where the model simulates one
    (:func:`~surrogate.models.capabilities.burn_in_of`; every decision layer starts its cells
    from the internal model's initial state). One SSA call of ``seconds``, not a loop of
    steps: no fixed cost per step. ``cell_step_seconds``: instead of the model's estimate on
    ``device``."""
    seconds = burn_in_of(model.internal)
    if seconds <= 0:
        return []
    cell_step = model.cell_step_seconds(dt, device=device) if cell_step_seconds is None \
        else cell_step_seconds  # fmt: skip
    return [Work("the initial states' burn-in", cells, seconds / dt, cell_step,
                 f"model.burn_in={seconds:g} s", model.name, step_seconds=0.0)]  # fmt: skip


def evaluate_work(settings: EvaluateSettings) -> list[Work]:
    """The runs it compares (and, with ``evaluate.run_missing``, the abstraction they need)."""
    works: list[Work] = []
    runs = [settings.candidate, settings.full, settings.full_repeat]
    if settings.run_missing:
        train = settings.candidate.decision.train
        if train is not None and not _exists(train.directory):
            works += train_work(train)
        for run in runs:
            if run is not None:
                works += run_work(run)
    return works


def reproduce_work(settings: ReproduceSettings, reuse: bool = True) -> list[Work]:
    """Collection, training diagnostic and every population run of the report."""
    train = settings.train
    works = train_work(train, reuse) if not _exists(train.directory, reuse) else []
    for run in settings.runs():
        works += run_work(run, reuse)
    return works


def max_hours(cfg: Mapping[str, Any]) -> float:
    """The ``max_hours`` setting: a positive number of hours."""
    value = cfg.get("max_hours", 24.0)
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0 \
            or not math.isfinite(value):  # fmt: skip
        raise ConfigError(f"max_hours must be a positive number of hours, got {value!r}")
    return float(value)


def check(cfg: Mapping[str, Any], works: Sequence[Work], stage: str, basis: str = "") -> float:
    """Log the estimated cost of ``works``; warn past :data:`WARN_SECONDS`; refuse past
    ``max_hours``, naming the settings of the costliest work (``basis``: what it is priced at,
    as in :func:`log_estimate`). Returns the estimate (s)."""
    limit = max_hours(cfg)
    total = sum(w.seconds for w in works)
    if not works:
        return 0.0
    worst = max(works, key=lambda w: w.seconds)
    if not math.isfinite(total) or total > limit * 3600:
        at = f" {basis}" if basis else ""
        raise ConfigError(
            f"{stage}: the simulations this asks for would take ~{duration(total)}{at} (the "
            f"costliest, {worst.describe()}: ~{duration(worst.seconds)}), above max_hours="
            f"{limit:g}. Lower those settings, or raise max_hours to run it anyway"
        )
    return log_estimate(works, stage, basis)


def log_estimate(works: Sequence[Work], stage: str, basis: str = "") -> float:
    """Log the estimated cost of ``works`` (a warning past :data:`WARN_SECONDS`), without the
    ``max_hours`` check; ``basis`` (e.g. ``"at the events measured after the burn-in (...)"``)
    says what it is priced at, after the figure. Returns the estimate (s)."""
    if not works:
        return 0.0
    total = sum(w.seconds for w in works)
    parts = f" {basis}: {_summary(works)}" if basis else f" ({_summary(works)})"
    if total > WARN_SECONDS:
        log.warning("%s: estimated ~%s of simulation before it is done%s; lower those "
                    "settings for a quicker run%s", stage, duration(total), parts,
                    quiet_note())  # fmt: skip
    else:
        log.info("%s: estimated ~%s of simulation%s%s", stage, duration(total), parts,
                 quiet_note())  # fmt: skip
    return total


def quiet_note(load: float | None = None, cores: int | None = None) -> str:
    """What an estimate assumes: a quiet machine (its costs per cell-step were measured on
    one; beside other work the runs take longer: collect 3-4x at a load of 4.5 on 2 cores,
    docs/performance.md), and the load now where it exceeds the cores.

    Args:
        load: the 1-minute load average (default: this machine's now).
        cores: the cores this process may run on (default: its affinity mask).
    """
    if load is None:
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
    busy = f"; this one is busy now (load {load:.1f} on {cores} cores)" if load > cores else ""
    return f"; priced for a quiet machine: other work beside it makes it longer{busy}"


def _summary(works: Sequence[Work]) -> str:
    """The works, identical ones counted once: ``2 x the full-model run: ...: ~5 min each``."""
    groups: dict[str, list[Work]] = {}
    for w in works:
        groups.setdefault(w.describe(), []).append(w)
    return "; ".join(
        f"{len(g)} x {text}: ~{duration(g[0].seconds)} each" if len(g) > 1
        else f"{text}: ~{duration(g[0].seconds)}" for text, g in groups.items()
    )  # fmt: skip


__all__ = [
    "WARN_SECONDS",
    "burn_in_work",
    "check",
    "collect_cost",
    "collect_work",
    "evaluate_work",
    "log_estimate",
    "max_hours",
    "quiet_note",
    "reproduce_work",
    "run_work",
    "train_work",
]

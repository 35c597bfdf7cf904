"""The simulate stage: settings -> one population run -> artefact directory.

``python scripts/simulate.py [decision=full|abstract|exact] [field=...] [n_cells=...]`` writes
the recorders' files (:mod:`surrogate.simulate.recorders`: ``observables.parquet``,
``observable_histograms.parquet``, ``observable_moments.parquet``,
``duration_histogram.parquet``, ``durations.parquet``), for a run in a grid field
(``field=channel_consumed``) also its profiles along x (:mod:`surrogate.simulate.profiles`:
``profiles.parquet``) and their kymograph (``kymograph.png``), and, last, ``manifest.json``
(with the band's speed for a run in a grid field, :func:`~surrogate.evaluate.band.band_summary`).
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from surrogate.config import seed_everything, to_dict
from surrogate.fields import Field
from surrogate.grid import GridField
from surrogate.io import (
    MANIFEST,
    artefact_lock,
    existing_artefact,
    make_once,
    read_manifest,
    save_figure,
    write_manifest,
)
from surrogate.kinds import LayerRequest

# the layers' builders, which the kinds own (ChainKind.decision_layer and exact_layer), kept
# importable from here
from surrogate.kinds import abstract_decision as abstract_decision
from surrogate.kinds import exact_class_decision as exact_class_decision
from surrogate.kinds import exact_clock_decision as exact_clock_decision
from surrogate.kinds import exact_decision as exact_decision
from surrogate.kinds import learned_class_decision as learned_class_decision
from surrogate.models.base import Model
from surrogate.simulate.decision import DecisionLayer, FullDecision
from surrogate.simulate.loop import Simulator, resolve_backend, use_compile_cache
from surrogate.simulate.memory import AGE
from surrogate.simulate.population import PopulationSummary, simulate_population
from surrogate.simulate.recorders import DurationMode, RecorderSpec
from surrogate.simulate.support import TrainedRange, warn_outside
from surrogate.stages import budget
from surrogate.stages.artefacts import KYMOGRAPH_FIGURE
from surrogate.stages.settings import SimulateSettings, TrainSettings, batchable

log = logging.getLogger(__name__)

#: torch.compile's on-disk cache, under the data directory (shared by runs and sweep jobs)
COMPILE_CACHE = "cache/torch_compile"


def validate(cfg: Mapping[str, Any]) -> SimulateSettings:
    """All checks of a simulate config and its estimated cost, before any work starts; the
    typed settings."""
    settings = SimulateSettings.from_config(cfg)
    budget.check(cfg, budget.run_work(settings), "simulate")
    return settings


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Run (or reuse) the population simulation described by ``cfg``; return its directory."""
    return simulate(validate(cfg), config=to_dict(cfg), force=force)


def simulate(
    settings: SimulateSettings, config: Mapping[str, Any] | None = None, force: bool = False
) -> Path:
    """Run (or reuse) the population run described by ``settings``."""
    out = settings.directory
    return make_once(out, settings.identity(), settings.command(),
                     lambda _: _simulate(settings, out, config), what="simulation", force=force)  # fmt: skip


def build_decision(
    settings: SimulateSettings, model: Model | None = None
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The decision layer of a run, and facts about it for the manifest; over ``model`` when
    given (a batch's runs share one model object, so their layers can share blocks), else
    the run's own."""
    model = model if model is not None else settings.setup.model
    device = settings.job.device
    d = settings.decision
    if d.kind.full:
        return FullDecision(model.internal), {}
    if d.kind.exact:
        assert d.chain is not None  # the settings made it
        return d.chain.exact_layer(LayerRequest(model, settings.setup.dt, d.mode or "lookup",
                                                d.lookup_size, device, d.max_age))  # fmt: skip
    assert d.train is not None
    # the fit is found and loaded here, at the stage's edge (the train stage's module is
    # imported only by runs that need it)
    from surrogate.stages.train import resolve_abstraction

    directory = resolve_abstraction(d.train)
    request = LayerRequest.of_fit(model, d.train, d.mode or "lookup", d.lookup_size, device,
                                  d.start)  # fmt: skip
    layer, info = learned_decision(request, d.train, directory, settings.job.support_min_rows)
    return layer, {"abstraction_dir": str(directory), **info}


def learned_decision(
    request: LayerRequest,
    train: TrainSettings,
    directory: Path,
    min_rows: int | None = None,
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The learned abstraction of the fit ``directory`` (made by ``train``) as the decision
    layer ``request`` asks for (:meth:`LayerRequest.of_fit`), as its kind makes it
    (``ChainKind.decision_layer``): the K-lumps chain (``gp.lumps=classes``, a table; its cells
    start as ``request.start`` says, see :class:`ClassDecision`), the switch clock's or the
    chain over phi's (:func:`abstract_decision`: a lookup table of psi or the classifier itself).

    The layer carries the range its training data covered (``trained_range``: each input's
    min and max over the training rows, the fit's ``domain``; the switch clock, capped by
    construction, excepted) and, where the fit stored it, its rows' histogram over that range
    (``support_histogram``; a bin with fewer than ``min_rows`` rows of a state is sparse; None:
    the default rule, :func:`~surrogate.simulate.support.min_rows_of`), which the simulator's
    support monitor checks the cells against; a K-lumps fit's per class
    (``support_class_histogram``: each cell against its own class's rows; an older fit
    without it, per state)."""
    layer, info = train.kind.decision_layer(request, directory)
    manifest = read_manifest(directory)
    domain = manifest.get("domain") or {}
    names = [n for n in info["inputs"] if n != AGE]
    if names and all(n in domain for n in names):
        classes = info.get("classes") if train.kind.classes else None
        layer.trained_range = TrainedRange.from_domain(  # type: ignore[attr-defined]
            domain, names, manifest.get("support_histogram"), min_rows,
            manifest.get("support_class_histogram") if classes else None, classes,
        )  # fmt: skip
    return layer, info


def _simulate(settings: SimulateSettings, out: Path, config: Mapping[str, Any] | None) -> None:
    setup, job = settings.setup, settings.job
    if settings.compile:
        use_compile_cache(job.data_dir / COMPILE_CACHE)
    seed_everything(setup.seed)
    decision, info = build_decision(settings)
    # a compiled run that fell back to eager is not the run its identity (compile=true) names
    simulator = Simulator(setup.model, decision, setup.field, setup.dt, job.device,
                          compile=settings.compile, backend=settings.backend,
                          compile_fallback=False)  # fmt: skip
    _log_backend(simulator)
    # a rerun (force) must not leave the old manifest vouching for half-replaced tables
    (out / MANIFEST).unlink(missing_ok=True)
    t0 = time.perf_counter()
    summary = simulate_population(
        simulator,
        n_cells=settings.n_cells,
        t_end=settings.t_end,
        out_dir=out,
        record_interval=settings.record_interval,
        start=torch.tensor(settings.start),
        equilibration_time=settings.equilibration_time,
        record_durations=settings.record_durations,
        progress=job.progress,
        # null = every cell and every duration (the complete tables, for small runs)
        record_cells=settings.record_cells,
        durations=None if settings.record_cells or not settings.record_durations else "all",
    )
    _write_manifest(settings, out, config, summary, time.perf_counter() - t0,
                    compiled=simulator.compiled, loop_backend=simulator.backend,
                    **info)  # fmt: skip


def _log_backend(simulator: Simulator) -> None:
    if simulator.backend_note:
        log.info("backend=auto: the torch step (%s)", simulator.backend_note)


def _write_manifest(
    settings: SimulateSettings,
    out: Path,
    config: Mapping[str, Any] | None,
    summary: PopulationSummary,
    wall_time_s: float,
    **facts: Any,
) -> None:
    setup = settings.setup
    if summary.profiles is not None:
        facts = {**facts, **profile_outputs(out, summary.profiles, settings.decision.name,
                                            uptake=read_uptake(setup.field))}  # fmt: skip
    write_manifest(
        out,
        stage="simulate",
        config=dict(config) if config is not None else settings.identity(),
        seed=setup.seed,
        settings=settings.identity(),
        decision=settings.decision.name,
        device=str(settings.job.device),
        wall_time_s=wall_time_s,
        loop_time_s=summary.loop_time_s,
        compile_time_s=summary.compile_time_s,
        compile=settings.compile,
        cell_steps_per_s=summary.cell_steps_per_s,
        n_cells=summary.n_cells,
        n_steps=summary.n_steps,
        n_durations=summary.n_durations,
        final_means={k: v[-1] for k, v in summary.means.items()},
        observables=list(setup.model.body.observable_names),
        lump_names=list(setup.model.internal.lump_names),
        outside_training=summary.outside_training,
        **facts,
    )
    warn_outside(summary.outside_training, settings.job.outside_warning,
                 f"{settings.decision.name} run in {setup.field_name} ({out.name})")  # fmt: skip
    batch = facts.get("batched")
    speed = (f"one loop of {len(batch['runs'])} runs, {batch['n_cells']} cells" if batch
             else f"{summary.cell_steps_per_s:.3g} cell-steps/s")  # fmt: skip
    log.info(
        "%s simulation of %d cells x %d steps: %.2f s (%s); artefacts in %s",
        settings.decision.name, summary.n_cells, summary.n_steps, summary.loop_time_s, speed, out,
    )  # fmt: skip


def read_uptake(field: Field) -> tuple[float, float] | None:
    """The uptake ``(vmax, km)`` of the species a grid field's cells read, None if it has none
    (or the field is not a grid)."""
    if not isinstance(field, GridField):
        return None
    species = field.species[field.species_names.index(field.read)]
    return None if species.uptake is None else (species.uptake.vmax, species.uptake.km)


def profile_outputs(
    out: Path,
    profiles: Mapping[str, Any],
    label: str,
    uptake: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """A run in a grid field: its kymograph (``kymograph.png``) and the manifest's facts about
    its profiles (``profiles``: the recorder's facts) and band (``band``: speeds from the front
    and the density's peak, :func:`~surrogate.evaluate.band.band_summary`, and with ``uptake``,
    the read species' ``(vmax, km)``, the front's speed by mass balance)."""
    from surrogate.evaluate.band import band_summary
    from surrogate.evaluate.kymograph import plot_kymograph
    from surrogate.simulate.profiles import read_profiles

    data = read_profiles(out)
    save_figure(out / KYMOGRAPH_FIGURE, plot_kymograph([data], [label]), crop=False)
    band = band_summary(data, uptake=uptake)
    front = band["front"]
    if front["speed"] is None:
        log.info("no band speed from the front: %d of %d records have one (the read "
                 "species depleted to half inside the channel)", front["n"], len(data.t))  # fmt: skip
    else:
        log.info("band front: %.4g mm/s (s.e. %s) over %d records, from %.4g to %.4g mm",
                 front["speed"], front["stderr"], front["n"], front["first"],
                 front["last"])  # fmt: skip
        balance = band.get("mass_balance") or {}
        if balance.get("speed") is not None:
            log.info("band front by mass balance (the cells' uptake / (A c_ahead)): %.4g mm/s "
                     "(%.4g to %.4g over those records)", balance["speed"], balance["min"],
                     balance["max"])  # fmt: skip
    return {"profiles": dict(profiles), "band": band}


def batch_key(settings: SimulateSettings) -> str:
    """Runs with equal keys can be simulated in one batch (same model, step, recording)."""
    s = settings
    return json.dumps([s.setup.identity().get("model"), s.setup.dt, s.t_end, s.record_interval,
                       s.equilibration_time, s.record_durations, s.record_cells, s.compile,
                       s.backend, str(s.job.device)], sort_keys=True, default=str)  # fmt: skip


def simulate_together(runs: Sequence[SimulateSettings]) -> list[Path]:
    """Make the missing runs of ``runs`` as replicates of one population per :func:`batch_key`
    (:class:`~surrogate.simulate.batch.BatchSimulator`: one loop for all, each run's cells seeded
    as its standalone run's), each written to its own directory with its own manifest; reuse
    the complete ones. Returns the runs' directories, in order.

    Small populations pay the per-step cost once per batch instead of once per run; runs of
    more than ``BATCH_MAX_CELLS`` cells are simulated alone (:func:`simulate`). Eager, a
    batched run is the standalone run bit for bit; compiled, kernels fused for another shape
    round differently, so ``SimulateSettings.batched`` puts such runs in their own directories.
    The manifests say ``batched``: their loop time is the batch's, not a run's own.
    """
    unique = {s.directory: s for s in runs}
    missing = [s for d, s in unique.items()
               if existing_artefact(d, s.identity(), s.command()) is None]  # fmt: skip
    groups: dict[str, list[SimulateSettings]] = {}
    for s in missing:
        if batchable(s):
            groups.setdefault(batch_key(s), []).append(s)
        else:  # a large population: alone (batching would only slow it down)
            simulate(s)
    for group in groups.values():
        # one global order (by directory) whatever the caller's: two jobs sharing runs in
        # opposite orders would otherwise each hold a lock the other waits for
        # (_simulate_group orders the batch itself, decision-major)
        group.sort(key=lambda s: str(s.directory))
        with contextlib.ExitStack() as stack:
            for s in group:
                stack.enter_context(artefact_lock(s.directory))
            todo = [s for s in group
                    if existing_artefact(s.directory, s.identity(), s.command()) is None]  # fmt: skip
            if todo:
                _simulate_group(todo)
    return [s.directory for s in runs]


def _key(config: Any) -> str:
    return json.dumps(config, sort_keys=True, default=str)


def _simulate_group(runs: Sequence[SimulateSettings]) -> None:
    from surrogate.simulate.batch import Replicate

    first = runs[0]
    setup, job = first.setup, first.job
    if first.compile:
        use_compile_cache(job.data_dir / COMPILE_CACHE)
    # decision-major, then field: consecutive runs with one decision (a shared table) and one
    # field are one block of the batch, so its step costs about as many tensor ops as one run
    runs = sorted(runs, key=lambda s: (s.decision.name, _key(s.decision.identity()),
                                       _key(s.setup.field_config)))  # fmt: skip
    built: dict[str, tuple[DecisionLayer, dict[str, Any]]] = {}
    fields: dict[str, Field] = {}
    replicates, infos = [], []
    for s in runs:
        key = _key(s.decision.identity())
        if key not in built:
            built[key] = build_decision(s, setup.model)  # one model: layers can share blocks
        decision, info = built[key]
        field = fields.setdefault(_key(s.setup.field_config), s.setup.field)
        # a layer per run (its own state), sharing the built table with the others
        replicates.append(Replicate(copy.copy(decision), field, s.n_cells, s.setup.seed,
                                    torch.tensor(s.start)))  # fmt: skip
        infos.append(info)
        (s.directory / MANIFEST).unlink(missing_ok=True)
    # backend=auto: a run is batched only with runs its standalone run would share a loop
    # backend with (a batch of kernel runs gives each run its standalone numbers, bit for bit)
    by_backend: dict[str, list[int]] = {}
    for i, (s, rep) in enumerate(zip(runs, replicates, strict=True)):
        alone = resolve_backend(s.backend, setup.model, rep.decision, rep.field, setup.dt,
                                job.device, s.compile)  # fmt: skip
        by_backend.setdefault(alone, []).append(i)
    for members in by_backend.values():
        _simulate_batch(setup.model, [runs[i] for i in members],
                        [replicates[i] for i in members], [infos[i] for i in members])  # fmt: skip


def _simulate_batch(
    model: Model,
    runs: Sequence[SimulateSettings],
    replicates: Sequence[Any],
    infos: Sequence[dict[str, Any]],
) -> None:
    """One batch over ``model`` (the one the replicates' decision layers were built over)."""
    from surrogate.simulate.batch import BatchSimulator, simulate_batch

    first = runs[0]
    setup, job = first.setup, first.job
    t0 = time.perf_counter()
    seed_everything(setup.seed)
    simulator = BatchSimulator(model, replicates, setup.dt, job.device,
                               compile=first.compile, backend=first.backend,
                               compile_fallback=False)  # fmt: skip
    _log_backend(simulator)
    log.info("simulating %d runs in one batch (%d cells, %d decision blocks, %d distinct fields; "
             "%s loop)", len(runs), sum(s.n_cells for s in runs),
             len(simulator.decision.members), len(simulator.field.distinct),
             simulator.backend)  # fmt: skip
    # every segment where every cell is recorded, else the recorded cells' (or none)
    durations: DurationMode = ("none" if not first.record_durations
                               else "histogram" if first.record_cells else "all")  # fmt: skip
    summaries = simulate_batch(
        simulator, first.t_end, [s.directory for s in runs],
        record_interval=first.record_interval, equilibration_time=first.equilibration_time,
        progress=job.progress,
        recording=RecorderSpec(record_cells=first.record_cells, durations=durations),
    )  # fmt: skip
    wall = time.perf_counter() - t0
    labels = [f"{s.decision.name}|{s.setup.label().get('field')}|seed={s.setup.seed}" for s in runs]
    for s, summary, info in zip(runs, summaries, infos, strict=True):
        _write_manifest(s, s.directory, None, summary, wall,
                        compiled=simulator.compiled,
                        loop_backend=simulator.backend,
                        batched={"runs": labels, "n_cells": sum(r.n_cells for r in runs)},
                        **info)  # fmt: skip


__all__ = ["batch_key", "build_decision", "run", "simulate", "simulate_together", "validate"]

"""The simulate stage: settings -> one population run -> artefact directory.

``python scripts/simulate.py [decision=full|abstract|exact] [field=...] [n_cells=...]`` writes
``observables.parquet``, ``durations.parquet`` and ``manifest.json``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from surrogate.config import seed_everything, to_dict
from surrogate.gp import PsiLookupTable
from surrogate.io import MANIFEST, make_once, write_manifest
from surrogate.models.base import Model
from surrogate.simulate.decision import (
    AbstractDecision,
    DecisionLayer,
    ExactDecision,
    ExactPsi,
    FullDecision,
)
from surrogate.simulate.loop import Simulator, use_compile_cache
from surrogate.simulate.population import simulate_population
from surrogate.stages.settings import SimulateSettings, TrainSettings

log = logging.getLogger(__name__)

#: torch.compile's on-disk cache, under the data directory (shared by runs and sweep jobs)
COMPILE_CACHE = "cache/torch_compile"


def validate(cfg: Mapping[str, Any]) -> SimulateSettings:
    """All checks of a simulate config, before any work starts; the typed settings."""
    return SimulateSettings.from_config(cfg)


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


def build_decision(settings: SimulateSettings) -> tuple[DecisionLayer, dict[str, Any]]:
    """The decision layer of a run, and facts about it for the manifest."""
    model, device = settings.setup.model, settings.job.device
    d = settings.decision
    if d.name == "full":
        return FullDecision(model.internal), {}
    if d.name == "exact":
        return exact_decision(model, settings.setup.dt, d.mode or "lookup", d.lookup_size, device)
    assert d.train is not None
    return abstract_decision(model, d.train, d.mode or "lookup", d.lookup_size, device)


def exact_decision(
    model: Model, dt: float, mode: str, size: Sequence[int] | None, device: torch.device
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The chain driven by the model's exact lumped psi: ``direct`` (exp(Q dt) per cell and
    step) or ``lookup`` (a table over the signal's bounds, checked against direct)."""
    internal = model.internal
    if mode == "direct":
        return ExactDecision(internal, dt), {}
    bounds = internal.signal_bounds  # type: ignore[attr-defined]
    ranges = [bounds[n] for n in internal.signal_names]
    exact = ExactPsi(internal, dt)
    table = PsiLookupTable.from_function(exact, ranges, internal.signal_names, size).to(device)
    deviation = table.max_deviation(exact, n_check=2048)
    log.info("exact psi table %s: max |table - exact| = %.2e", table.shape, deviation)
    return ExactDecision(internal, dt, table), {"lookup_max_deviation": deviation}


def abstract_decision(
    model: Model,
    train: TrainSettings,
    mode: str,
    size: Sequence[int] | None,
    device: torch.device,
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The learned abstraction of ``train`` (which must exist): a lookup table of it, or the
    classifier every step in closed form with cached factors (checked against the classifier)."""
    from surrogate.stages.train import load_abstraction, resolve_abstraction

    directory = resolve_abstraction(train)
    psi = load_abstraction(directory, device=device)
    info: dict[str, Any] = {"abstraction_dir": str(directory), "inputs": list(psi.input_names)}
    featurize = model.featurizer(psi.input_names)
    if mode == "lookup":
        ranges = [psi.domain[n] for n in psi.input_names]
        table = PsiLookupTable.from_function(psi, ranges, psi.input_names, size).to(device)
        info["lookup_max_deviation"] = float(table.max_deviation(psi))
        log.info("lookup table %s: max |table - classifier| = %.2e", table.shape,
                 info["lookup_max_deviation"])  # fmt: skip
        return AbstractDecision(table, model.internal, featurize), info
    # classifier every step: the same predictive in closed form with cached factors (no gpytorch,
    # no host sync per step); its agreement with the classifier is checked and recorded
    from surrogate.gp.fast import CachedPsi

    cached = CachedPsi.from_classifier(psi)
    info["cached_max_deviation"] = cached.max_deviation(psi)
    log.info("cached classifier: max |cached - classifier| = %.2e", info["cached_max_deviation"])
    return AbstractDecision(cached, model.internal, featurize), info


def _simulate(settings: SimulateSettings, out: Path, config: Mapping[str, Any] | None) -> None:
    """Simulate, then write the tables and (last) the manifest into ``out``."""
    setup, job = settings.setup, settings.job
    if settings.compile:
        use_compile_cache(job.data_dir / COMPILE_CACHE)
    seed_everything(setup.seed)
    decision, info = build_decision(settings)
    simulator = Simulator(setup.model, decision, setup.field, setup.dt, job.device,
                          compile=settings.compile)  # fmt: skip
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
    )
    write_manifest(
        out,
        stage="simulate",
        config=dict(config) if config is not None else settings.identity(),
        seed=setup.seed,
        settings=settings.identity(),
        decision=settings.decision.name,
        device=str(job.device),
        wall_time_s=time.perf_counter() - t0,
        loop_time_s=summary.loop_time_s,
        compile_time_s=summary.compile_time_s,
        compile=settings.compile,
        compiled=simulator.compile_error is None and settings.compile,
        cell_steps_per_s=summary.cell_steps_per_s,
        n_cells=summary.n_cells,
        n_steps=summary.n_steps,
        n_durations=summary.n_durations,
        final_means={k: v[-1] for k, v in summary.means.items()},
        observables=list(setup.model.body.observable_names),
        lump_names=list(setup.model.internal.lump_names),
        **info,
    )
    log.info(
        "%s simulation of %d cells x %d steps: %.2f s (%.3g cell-steps/s); artefacts in %s",
        settings.decision.name, summary.n_cells, summary.n_steps, summary.loop_time_s,
        summary.cell_steps_per_s, out,
    )  # fmt: skip


__all__ = ["build_decision", "run", "simulate", "validate"]

"""The simulate stage: config -> population run -> artefact directory."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from surrogate.config import (
    build_field,
    build_params,
    grid_shape,
    non_negative,
    positive,
    resolve_device,
    seed_everything,
    to_dict,
    validate_common,
    validate_start,
)
from surrogate.errors import ConfigError
from surrogate.io import MANIFEST, make_once, write_manifest
from surrogate.paths import SIMULATE_CMD, abstraction_config, simulate_dir, simulate_settings
from surrogate.simulate.decision import AbstractDecision, DecisionLayer, FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.population import simulate_population, steps_between

log = logging.getLogger(__name__)

DECISIONS = ("full", "abstract")
ABSTRACT_MODES = ("lookup", "classifier")


def validate(cfg: Mapping[str, Any]) -> None:
    """All checks of a simulate config, before any work starts."""
    validate_common(cfg)
    positive(cfg, "n_cells", integer=True)
    t_end = positive(cfg, "t_end")
    interval = positive(cfg, "record_interval")
    dt = float(cfg["dt"])
    if dt > interval:
        raise ConfigError(f"dt={dt:g} s is larger than record_interval={interval:g} s")
    try:
        steps_between(interval, dt, "record_interval")
        steps_between(t_end, dt, "t_end")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    non_negative(cfg, "equilibration_time")
    validate_start(cfg)
    decision = cfg["decision"]
    if decision.get("name") not in DECISIONS:
        raise ConfigError(
            f"decision.name must be one of {list(DECISIONS)} (select with decision=full|abstract), "
            f"got {decision.get('name')!r}"
        )
    if decision["name"] == "abstract":
        if decision.get("mode") not in ABSTRACT_MODES:
            raise ConfigError(
                f"decision.mode must be one of {list(ABSTRACT_MODES)}, got {decision.get('mode')!r}"
            )
        grid_shape(decision.get("lookup_size"), "decision.lookup_size")
        # The collect/gp settings locate the abstraction: refuse invalid ones (and an unknown
        # decision.train_field) here, not as a missing artefact after the lookups.
        from surrogate import collect, train

        train_cfg = abstraction_config(cfg)  # unknown train field -> ConfigError
        collect.validate(train_cfg)
        train.validate(train_cfg)


def build_decision(cfg: Mapping[str, Any], device: Any) -> tuple[DecisionLayer, dict[str, Any]]:
    """The decision layer of a config, and facts about it for the manifest."""
    params = build_params(cfg["model"])
    if cfg["decision"]["name"] == "full":
        return FullDecision(params), {}
    from surrogate.train import load_abstraction, resolve_abstraction

    directory = resolve_abstraction(abstraction_config(cfg))
    psi = load_abstraction(directory, device=device)
    info: dict[str, Any] = {"abstraction_dir": str(directory)}
    if cfg["decision"]["mode"] == "lookup":
        from surrogate.gp import PsiLookupTable

        domain = psi.domain
        table = PsiLookupTable.from_classifier(
            psi, domain["m"], domain["L"], size=tuple(cfg["decision"]["lookup_size"])
        ).to(device)
        info["lookup_max_deviation"] = float(table.max_deviation(psi))
        log.info(
            "lookup table %s: max |table - classifier| = %.2e",
            tuple(table.shape),
            info["lookup_max_deviation"],
        )
        return AbstractDecision(table, params), info
    # classifier every step: the same predictive in closed form with cached factors (no gpytorch,
    # no host sync per step); its agreement with the classifier is checked and recorded
    from surrogate.gp.fast import CachedPsi

    cached = CachedPsi.from_classifier(psi)
    info["cached_max_deviation"] = cached.max_deviation(psi)
    log.info("cached classifier: max |cached - classifier| = %.2e", info["cached_max_deviation"])
    return AbstractDecision(cached, params), info


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Run (or reuse) the population simulation described by ``cfg``; return its directory."""
    validate(cfg)
    out = simulate_dir(cfg)
    return make_once(out, simulate_settings(cfg), SIMULATE_CMD, lambda _: _simulate(cfg, out),
                     what="simulation", force=force)  # fmt: skip


def _simulate(cfg: Mapping[str, Any], out: Path) -> None:
    """Simulate, then write the tables and (last) the manifest into ``out``."""
    device = resolve_device(cfg.get("device", "cpu"))
    seed_everything(int(cfg["seed"]))
    decision, info = build_decision(cfg, device)
    simulator = Simulator(
        decision,
        build_field(cfg["field"]),
        build_params(cfg["model"]),
        float(cfg["dt"]),
        device,
        compile=bool(cfg.get("compile", False)),
    )
    # a rerun (force) must not leave the old manifest vouching for half-replaced tables
    (out / MANIFEST).unlink(missing_ok=True)
    t0 = time.perf_counter()
    summary = simulate_population(
        simulator,
        n_cells=int(cfg["n_cells"]),
        t_end=float(cfg["t_end"]),
        out_dir=out,
        record_interval=float(cfg["record_interval"]),
        start=validate_start(cfg),
        equilibration_time=float(cfg["equilibration_time"]),
        record_durations=bool(cfg["record_durations"]),
        progress=bool(cfg.get("progress", True)),
    )
    write_manifest(
        out,
        stage="simulate",
        config=to_dict(cfg),
        seed=int(cfg["seed"]),
        settings=simulate_settings(cfg),
        decision=cfg["decision"]["name"],
        device=str(device),
        wall_time_s=time.perf_counter() - t0,
        loop_time_s=summary.loop_time_s,
        compile_time_s=summary.compile_time_s,
        compiled=simulator.compile_error is None and bool(cfg.get("compile", False)),
        cell_steps_per_s=summary.cell_steps_per_s,
        n_cells=summary.n_cells,
        n_steps=summary.n_steps,
        n_durations=summary.n_durations,
        final_mean_distance=summary.mean_distance[-1],
        **info,
    )
    log.info(
        "%s simulation of %d cells x %d steps: %.2f s (%.3g cell-steps/s); artefacts in %s",
        cfg["decision"]["name"], summary.n_cells, summary.n_steps, summary.loop_time_s,
        summary.cell_steps_per_s, out,
    )  # fmt: skip


__all__ = ["SIMULATE_CMD", "build_decision", "run", "validate"]

"""Collect's cost probe (surrogate/diagnosis/probe.py, run by surrogate/stages/collect.py before
its first simulation): a runaway network (autocatalysis A -> 2A) refused in seconds with the
rate measured, instead of burning in for hours; a network that stays put (the open birth-death
process) collected exactly as without the probe, in the same directory; a negative budget
refused as a bad setting; a birth-death process ~2e4x costlier at stationarity than at the
file's counts priced by collect at the rate measured after the burn-in (the rate reached where
the probe ran out; the file's counts where it is off). The other networks are the inspection
tests'."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest
import torch
import yaml

from surrogate.diagnosis.cost import duration
from surrogate.errors import ConfigError
from surrogate.stages import budget, collect
from surrogate.stages.settings import CollectSettings, InspectSettings
from tests.diagnosis.test_inspection import birth_death
from tests.sbml.builder import Reaction, Species, build
from tests.stages.test_inspection import runaway

MEASURED = "at the events measured after the burn-in"


def test_collect_refuses_a_runaway_network_in_seconds(tmp_path, compose_cfg) -> None:
    """The probe (collect.probe_seconds=0.5) stops the runaway's burn-in before any cell is
    simulated; the refusal gives the rate reached, its growth from the file's counts, the
    remedies and the inspector's command, and nothing is written."""
    _, spec = runaway(tmp_path)
    cfg = compose_cfg("collect", ["model=sbml", f"model.spec={spec}", "collect.probe_seconds=0.5"])
    settings = collect.validate(cfg)
    settings.setup.model.internal.prepare()  # the compile is not the probe's
    start = time.perf_counter()
    with pytest.raises(ConfigError) as error:
        collect.collect(settings)
    assert time.perf_counter() - start < 3.0
    message = str(error.value)
    assert message.startswith("collect: the network's cost outgrew collect's cost probe"), message
    assert "ran out of the cost probe's 0.5 s (collect.probe_seconds=0.5)" in message, message
    rate = float(message.split("fire ~")[1].split(" events")[0].replace(",", ""))
    assert rate > 1000, message  # the file's counts say 25
    assert "x the 25 estimated from the file's counts" in message
    assert "Fastest-growing: A = " in message and "this collection (" in message
    for remedy in ("units", "model.burn_in", "collect.probe_seconds", "device=cuda",
                   "scripts/inspect_model.py"):  # fmt: skip
        assert remedy in message
    assert not (settings.directory / "manifest.json").exists()


def test_the_probe_changes_neither_a_collection_nor_its_directory(
    tmp_path, compose_cfg, caplog
) -> None:
    """The open birth-death process (not enumerable: probed) collected with the probe on and
    off: the same identity and directory (the inspection's too), the same table bit for bit; the probe logs its rate
    once and leaves torch's generator as it was."""
    _, spec = birth_death(tmp_path, "X >= 1", reservoir=False)
    small = ["model=sbml", f"model.spec={spec}", "collect.n_per_state=100", "collect.n_cells=50",
             "collect.record_every=1", "collect.equilibration_time=1", "collect.max_time=200"]  # fmt: skip
    on = CollectSettings.from_config(compose_cfg("collect", [*small, "collect.probe_seconds=2"]))
    off = CollectSettings.from_config(compose_cfg("collect", [*small, "collect.probe_seconds=0"]))
    assert "probe_seconds" not in on.identity()["collect"]
    assert on.directory == off.directory and on.command() != off.command()
    inspections = [InspectSettings.from_config(compose_cfg("inspect", [*small[:2], probe]))
                   for probe in ("collect.probe_seconds=2", "collect.probe_seconds=0")]  # fmt: skip
    assert inspections[0].directory == inspections[1].directory  # nor the inspection's
    before = torch.get_rng_state()
    measured = collect.cost_probe(on)
    assert measured is not None and measured["completed"]
    assert torch.equal(torch.get_rng_state(), before)
    assert collect.cost_probe(off) is None
    caplog.clear()  # the calls above logged too where an earlier test left the root at INFO
    with caplog.at_level(logging.INFO, logger="surrogate.diagnosis.probe"), \
            caplog.at_level(logging.INFO, logger="surrogate.stages.budget"):  # fmt: skip
        table = pd.read_parquet(collect.collect(on) / "transitions.parquet")
    assert sum("collect: cost probe, 4 cells" in r.getMessage() for r in caplog.records) == 1
    # its rate kept for the later stages' estimates (budget.collected_cell_step)
    manifest = on.directory / "manifest.json"
    assert json.loads(manifest.read_text())["cost_probe"] == {
        k: measured[k] for k in collect.PROBE_RECORD}  # fmt: skip
    assert sum(MEASURED in r.getMessage() for r in caplog.records) == 1  # its estimate
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="surrogate.diagnosis.probe"), \
            caplog.at_level(logging.INFO, logger="surrogate.stages.budget"):  # fmt: skip
        again = pd.read_parquet(collect.collect(off, force=True) / "transitions.parquet")
    assert not any("cost probe" in r.getMessage() or MEASURED in r.getMessage()
                   for r in caplog.records)  # fmt: skip
    assert len(table) >= 200
    pd.testing.assert_frame_equal(table, again, check_exact=True)
    assert "cost_probe" not in json.loads(manifest.read_text())


def test_a_negative_probe_budget_is_refused_by_name(compose_cfg) -> None:
    with pytest.raises(ConfigError, match=r"collect\.probe_seconds must be a non-negative"):
        CollectSettings.from_config(compose_cfg("collect", ["collect.probe_seconds=-1"]))


def logistic(tmp_path: Path) -> Path:
    """A birth-death process from X = 0: births at k s (1 + X) (k = 1), deaths at g X^2 (g =
    1e-4), a 20-s burn-in. The file's counts fire 1 event per second (births alone); X grows
    logistically to ~1e4 (+- 100; 99 % there by ~14 s, then relaxing in ~1 s), where births and
    deaths are ~1e4 per second each: ~2e4x more events."""
    species = [Species("X", amount=0)]
    reactions = [Reaction("birth", "k * s * (1 + X)", {}, {"X": 1}, modifiers=("X",)),
                 Reaction("death", "g * X * X", {"X": 1}, {})]  # fmt: skip
    (tmp_path / "logistic.xml").write_text(build("logistic", species,
                                                 {"k": 1.0, "g": 1e-4, "s": 1.0}, reactions))  # fmt: skip
    spec = tmp_path / "logistic.yaml"
    spec.write_text(yaml.safe_dump({"name": "logistic", "network": "logistic.xml",
                                    "inputs": {"s": "L"}, "lump": "X >= 10000",
                                    "lump_names": ["off", "on"], "body": {"kind": "static"},
                                    "burn_in": 20.0}))  # fmt: skip
    return spec


def logistic_settings(tmp_path: Path, compose_cfg, probe_seconds: float) -> CollectSettings:
    spec = logistic(tmp_path)
    return collect.validate(compose_cfg("collect", [
        "model=sbml", f"model.spec={spec}", "collect.n_per_state=100", "collect.n_cells=50",
        "collect.record_every=1", "collect.equilibration_time=1",
        f"collect.probe_seconds={probe_seconds:g}"]))  # fmt: skip


def test_collect_prices_its_windows_at_the_rate_measured_after_the_burn_in(
    tmp_path, compose_cfg, caplog
) -> None:
    """The file's counts (X = 0) say 0.05 events per window of 0.05 s; the probe measures ~2e4x
    that after the 20-s burn-in, and collect's logged estimate (its windows' and the burn-in's)
    is priced at it, naming both rates; validate's, at the file's counts, is unchanged."""
    with caplog.at_level(logging.INFO, logger="surrogate.stages.budget"):
        settings = logistic_settings(tmp_path, compose_cfg, 3.0)
    [before] = [r.getMessage() for r in caplog.records if "collect: estimated" in r.getMessage()]
    assert "measured" not in before, before
    network, dt = settings.setup.model.internal, settings.setup.dt
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="surrogate.stages.budget"):
        estimate = collect.measured_cost(settings, collect.cost_probe(settings))
    assert estimate is not None and estimate.completed
    assert estimate.reached_s == pytest.approx(20.0) == estimate.horizon_s
    assert estimate.file_events == pytest.approx(1.0 * dt)
    assert 1e4 < estimate.events / estimate.file_events < 3e4, estimate  # 2e4 at stationarity
    assert estimate.cell_step_seconds == network.cell_step_seconds(dt, estimate.events)
    works = budget.collect_work(settings, reuse=False)
    assert estimate.file_seconds == pytest.approx(sum(w.seconds for w in works))
    at = [replace(w, cell_step_seconds=estimate.cell_step_seconds) for w in works]
    assert estimate.seconds == pytest.approx(sum(w.seconds for w in at))
    assert estimate.seconds > 5 * estimate.file_seconds, estimate
    [record] = [r for r in caplog.records if "collect: estimated" in r.getMessage()]
    message = record.getMessage()
    assert f"~{duration(estimate.seconds)} of simulation {MEASURED} (" in message
    logged = message.split(f"{MEASURED} (")[1].split(" per window per cell; the file's")[0]
    assert float(logged.replace(",", "")) == pytest.approx(estimate.events, abs=0.5), message
    assert " per window per cell; the file's counts: 0.05, " in message
    assert f"~{duration(estimate.file_seconds)})" in message
    assert "the initial states' burn-in" in message and "collect (at least)" in message
    # max_hours holds at the measured rate too: past it, refused with both figures (the
    # file's counts' estimate passed validate's check)
    limit = 0.5 * estimate.seconds / 3600
    assert estimate.file_seconds < limit * 3600
    with pytest.raises(ConfigError, match=r"above max_hours=.*raise max_hours") as error:
        collect.measured_cost(settings, collect.cost_probe(settings), {"max_hours": limit})
    assert f"~{duration(estimate.seconds)} {MEASURED} (" in str(error.value)


def test_the_train_diagnostic_is_priced_at_the_rate_its_collection_measured(
    tmp_path, compose_cfg
) -> None:
    """The collection keeps its probe's rate in its manifest; the train stage's estimate of its
    diagnostic population (and that population's burn-in) is priced at it, not at the file's
    counts (~2e4x fewer events: Vilar's oscillator's diagnostic was estimated at 42 s and took
    6 min); before the collection exists, at the file's counts (what the collection's manifest
    records is the test above's)."""
    from surrogate.io import write_manifest
    from surrogate.stages import train as train_stage

    overrides = ["model=sbml", f"model.spec={logistic(tmp_path)}", "collect.n_per_state=100",
                 "collect.n_cells=50", "collect.record_every=1", "collect.equilibration_time=1",
                 "collect.probe_seconds=3"]  # fmt: skip
    train = train_stage.validate(compose_cfg("train", [*overrides, "gp.n_inducing=10"]))
    network, dt = train.setup.model.internal, train.setup.dt

    def diagnostic() -> list[float]:  # the population's cell-step and its burn-in's
        works = budget.train_work(train)
        [i] = [i for i, w in enumerate(works)
               if w.what == "the train diagnostic's full-model population"]  # fmt: skip
        assert works[i + 1].what == "the initial states' burn-in"
        return [works[i].cell_step_seconds, works[i + 1].cell_step_seconds]

    at_file = network.cell_step_seconds(dt)
    assert budget.collected_cell_step(train.source) is None
    assert diagnostic() == [at_file, at_file]
    events = 2e4 * network.events_per_window(dt)  # the probe's ~2e4x after the burn-in
    recorded = {"events_per_window_last": events, "events_per_window_file": events / 2e4,
                "reached_s": 20.0, "completed": True}  # fmt: skip
    write_manifest(train.source.directory, stage="collect", config={}, seed=0,
                   cost_probe=recorded)  # fmt: skip
    measured = network.cell_step_seconds(dt, events)
    assert measured > 100 * at_file
    assert budget.collected_cell_step(train.source) == measured
    assert diagnostic() == [measured, measured]


def test_collect_prices_at_the_rate_reached_where_the_probe_ran_out(
    tmp_path, compose_cfg, caplog
) -> None:
    """A probe out of budget at 5 s of the 20-s burn-in (a steady rate: a growing one is
    refused) prices the collection at the rate it reached and says so; one that reached
    nothing, or is off (collect.probe_seconds=0), leaves the estimate at the file's counts."""
    settings = logistic_settings(tmp_path, compose_cfg, 3.0)
    measured = {"reached_s": 5.0, "horizon_s": 20.0, "completed": False, "budget_s": 3.0,
                "events_per_window_last": 8.0, "events_per_window_file": 0.05,
                "burn_in_s": 20.0}  # fmt: skip
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="surrogate.stages.budget"):
        estimate = collect.measured_cost(settings, measured)
    assert estimate is not None and not estimate.completed and estimate.events == 8.0
    assert estimate.cell_step_seconds == settings.setup.model.internal.cell_step_seconds(
        settings.setup.dt, 8.0)  # fmt: skip
    [message] = [r.getMessage() for r in caplog.records]
    reached = ("collect: estimated ~{} of simulation at the steady rate the cost probe "
               "reached at 5 s of the 20-s burn-in, when collect.probe_seconds=3 ran out (8 per "
               "window per cell; the file's counts: 0.05, ~{}): ")  # fmt: skip
    assert message.startswith(reached.format(duration(estimate.seconds),
                                             duration(estimate.file_seconds))), message  # fmt: skip
    assert collect.measured_cost(settings, {**measured, "reached_s": 0.0}) is None
    off = logistic_settings(tmp_path, compose_cfg, 0)
    assert collect.cost_probe(off) is None and collect.measured_cost(off, None) is None


def test_a_window_past_the_runaway_cap_is_a_clear_error(tmp_path, monkeypatch) -> None:
    """A cell whose count grows without bound (the textbook's Lotka-Volterra,
    whose prey explode once the predators die out, hung the inspector's population run for
    more than 5 minutes) stops at the network's cap on events per cell and window with an
    error that is a ConfigError (the stages print it) and a RuntimeError (the cost probe's
    cap), naming the cap and the largest counts where the window started."""
    from surrogate.errors import RunawayError
    from surrogate.models import network

    model, _ = runaway(tmp_path)
    internal = model.internal
    inputs = torch.ones(3, 1, dtype=torch.float64)
    state = internal.start_state(3, torch.device("cpu"), inputs)
    monkeypatch.setattr(network, "RUNAWAY_EVENTS", 200)
    with pytest.raises(RunawayError) as error:
        for _ in range(40):  # e^(50 t) from A = 10: past 200 events a window within 0.2 s
            state = internal.advance_at(state, inputs, 0.05)
    assert isinstance(error.value, ConfigError) and isinstance(error.value, RuntimeError)
    message = str(error.value)
    assert "more than 200 SSA events in one window of 0.05 s" in message
    assert "the largest counts at the window's start: A = " in message
    # a cap the caller gives (the cost probe's) trips the same way
    with pytest.raises(RuntimeError, match="max_events"):
        internal.advance_at(internal.start_state(3, torch.device("cpu"), inputs), inputs, 1.0,
                            max_events=50)  # fmt: skip


def test_a_runaway_is_the_ssas_cap_not_a_messages_wording(tmp_path, monkeypatch) -> None:
    """The network turns the SSA's cap (:class:`EventCapError`, raised where it is hit) into a
    :class:`RunawayError`, whatever its message says; another failure whose message mentions
    ``max_rounds`` stays what it was (it read as a runaway when the wording decided)."""
    from surrogate.errors import EventCapError, RunawayError
    from surrogate.models import network

    internal = runaway(tmp_path)[0].internal
    monkeypatch.setattr(internal, "ssa", "batched")
    inputs = torch.ones(3, 1, dtype=torch.float64)
    state = internal.start_state(3, torch.device("cpu"), inputs)

    def fails(error: Exception):
        def gillespie(*args, **kwargs):
            raise error

        return gillespie

    monkeypatch.setattr(network, "gillespie", fails(EventCapError("the cap, in other words")))
    with pytest.raises(RunawayError, match="more than 50 SSA events in one window"):
        internal.advance_at(state, inputs, 0.05, max_events=50)
    other = RuntimeError("a device fault near max_rounds")
    monkeypatch.setattr(network, "gillespie", fails(other))
    with pytest.raises(RuntimeError) as error:
        internal.advance_at(state, inputs, 0.05, max_events=50)
    assert error.value is other

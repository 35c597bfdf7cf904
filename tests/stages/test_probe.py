"""Collect's cost probe (surrogate/stages/probe.py, run by surrogate/stages/collect.py before
its first simulation): a runaway network (autocatalysis A -> 2A) refused in seconds with the
rate measured, instead of burning in for hours; a network that stays put (the open birth-death
process) collected exactly as without the probe, in the same directory; a negative budget
refused as a bad setting. The networks are the inspection tests'."""

from __future__ import annotations

import logging
import time

import pandas as pd
import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.stages import collect
from surrogate.stages.settings import CollectSettings, InspectSettings
from tests.stages.test_inspection import birth_death, runaway


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
    with caplog.at_level(logging.INFO, logger="surrogate.stages.probe"):
        table = pd.read_parquet(collect.collect(on) / "transitions.parquet")
    assert sum("collect: cost probe, 4 cells" in r.getMessage() for r in caplog.records) == 1
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="surrogate.stages.probe"):
        again = pd.read_parquet(collect.collect(off, force=True) / "transitions.parquet")
    assert not any("cost probe" in r.getMessage() for r in caplog.records)
    assert len(table) >= 200
    pd.testing.assert_frame_equal(table, again, check_exact=True)


def test_a_negative_probe_budget_is_refused_by_name(compose_cfg) -> None:
    with pytest.raises(ConfigError, match=r"collect\.probe_seconds must be a non-negative"):
        CollectSettings.from_config(compose_cfg("collect", ["collect.probe_seconds=-1"]))

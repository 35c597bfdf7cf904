"""The SSA comparison measures every backend on one workload (cells x simulated seconds, with
repeats) in cell-seconds per wall second, and reports no event counts it did not count."""

from __future__ import annotations

import sys
import time
import types

import numpy as np
import pytest

from surrogate.benchmarks import ssa


def _fake_gillespy2(calls: list[tuple[int, int]]) -> types.ModuleType:
    """A stand-in for gillespy2 (not installed here): a solver that takes 20 ms per run."""
    module = types.ModuleType("gillespy2")

    class Model:
        def timespan(self, times) -> None:
            self.times = np.asarray(times)

    class SSACSolver:
        def __init__(self, model: Model) -> None:
            self.model = model

        def run(self, number_of_trajectories: int, seed: int) -> list[dict]:
            calls.append((number_of_trajectories, seed))
            time.sleep(0.02)
            return [{"CheYp": np.full(3, 100.0)} for _ in range(number_of_trajectories)]

    module.import_SBML = lambda path: (Model(), [])  # type: ignore[attr-defined]
    module.SSACSolver = SSACSolver  # type: ignore[attr-defined]
    module.__version__ = "fake"  # type: ignore[attr-defined]
    return module


def test_gillespy2_is_timed_on_the_workload_it_ran(monkeypatch) -> None:
    calls: list[tuple[int, int]] = []
    monkeypatch.setitem(sys.modules, "gillespy2", _fake_gillespy2(calls))
    g = ssa.bench_gillespy2(cells=4, t_end=10.0, repeats=3)
    assert calls == [(4, 1), (4, 2), (4, 3)]  # every repeat runs the whole workload
    assert (g["cells"], g["t_end_s"], g["repeats"], g["threads"]) == (4, 10.0, 3, 1)
    assert g["wall_s"] == min(g["walls_s"]) and g["wall_s"] >= 0.02
    assert g["cell_s_per_s"] == pytest.approx(4 * 10.0 / g["wall_s"])
    # it counts no events: none derived from another backend's rate
    assert not any("event" in key for key in g)


def test_the_compiled_ssa_counts_its_events_on_the_same_workload() -> None:
    c = ssa.bench_compiled(cells=3, t_end=0.1, dt=0.05, threads=1, repeats=2)
    assert (c["cells"], c["t_end_s"], c["repeats"]) == (3, 0.1, 2) and len(c["walls_s"]) == 2
    assert c["cell_s_per_s"] == pytest.approx(3 * 0.1 / c["wall_s"])
    assert c["events"] > 0 and c["events_per_s"] == pytest.approx(c["events"] / c["wall_s"])
    # ~10,000 events per cell per dt (docs/sbml.md): a count, not an estimate
    assert 5e3 < c["events_per_cell_per_s"] * 0.05 < 2e4


def test_a_ratio_only_over_equal_workloads() -> None:
    def run(cells: int, t_end: float, rate: float) -> dict:
        return {"cells": cells, "t_end_s": t_end, "cell_s_per_s_per_thread": rate}

    assert ssa.equal_workload_ratio(run(20, 10.0, 80.0), run(20, 10.0, 20.0)) == 4.0
    assert ssa.equal_workload_ratio(run(256, 1.0, 80.0), run(64, 1.0, 20.0)) is None
    assert ssa.equal_workload_ratio(run(20, 10.0, 80.0), {"skipped": "missing"}) is None

"""One speed formula behind every speed figure: per cell-step, only between loops timed under
one set-up (device, threads, loop setting, compile state)."""

from __future__ import annotations

import dataclasses
from typing import Any

import pandas as pd
import pytest

from surrogate.evaluate.statistics import SimulationRun
from surrogate.simulate.speed import (
    IncomparableSpeeds,
    LoopTiming,
    cell_steps_per_s,
    compare,
    differences,
    speedup,
)
from surrogate.stages import evaluate as evaluate_stage

LOOP = LoopTiming(n_cells=100, steps=1000, seconds=2.0, device="cpu", threads=2,
                  backend="numba", compiled=False)  # fmt: skip


def test_throughput_is_cells_times_steps_per_second() -> None:
    assert cell_steps_per_s(100, 1000, 2.0) == 50_000.0
    assert LOOP.cell_steps_per_s == 50_000.0
    for bad in [(0, 10, 1.0), (10, 0, 1.0), (10, 10, 0.0), (10, 10, float("nan"))]:
        with pytest.raises(ValueError):
            cell_steps_per_s(*bad)


def test_speedup_over_unequal_workloads_is_per_cell_step() -> None:
    """The issue's case: a full run of 20k cells in 20 s against 1e6 abstract cells in 500 s
    (same steps): 1e7 against 2e7 cell-steps/s, a speed-up of 2.0, not 20/500 = 0.04."""
    full = dataclasses.replace(LOOP, n_cells=20_000, steps=10_000, seconds=20.0)
    abstract = dataclasses.replace(LOOP, n_cells=1_000_000, steps=10_000, seconds=500.0)
    assert speedup(full, abstract) == pytest.approx(2.0)
    # equal workloads: the ratio of loop times
    assert speedup(LOOP, LOOP.with_seconds(0.5)) == pytest.approx(4.0)


@pytest.mark.parametrize(
    ("change", "reason"),
    [({"device": "cuda"}, "device cpu vs cuda"), ({"threads": 1}, "threads 2 vs 1"),
     ({"backend": "torch"}, "backend numba vs torch"),
     ({"compiled": True}, "compiled False vs True")],
)  # fmt: skip
def test_loops_under_different_setups_do_not_compare(change: dict, reason: str) -> None:
    other = dataclasses.replace(LOOP, **change)
    assert differences(LOOP, other) == [reason]
    with pytest.raises(IncomparableSpeeds, match=reason):
        speedup(LOOP, other)


def _manifest(n_cells: int, steps: int, loop_s: float, **extra: Any) -> dict[str, Any]:
    """A simulate stage's manifest with the keys its loop timing reads."""
    return {"n_cells": n_cells, "n_steps": steps, "loop_time_s": loop_s, "wall_time_s": loop_s + 1,
            "cell_steps_per_s": n_cells * steps / loop_s, "device": "cpu", "torch_threads": 2,
            "loop_backend": "torch", "compile": True, "compiled": True, "decision": "abstract",
            "lump_names": ["tumble", "run"], **extra}  # fmt: skip


def _run(manifest: dict[str, Any]) -> SimulationRun:
    durations = pd.DataFrame({"kind": ["run", "tumble"], "duration": [1.0, 0.1],
                              "cell": [0, 0], "t_end": [1.0, 1.0]})  # fmt: skip
    return SimulationRun(pd.DataFrame({"t": [0.0], "cell": [0], "distance": [1.0]}), durations,
                         manifest=manifest)  # fmt: skip


def _summary(full: dict[str, Any], candidate: dict[str, Any]) -> dict[str, Any]:
    runs = evaluate_stage.RunSet(_run(full), _run(candidate), None)
    return evaluate_stage.summarise(runs, pd.DataFrame({"ks": [0.1]}))


def test_evaluate_compares_a_small_full_run_with_a_large_abstraction_per_cell_step() -> None:
    """``evaluate.full_n_cells`` (experiment=large): 20,000 full cells in 20 s against 1e6
    abstract cells in 500 s is a 2.0x speed-up per cell-step (the old ratio of loop times said
    0.04x and called it comparable)."""
    summary = _summary(_manifest(20_000, 10_000, 20.0), _manifest(1_000_000, 10_000, 500.0))
    assert summary["speedup_loop"] == pytest.approx(2.0)
    assert summary["speed_comparable"] and summary["speed_not_comparable"] == []
    assert summary["cell_steps_per_s"] == {"full": 1e7, "candidate": 2e7}
    # the wall times (loop + 1 s each) through the same formula
    assert summary["speedup_wall"] == pytest.approx((1e6 / 501) / (2e4 / 21))


def test_evaluate_names_why_loops_do_not_compare() -> None:
    fell_back = _summary(_manifest(100, 10, 1.0), _manifest(100, 10, 0.5, compiled=False))
    assert fell_back["speedup_loop"] is None and not fell_back["speed_comparable"]
    assert fell_back["speed_not_comparable"] == ["compiled True vs False"]
    batched = _summary(_manifest(100, 10, 1.0, batched={"runs": []}), _manifest(100, 10, 0.5))
    assert batched["speedup_loop"] is None and "batch" in batched["speed_not_comparable"][0]


def _entry(timing: LoopTiming) -> dict[str, Any]:
    """A measure_speed / bench throughput entry of ``timing``."""
    return {**dataclasses.asdict(timing), "cell_steps_per_s": timing.cell_steps_per_s}


def test_compare_takes_timings_or_the_speed_stages_and_benchs_entries() -> None:
    """The speed stage, reproduce and the bench give compare() their measurement entries: a
    compiled step that fell back to eager in one model gives no speed-up (the loops ran
    differently); otherwise the ratio is the formula's."""
    from surrogate.benchmarks.loop import ratio

    eager = dataclasses.replace(LOOP, compiled=False)
    compiled = dataclasses.replace(LOOP, compiled=True, seconds=0.5)
    assert compare(_entry(eager), _entry(compiled)) == (None, ["compiled False vs True"])
    assert compare(eager, compiled) == (None, ["compiled False vs True"])
    assert ratio(_entry(eager), _entry(compiled)) is None
    fast = LOOP.with_seconds(0.5)
    assert compare(_entry(LOOP), _entry(fast)) == (pytest.approx(4.0), [])
    assert ratio(_entry(LOOP), _entry(fast)) == pytest.approx(4.0)

"""One speed formula behind every speed figure: per cell-step, only between loops timed on one
machine set-up and population size (device, threads, cells), loop for loop (same loop and
compile state) or each model on its fastest loop."""

from __future__ import annotations

import dataclasses
from typing import Any

import pandas as pd
import pytest

from surrogate.evaluate.statistics import SimulationRun
from surrogate.simulate.speed import (
    IncomparableSpeeds,
    LoopTiming,
    best_loop_speedup,
    cell_steps_per_s,
    compare,
    differences,
    speed_summary,
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


def test_speedup_is_per_cell_step_and_refused_between_population_sizes() -> None:
    """Equal cells: the ratio of throughputs (over equal steps, of loop times; over unequal
    steps, per cell-step). A full run of 20k cells against 1e6 abstract cells is refused: a
    loop's throughput per cell-step changes several-fold with the population's size."""
    assert speedup(LOOP, LOOP.with_seconds(0.5)) == pytest.approx(4.0)
    longer = dataclasses.replace(LOOP, steps=4000, seconds=4.0)  # 1e5 against 5e4 cell-steps/s
    assert speedup(LOOP, longer) == pytest.approx(2.0)
    full = dataclasses.replace(LOOP, n_cells=20_000, steps=10_000, seconds=20.0)
    abstract = dataclasses.replace(LOOP, n_cells=1_000_000, steps=10_000, seconds=500.0)
    assert differences(full, abstract) == ["n_cells 20000 vs 1000000"]
    with pytest.raises(IncomparableSpeeds, match="n_cells 20000 vs 1000000"):
        speedup(full, abstract)


def test_each_model_on_its_fastest_loop() -> None:
    """The full model's torch step (its only loop) against the abstraction's kernel and torch
    step: the best of each, whatever the loops; the same-loop ratio where both ran one."""
    full_torch = dataclasses.replace(LOOP, backend="torch", seconds=40.0)
    abstract_torch = dataclasses.replace(LOOP, backend="torch", seconds=0.4)
    abstract_kernel = dataclasses.replace(LOOP, backend="numba", seconds=0.01)
    ratio, best_full, best_abstract = best_loop_speedup([full_torch],
                                                        [abstract_torch, abstract_kernel])  # fmt: skip
    assert ratio == pytest.approx(4000.0)
    assert best_full is full_torch and best_abstract is abstract_kernel
    summary = speed_summary([full_torch], [abstract_torch, abstract_kernel])
    assert summary["speedup"] == pytest.approx(4000.0)
    assert summary["fastest"] == {"full": "torch step", "abstract": "numba kernel"}
    assert summary["same_loop"] == {"torch step": pytest.approx(100.0)}
    # another size, device or thread count on either side: no figure, and why
    for change in ({"n_cells": 1000}, {"device": "cuda"}, {"threads": 1}):
        other = dataclasses.replace(abstract_kernel, **change)
        with pytest.raises(IncomparableSpeeds, match="fastest loops compare only"):
            best_loop_speedup([full_torch], [abstract_torch, other])
        refused = speed_summary([full_torch], [other])
        assert refused["speedup"] is None and refused["speed_not_comparable"]


@pytest.mark.parametrize(
    ("change", "reason"),
    [({"device": "cuda"}, "device cpu vs cuda"), ({"threads": 1}, "threads 2 vs 1"),
     ({"n_cells": 1000}, "n_cells 100 vs 1000"), ({"backend": "torch"}, "backend numba vs torch"),
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


@pytest.mark.parametrize(
    ("full", "candidate"),
    [((20_000, 10_000, 20.0), (1_000_000, 10_000, 500.0)),  # experiment=large: other sizes
     ((1000, 10_000, 20.0), (1000, 10_000, 5.0))],  # the same set-up, but timed apart
)  # fmt: skip
def test_evaluate_gives_no_speed_up_between_runs_timed_apart(full, candidate) -> None:
    """Runs made apart (the band's first full run paid a cold compile beside other work: 6.2x
    where side by side gave ~1.2x) report their throughputs but no ratio, naming the command
    that measures one side by side, however alike their set-ups."""
    summary = _summary(_manifest(*full), _manifest(*candidate))
    assert summary["speedup_loop"] is None and summary["speedup_wall"] is None
    assert not summary["speed_comparable"]
    assert summary["speed_not_comparable"] == [evaluate_stage.SIDE_BY_SIDE]
    assert "scripts/speed.py" in evaluate_stage.SIDE_BY_SIDE
    assert summary["cell_steps_per_s"] == {
        "full": full[0] * full[1] / full[2],
        "candidate": candidate[0] * candidate[1] / candidate[2],
    }


def _entry(timing: LoopTiming) -> dict[str, Any]:
    """A measure_speed / bench throughput entry of ``timing``."""
    return {**dataclasses.asdict(timing), "cell_steps_per_s": timing.cell_steps_per_s}


def test_compare_takes_timings_or_the_speed_stages_and_benchs_entries() -> None:
    """The speed stage, reproduce and the bench give compare() their measurement entries: a
    compiled step that fell back to eager in one model gives no speed-up (the loops ran
    differently); otherwise the ratio is the formula's."""
    from surrogate.benchmarks.timing import ratio

    eager = dataclasses.replace(LOOP, compiled=False)
    compiled = dataclasses.replace(LOOP, compiled=True, seconds=0.5)
    assert compare(_entry(eager), _entry(compiled)) == (None, ["compiled False vs True"])
    assert compare(eager, compiled) == (None, ["compiled False vs True"])
    assert ratio(_entry(eager), _entry(compiled)) is None
    fast = LOOP.with_seconds(0.5)
    assert compare(_entry(LOOP), _entry(fast)) == (pytest.approx(4.0), [])
    assert ratio(_entry(LOOP), _entry(fast)) == pytest.approx(4.0)

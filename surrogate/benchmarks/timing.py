"""The benchmarks' measurements of one simulator: throughput (cell-steps/s, :func:`throughput`)
and speed-ups (:func:`ratio`), the split of a step's time (:func:`step_breakdown`), the paper's
workload (:func:`paper_workload`) and a large run's peak memory in a fresh process
(:func:`memory_run`)."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from surrogate.benchmarks.machine import sync
from surrogate.config import build_field, build_model, to_dict
from surrogate.io import load_tensors, save_tensors
from surrogate.simulate.decision import AbstractDecision, is_fusable
from surrogate.simulate.loop import Simulator
from surrogate.simulate.population import simulate_population
from surrogate.simulate.speed import LoopTiming, compare

#: steps per Simulator.advance call, as the simulate stage takes a record interval (1 s at dt 0.05)
CHUNK_STEPS = 20


def modes(s: Mapping[str, Any]) -> list[tuple[str, bool]]:
    """(backend, compile) pairs to measure: torch with each compile setting, numba once."""
    backends = s.get("backends") or ["torch"]
    return [(b, c) for b in backends for c in (s["compile"] if b == "torch" else [False])]


def throughput(simulator: Simulator, n_cells: int, s: Mapping[str, Any]) -> dict[str, Any]:
    """Best cell-steps/s over ``repeats`` timed runs (after a warm-up, which also compiles)."""
    device = simulator.device
    with torch.inference_mode():  # cheaper per op than no_grad
        state = simulator.initial_state(n_cells, s["start"], 0.0)
        warm_s = simulator.warm_up(state)
        best: LoopTiming | None = None
        for _ in range(int(s["repeats"])):
            steps = 0
            t0 = time.perf_counter()
            while True:
                k = max(1, min(CHUNK_STEPS, int(s["max_steps"]) - steps))
                simulator.advance(state, k)
                steps += k
                if steps >= int(s["max_steps"]):
                    break
                if steps >= int(s["min_steps"]) and time.perf_counter() - t0 >= s["min_seconds"]:
                    break
            sync(device)
            timing = LoopTiming.of(simulator, n_cells, steps, time.perf_counter() - t0)
            if best is None or timing.cell_steps_per_s > best.cell_steps_per_s:
                best = timing
    assert best is not None
    return {
        **dataclasses.asdict(best),
        "cell_steps_per_s": best.cell_steps_per_s,
        "us_per_step": 1e6 * best.seconds / best.steps,
        "warm_up_s": warm_s,
        "compile_error": simulator.compile_error,
    }


def ratio(full: Mapping[str, Any], candidate: Mapping[str, Any]) -> float | None:
    """The candidate's speed-up over the full model from two :func:`throughput` results
    (:func:`~surrogate.simulate.speed.compare`: per cell-step; None where they ran under
    different set-ups, e.g. the classifier's torch step beside the full model's kernel)."""
    return compare(full, candidate)[0]


#: most calls per timing in :func:`step_breakdown` (fewer where many cells make a call long)
BREAKDOWN_CALLS = 500


def step_breakdown(
    simulator: Simulator, n_cells: int, repeats: int = 5, max_calls: int = BREAKDOWN_CALLS
) -> dict[str, float]:
    """Per-step microseconds of the torch step: drawing the random numbers, the fused kernel
    alone, the whole step, and the rest (Python, bookkeeping) = step - randoms - kernel; each
    the best of ``repeats`` timings of up to ``max_calls`` calls (fewer on many cells)."""
    if not is_fusable(simulator.decision) or simulator.kernel is not None:
        return {}
    device = simulator.device

    def best_us(fn: Callable[[], Any], k: int) -> float:
        fn()
        out = math.inf
        for _ in range(repeats):
            sync(device)
            t0 = time.perf_counter()
            for _ in range(k):
                fn()
            sync(device)
            out = min(out, (time.perf_counter() - t0) / k)
        return 1e6 * out

    with torch.inference_mode():  # cheaper per op than no_grad
        state = simulator.initial_state(n_cells, (2.0, 0.0), 0.0)
        simulator.warm_up(state)
        k = max(3, min(max_calls, 2_000_000 // n_cells))
        u, u64, z, extra = simulator.draw_randoms(n_cells)
        decision = simulator.decision
        args = (
            state.body, state.phi.view(torch.uint8), state.segment_steps,
            state.segment_complete.view(torch.uint8), decision.fused_state(), (u, u64, z, extra),
            1.0,
        )  # fmt: skip
        rng = best_us(lambda: simulator.draw_randoms(n_cells), k)
        kernel = best_us(lambda: simulator._run("_fused_step", *args), k)
        step = best_us(lambda: simulator.step(state), k)
    return {"randoms_us": rng, "kernel_us": kernel, "step_us": step, "rest_us": step - rng - kernel}


def paper_workload(simulator: Simulator, p: Mapping[str, Any], out_dir: Path) -> dict[str, Any]:
    """Wall time of simulate_population for the paper's workload (durations recorded)."""
    t0 = time.perf_counter()
    summary = simulate_population(
        simulator,
        n_cells=int(p["n_cells"]),
        t_end=float(p["t_end"]),
        out_dir=out_dir,
        record_interval=float(p["record_interval"]),
        equilibration_time=float(p["equilibration_time"]),
        record_durations=True,
        progress=False,
    )
    return {
        "wall_s": time.perf_counter() - t0,
        "loop_s": summary.loop_time_s,
        "compile_s": summary.compile_time_s,
        "n_steps": summary.n_steps,
        "cell_steps_per_s": summary.cell_steps_per_s,
        "n_durations": summary.n_durations,
    }


def _proc_status_mb(key: str) -> float | None:
    """``key`` (e.g. ``VmHWM``) of /proc/self/status in MiB; None where it cannot be read."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(f"{key}:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB (/proc VmHWM, else getrusage)."""
    peak = _proc_status_mb("VmHWM")
    if peak is not None:
        return peak
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _rss_mb() -> float:
    rss = _proc_status_mb("VmRSS")
    return math.nan if rss is None else rss


def memory_child(spec_json: str) -> None:
    """Subprocess entry: one abstracted (lookup) run; prints a JSON line with peak RSS."""
    spec = json.loads(spec_json)
    torch.set_num_threads(int(spec["threads"]))
    from surrogate.gp import PsiLookupTable

    device = torch.device(spec["device"])
    model = build_model(spec["model"])
    table = PsiLookupTable.from_state(load_tensors(spec["table"]), device)
    field = build_field(spec["field"])
    decision = AbstractDecision(table, model.internal, model.featurizer(table.input_names))
    simulator = Simulator(model, decision, field, spec["dt"], device, compile=bool(spec["compile"]))
    rss_before = _rss_mb()
    with tempfile.TemporaryDirectory() as tmp:
        summary = simulate_population(
            simulator,
            n_cells=int(spec["n_cells"]),
            t_end=float(spec["t_end"]),
            out_dir=tmp,
            record_interval=float(spec["record_interval"]),
            record_durations=False,
            progress=False,
        )
    out = {
        "peak_rss_mb": peak_rss_mb(),
        "rss_before_mb": rss_before,
        "n_cells": summary.n_cells,
        "t_end": summary.t_end,
        "loop_s": summary.loop_time_s,
        "cell_steps_per_s": summary.cell_steps_per_s,
    }
    if device.type == "cuda":
        out["cuda_max_allocated_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    print("BENCH_MEMORY " + json.dumps(out), flush=True)


def memory_run(
    table: Any, cfg: Mapping[str, Any], m: Mapping[str, Any], t_end: float, tmp: Path
) -> dict[str, Any]:
    """Peak RSS of an abstracted run in a fresh Python process (so earlier work in this one
    does not pollute the peak)."""
    path = save_tensors(tmp / "table.pt", table.to_state())
    spec = {
        "threads": torch.get_num_threads(),
        "device": str(table.device),
        "model": to_dict(cfg["model"]),
        "field": to_dict(cfg["field"]),
        "dt": float(cfg["dt"]),
        "table": str(path),
        "n_cells": int(m["n_cells"]),
        "t_end": float(t_end),
        "record_interval": float(cfg["dt"]) * max(1, round(0.5 / float(cfg["dt"]))),
        "compile": bool(m.get("compile", False)),
    }
    code = "import sys; from surrogate.benchmarks.timing import memory_child; memory_child(sys.argv[1])"
    proc = subprocess.run(
        [sys.executable, "-c", code, json.dumps(spec)],
        capture_output=True,
        text=True,
        check=False,
    )
    for line in proc.stdout.splitlines():
        if line.startswith("BENCH_MEMORY "):
            return json.loads(line[len("BENCH_MEMORY ") :])
    raise RuntimeError(f"memory benchmark subprocess failed:\n{proc.stderr[-3000:]}")


def si(x: float) -> str:
    return f"{x:.3g}"


__all__ = [
    "BREAKDOWN_CALLS",
    "CHUNK_STEPS",
    "memory_child",
    "memory_run",
    "modes",
    "paper_workload",
    "peak_rss_mb",
    "ratio",
    "si",
    "step_breakdown",
    "throughput",
]

"""SSA backends side by side on one SBML network (the E. coli CheY phosphorylation network).

One run (``python scripts/bench_ssa.py``) simulates, on ``network_amounts.xml`` at the adapted
activity a* = 0.45, the same workload with every backend that compares: ``cells`` independent
trajectories of ``t_end`` simulated seconds each, ``repeats`` times, and reports the best (and
every) wall time as **cell-seconds per wall second** (cells x simulated seconds / wall seconds),
per thread too. Enough simulated time (default 20 x 10 s) makes the event loop dominate what
each backend pays once per call (process start, argument checks, output).

* compiled SSA (numba, :class:`~surrogate.ctmc.CompiledSSA`), windows of dt: compile time cold
  (fresh process, empty cache) and from numba's on-disk cache (fresh process), then the
  workload with 1 and 2 threads. Timed: the ``advance`` calls (checks, kernel, conversion).
  It counts its events: events/s are measured, for it alone.
* GillesPy2's C++ SSA (``gillespy2.SSACSolver``, optional extra ``compare``) on the same file
  imported with ``gillespy2.import_SBML``, one thread: the C++ build (solver construction)
  timed apart from ``run``, which includes starting the solver process and parsing its text
  output (three output times per trajectory, to keep that small). It counts no events, so none
  are reported for it; its final mean CheY-P shows it read the same model. The ratio compiled
  (one thread) / GillesPy2 is reported only over the equal workload.
* batched torch SSA (:func:`~surrogate.ctmc.gillespie` with ``propensity=``) on the CPU, one
  torch thread, on its own (smaller) workload: it is the CUDA path, and on the CPU its cost per
  event round hardly depends on the number of cells, so its rate is not compared with the
  others.

Nothing is asserted; the numbers are printed as a table and written as JSON.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from surrogate.ctmc import CellStreams, CompiledSSA, gillespie
from surrogate.io import write_json
from surrogate.models.ecoli_phospho import NETWORK_AMOUNTS_PATH, calibrated, load_network
from surrogate.simulate.population import steps_between
from surrogate.simulate.speed import cell_steps_per_s

__all__ = [
    "bench_compiled",
    "bench_cuda",
    "bench_gillespy2",
    "bench_torch",
    "cell_seconds_per_s",
    "compile_times",
    "cuda_law_check",
    "equal_workload_ratio",
    "run_bench",
]

_COMPILE_CHILD = """
import json, sys, time
t0 = time.perf_counter()
from surrogate.ctmc import CompiledSSA
from surrogate.models.ecoli_phospho import load_network
model = load_network(sys.argv[1])
t1 = time.perf_counter()
seconds = CompiledSSA(model.kinetics).compile()
print(json.dumps({"import_and_read_s": t1 - t0, "compile_s": seconds}))
"""


def compile_times(path: Path = NETWORK_AMOUNTS_PATH) -> dict[str, Any]:
    """Compile time in a fresh process with an empty cache (cold) and again (numba's cache)."""
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "SURROGATE_CACHE_DIR": cache}
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
        for label in ("cold", "cached"):
            result = subprocess.run(
                [sys.executable, "-c", _COMPILE_CHILD, str(path)],
                env=env,
                capture_output=True,
                text=True,
                check=True,
            )
            out[label] = json.loads(result.stdout.strip().splitlines()[-1])
    return out


def _machine() -> dict[str, Any]:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "load_avg_1_5_15": list(os.getloadavg()),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numba": __import__("numba").__version__,
    }


def cell_seconds_per_s(cells: int, t_end: float, wall: float) -> float:
    """Simulated cell-seconds per wall second of ``cells`` trajectories of ``t_end`` s: the
    speed formula of the simulations (:func:`~surrogate.simulate.speed.cell_steps_per_s`) with
    simulated seconds in place of steps."""
    return cell_steps_per_s(cells, t_end, wall)


def _best(walls: list[float], cells: int, t_end: float, threads: int) -> dict[str, Any]:
    """The workload and its rates from the best of ``walls`` (every wall time kept)."""
    wall = min(walls)
    rate = cell_seconds_per_s(cells, t_end, wall)
    return {"threads": threads, "cells": cells, "t_end_s": t_end, "repeats": len(walls),
            "wall_s": wall, "walls_s": walls, "cell_s_per_s": rate,
            "cell_s_per_s_per_thread": rate / threads}  # fmt: skip


def bench_compiled(cells: int, t_end: float, dt: float, threads: int, repeats: int) -> dict:
    """The compiled SSA on ``cells`` trajectories of ``t_end`` s in windows of ``dt`` (after a
    warm-up window), ``repeats`` times; its events are counted."""
    import numba

    model = load_network(NETWORK_AMOUNTS_PATH)
    ssa = CompiledSSA(model.kinetics)
    ssa.compile()
    inputs = torch.tensor([calibrated().adapted_activity], dtype=torch.float64)
    windows = steps_between(t_end, dt, "t_end")
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    walls, events = [], []
    try:
        for repeat in range(repeats):
            streams = CellStreams.from_seed(repeat, cells)
            state, _ = ssa.advance(model.initial_states(cells), inputs, dt, streams)  # warm-up
            count = 0
            start = time.perf_counter()
            for _ in range(windows):
                state, ev = ssa.advance(state, inputs, dt, streams)
                count += int(ev.sum())
            walls.append(time.perf_counter() - start)
            events.append(count)
    finally:
        numba.set_num_threads(before)
    out = _best(walls, cells, t_end, threads)
    best = walls.index(out["wall_s"])
    out.update(events=events[best], events_per_s=events[best] / out["wall_s"],
               events_per_cell_per_s=events[best] / (cells * t_end))  # fmt: skip
    return out


def bench_torch(cells: int, t_end: float, dt: float, repeats: int) -> dict[str, Any]:
    """The batched torch SSA (one thread) on its own workload, ``repeats`` times."""
    model = load_network(NETWORK_AMOUNTS_PATH)
    inputs = torch.tensor([calibrated().adapted_activity], dtype=torch.float64)
    inputs = inputs.expand(cells, 1).contiguous()
    windows = steps_between(t_end, dt, "torch t_end")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    walls = []
    try:
        for repeat in range(repeats):
            generator = torch.Generator().manual_seed(repeat)
            state = model.initial_states(cells)
            start = time.perf_counter()
            for _ in range(windows):
                state = gillespie(model.network, state, inputs, dt, generator,
                                  propensity=model.torch_propensity)  # fmt: skip
            walls.append(time.perf_counter() - start)
    finally:
        torch.set_num_threads(before)
    out = _best(walls, cells, t_end, 1)
    out["mean_cheyp_end"] = float(state[:, model.species.index("CheYp")].double().mean())
    return out


def bench_gillespy2(cells: int, t_end: float, repeats: int) -> dict[str, Any]:
    """GillesPy2's SSACSolver on the same SBML file and workload (skipped when gillespy2 is
    missing): ``cells`` trajectories of ``t_end`` s per ``run``, ``repeats`` runs."""
    try:
        import gillespy2
    except ImportError:
        return {"skipped": "gillespy2 is not installed (pip install surrogate[compare])"}
    model, errors = gillespy2.import_SBML(str(NETWORK_AMOUNTS_PATH))
    if errors:
        return {"skipped": f"import_SBML errors: {errors}"}
    model.timespan(np.linspace(0.0, t_end, 3))
    start = time.perf_counter()
    solver = gillespy2.SSACSolver(model=model)
    build = time.perf_counter() - start
    walls, cheyp = [], []
    for repeat in range(repeats):
        start = time.perf_counter()
        results = solver.run(number_of_trajectories=cells, seed=1 + repeat)
        walls.append(time.perf_counter() - start)
        cheyp.append(float(np.mean([r["CheYp"][-1] for r in results])))
    return {**_best(walls, cells, t_end, 1), "build_s": build, "mean_cheyp_end": cheyp[-1],
            "version": gillespy2.__version__}  # fmt: skip


def equal_workload_ratio(a: dict[str, Any], b: dict[str, Any]) -> float | None:
    """``a``'s cell-seconds per second per thread over ``b``'s, when both simulated the same
    workload (cells and simulated time; None otherwise, or when either was skipped)."""
    if "skipped" in a or "skipped" in b:
        return None
    if (a["cells"], a["t_end_s"]) != (b["cells"], b["t_end_s"]):
        return None
    return a["cell_s_per_s_per_thread"] / b["cell_s_per_s_per_thread"]


def run_bench(
    cells: int = 20,
    t_end: float = 10.0,
    repeats: int = 3,
    torch_cells: int = 256,
    torch_t_end: float = 0.05,
    dt: float = 0.05,
    output: Path | None = None,
) -> dict[str, Any]:
    """Run every part, print the table, write JSON to ``output`` when given."""
    result: dict[str, Any] = {"machine": _machine(), "network": str(NETWORK_AMOUNTS_PATH)}
    result["dt"] = dt
    result["compile"] = compile_times()
    result["compiled"] = [bench_compiled(cells, t_end, dt, t, repeats) for t in (1, 2)]
    result["torch"] = bench_torch(torch_cells, torch_t_end, dt, repeats)
    result["gillespy2"] = bench_gillespy2(cells, t_end, repeats)
    result["compiled_vs_gillespy2"] = equal_workload_ratio(result["compiled"][0],
                                                           result["gillespy2"])  # fmt: skip
    result["mean_cheyp_initial"] = int(load_network().initial_state[6])
    print(format_table(result))
    if output is not None:
        write_json(output, result)
    return result


def format_table(r: dict[str, Any]) -> str:
    """A plain-text table of a :func:`run_bench` result."""
    m = r["machine"]
    c1 = r["compiled"][0]
    lines = [
        f"machine: {m['cpu']}, {m['cores']} cores, load {m['load_avg_1_5_15']}",
        f"network: {r['network']}  ({c1['events_per_cell_per_s'] * r['dt']:.0f} events/cell/dt"
        f" measured, dt = {r['dt']})",
        "compile (fresh process): cold {:.2f} s, from cache {:.2f} s".format(
            r["compile"]["cold"]["compile_s"], r["compile"]["cached"]["compile_s"]
        ),
        f"{'backend':30s} {'threads':>7s} {'workload':>14s} {'best wall s':>11s} "
        f"{'cell-s/s':>10s} {'per thread':>10s} {'events/s':>10s}",
    ]

    def row(name: str, x: dict[str, Any], events: str = "") -> str:
        work = f"{x['cells']} x {x['t_end_s']:g} s"
        return (f"{name:30s} {x['threads']:7d} {work:>14s} {x['wall_s']:11.2f} "
                f"{x['cell_s_per_s']:10.3g} {x['cell_s_per_s_per_thread']:10.3g} {events:>10s}")  # fmt: skip

    for c in r["compiled"]:
        lines.append(row("compiled SSA (numba)", c, f"{c['events_per_s']:.3g}"))
    lines.append(row("batched torch SSA (CPU)", r["torch"]) + "  (own workload)")
    g = r["gillespy2"]
    if "skipped" in g:
        lines.append(f"{'GillesPy2 SSACSolver':30s} skipped: {g['skipped']}")
    else:
        lines.append(row("GillesPy2 SSACSolver (C++)", g) + f"  (C++ build {g['build_s']:.1f} s)")
        lines.append(
            f"compiled SSA (1 thread) / GillesPy2, equal workloads: "
            f"{r['compiled_vs_gillespy2']:.2f}x per thread"
        )
        lines.append(
            f"mean CheY-P at the end: torch {r['torch']['mean_cheyp_end']:.0f}, GillesPy2 "
            f"{g['mean_cheyp_end']:.0f} (start {r['mean_cheyp_initial']})"
        )
    return "\n".join(lines)


def bench_cuda(cells: int, t_end: float, dt: float, repeats: int) -> dict[str, Any]:
    """The CUDA SSA (:class:`~surrogate.ctmc.cuda_ssa.CudaSSA`, one thread per cell) on
    ``cells`` trajectories of ``t_end`` s in windows of ``dt`` on the GPU (after a warm-up
    window that pays the kernel's compile), ``repeats`` times; its events are counted, and
    each timed window ends with a device synchronisation."""
    from surrogate.ctmc.cuda_ssa import CudaSSA

    model = load_network(NETWORK_AMOUNTS_PATH)
    ssa = CudaSSA(model.kinetics)
    device = torch.device("cuda")
    inputs = torch.tensor([calibrated().adapted_activity], dtype=torch.float64, device=device)
    windows = steps_between(t_end, dt, "t_end")
    walls, events = [], []
    start = time.perf_counter()
    for repeat in range(repeats):
        streams = torch.from_numpy(CellStreams.from_seed(repeat, cells).state.view(np.int64))
        streams = streams.to(device)
        state = model.initial_states(cells).to(device)
        state, _ = ssa.advance(state, inputs, dt, streams)  # warm-up (and compile, first time)
        if repeat == 0:
            torch.cuda.synchronize()
            compile_s = time.perf_counter() - start
        count = torch.zeros((), dtype=torch.int64, device=device)
        torch.cuda.synchronize()
        begin = time.perf_counter()
        for _ in range(windows):
            state, ev = ssa.advance(state, inputs, dt, streams)
            count += ev.sum()
        torch.cuda.synchronize()
        walls.append(time.perf_counter() - begin)
        events.append(int(count))
    out = _best(walls, cells, t_end, 1)
    best = walls.index(out["wall_s"])
    out.update(events=events[best], events_per_s=events[best] / out["wall_s"],
               events_per_cell_per_s=events[best] / (cells * t_end),
               cell_steps_per_s=cells * windows / out["wall_s"],
               first_window_s=compile_s, device=torch.cuda.get_device_name())  # fmt: skip
    return out


def cuda_law_check(cells: int = 4000, dt: float = 0.05, windows: int = 4) -> dict[str, Any]:
    """The CUDA SSA against the compiled CPU SSA at fixed inputs, independent streams: per
    species, the two-sample KS distance of the counts after ``windows`` windows from the
    network's initial counts, against its critical value at a family-wise 5 % (Bonferroni
    over the species). Returns each species' distance and whether every one is within."""
    from scipy import stats

    from surrogate.ctmc.cuda_ssa import CudaSSA

    model = load_network(NETWORK_AMOUNTS_PATH)
    cpu, gpu = CompiledSSA(model.kinetics), CudaSSA(model.kinetics)
    inputs = torch.tensor([calibrated().adapted_activity], dtype=torch.float64)
    a = model.initial_states(cells)
    streams = CellStreams.from_seed(1, cells)
    for _ in range(windows):
        a, _ = cpu.advance(a, inputs, dt, streams)
    b = model.initial_states(cells).cuda()
    words = torch.from_numpy(CellStreams.from_seed(2, cells).state.view(np.int64)).cuda()
    for _ in range(windows):
        b, _ = gpu.advance(b, inputs.cuda(), dt, words)
    b = b.cpu()
    species = model.network.species
    alpha = 0.05 / max(1, len(species))
    critical = float(stats.kstwo.ppf(1 - alpha, cells // 2))  # n_eff = n m / (n + m)
    distances = {
        s: float(stats.ks_2samp(a[:, j].numpy(), b[:, j].numpy()).statistic)
        for j, s in enumerate(species)
        if bool((a[:, j] != a[0, j]).any() or (b[:, j] != b[0, j]).any())
    }
    return {"cells": cells, "windows": windows, "critical": critical, "ks": distances,
            "within": all(d <= critical for d in distances.values())}  # fmt: skip

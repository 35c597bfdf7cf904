"""SSA backends side by side on one SBML network (the E. coli CheY phosphorylation network).

One run (``python scripts/bench_ssa.py``) measures, on ``network_amounts.xml`` at the adapted
activity a* = 0.45 and windows dt = 0.05 s:

* compiled SSA (numba, :class:`~surrogate.ctmc.CompiledSSA`): compile time cold (fresh process,
  empty cache) and from numba's on-disk cache (fresh process), then events/s with 1 and 2
  threads. Timed: ``advance`` calls only (argument checks, the kernel, result conversion).
* batched torch SSA (:func:`~surrogate.ctmc.gillespie` with ``propensity=``) on the CPU, one
  torch thread. Timed: the ``gillespie`` calls. It does not count events; its events are the
  compiled run's measured events per cell per second times its cell-seconds (both are exact
  samplers of the same law, so the expected counts are equal).
* GillesPy2's C++ SSA (``gillespy2.SSACSolver``, optional extra ``compare``) on the same file
  imported with ``gillespy2.import_SBML``: the C++ build (solver construction) timed apart from
  ``run``; ``run`` includes starting the solver process and parsing its text output. Events are
  estimated like the torch ones; its final mean CheY-P is reported to show it read the same model.

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

__all__ = ["compile_times", "run_bench"]

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


def bench_compiled(n_cells: int, windows: int, dt: float, threads: int) -> dict[str, Any]:
    """Events/s of the compiled SSA on ``n_cells`` for ``windows`` windows (after a warm-up)."""
    import numba

    model = load_network(NETWORK_AMOUNTS_PATH)
    ssa = CompiledSSA(model.kinetics)
    ssa.compile()
    inputs = torch.tensor([calibrated().adapted_activity], dtype=torch.float64)
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        streams = CellStreams.from_seed(0, n_cells)
        state, _ = ssa.advance(model.initial_states(n_cells), inputs, dt, streams)  # warm-up
        events = 0
        start = time.perf_counter()
        for _ in range(windows):
            state, ev = ssa.advance(state, inputs, dt, streams)
            events += int(ev.sum())
        wall = time.perf_counter() - start
    finally:
        numba.set_num_threads(before)
    return {
        "threads": threads,
        "n_cells": n_cells,
        "windows": windows,
        "events": events,
        "wall_s": wall,
        "events_per_s": events / wall,
        "events_per_s_per_thread": events / wall / threads,
        "events_per_cell_per_dt": events / (n_cells * windows),
    }


def bench_torch(n_cells: int, windows: int, dt: float, events_per_cell_per_s: float) -> dict:
    """Wall time of the batched torch SSA (one thread) on the same network."""
    model = load_network(NETWORK_AMOUNTS_PATH)
    inputs = torch.tensor([calibrated().adapted_activity], dtype=torch.float64)
    inputs = inputs.expand(n_cells, 1).contiguous()
    generator = torch.Generator().manual_seed(0)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        state = model.initial_states(n_cells)
        start = time.perf_counter()
        for _ in range(windows):
            state = gillespie(
                model.network, state, inputs, dt, generator, propensity=model.torch_propensity
            )
        wall = time.perf_counter() - start
    finally:
        torch.set_num_threads(before)
    events = events_per_cell_per_s * n_cells * windows * dt
    return {
        "threads": 1,
        "n_cells": n_cells,
        "windows": windows,
        "events_estimated": events,
        "wall_s": wall,
        "events_per_s": events / wall,
        "mean_cheyp_end": float(state[:, model.species.index("CheYp")].double().mean()),
    }


def bench_gillespy2(trajectories: int, t_end: float, events_per_cell_per_s: float) -> dict:
    """GillesPy2's SSACSolver on the same SBML file (skipped when gillespy2 is missing)."""
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
    start = time.perf_counter()
    results = solver.run(number_of_trajectories=trajectories, seed=1)
    wall = time.perf_counter() - start
    cheyp = float(np.mean([r["CheYp"][-1] for r in results]))
    events = events_per_cell_per_s * trajectories * t_end
    return {
        "threads": 1,
        "trajectories": trajectories,
        "t_end_s": t_end,
        "build_s": build,
        "wall_s": wall,
        "events_estimated": events,
        "events_per_s": events / wall,
        "mean_cheyp_end": cheyp,
        "version": gillespy2.__version__,
    }


def run_bench(
    n_cells: int = 256,
    windows: int = 20,
    torch_cells: int = 256,
    torch_windows: int = 1,
    trajectories: int = 64,
    t_end: float = 1.0,
    dt: float = 0.05,
    output: Path | None = None,
) -> dict[str, Any]:
    """Run every part, print the table, write JSON to ``output`` when given."""
    result: dict[str, Any] = {"machine": _machine(), "network": str(NETWORK_AMOUNTS_PATH)}
    result["dt"] = dt
    result["compile"] = compile_times()
    result["compiled"] = [bench_compiled(n_cells, windows, dt, t) for t in (1, 2)]
    rate = result["compiled"][0]["events_per_cell_per_dt"] / dt
    result["events_per_cell_per_s"] = rate
    result["torch"] = bench_torch(torch_cells, torch_windows, dt, rate)
    result["gillespy2"] = bench_gillespy2(trajectories, t_end, rate)
    result["mean_cheyp_initial"] = int(load_network().initial_state[6])
    print(format_table(result))
    if output is not None:
        write_json(output, result)
    return result


def format_table(r: dict[str, Any]) -> str:
    """A plain-text table of a :func:`run_bench` result."""
    m = r["machine"]
    lines = [
        f"machine: {m['cpu']}, {m['cores']} cores, load {m['load_avg_1_5_15']}",
        f"network: {r['network']}  ({r['events_per_cell_per_s'] * r['dt']:.0f} events/cell/dt,"
        f" dt = {r['dt']})",
        "compile (fresh process): cold {:.2f} s, from cache {:.2f} s".format(
            r["compile"]["cold"]["compile_s"], r["compile"]["cached"]["compile_s"]
        ),
        f"{'backend':34s} {'threads':>7s} {'wall s':>8s} {'events/s':>12s} {'per thread':>12s}",
    ]
    for c in r["compiled"]:
        lines.append(
            f"{'compiled SSA (numba)':34s} {c['threads']:7d} {c['wall_s']:8.2f} "
            f"{c['events_per_s']:12.3e} {c['events_per_s_per_thread']:12.3e}"
        )
    t = r["torch"]
    lines.append(
        f"{'batched torch SSA (CPU)':34s} {1:7d} {t['wall_s']:8.2f} {t['events_per_s']:12.3e} "
        f"{t['events_per_s']:12.3e}"
    )
    g = r["gillespy2"]
    if "skipped" in g:
        lines.append(f"{'GillesPy2 SSACSolver':34s} skipped: {g['skipped']}")
    else:
        lines.append(
            f"{'GillesPy2 SSACSolver (C++)':34s} {1:7d} {g['wall_s']:8.2f} "
            f"{g['events_per_s']:12.3e} {g['events_per_s']:12.3e}   (C++ build {g['build_s']:.1f} s)"
        )
        lines.append(
            f"mean CheY-P at the end: torch {t['mean_cheyp_end']:.0f}, GillesPy2 "
            f"{g['mean_cheyp_end']:.0f} (start {r['mean_cheyp_initial']})"
        )
    return "\n".join(lines)

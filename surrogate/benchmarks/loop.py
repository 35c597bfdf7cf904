"""Benchmark: speed of the full and the abstracted simulation, and of the stages around them.

One run (``python scripts/bench.py``, config ``conf/bench.yaml``) measures, in this order:

* the per-cell kernel's one-time compilation in fresh processes: with an empty numba cache
  (what a new machine pays once) and loading what that cached (``kernel_compile``);
* data collection (20k transitions with ``collect_transitions``) and GP training (both
  classifiers with ``fit_psi``); the classifiers trained here are the abstraction used below
  (trained on the fly: it is about speed, not accuracy);
* throughput (cell-steps/s) of the full model and of the abstraction in lookup-table mode and in
  classifier-every-step mode (:class:`~surrogate.gp.fast.CachedPsi`) at each size, per thread
  count and eager / ``torch.compile``, side by side, with the abstract/full ratios;
* the abstract/full ratio as the number of motors grows;
* a split of the step time into random numbers, the fused kernel and the rest;
* the wall time of the paper's workload (100 cells, 500 s, dt 0.05) with ``simulate_population``;
* the peak RSS of a 1e6-cell abstracted run in a fresh subprocess, for two t_end.

It prints a table and writes everything as JSON (``surrogate.io.write_json``). Timings are the
best of ``repeats``; the machine's load average is recorded with them, since other processes
on a small machine distort them. The benchmark asserts nothing.

``lookup_only=true`` (:func:`run_lookup_bench`) measures only the abstraction's loop: the
lookup throughput per thread count, backend and size over a table built from a smooth function
of the model's signal (:func:`function_table`; no collection, training or full model), so it
runs on any model whose full model is slow, e.g.
``python scripts/bench.py lookup_only=true model=ecoli_phospho model.burn_in=0 threads=[2]
compile=[false] sizes=[100,10000]`` (``model.burn_in=0``: the cells' first phi from the
network's file state, not 2 s of SSA per cell; the throughput does not depend on it).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

import torch

from surrogate.config import build_field, build_model, grid_size, resolve_device, to_dict
from surrogate.errors import ConfigError
from surrogate.fields import Field
from surrogate.io import load_tensors, save_tensors, write_json
from surrogate.kinds import TWO_STATE, ChainKind, chain_kind, decision_kind
from surrogate.models.base import Model
from surrogate.models.capabilities import signal_bounds_of
from surrogate.simulate.classes import ClassDecision, ClassTable, exact_class_table
from surrogate.simulate.decision import AbstractDecision, FullDecision, is_fusable
from surrogate.simulate.loop import Simulator
from surrogate.simulate.memory import (
    AGE,
    MemoryDecision,
    has_history,
    tabulate_with_clock,
)
from surrogate.simulate.population import simulate_population
from surrogate.simulate.precompile import precompiler_code
from surrogate.simulate.speed import LoopTiming, compare

MODELS = ("full", "lookup", "classifier")
#: the chains :func:`run_lookup_bench` runs side by side, by its ``histories`` word: gp.history's
#: (the two-state chain, the switch clock) and the K-lumps chain (gp.lumps=classes)
HISTORY_CHAINS: dict[str, ChainKind] = {
    "none": chain_kind(), "age": chain_kind(history="age"), "classes": chain_kind("classes")
}  # fmt: skip


# ----------------------------------------------------------------------------------------------
# settings and machine


def bench_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Plain settings of a bench config, with ``quick_settings`` applied when ``quick``."""
    data = to_dict(cfg)
    quick = data.pop("quick_settings", {}) or {}
    if data.get("quick"):
        data.update(quick)
    return data


def read_load() -> list[float]:
    """1/5/15-minute load averages (empty where unsupported)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return []


def machine_info(device: torch.device) -> dict[str, Any]:
    """CPU model, cores, torch threads and versions, device, load."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info: dict[str, Any] = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "device": str(device),
        "host": platform.node(),
        "load_average": read_load(),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


@contextmanager
def num_threads(n: int) -> Iterator[None]:
    """Temporarily set torch's intra-op thread count."""
    before = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# ----------------------------------------------------------------------------------------------
# abstraction (trained on the fly) and simulators


def train_abstraction(
    s: Mapping[str, Any], cfg: Mapping[str, Any], device: torch.device
) -> tuple[Any, dict[str, Any]]:
    """Collect transitions and fit both classifiers (each timed) with the collect and gp
    settings of ``cfg`` (``training`` overrides sizes); return (psi, facts)."""
    from surrogate.gp import fit_psi
    from surrogate.simulate.transitions import collect_transitions
    from surrogate.stages.settings import TrainSettings

    t = s["training"]
    c = {**to_dict(cfg["collect"]), "n_per_state": int(t["n_per_state"])}
    gp = {**to_dict(cfg["gp"]), "n_inducing": int(t["n_inducing"]), "epochs": int(t["epochs"]),
          "batch_size": int(t["batch_size"])}  # fmt: skip
    settings = TrainSettings.from_config({**to_dict(cfg), "collect": c, "gp": gp})
    setup, opts = settings.setup, settings.source.options  # type: ignore[union-attr]
    model = setup.model
    simulator = Simulator(model, FullDecision(model.internal), setup.field, setup.dt, device)
    perturbation = model.body.perturbation(setup.field, model.perturbation_options)
    t0 = time.perf_counter()
    data = collect_transitions(
        simulator,
        perturbation,
        n_cells=int(opts["n_cells"]),
        n_per_state=int(opts["n_per_state"]),
        perturb_rate=float(opts["perturb_rate"]),
        record_every=int(opts["record_every"]),
        equilibration_time=float(opts["equilibration_time"]),
        max_time=float(opts["max_time"]),
        progress=False,
    )
    collect_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    psi = fit_psi(data, settings.inputs, settings.gp, progress=False, device=device,
                  lump_names=model.internal.lump_names)  # fmt: skip
    train_s = time.perf_counter() - t0
    facts = {
        "collect": {
            "n_transitions": len(data),
            "seconds": collect_s,
            "transitions_per_s": len(data) / collect_s,
            "n_cells": int(opts["n_cells"]),
            "record_every": int(opts["record_every"]),
        },
        "training": {
            "seconds": train_s,
            "n_points": len(data),
            "n_per_classifier": int(t["n_per_state"]),
            "inputs": list(settings.inputs),
            "fit_seconds": {f"psi_{p}": c.train_seconds for p, c in enumerate(psi.classifiers)},
            "settings": settings.gp.to_dict(),
            "threads": torch.get_num_threads(),
        },
    }
    return psi, facts


def make_decision(
    name: str, model: Model, tables: Mapping[str, Any], dt: float | None = None
) -> Any:
    """A decision layer: ``full``, ``lookup`` (table) or ``classifier`` (CachedPsi); a psi
    whose last input is the switch clock gets the chain with a clock (gp.history=age)."""
    if name not in tables and decision_kind(name).full:  # the one layer without a table
        return FullDecision(model.internal)
    psi = tables[name]
    names = tuple(psi.input_names)
    if isinstance(psi, ClassTable):  # the K-lumps chain (gp.lumps=classes)
        return ClassDecision(psi, model.internal, model.featurizer(names))
    if has_history(names):
        return MemoryDecision(psi, model.internal, model.featurizer(names[:-1]),
                              psi.domain[AGE][1], dt=dt)  # fmt: skip
    return AbstractDecision(psi, model.internal, model.featurizer(names))


def make_simulator(
    name: str,
    model: Model,
    field: Field,
    dt: float,
    device: torch.device,
    tables: Mapping[str, Any],
    compile: bool,
    backend: str = "torch",
) -> Simulator:
    """A simulator for one decision layer (``backend`` numba falls back to torch where the
    model has no kernel, e.g. the classifier; the results say which ran)."""
    backend = "auto" if backend == "numba" else backend
    return Simulator(model, make_decision(name, model, tables, dt), field, dt, device,
                     compile=compile, backend=backend)  # fmt: skip


#: steps per Simulator.advance call, as the simulate stage takes a record interval (1 s at dt 0.05)
CHUNK_STEPS = 20


def modes(s: Mapping[str, Any]) -> list[tuple[str, bool]]:
    """(backend, compile) pairs to measure: torch with each compile setting, numba once."""
    backends = s.get("backends") or ["torch"]
    return [(b, c) for b in backends for c in (s["compile"] if b == "torch" else [False])]


# ----------------------------------------------------------------------------------------------
# measurements


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
            _sync(device)
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


def step_breakdown(simulator: Simulator, n_cells: int, repeats: int = 5) -> dict[str, float]:
    """Per-step microseconds of the torch step: drawing the random numbers, the fused kernel
    alone, the whole step, and the rest (Python, bookkeeping) = step - randoms - kernel."""
    if not is_fusable(simulator.decision) or simulator.kernel is not None:
        return {}
    device = simulator.device

    def best_us(fn: Callable[[], Any], k: int) -> float:
        fn()
        out = math.inf
        for _ in range(repeats):
            _sync(device)
            t0 = time.perf_counter()
            for _ in range(k):
                fn()
            _sync(device)
            out = min(out, (time.perf_counter() - t0) / k)
        return 1e6 * out

    with torch.inference_mode():  # cheaper per op than no_grad
        state = simulator.initial_state(n_cells, (2.0, 0.0), 0.0)
        simulator.warm_up(state)
        k = max(3, min(500, 2_000_000 // n_cells))
        u, u64, z, extra = simulator.draw_randoms(n_cells)
        decision = simulator.decision
        args = (
            state.body, state.phi.view(torch.uint8), state.segment_steps,
            state.segment_complete.view(torch.uint8), decision.fused_state(), u, u64, z, extra,
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


def _peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB (psutil, /proc VmHWM or getrusage)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _rss_mb() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


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
        "peak_rss_mb": _peak_rss_mb(),
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
    code = (
        "import sys; from surrogate.benchmarks.loop import memory_child; memory_child(sys.argv[1])"
    )
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


# ----------------------------------------------------------------------------------------------
# the abstraction's loop alone (lookup_only=true)


def function_table(model: Model, dt: float, size: Any = None, max_age: float | None = None) -> Any:
    """A lookup table over the model's signal (its ``signal_bounds``) from a smooth psi with
    E. coli-like switching, no training: runs end at ~1/s and tumbles at ~5/s, each rate
    scaled by 0.5-1.5 across the signal's range (so the lookup's inputs matter). With
    ``max_age`` (s) the table also spans the switch clock (its last axis, ``size`` nodes too):
    the rates rise by up to 50 % with the time since the last switch."""
    from surrogate.gp import PsiLookupTable

    internal = model.internal
    names = tuple(internal.signal_names)
    bounds = signal_bounds_of(internal) or {}
    missing = [n for n in names if n not in bounds]
    if missing:
        raise ValueError(f"lookup_only needs the internal model's signal_bounds for {missing}")
    lo = torch.tensor([bounds[n][0] for n in names])
    width = torch.tensor([bounds[n][1] - bounds[n][0] for n in names])
    k = len(names)

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        s = ((z[:, :k] - lo) / width).mean(1).clamp(0.0, 1.0) + 0.5
        if max_age:
            s = s * (1.0 + 0.5 * z[:, k] / max_age)
        stop = -torch.expm1(-s * dt)  # run -> tumble at ~1/s
        start = -torch.expm1(-5.0 * s * dt)  # tumble -> run at ~5/s
        return torch.where(phi > 0, 1.0 - stop, start)

    ranges = [bounds[n] for n in names]
    if max_age:  # a clock node at every step, as the simulate stage tabulates a learned psi
        lead = grid_size(size, "lookup_size", len(names)) if size else None
        return tabulate_with_clock(psi, ranges, (*names, AGE), dt, max_age, lead)
    shape = grid_size(size, "lookup_size", len(names))
    return PsiLookupTable.from_function(psi, ranges, names, shape)


def _setup(
    cfg: Mapping[str, Any],
) -> tuple[dict[str, Any], torch.device, Model, Field, float, dict[str, Any]]:
    """What every benchmark run starts from: its settings, device, model, field and dt (torch
    seeded), and the head of its results (start time, machine, settings)."""
    s = bench_settings(cfg)
    device = resolve_device(cfg.get("device", "cpu"))
    torch.manual_seed(int(cfg["seed"]))
    head = {
        "started": datetime.now().isoformat(timespec="seconds"),
        "machine": machine_info(device),
        "settings": {k: v for k, v in s.items() if k not in ("hydra",)},
    }
    return s, device, build_model(cfg["model"]), build_field(cfg["field"]), float(cfg["dt"]), head


def run_lookup_bench(cfg: Mapping[str, Any], log: Callable[[str], None] = print) -> dict[str, Any]:
    """The abstraction's lookup throughput (cell-steps/s) for each thread count, (backend,
    compile) and size, over :func:`function_table`, one simulator per (threads, backend,
    compile) as :func:`run_bench`; each row records the backend that ran (``numba`` falls
    back to torch where the model has no kernel). ``histories`` (``[none, age, classes]``): each
    also with the switch clock (gp.history=age) and the K-lumps chain over the model's exact
    class law (gp.lumps=classes; the same number of signal nodes), side by side, row after
    row."""
    s, device, model, field, dt, head = _setup(cfg)
    started = time.perf_counter()
    histories = list(s.get("histories") or ["none"])
    unknown = [h for h in histories if h not in HISTORY_CHAINS]
    if unknown:
        raise ConfigError(f"histories: unknown {unknown}; allowed {list(HISTORY_CHAINS)}")
    max_age = float(cfg.get("gp", {}).get("max_age", 5.0))

    def table(h: str) -> Any:
        kind = HISTORY_CHAINS[h]
        if kind.classes:
            nodes = grid_size(s.get("lookup_size"), "lookup_size", 1)
            try:
                return exact_class_table(model.internal, dt, nodes[0] if nodes else 4096)
            except ValueError as exc:
                raise ConfigError(f"histories=classes: {exc}") from None
        return function_table(model, dt, s.get("lookup_size"), max_age if kind.clock else None)

    tables = {h: table(h).to(device) for h in histories}
    results: dict[str, Any] = {
        **head,
        "model": model.name,
        "abstraction": {
            "source": "a smooth function of the signal (bench.function_table; no training)",
            "inputs": {h: list(t.input_names) for h, t in tables.items()},
            "lookup_size": {h: list(t.shape) for h, t in tables.items()},
        },
    }
    rows = []
    for threads in s["threads"]:
        with num_threads(threads):
            for backend, compile in modes(s):
                sims = {h: make_simulator("lookup", model, field, dt, device, {"lookup": t},
                                          compile, backend)
                        for h, t in tables.items()}  # fmt: skip
                for n in s["sizes"]:
                    for h, sim in sims.items():
                        log(f"lookup throughput: n={n} threads={threads} backend={backend} "
                            f"compile={compile} history={h}")  # fmt: skip
                        rows.append({"threads": threads, "backend": backend, "compile": compile,
                                     "n_cells": n, "history": h, "load": read_load(),
                                     "lookup": throughput(sim, n, s)})  # fmt: skip
    results["throughput"] = rows
    results["machine"]["load_average_end"] = read_load()
    results["total_s"] = time.perf_counter() - started
    return results


def format_lookup_report(r: Mapping[str, Any]) -> str:
    """The lookup-only results as a plain-text table (``ran``: the backend that ran)."""
    m, a = r["machine"], r["abstraction"]
    lines = [
        f"machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']}, device {m['device']}, "
        f"load {m['load_average']} -> {m.get('load_average_end')}",
        f"model {r['model']}; abstraction: {a['source']}; lookup over {a['inputs']} "
        f"{a['lookup_size']}",
        "",
        "lookup throughput (cell-steps/s; best of repeats); cost: per cell-step, relative to",
        "the same row of the two-state chain (history none)",
        f"{'thr':>3} {'backend':>7} {'compile':>7} {'cells':>7} {'history':>7} {'lookup':>9} "
        f"{'ran':>5} {'us/step':>9} {'cost':>5}  load",
    ]
    plain: dict[tuple, float] = {}
    for row in r["throughput"]:
        k = row["lookup"]
        key = (row["threads"], row["backend"], row["compile"], row["n_cells"])
        history = row.get("history", "none")
        if HISTORY_CHAINS.get(history) is TWO_STATE:
            plain[key] = k["cell_steps_per_s"]
        cost = plain[key] / k["cell_steps_per_s"] if key in plain else float("nan")
        lines.append(
            f"{row['threads']:>3} {row['backend']:>7} {row['compile']!s:>7} {row['n_cells']:>7} "
            f"{history:>7} {_si(k['cell_steps_per_s']):>9} {k['backend']:>5} "
            f"{k['us_per_step']:>9.1f} {cost:>5.2f}  {row['load'][:1]}"
        )
    lines.append(f"\ntotal {r['total_s']:.0f} s")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# the whole benchmark


#: what the child prints for a model without a kernel (its own word, no kind's)
_NO_KERNEL = "none"
#: a fresh process: the model's precompile target where numba's cache lacks the kernel
_TARGET_CHILD = (
    "import json, sys; from surrogate.config import build_model; "
    f"print(build_model(json.loads(sys.argv[1])).kernel_precompiler() or {_NO_KERNEL!r})"
)


def kernel_compile_times(model_cfg: Mapping[str, Any], cache_dir: Path) -> dict[str, Any] | None:
    """The per-cell kernel's one-time compilation as a new machine pays it: a fresh process
    with an empty numba cache (``cache_dir``), then a second one loading what the first
    cached (seconds, imports excluded). None when the model has no kernel."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}

    def child(*args: str) -> str:
        proc = subprocess.run([sys.executable, "-c", *args], capture_output=True, text=True,
                              env=env, check=False)  # fmt: skip
        if proc.returncode != 0:
            raise RuntimeError(f"kernel compile subprocess failed:\n{proc.stderr[-3000:]}")
        return proc.stdout.split()[-1]

    target = child(_TARGET_CHILD, json.dumps(dict(model_cfg)))
    if target == _NO_KERNEL:
        return None
    code = precompiler_code(target)
    return {"target": target, "cold_s": float(child(code)), "cached_s": float(child(code))}


def run_bench(cfg: Mapping[str, Any], log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run every measurement of ``cfg`` (see the module docstring); return the results."""
    from surrogate.gp import PsiLookupTable
    from surrogate.gp.fast import CachedPsi

    s, device, model, field, dt, head = _setup(cfg)
    started = time.perf_counter()
    results: dict[str, Any] = dict(head)

    # 1. collection + training (their own timings), giving the abstraction
    log("collecting transitions and training the classifiers ...")
    psi, facts = train_abstraction(s, cfg, device)
    results.update(facts)
    ranges = [psi.domain[n] for n in psi.input_names]
    size = grid_size(s.get("lookup_size"), "lookup_size", len(psi.input_names))
    table = PsiLookupTable.from_function(psi, ranges, psi.input_names, size).to(device)
    cached = CachedPsi.from_classifier(psi)
    tables = {"lookup": table, "classifier": cached}
    results["abstraction"] = {
        "source": "trained on the fly (collect_transitions + fit_psi, timed above)",
        "n_per_state": int(s["training"]["n_per_state"]),
        "n_inducing": int(s["training"]["n_inducing"]),
        "inputs": list(psi.input_names),
        "epochs": int(s["training"]["epochs"]),
        "lookup_size": list(table.shape),
        "lookup_max_deviation": table.max_deviation(psi, n_check=4096),
        "cached_max_deviation": cached.max_deviation(psi),
        "domain": {k: list(v) for k, v in psi.domain.items()},
    }

    # 2. the per-cell kernel's one-time compilation (fresh processes, empty numba cache)
    if s.get("kernel_compile", True) and "numba" in s["backends"] and device.type == "cpu":
        log("kernel compilation: cold and cached, in fresh processes")
        with tempfile.TemporaryDirectory() as tmp:
            results["kernel_compile"] = kernel_compile_times(to_dict(cfg["model"]), Path(tmp))

    # 3. throughput: models x sizes, per thread count and compile mode
    rows = []
    for threads in s["threads"]:
        with num_threads(threads):
            for backend, compile in modes(s):
                sims = {
                    name: make_simulator(name, model, field, dt, device, tables, compile, backend)
                    for name in MODELS
                }
                for n in s["sizes"]:
                    load = read_load()
                    row: dict[str, Any] = {
                        "threads": threads, "backend": backend, "compile": compile,
                        "n_cells": n, "load": load,
                    }  # fmt: skip
                    for name in MODELS:
                        log(f"throughput: {name} n={n} threads={threads} backend={backend} "
                            f"compile={compile}")  # fmt: skip
                        row[name] = throughput(sims[name], n, s)
                    row["ratio_lookup"] = ratio(row["full"], row["lookup"])
                    row["ratio_classifier"] = ratio(row["full"], row["classifier"])
                    rows.append(row)
    results["throughput"] = rows

    best_threads, best_compile = _best_config(rows)
    results["best_config"] = {"threads": best_threads, "compile": best_compile}

    with num_threads(best_threads):
        # 4. ratio as the number of motors grows (lookup abstraction; independent of motors)
        motors = []
        n = int(s["motors_size"])
        sim_abs = make_simulator("lookup", model, field, dt, device, tables, best_compile)
        abstract = throughput(sim_abs, n, s)
        for n_motors in s["motors"]:
            m_model = build_model({**to_dict(cfg["model"]), "n_motors": int(n_motors)})
            log(f"motors: {n_motors} motors, n={n}")
            sim_full = make_simulator("full", m_model, field, dt, device, tables, best_compile)
            full = throughput(sim_full, n, s)
            motors.append({
                "n_motors": int(n_motors), "n_cells": n, "full": full, "lookup": abstract,
                "ratio_lookup": ratio(full, abstract),
            })  # fmt: skip
        results["motors"] = motors

        # 5. per-step split (best config)
        breakdown = []
        for n in s["breakdown_sizes"]:
            for name in MODELS:
                sim = make_simulator(name, model, field, dt, device, tables, best_compile)
                breakdown.append({"model": name, "n_cells": n, **step_breakdown(sim, n)})
        results["breakdown"] = breakdown

        # 6. the paper's workload through simulate_population: eager, compiled, numba
        paper = []
        with tempfile.TemporaryDirectory() as tmp:
            for backend, compile in modes(s):
                for name in ("full", "lookup"):
                    log(f"paper workload: {name} backend={backend} compile={compile}")
                    sim = make_simulator(name, model, field, dt, device, tables, compile, backend)
                    out = paper_workload(sim, s["paper"],
                                         Path(tmp) / f"{name}-{backend}-{compile}")  # fmt: skip
                    paper.append({"model": name, "backend": sim.backend, "compile": compile,
                                  "load": read_load(), **out})  # fmt: skip
        results["paper"] = {
            "n_cells": int(s["paper"]["n_cells"]),
            "t_end": float(s["paper"]["t_end"]),
            "dt": dt,
            "threads": best_threads,
            "runs": paper,
        }

        # 7. memory of a large abstracted run, in a fresh process, for two t_end
        memory = []
        with tempfile.TemporaryDirectory() as tmp:
            for t_end in s["memory"]["t_end"]:
                log(f"memory: {s['memory']['n_cells']} cells, t_end={t_end}")
                memory.append(memory_run(table, cfg, s["memory"], float(t_end), Path(tmp)))
        results["memory"] = {"runs": memory, "threads": best_threads}

    results["machine"]["load_average_end"] = read_load()
    results["total_s"] = time.perf_counter() - started
    return results


def _best_config(rows: list[dict[str, Any]]) -> tuple[int, bool]:
    """(threads, compile) of the torch step with the highest throughput at the largest size."""
    rows = [r for r in rows if r.get("backend", "torch") == "torch"] or rows
    largest = max(r["n_cells"] for r in rows)
    top = max((r for r in rows if r["n_cells"] == largest), key=lambda r: _score(r))
    return int(top["threads"]), bool(top["compile"])


def _score(row: Mapping[str, Any]) -> float:
    return row["full"]["cell_steps_per_s"] + row["lookup"]["cell_steps_per_s"]


# ----------------------------------------------------------------------------------------------
# output


def _si(x: float) -> str:
    return f"{x:.3g}"


def _ratio(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def format_report(r: Mapping[str, Any]) -> str:
    """The results as plain-text tables."""
    m = r["machine"]
    lines = [
        f"machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']}, device {m['device']}, "
        f"load {m['load_average']} -> {m.get('load_average_end')}",
        f"abstraction: {r['abstraction']['source']}; lookup {r['abstraction']['lookup_size']} "
        f"(max dev {r['abstraction']['lookup_max_deviation']:.1e}), cached classifier "
        f"(max dev {r['abstraction']['cached_max_deviation']:.1e})",
        "",
        "throughput (cell-steps/s; best of repeats)",
        f"{'thr':>3} {'backend':>7} {'compile':>7} {'cells':>7} {'full':>9} {'lookup':>9} "
        f"{'classif':>9} {'lk/full':>7} {'cl/full':>7}  load",
    ]
    for row in r["throughput"]:
        lines.append(
            f"{row['threads']:>3} {row.get('backend', 'torch'):>7} {row['compile']!s:>7} "
            f"{row['n_cells']:>7} "
            f"{_si(row['full']['cell_steps_per_s']):>9} {_si(row['lookup']['cell_steps_per_s']):>9} "
            f"{_si(row['classifier']['cell_steps_per_s']):>9} {_ratio(row['ratio_lookup']):>7} "
            f"{_ratio(row['ratio_classifier']):>7}  {row['load'][:1]}"
        )
    b = r["best_config"]
    lines += ["", f"motors (threads={b['threads']}, compile={b['compile']})"]
    lines.append(f"{'motors':>6} {'cells':>7} {'full':>9} {'lookup':>9} {'lk/full':>7}")
    for row in r["motors"]:
        lines.append(
            f"{row['n_motors']:>6} {row['n_cells']:>7} {_si(row['full']['cell_steps_per_s']):>9} "
            f"{_si(row['lookup']['cell_steps_per_s']):>9} {_ratio(row['ratio_lookup']):>7}"
        )
    lines += ["", "per-step split (us): randoms / fused kernel / rest = step"]
    for row in r["breakdown"]:
        if "step_us" in row:
            lines.append(
                f"  {row['model']:>10} n={row['n_cells']:<7} {row['randoms_us']:8.1f} "
                f"{row['kernel_us']:9.1f} {row['rest_us']:8.1f} = {row['step_us']:9.1f}"
            )
    p = r["paper"]
    lines += ["", f"paper workload ({p['n_cells']} cells, {p['t_end']:g} s, dt {p['dt']:g})"]
    for run in p["runs"]:
        lines.append(
            f"  {run['model']:>7} {run.get('backend', 'torch'):>5} compile={run['compile']!s:<5} "
            f"wall {run['wall_s']:7.2f} s "
            f"(loop {run['loop_s']:.2f} s, compile {run['compile_s']:.1f} s)  load {run['load'][:1]}"
        )
    k = r.get("kernel_compile")
    if k:
        lines += ["", f"per-cell kernel compilation (fresh process): {k['cold_s']:.1f} s with an "
                      f"empty numba cache, {k['cached_s']:.2f} s loading it from the cache"]  # fmt: skip
    c, t = r["collect"], r["training"]
    lines += [
        "",
        f"collect {c['n_transitions']} transitions: {c['seconds']:.2f} s",
        f"train both classifiers ({t['n_per_classifier']} points each, "
        f"{t['settings']['n_inducing']} inducing, {t['settings']['epochs']} epochs, "
        f"batch {t['settings']['batch_size']}): {t['seconds']:.2f} s",
        "",
        "memory (abstracted lookup run in a fresh process, record_durations off)",
    ]
    for run in r["memory"]["runs"]:
        lines.append(
            f"  {run['n_cells']} cells, t_end {run['t_end']:g} s: peak RSS "
            f"{run['peak_rss_mb']:.0f} MiB (after imports {run['rss_before_mb']:.0f} MiB)"
        )
    lines.append(f"\ntotal {r['total_s']:.0f} s")
    return "\n".join(lines)


def default_output(cfg: Mapping[str, Any]) -> Path:
    """``<data_dir>/bench/bench-<timestamp>.json``."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path(str(cfg.get("data_dir", "data"))) / "bench" / f"bench-{stamp}.json"


def main(cfg: Mapping[str, Any]) -> Path:
    """Run the benchmark, print the tables, write the JSON; return its path."""

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    if bench_settings(cfg).get("lookup_only"):
        results = run_lookup_bench(cfg, log=log)
        print(format_lookup_report(results), flush=True)
    else:
        results = run_bench(cfg, log=log)
        print(format_report(results), flush=True)
    out = Path(str(cfg["output"])) if cfg.get("output") else default_output(cfg)
    write_json(out, results)
    print(f"results: {out}", flush=True)
    return out


__all__ = [
    "bench_settings",
    "format_lookup_report",
    "format_report",
    "function_table",
    "machine_info",
    "main",
    "run_bench",
    "run_lookup_bench",
]

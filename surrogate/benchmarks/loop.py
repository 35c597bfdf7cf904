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

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

import torch

from surrogate.benchmarks.layers import make_simulator
from surrogate.benchmarks.lookup import format_lookup_report, run_lookup_bench
from surrogate.benchmarks.machine import bench_settings, num_threads, read_load, setup
from surrogate.benchmarks.timing import (
    BREAKDOWN_CALLS,
    memory_run,
    modes,
    paper_workload,
    ratio,
    si,
    step_breakdown,
    throughput,
)
from surrogate.config import build_model, grid_size, to_dict
from surrogate.io import write_json
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.precompile import precompiler_code

MODELS = ("full", "lookup", "classifier")


# ----------------------------------------------------------------------------------------------
# the abstraction, trained on the fly


def train_abstraction(
    s: Mapping[str, Any], cfg: Mapping[str, Any], device: torch.device
) -> tuple[Any, dict[str, Any]]:
    """Collect transitions and fit both classifiers (each timed) with the collect and gp
    settings of ``cfg`` (``training`` overrides sizes); return (psi, facts)."""
    from surrogate.gp import fit_psi
    from surrogate.simulate.transitions import CollectOptions, collect_transitions
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
        options=CollectOptions(
            record_every=int(opts["record_every"]),
            equilibration_time=float(opts["equilibration_time"]),
            max_time=float(opts["max_time"]),
        ),
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

    s, device, model, field, dt, head = setup(cfg)
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
                # the settings' repeats and step cap (the quick bench's 50 calls, not 500)
                calls = min(BREAKDOWN_CALLS, int(s["max_steps"]))
                split = step_breakdown(sim, n, int(s["repeats"]), calls)
                breakdown.append({"model": name, "n_cells": n, **split})
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
            f"{si(row['full']['cell_steps_per_s']):>9} {si(row['lookup']['cell_steps_per_s']):>9} "
            f"{si(row['classifier']['cell_steps_per_s']):>9} {_ratio(row['ratio_lookup']):>7} "
            f"{_ratio(row['ratio_classifier']):>7}  {row['load'][:1]}"
        )
    b = r["best_config"]
    lines += ["", f"motors (threads={b['threads']}, compile={b['compile']})"]
    lines.append(f"{'motors':>6} {'cells':>7} {'full':>9} {'lookup':>9} {'lk/full':>7}")
    for row in r["motors"]:
        lines.append(
            f"{row['n_motors']:>6} {row['n_cells']:>7} {si(row['full']['cell_steps_per_s']):>9} "
            f"{si(row['lookup']['cell_steps_per_s']):>9} {_ratio(row['ratio_lookup']):>7}"
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
    "main",
    "run_bench",
    "run_lookup_bench",
]

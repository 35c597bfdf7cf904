"""The abstraction's loop alone (``lookup_only=true``): the lookup throughput over
:func:`~surrogate.benchmarks.layers.function_table` per thread count, backend and size, with the
chains of ``histories`` side by side (:func:`run_lookup_bench`, :func:`format_lookup_report`)."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

from surrogate.benchmarks.layers import function_table, history_chains, make_simulator
from surrogate.benchmarks.machine import num_threads, read_load, setup
from surrogate.benchmarks.timing import modes, si, throughput
from surrogate.config import grid_size
from surrogate.errors import ConfigError
from surrogate.kinds import TWO_STATE
from surrogate.simulate.classes import exact_class_table


def run_lookup_bench(cfg: Mapping[str, Any], log: Callable[[str], None] = print) -> dict[str, Any]:
    """The abstraction's lookup throughput (cell-steps/s) for each thread count, (backend,
    compile) and size, over :func:`function_table`, one simulator per (threads, backend,
    compile) as :func:`run_bench`; each row records the backend that ran (``numba`` falls
    back to torch where the model has no kernel). ``histories`` (``[none, age, classes]``): each
    also with the switch clock (gp.history=age) and the K-lumps chain over the model's exact
    class law (gp.lumps=classes; the same number of signal nodes), side by side, row after
    row."""
    s, device, model, field, dt, head = setup(cfg)
    started = time.perf_counter()
    histories = list(s.get("histories") or [TWO_STATE.history])
    chains = history_chains()
    unknown = [h for h in histories if h not in chains]
    if unknown:
        raise ConfigError(f"histories: unknown {unknown}; allowed {list(chains)}")
    max_age = float(cfg.get("gp", {}).get("max_age", 5.0))

    def table(h: str) -> Any:
        kind = chains[h]
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
    chains = history_chains()
    plain: dict[tuple, float] = {}
    for row in r["throughput"]:
        k = row["lookup"]
        key = (row["threads"], row["backend"], row["compile"], row["n_cells"])
        history = row.get("history", TWO_STATE.history)
        if chains.get(history) is TWO_STATE:
            plain[key] = k["cell_steps_per_s"]
        cost = plain[key] / k["cell_steps_per_s"] if key in plain else float("nan")
        lines.append(
            f"{row['threads']:>3} {row['backend']:>7} {row['compile']!s:>7} {row['n_cells']:>7} "
            f"{history:>7} {si(k['cell_steps_per_s']):>9} {k['backend']:>5} "
            f"{k['us_per_step']:>9.1f} {cost:>5.2f}  {row['load'][:1]}"
        )
    lines.append(f"\ntotal {r['total_s']:.0f} s")
    return "\n".join(lines)


__all__ = ["format_lookup_report", "run_lookup_bench"]

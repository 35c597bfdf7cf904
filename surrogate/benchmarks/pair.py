"""psi_0 and psi_1 fitted one after the other or in two processes (:func:`fit_classifiers`'s
``processes``), quiet and beside busy-looping processes.

One run (``python scripts/bench_pair.py``) fits two natural-gradient classifiers (the clock
recipes' optimiser, so they go one by one) on synthetic two-input data, each on one torch
thread, with ``processes`` 1 and 2, beside 0 and ``busy`` processes that loop forever (stopped
after); the wall seconds are printed as a table and written as JSON. A spawned process pays
its imports (torch, gpytorch: seconds), so the gain needs fits of that order and more, and a
core to run on. Nothing is asserted.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from surrogate.benchmarks.threads import busy_loops
from surrogate.gp.settings import GPSettings
from surrogate.gp.training import fit_classifiers
from surrogate.io import write_json

__all__ = ["pair_data", "run_bench"]


def pair_data(rows: int, seed: int = 0) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Two classifiers' data (``rows x 2`` inputs in [-2, 2]^2, 0/1 labels of two probit-like
    surfaces), fixed by ``seed``."""
    gen = torch.Generator().manual_seed(seed)
    data = []
    for shift in (0.0, 1.0):
        x = torch.rand(rows, 2, generator=gen) * 4 - 2
        p = torch.sigmoid(3 * x[:, 0] - 2 * x[:, 1] ** 2 + shift)
        data.append((x, (torch.rand(rows, generator=gen) < p).float()))
    return data


def run_bench(
    epochs: int = 600,
    rows: int = 200_000,
    busy: Sequence[int] = (0, 1),
    output: Path | None = None,
) -> list[dict[str, Any]]:
    """Time the pair's fit (``epochs`` natural-gradient steps, 100 inducing points, 30 x 30
    bins) on one thread with 1 and 2 processes beside each count of ``busy`` loops; print the
    table and write it to ``output`` (JSON) where given."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    data = pair_data(rows)
    settings = GPSettings(n_inducing=100, epochs=epochs, bins=(30, 30), natural_gradient=True,
                          seed=0)  # fmt: skip
    rows_out: list[dict[str, Any]] = []
    try:
        for loops in busy:
            with busy_loops(loops):
                for processes in (1, 2):
                    start = time.perf_counter()
                    fit_classifiers(data, settings, progress=False, processes=processes)
                    rows_out.append({"busy": loops, "processes": processes,
                                     "wall_s": time.perf_counter() - start})  # fmt: skip
    finally:
        torch.set_num_threads(threads)
    print(f"psi pair, {epochs} natural-gradient steps, {rows} rows each, 1 thread per fit")
    print("busy | processes | wall s")
    for r in rows_out:
        print(f"{r['busy']:4d} | {r['processes']:9d} | {r['wall_s']:6.1f}")
    if output is not None:
        write_json(output, {"epochs": epochs, "rows": rows, "runs": rows_out})
    return rows_out

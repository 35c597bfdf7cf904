"""The exact limits of two memory routes for E. coli, beside the full model (docs/fidelity.md,
"Memory"): the two-state chain, the chain with a switch clock, and a K-state chain over
(phi, number of CCW motors) driven by the exact class-to-class matrix of adapted cells (the
"K lumps" route at its limit: :func:`surrogate.simulate.classes.exact_class_table`).

python scripts/memory_limits.py [--field gaussian|linear] [--cells 2000] [--abstract-cells N]
    [--runs full,full_repeat,exact,exact+clock,klumps] [--learned FIT_DIR ...] [--out limits.json]

``--abstract-cells`` (default ``--cells``) sizes the abstract runs apart from the full ones: the
two-sample KS test's power is set by the smaller sample, so 1e5 abstract cells against 20,000 full
cells see what ``experiment=large``'s 1e6 see (critical value 0.0105 vs 0.0097 at 5 %).

Seeds as `scripts/fidelity.py`'s defaults (full 5000, second full run 6000, exact chains 7000),
so the full, two-state and clock rows reproduce that report's numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import surrogate  # noqa: F401  first: sets OpenMP's wait policy before torch loads it

# isort: split
import torch
from scipy import stats

from surrogate.fields import GaussianField, LinearField
from surrogate.gp import PsiLookupTable
from surrogate.kinds import load_class_chain
from surrogate.models.base import FeatureMap
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import ExactDecision, FullDecision, MemoryDecision, Simulator
from surrogate.simulate.classes import ClassDecision, exact_class_table
from surrogate.simulate.decision import ExactPsi
from surrogate.simulate.memory import exact_age_table

DT = 0.05
KS_C = 1.358  # two-sample KS critical value factor at alpha = 0.05


def observe(model, decision, field, seed: int, n: int, times, backend: str = "auto"):
    """The observable (distance) of every cell at ``times`` (s), 10 s of equilibration first."""
    torch.manual_seed(seed)
    sim = Simulator(model, decision, field, DT, backend=backend)
    out, done = {}, 0
    with torch.inference_mode():
        state = sim.initial_state(n, (2.0, 0.0), equilibration_time=10.0)
        for t in times:
            todo = round(t / DT) - done
            while todo > 0:
                k = min(todo, 20)
                sim.advance(state, k)
                todo, done = todo - k, done + k
            out[t] = model.body.observables(state.body, field)["distance"].double().numpy()
    return out


def main() -> None:
    """Simulate the five runs, print and write each one's KS against the full model and its
    mean distance (with s.e.) at 125, 250, 375 and 500 s."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--field", choices=["gaussian", "linear"], default="gaussian")
    parser.add_argument("--cells", type=int, default=2000)
    parser.add_argument("--abstract-cells", type=int, default=None)
    parser.add_argument("--runs", default="full,full_repeat,exact,exact+clock,klumps")
    parser.add_argument(
        "--learned",
        nargs="*",
        default=[],
        type=Path,
        help="fit directories of gp.lumps=classes: their learned chains too",
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    model = EcoliModel()
    internal = model.internal
    field = GaussianField() if args.field == "gaussian" else LinearField()
    times = (125.0, 250.0, 375.0, 500.0)
    lo, hi = internal.signal_bounds["dG"]
    two_state = PsiLookupTable.from_function(ExactPsi(internal, DT), [(lo, hi)], ("dG",))
    clocked = MemoryDecision(exact_age_table(internal, DT, 5.0), internal,
                             FeatureMap(internal, ("dG",)), 5.0, "exact+clock", DT)  # fmt: skip
    runs = {
        "full": (FullDecision(internal), 5000, "auto"),
        "full_repeat": (FullDecision(internal), 6000, "auto"),
        "exact": (ExactDecision(internal, DT, two_state), 7000, "auto"),
        "exact+clock": (clocked, 7000, "auto"),
        "klumps": (
            ClassDecision(
                exact_class_table(internal, DT, 2048),
                internal,
                FeatureMap(internal, ("dG",)),
                "exact+classes",
            ),
            7000,
            "auto",
        ),
    }
    for directory in args.learned:  # learned K-lumps chains (gp.lumps=classes)
        table = load_class_chain(directory)
        learned = ClassDecision(table, internal, FeatureMap(internal, table.input_names),
                                "abstract")  # fmt: skip
        runs[f"learned:{directory.name}"] = (learned, 7000, "auto")
    chosen = args.runs.split(",") + [f"learned:{d.name}" for d in args.learned]
    unknown = sorted(set(chosen) - set(runs))
    if unknown or not {"full", "full_repeat"} <= set(chosen):
        parser.error(f"--runs: unknown {unknown} or missing full/full_repeat; known {list(runs)}")
    abstract_cells = args.abstract_cells or args.cells
    t0 = time.perf_counter()
    observed = {}
    for name in chosen:
        decision, seed, backend = runs[name]
        n = args.cells if name.startswith("full") else abstract_cells
        observed[name] = observe(model, decision, field, seed, n, times, backend)
        print(f"{name}: done at {time.perf_counter() - t0:.0f} s", flush=True)
    crit = KS_C * math.sqrt(1.0 / args.cells + 1.0 / abstract_cells)
    result = {"field": args.field, "cells": args.cells, "abstract_cells": abstract_cells,
              "ks_critical": crit, "runs": {}}  # fmt: skip
    for name, obs in observed.items():
        rows = {}
        for t in times:
            ks = float(stats.ks_2samp(obs[t], observed["full"][t]).statistic)
            floor = float(stats.ks_2samp(observed["full_repeat"][t], observed["full"][t]).statistic)
            rows[f"{t:g}"] = {"ks": ks, "noise_floor": floor, "mean": float(obs[t].mean()),
                              "se": float(obs[t].std(ddof=1) / math.sqrt(obs[t].size))}  # fmt: skip
        result["runs"][name] = rows
        print(name, {t: f"KS {r['ks']:.3f} (floor {r['noise_floor']:.3f}) mean {r['mean']:.4f}"
                     for t, r in rows.items()})  # fmt: skip
    print(f"KS critical value at 5 %: {crit:.4f}")
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

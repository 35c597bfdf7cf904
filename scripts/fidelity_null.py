"""The fidelity check's own false-failure rate: the full model itself as the candidate.

For each field and each of ``--pairs`` reference pairs (a full run and a second full run, the
noise floor), six more full runs (the "training seeds") get the distance checks of
``scripts/fidelity.py``: distance KS at 125 / 250 / 375 / 500 s within min(max(ks_factor x
floor, critical value at alpha), ks_max), the values of conf/fidelity.yaml (the duration checks
are left out). A chain that cannot be told from the full model fails about as many of them as
this (docs/fidelity.md, "Memory: K lumps").

python scripts/fidelity_null.py [--pairs 3] [--cells 2000] [--fields gaussian,linear,...]

E. coli, start (2, 0), 10 s equilibration, dt 0.05 s; seeds 5000 + 10 p (reference), 6000 + 10 p
(floor), 7000 + 100 p + k (the six candidates), each moved by i x 10,000,000 on the i-th field
(``fidelity.streams=per_field``'s rule, :func:`surrogate.stages.reference.field_seed`: each
field its own draw, as the check draws them). 2,000 cells: ~37 s per field and pair on one
core of the 2-core box (the numba kernel).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import surrogate  # noqa: F401  first: sets OpenMP's wait policy before torch loads it

# isort: split
import numpy as np
import torch
from omegaconf import OmegaConf
from scipy import stats

from surrogate.config import build_field, field_config
from surrogate.fields import Field
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import FullDecision, Simulator
from surrogate.stages.fidelity import KS_C
from surrogate.stages.reference import field_seed

DT = 0.05
TIMES = (125.0, 250.0, 375.0, 500.0)
CHECK = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "fidelity.yaml").fidelity
FIELDS = "gaussian,linear,dynamic,exponential"


def distances(model: EcoliModel, field: Field, seed: int, n: int) -> dict[float, np.ndarray]:
    """Every cell's distance from the peak at ``TIMES`` in one full-model run."""
    torch.manual_seed(seed)
    sim = Simulator(model, FullDecision(model.internal), field, DT)
    out, done = {}, 0
    with torch.inference_mode():
        state = sim.initial_state(n, (2.0, 0.0), equilibration_time=10.0)
        for t in TIMES:
            todo = round(t / DT) - done
            sim.advance(state, todo)
            done += todo
            out[t] = model.body.observables(state.body, field)["distance"].double().numpy()
    return out


def main() -> None:
    """Run every pair and candidate; print the failures as they come and a JSON summary."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--cells", type=int, default=2000)
    parser.add_argument("--fields", default=FIELDS)
    args = parser.parse_args()
    model = EcoliModel()
    crit = KS_C[float(CHECK.alpha)] * math.sqrt(2.0 / args.cells)
    fails, checks, largest = 0, 0, 0.0
    t0 = time.perf_counter()
    streams = str(CHECK.streams)  # each field its own draws, as the check's
    for i, name in enumerate(args.fields.split(",")):
        field = build_field(field_config(name))
        for p in range(args.pairs):
            ref = distances(model, field, field_seed(5000 + 10 * p, i, streams), args.cells)
            floor = distances(model, field, field_seed(6000 + 10 * p, i, streams), args.cells)
            limits = {t: min(max(CHECK.ks_factor * stats.ks_2samp(floor[t], ref[t]).statistic,
                                 crit), CHECK.ks_max) for t in TIMES}  # fmt: skip
            for k in range(6):
                cand = distances(model, field, field_seed(7000 + 100 * p + k, i, streams),
                                 args.cells)  # fmt: skip
                for t in TIMES:
                    ks = float(stats.ks_2samp(cand[t], ref[t]).statistic)
                    checks += 1
                    fails += int(ks > limits[t])
                    largest = max(largest, ks)
            print(f"{name} pair {p}: {fails} of {checks} checks failed so far "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)  # fmt: skip
    per_96 = 96 * fails / checks
    print(json.dumps({"failed": fails, "checks": checks, "rate": fails / checks,
                      "per_96_checks": per_96, "largest_ks": largest}))  # fmt: skip


if __name__ == "__main__":
    main()

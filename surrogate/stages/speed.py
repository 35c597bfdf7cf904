"""Loop speed of the full model and of the abstraction, side by side in one process.

``python scripts/speed.py [model=...] [n_cells=...] [t_end=...] [compile=true] [steps=...]``
times ``steps`` steps (default: the whole run, ``t_end / dt``) of the same population under each
decision layer (:func:`~surrogate.simulate.speed.measure_speed`), after a warm-up that also
compiles (compile time reported apart), and writes ``speed.json`` (with the machine and its
load) under ``data/speed/``. The abstraction must exist (the error names the train command).
"""

from __future__ import annotations

import logging
import os
import platform
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from surrogate.config import non_negative, positive, seed_everything, to_dict
from surrogate.errors import ConfigError
from surrogate.io import artefact_dir, write_json
from surrogate.simulate.speed import compare, measure_speed
from surrogate.stages.settings import SimulateSettings
from surrogate.stages.simulate import build_decision

log = logging.getLogger(__name__)

SPEED = "speed.json"


def run(cfg: Mapping[str, Any]) -> Path:
    """Measure and write ``speed.json``; return its directory."""
    c = to_dict(cfg)
    candidate = SimulateSettings.from_config(c)
    if candidate.decision.name == "full":
        raise ConfigError("speed compares an abstraction with the full model: use "
                          "decision=abstract (or decision=exact)")  # fmt: skip
    full = SimulateSettings.from_config({**c, "decision": {"name": "full"}})
    dt = candidate.setup.dt
    steps = c.get("steps")
    steps = (
        round(candidate.t_end / dt) if steps is None else int(positive(c, "steps", integer=True))
    )
    repeats = int(positive(c, "repeats", integer=True))
    non_negative(c, "equilibration_time")
    seed_everything(candidate.setup.seed)
    decisions = {"abstract": build_decision(candidate)[0], "full": build_decision(full)[0]}
    log.info("timing %d steps of %d cells: abstraction, then the full model", steps,
             candidate.n_cells)  # fmt: skip
    setup = candidate.setup
    result = measure_speed(setup.model, decisions, setup.field, candidate.n_cells, steps, dt,
                           candidate.job.device, compile=candidate.compile,
                           start=candidate.start, repeats=repeats, backend=candidate.backend,
                           chunk_steps=round(candidate.record_interval / dt))  # fmt: skip
    ratio, why = compare(result["full"], result["abstract"])
    identity = {**candidate.identity(), "steps": steps, "repeats": repeats}
    out = artefact_dir(candidate.job.data_dir, "speed", candidate.label(), identity)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / SPEED, {
        "speedup": ratio, "speed_not_comparable": why, "n_cells": candidate.n_cells,
        "steps": steps, "dt": dt,
        "compile": candidate.compile, "backend": candidate.backend,
        "threads": torch.get_num_threads(),
        "device": str(candidate.job.device), "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(), "load_average": list(os.getloadavg()),
        "settings": identity, **result,
    })  # fmt: skip
    for name in ("full", "abstract"):
        r = result[name]
        log.info("%-8s %8.2f s loop (%7.1f us/step, %.3g cell-steps/s, %s loop), compile %.1f s",
                 name, r["seconds"], r["us_per_step"], r["cell_steps_per_s"], r["backend"],
                 r["compile_s"])  # fmt: skip
    if ratio is None:
        log.warning("no speed-up: the loops were timed under different set-ups (%s); written "
                    "to %s", "; ".join(why), out / SPEED)  # fmt: skip
    else:
        log.info("abstraction speed-up %.1fx per cell-step; written to %s", ratio, out / SPEED)
    return out


__all__ = ["run"]

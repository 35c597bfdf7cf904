"""Loop speed of the full model and of the abstraction, side by side in one process.

``python scripts/speed.py [model=...] [n_cells=...] [t_end=...] [loops=...] [steps=...]`` times
``steps`` steps (default: the whole run, ``t_end / dt``) of the same population under each
decision layer, on every loop of ``loops`` that runs it (default ``auto``: the torch step, the
model's per-cell kernel where it has one, and with ``compile=true`` the compiled torch step), each
after a warm-up that also compiles (compile time reported apart). It reports the abstraction's
speed-up two ways (:func:`~surrogate.simulate.speed.speed_summary`): each model on its fastest
loop (what a user gets), and loop for loop where both ran the same loop; always the same
device, threads and number of cells. Writes ``speed.json`` (with the machine and its load) under
``data/speed/``. The abstraction must exist (the error names the train command).
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
from surrogate.errors import ConfigError, KernelUnsupported
from surrogate.io import artefact_dir, write_json
from surrogate.simulate.speed import (
    LoopTiming,
    SpeedWorkload,
    loop_name,
    measure_speed,
    speed_summary,
)
from surrogate.stages.settings import SimulateSettings
from surrogate.stages.simulate import build_decision

log = logging.getLogger(__name__)

SPEED = "speed.json"
#: the loops the stage can time: (backend, compile)
LOOPS = {"torch": ("torch", False), "numba": ("numba", False), "compiled": ("torch", True)}


def loops_setting(cfg: Mapping[str, Any]) -> list[str]:
    """``loops``: ``auto`` (torch and numba, plus compiled with ``compile=true``) or a list of
    :data:`LOOPS` names."""
    value = cfg.get("loops", "auto")
    if value == "auto":
        return ["torch", "numba", *(["compiled"] if cfg.get("compile") else [])]
    names = [value] if isinstance(value, str) else list(value or [])
    bad = [n for n in names if n not in LOOPS]
    if not names or bad:
        raise ConfigError(f"loops must be auto or a list of {list(LOOPS)}, got {value!r}")
    return names


def run(cfg: Mapping[str, Any]) -> Path:
    """Measure and write ``speed.json``; return its directory."""
    c = to_dict(cfg)
    candidate = SimulateSettings.from_config(c)
    if candidate.decision.kind.full:
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
    loops = loops_setting(c)
    seed_everything(candidate.setup.seed)
    decisions = {"abstract": build_decision(candidate)[0], "full": build_decision(full)[0]}
    setup = candidate.setup
    log.info("timing %d steps of %d cells on each of the loops %s: abstraction, then the full "
             "model", steps, candidate.n_cells, loops)  # fmt: skip
    entries: dict[str, dict[str, Any]] = {"abstract": {}, "full": {}}
    for name, decision in decisions.items():
        for loop in loops:
            backend, compile_ = LOOPS[loop]
            try:
                workload = SpeedWorkload(candidate.n_cells, steps, dt, candidate.start, repeats,
                                         round(candidate.record_interval / dt))  # fmt: skip
                result = measure_speed(setup.model, {name: decision}, setup.field, workload,
                                       candidate.job.device, compile=compile_,
                                       backend=backend)  # fmt: skip
            except KernelUnsupported as exc:
                entries[name][loop] = {"skipped": str(exc)}
                log.info("%-8s %s loop: skipped (%s)", name, loop, exc)
                continue
            r = result[name]
            if compile_ and not r["compiled"]:
                entries[name][loop] = {"skipped": f"torch.compile failed: {r['compile_error']}"}
                continue
            entries[name][loop] = r
            log.info("%-8s %-20s %8.2f s loop (%8.1f us/step, %.3g cell-steps/s), compile "
                     "%.1f s", name, loop_name(LoopTiming.from_mapping(r)), r["seconds"],
                     r["us_per_step"], r["cell_steps_per_s"], r["compile_s"])  # fmt: skip
    timed = {name: [LoopTiming.from_mapping(r) for r in e.values() if "skipped" not in r]
             for name, e in entries.items()}  # fmt: skip
    summary = speed_summary(timed["full"], timed["abstract"])
    identity = {**candidate.identity(), "steps": steps, "repeats": repeats, "loops": loops}
    out = artefact_dir(candidate.job.data_dir, "speed", candidate.label(), identity)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / SPEED, {
        **summary, "n_cells": candidate.n_cells, "steps": steps, "dt": dt,
        "loops": entries, "threads": torch.get_num_threads(),
        "device": str(candidate.job.device), "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(), "load_average": list(os.getloadavg()), "settings": identity,
    })  # fmt: skip
    if summary["speedup"] is None:
        log.warning("no speed-up: %s; written to %s", "; ".join(summary["speed_not_comparable"]),
                    out / SPEED)  # fmt: skip
    else:
        fastest = summary["fastest"]
        same = ", ".join(f"{k} {v:.3g}x" for k, v in summary["same_loop"].items()) or "none"
        log.info("abstraction speed-up %.4gx per cell-step at %d cells, each model on its fastest "
                 "loop (full: %s, abstraction: %s); on the same loop: %s; written to %s",
                 summary["speedup"], candidate.n_cells, fastest["full"], fastest["abstract"],
                 same, out / SPEED)  # fmt: skip
    return out


__all__ = ["run"]

"""The cost of a coupled field beside the agents it carries (issue 39): per step, the agents'
step (inputs read from the grid, decision, body) against the field's (the cells' uptake and
secretion deposited on the grid, then diffusion, decay and sources), at a population size and
grid where the split matters (1e6 abstracted cells on 512 x 64).

The abstraction is the model's exact lumped psi as a lookup table: per cell-step the same work
as a learned psi's table (one interpolation), with no training to wait for. The field step is
timed inside the loop (:meth:`~surrogate.simulate.Simulator._step_fields`, synchronised on
CUDA), so both shares come from the same steps; the peak resident memory is the process's.

Example:
    >>> from surrogate.benchmarks.field import run_field_bench   # doctest: +SKIP
    >>> run_field_bench(cfg)["field_share"]                      # doctest: +SKIP
    0.12
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from surrogate.benchmarks.machine import machine_info, num_threads, setup, sync
from surrogate.benchmarks.timing import peak_rss_mb
from surrogate.config import to_dict
from surrogate.errors import ConfigError
from surrogate.grid import GridField
from surrogate.io import write_json
from surrogate.kinds import exact_decision
from surrogate.simulate.loop import Simulator

__all__ = ["format_field_report", "run_field_bench"]


def run_field_bench(cfg: Mapping[str, Any], log: Callable[[str], None] = print) -> dict[str, Any]:
    """Time ``steps`` steps of ``n_cells`` abstracted cells in the coupled grid field ``field``
    (after ``warm_up`` steps), split into the agents' part and the field's; write the result
    as JSON (``output``, else ``data_dir/bench/field-<timestamp>.json``) and return it.

    Args:
        cfg: the ``bench_field`` config: ``model``, ``field`` (a :class:`GridField` config),
            ``dt``, ``n_cells``, ``steps``, ``warm_up``, ``threads``, ``start``, ``device``,
            ``seed``, ``scale_depth`` (multiply ``field.depth`` by ``n_cells / depth_cells``,
            so cells per cross-section stay those of the field's own population).
    """
    c = to_dict(cfg)
    n_cells, steps, warm = int(c["n_cells"]), int(c["steps"]), int(c["warm_up"])
    if n_cells < 1 or steps < 1 or warm < 0:
        raise ConfigError(f"n_cells and steps must be >= 1 and warm_up >= 0, got {n_cells}, "
                          f"{steps}, {warm}")  # fmt: skip
    if not str(c["field"].get("_target_", "")).endswith("GridField"):
        raise ConfigError(f"bench_field needs a grid field (field=channel_band, ...), got "
                          f"{c['field'].get('_target_')}")  # fmt: skip
    if c.get("scale_depth"):
        c["field"]["depth"] = float(c["field"]["depth"]) * n_cells / float(c["depth_cells"])
    _, device, model, field, dt, head = setup(c)
    assert isinstance(field, GridField)
    decision, _ = exact_decision(model, dt, "lookup", None, device)
    timed = {"field_s": 0.0}
    with num_threads(int(c["threads"])), torch.inference_mode():
        sim = Simulator(model, decision, field, dt, device, backend="torch")
        inner = sim._step_fields

        def step_fields(state: Any) -> None:
            sync(device)
            t0 = time.perf_counter()
            inner(state)
            sync(device)
            timed["field_s"] += time.perf_counter() - t0

        sim._step_fields = step_fields  # type: ignore[method-assign]
        state = sim.initial_state(n_cells, c["start"], 0.0)
        sim.advance(state, warm)
        timed["field_s"] = 0.0
        sync(device)
        t0 = time.perf_counter()
        sim.advance(state, steps)
        sync(device)
        total = time.perf_counter() - t0
    agents = total - timed["field_s"]
    nx, ny = field.grid.shape
    out = {
        **head,
        "machine": machine_info(device),
        "n_cells": n_cells, "grid": [nx, ny], "species": list(field.species_names),
        "steps": steps, "threads": int(c["threads"]), "dt": dt,
        "cell_steps_per_s": n_cells * steps / total,
        "agents_ms_per_step": 1e3 * agents / steps,
        "field_ms_per_step": 1e3 * timed["field_s"] / steps,
        "field_share": timed["field_s"] / total,
        "field_over_agents": timed["field_s"] / agents if agents > 0 else float("nan"),
        "peak_rss_mb": peak_rss_mb(),
        "field_fuse": field.fuse, "field_step_path": field.step_path,
    }  # fmt: skip
    path = (
        Path(c["output"])
        if c.get("output")
        else (Path(c["data_dir"]) / "bench" / f"field-{time.strftime('%Y%m%d-%H%M%S')}.json")
    )
    write_json(path, out)
    log(format_field_report(out))
    log(f"written to {path}")
    return out


def format_field_report(r: Mapping[str, Any]) -> str:
    """The bench's figures as a few lines of text."""
    nx, ny = r["grid"]
    return (
        f"{r['n_cells']:,} abstracted cells on a {nx} x {ny} grid ({', '.join(r['species'])}), "
        f"{r['steps']} steps of dt {r['dt']:g} s, {r['threads']} thread(s), "
        f"{r['machine'].get('device', '')}; field step {r.get('field_step_path', 'eager')} "
        f"(fuse={r.get('field_fuse', 'eager')})\n"
        f"  agents' step {r['agents_ms_per_step']:.1f} ms, field step "
        f"{r['field_ms_per_step']:.1f} ms per step: the field is "
        f"{100 * r['field_over_agents']:.0f} % of the agents' cost "
        f"({100 * r['field_share']:.0f} % of the whole)\n"
        f"  {r['cell_steps_per_s']:.3g} cell-steps/s; peak resident memory "
        f"{r['peak_rss_mb']:.0f} MiB"
    )

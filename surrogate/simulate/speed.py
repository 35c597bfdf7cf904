"""Speed of decision layers measured side by side, in one process, on the same population.

Runs simulated together in one batch share their steps, so a run's own loop time no longer
exists; the speed of the full model against the abstraction is measured here instead, the same
way for each: the same model, field and number of cells, the same compile setting, after a
warm-up (compile time reported separately), best of ``repeats``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from surrogate.fields import Field
from surrogate.models.base import Model
from surrogate.simulate.decision import DecisionLayer
from surrogate.simulate.loop import Simulator


def measure_speed(
    model: Model,
    decisions: Mapping[str, DecisionLayer],
    field: Field,
    n_cells: int,
    steps: int,
    dt: float,
    device: str | torch.device = "cpu",
    compile: bool = False,
    start: Sequence[float] = (2.0, 0.0),
    repeats: int = 2,
    backend: str = "torch",
    chunk_steps: int = 20,
) -> dict[str, dict[str, Any]]:
    """Loop time of ``steps`` steps of ``n_cells`` cells for each decision layer.

    The steps are taken ``chunk_steps`` per :meth:`Simulator.advance` call, as the simulate
    stage takes a record interval (20 steps: 1 s at dt 0.05) per call.

    Returns, per name: ``seconds`` (best of ``repeats``), ``cell_steps_per_s``,
    ``us_per_step``, ``compile_s`` (the warm-up), ``compile_error`` and ``backend`` (the
    loop's, resolved).
    """
    out = {}
    for name, decision in decisions.items():
        sim = Simulator(model, decision, field, dt, device, compile=compile, backend=backend)
        with torch.inference_mode():  # cheaper per op than no_grad
            state = sim.initial_state(n_cells, start)
            compile_s = sim.warm_up(state)
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                done = 0
                while done < steps:
                    k = min(chunk_steps, steps - done)
                    sim.advance(state, k)
                    done += k
                if sim.device.type == "cuda":
                    torch.cuda.synchronize(sim.device)
                best = min(best, time.perf_counter() - t0)
        out[name] = {
            "seconds": best,
            "cell_steps_per_s": n_cells * steps / best,
            "us_per_step": 1e6 * best / steps,
            "compile_s": compile_s,
            "compile_error": sim.compile_error,
            "backend": sim.backend,
            "n_cells": n_cells,
            "steps": steps,
        }
    return out


__all__ = ["measure_speed"]

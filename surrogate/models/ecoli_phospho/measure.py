"""Check the phospho network's calibration by simulation with the compiled SSA.

``measure`` runs ``n_cells`` independent cells at a fixed activity (default a* = 0.45) for a
burn-in and then ``duration`` seconds in windows of ``dt``, and reports the mean CheY-P (uM), the
CW fraction of motors (time average over cells: the CW bias), the events per cell per window,
the autocorrelation of CheY-P across one and two windows with the relaxation time it implies,
and the mean-field predictions beside them. Standard errors treat cells as independent
replicates (time averages per cell, then the sd over cells / sqrt(n_cells)).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

from surrogate.ctmc import CellStreams, CompiledSSA
from surrogate.models.ecoli_phospho.constants import (
    calibrated,
    cw_bias,
    mean_field_steady_state,
    relaxation_rates,
)
from surrogate.models.ecoli_phospho.sbml_writer import load_network

__all__ = ["measure"]


def _lag_correlation(series: np.ndarray, lag: int) -> float:
    """Pooled correlation of ``series`` (T, n) with itself ``lag`` steps later."""
    a = series[:-lag] - series.mean(axis=0)
    b = series[lag:] - series.mean(axis=0)
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


def measure(
    n_cells: int = 200,
    duration: float = 10.0,
    burn_in: float = 2.0,
    dt: float = 0.05,
    activity: float | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Simulate and summarise (see the module docstring); returns a JSON-ready dict."""
    constants = calibrated()
    a = constants.adapted_activity if activity is None else activity
    model = load_network()
    species = {name: s for s, name in enumerate(model.species)}
    ssa = CompiledSSA(model.kinetics)
    compile_s = ssa.compile()
    streams = CellStreams.from_seed(seed, n_cells)
    state = model.initial_states(n_cells)
    inputs = torch.tensor([a], dtype=torch.float64)
    for _ in range(round(burn_in / dt)):
        state, _ = ssa.advance(state, inputs, dt, streams)
    steps = round(duration / dt)
    yp = np.empty((steps, n_cells))
    cw = np.empty((steps, n_cells))
    events = np.empty((steps, n_cells))
    start = time.perf_counter()
    for k in range(steps):
        state, ev = ssa.advance(state, inputs, dt, streams)
        x = state.numpy()
        yp[k] = x[:, species["CheYp"]] / constants.n_per_um
        cw[k] = (x[:, species["S"]] + x[:, species["C"]]) / constants.n_motors
        events[k] = ev.numpy()
    wall = time.perf_counter() - start
    yp_cell, cw_cell = yp.mean(axis=0), cw.mean(axis=0)
    acf1, acf2 = _lag_correlation(yp, 1), _lag_correlation(yp, 2)
    slow, fast = relaxation_rates(constants, a)
    _, yp_mf = mean_field_steady_state(constants, a)
    return {
        "activity": a,
        "n_cells": n_cells,
        "duration_s": duration,
        "burn_in_s": burn_in,
        "dt": dt,
        "seed": seed,
        "k_a": constants.k_a,
        "cheyp_mean_uM": float(yp.mean()),
        "cheyp_mean_se": float(yp_cell.std(ddof=1) / math.sqrt(n_cells)),
        "cheyp_sd_uM": float(yp.std()),
        "cheyp_mean_field_uM": yp_mf,
        "cw_bias": float(cw.mean()),
        "cw_bias_se": float(cw_cell.std(ddof=1) / math.sqrt(n_cells)),
        "cw_bias_at_mean_field_cheyp": cw_bias(yp_mf, constants),
        "events_per_cell_per_dt": float(events.mean()),
        "cheyp_autocorrelation_lag_dt": acf1,
        "cheyp_autocorrelation_lag_2dt": acf2,
        "cheyp_relaxation_time_s_from_acf": -dt / math.log(acf1) if 0 < acf1 < 1 else None,
        "linearised_relaxation_times_s": [1 / slow, 1 / fast],
        "events_per_second_wall": float(events.sum() / wall),
        "compile_s": compile_s,
        "wall_s": wall,
    }

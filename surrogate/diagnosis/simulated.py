"""Items 3, 4 and 6 of the inspection by simulation: cells at each grid point run until every
point has settled, then the median point's cells window by window at stationarity (relaxation,
switch hazards, oscillation, the events per window), within a budget of estimated simulation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.diagnosis.fixed import SIMULATED_METHOD, FixedInputs, hazard_dict, oscillation_dict
from surrogate.diagnosis.options import InspectOptions
from surrogate.diagnosis.population import MIN_CELLS, Grid, network_of
from surrogate.diagnosis.probe import counter_species
from surrogate.evaluate.dynamics import (
    oscillation_from_acf,
    relaxation_from_series,
    segment_durations,
    settling_from_cells,
    switch_hazards,
)
from surrogate.models.base import Model

#: the settling runs' share of the seconds they are given (the stationary record gets the rest)
SETTLING_BUDGET = 0.7
#: samples per doubling of a settling run's horizon
SAMPLES = 64
#: share of the stationary record's budget kept for the range's ends (simulated networks),
#: spent only where phi oscillates at the median inputs: the period there sets gp.max_age
RANGE_SHARE = 0.25


def _range_periods(
    series: np.ndarray, group: np.ndarray, points: Sequence[int], grid: Grid, dt: float,
    depth: float,
) -> list[dict[str, Any]]:  # fmt: skip
    """Whether phi oscillates at each of ``points`` and its period and segments' 90th
    percentile, from each point's rows of ``series`` (cells x windows, at stationarity)."""
    out = []
    for g in points:
        rows = series[group == g]
        item: dict[str, Any] = {"at": grid.describe(g), "detected": False, "period_s": None,
                                "q90_s": None, "cells": int(rows.shape[0])}  # fmt: skip
        if rows.shape[0] >= 2:
            relax = relaxation_from_series(rows, dt, max_lag=max(1, (rows.shape[1] - 1) // 4))
            if np.isfinite(relax.rho[0]):
                found = oscillation_from_acf(relax.rho, relax.rho_se, dt, depth)
                durations = [d for d in segment_durations(rows) if d.size >= 2]
                period = float(found.period_s)
                item.update(detected=bool(found.detected),
                            period_s=period if math.isfinite(period) else None,
                            q90_s=max((float(np.quantile(d, 0.9) * dt) for d in durations),
                                      default=None))  # fmt: skip
        out.append(item)
    return out


def _take(state: tuple[Tensor, ...], index: Tensor) -> tuple[Tensor, ...]:
    return tuple(t.index_select(0, index.to(t.device)) for t in state)


def simulate_fixed_inputs(  # noqa: C901  # one branch per optional measurement
    model: Model, grid: Grid, options: InspectOptions, dt: float, device: torch.device,
    seconds: float,
) -> FixedInputs:  # fmt: skip
    """Items 3, 4 and 6 by simulation: ``inspect.n_cells`` cells at each grid point from the
    file's counts (a network) or the model's own initial state, run with a horizon doubled
    until every point has settled, then the median point's cells window by window at
    stationarity; within ``seconds`` of estimated simulation."""
    internal = model.internal
    network = network_of(model)
    g_count, n = grid.x.shape[0], int(options.n_cells)
    rel, alpha = options.settle_tolerance, options.markov_alpha
    notes: list[str] = []
    x_grid = torch.as_tensor(grid.x, dtype=torch.float32, device=device)
    group = torch.arange(g_count).repeat_interleave(n)
    x = x_grid[group.to(device)]
    kin = network.kinetic_inputs(x) if network is not None else None
    state = network.start_state(x.shape[0], device, kin) if network is not None else \
        internal.initial_state(x)  # fmt: skip
    step_cost = model.cell_step_seconds(dt, device=device)

    def cost(state: tuple[Tensor, ...], kin: Tensor | None, cells: int, span: float) -> float:
        """Estimated seconds of advancing ``cells`` cells by ``span`` (the events expected at
        the cells' current states, at the model's cost per event)."""
        if network is None:
            return cells * span / dt * step_cost
        assert kin is not None  # a network's kinetic inputs
        a0 = network.kinetics.torch_propensity(state[0], kin).sum(1)
        return cells * network.cell_step_seconds(span, float(a0.mean()) * span, device)

    def sample(state: tuple[Tensor, ...]) -> tuple[np.ndarray, np.ndarray | None]:
        phi = internal.phi(state).cpu().numpy()
        counts = state[0].cpu().numpy().astype(np.float64) if network is not None else None
        return phi, counts

    budget_settle = SETTLING_BUDGET * seconds
    counters = counter_species(network) if network is not None else []
    if counters:
        assert network is not None
        names = ", ".join(network.species[j] for j in counters)
        notes.append(f"not waited for: {names}, made and never consumed nor read (counters "
                     "of events: their means grow for ever and change nothing else)")  # fmt: skip
    times, phis, counts = [0.0], [], []
    p, c = sample(state)
    phis.append(p)
    counts.append(c)
    t, horizon, spent = 0.0, max(options.min_time, SAMPLES * dt), 0.0
    wall = time.perf_counter()
    while True:
        span = (horizon - t) / SAMPLES
        projected = SAMPLES * cost(state, kin, group.numel(), span)
        # a network's state holds its cells in rows (another model's is opaque: never thinned)
        while spent + projected > budget_settle and n // 2 >= MIN_CELLS and network is not None:
            old, n = n, n // 2  # thin every grid point's cells, keep the horizon growing
            keep = torch.cat([torch.arange(g * old, g * old + n) for g in range(g_count)])
            state, x = _take(state, keep), x[keep.to(device)]
            kin = kin[keep.to(device)] if kin is not None else None
            group = group[keep]
            phis = [v[keep.numpy()] for v in phis]
            counts = [v[keep.numpy()] if v is not None else None for v in counts]
            projected *= n / old
            notes.append(f"{n} cells per grid point from {t:g} s on (inspect.max_seconds)")
        if spent + projected > budget_settle:
            if t > 0:
                notes.append(f"the settling run stopped at {t:g} s (inspect.max_seconds)")
                break
            # not even the first horizon fits: a shorter one (the settling is then a bound)
            horizon = max(2 * dt, horizon * budget_settle / projected)
            span = horizon / SAMPLES
            notes.append(f"a first horizon of {horizon:g} s (inspect.max_seconds)")
        for _ in range(SAMPLES):
            spent += cost(state, kin, group.numel(), span)
            state = internal.advance(state, x, span)
            t += span
            p, c = sample(state)
            times.append(t)
            phis.append(p)
            counts.append(c)
        settle = _settling(np.array(times), np.stack(phis, 1), counts, group.numpy(), g_count,
                           rel, counters)  # fmt: skip
        if settle["settled"].all() or horizon >= options.max_time:
            if not settle["settled"].all():
                notes.append(f"not settled by inspect.max_time={options.max_time:g} s")
            break
        horizon = min(2 * horizon, options.max_time)
    settle_wall = time.perf_counter() - wall
    # the stationary record at the median point, window by window (a network's median cells
    # alone; another model's whole population, its state being opaque)
    median = (group == 0).nonzero().squeeze(1)
    windows = int(options.record_windows)
    left = max(seconds - spent, 0.0)
    ends = grid.ends()
    rows: slice | np.ndarray
    if network is not None:
        assert kin is not None  # a network's kinetic inputs
        state_m, x_m, kin_m = _take(state, median), x[median.to(device)], kin[median.to(device)]
        per_window = cost(state_m, kin_m, 1, dt)
        # a share is kept for the range's ends, recorded where phi oscillates (the period)
        share = 1.0 - RANGE_SHARE if ends else 1.0
        affordable = share * left / max(per_window * windows, 1e-300)
        cells_m = int(min(median.numel(), max(affordable, MIN_CELLS)))
        state_m, x_m = _take(state_m, torch.arange(cells_m)), x_m[:cells_m]
        rows = slice(None)
    else:
        state_m, x_m, kin_m = state, x, None
        per_window = cost(state, None, 1, dt)
        cells_m, rows = group.numel(), median.numpy()
    if cells_m * per_window * windows > left:
        windows = max(200, int(left / max(cells_m * per_window, 1e-300)))
        notes.append(f"{windows} windows recorded at stationarity (inspect.max_seconds)")
    series = np.empty((median.numel() if network is None else cells_m, windows + 1), np.int8)
    # another model's whole population runs (its state opaque): every point's phi is kept
    everyone = np.empty((group.numel(), windows + 1), np.int8) if network is None else None
    phi_now = internal.phi(state_m).cpu().numpy()
    series[:, 0] = phi_now[rows]
    if everyone is not None:
        everyone[:, 0] = phi_now
    snapshots = []
    every = max(1, windows // 8)
    for k in range(1, windows + 1):
        state_m = internal.advance(state_m, x_m, dt)
        phi_now = internal.phi(state_m).cpu().numpy()
        series[:, k] = phi_now[rows]
        if everyone is not None:
            everyone[:, k] = phi_now
        if network is not None and k % every == 0:
            snapshots.append(state_m[0].cpu())
    spent += cells_m * windows * per_window
    cells_m = series.shape[0]
    relax = relaxation_from_series(series, dt, max_lag=max(1, windows // 4))
    hz = switch_hazards(series, alpha)
    hazards = [hazard_dict(h, dt) for h in hz]
    oscillation = None
    depth = options.oscillation_depth
    if np.isfinite(relax.rho[0]):
        found = oscillation_from_acf(relax.rho, relax.rho_se, dt, depth)
        oscillation = oscillation_dict(found, dt, segment_durations(series))
    if oscillation is not None and oscillation["detected"] and ends:
        if everyone is not None:
            oscillation["over_range"] = _range_periods(everyone, group.numpy(), ends, grid,
                                                       dt, depth)  # fmt: skip
        else:
            assert kin is not None
            left = max(seconds - spent, 0.0)
            pick = torch.cat([(group == g).nonzero().squeeze(1) for g in ends])
            state_e, x_e, kin_e = _take(state, pick), x[pick.to(device)], kin[pick.to(device)]
            per_cell = cost(state_e, kin_e, 1, dt) * (windows + 1)
            cells_e = int(min(n, left / max(len(ends) * per_cell, 1e-300)))
            if cells_e >= MIN_CELLS // 2:
                keep = torch.cat([torch.arange(j * n, j * n + cells_e) for j in range(len(ends))])
                state_e, x_e = _take(state_e, keep), x_e[keep.to(device)]
                group_e = np.repeat(np.asarray(ends), cells_e)
                record = np.empty((group_e.size, windows + 1), np.int8)
                record[:, 0] = internal.phi(state_e).cpu().numpy()
                for k in range(1, windows + 1):
                    state_e = internal.advance(state_e, x_e, dt)
                    record[:, k] = internal.phi(state_e).cpu().numpy()
                spent += len(ends) * cells_e * per_cell
                oscillation["over_range"] = _range_periods(record, group_e, ends, grid, dt,
                                                           depth)  # fmt: skip
            else:
                notes.append("phi's period at the range's ends not measured "
                             "(inspect.max_seconds): gp.max_age from the median inputs'")  # fmt: skip
    memory = None
    if hz[0] is not None and hz[1] is not None:
        memory = any(h.p_value < alpha and h.effect > options.memory_effect
                     for h in (hz[0], hz[1]))  # fmt: skip
    before, after = series[:, :-1], series[:, 1:]
    switch = np.array([(after[before == v] != v).mean() if (before == v).any() else np.nan
                       for v in (0, 1)])  # fmt: skip
    events, species_law = None, {}
    stopped, stopped_state = None, None
    if network is not None:
        pooled = torch.cat(snapshots) if snapshots else state_m[0].cpu()
        assert kin_m is not None
        a0 = network.kinetics.torch_propensity(pooled, kin_m[:1].expand(pooled.shape[0], -1))
        events = float(a0.sum(1).mean()) * dt
        dead = a0.sum(1) <= 0
        stopped = float(dead.double().mean())
        if bool(dead.any()):
            values, counts = torch.unique(pooled[dead], dim=0, return_counts=True)
            state_row = values[int(torch.argmax(counts))].tolist()
            stopped_state = dict(zip(network.species, state_row, strict=True))
        weights = np.full(pooled.shape[0], 1.0 / pooled.shape[0])
        species_law = {s: (pooled[:, j].numpy(), weights) for j, s in enumerate(network.species)}
    relaxation = {"tau_s": relax.tau, "se": relax.tau_se, "amplitude": relax.amplitude,
                  "bound": relax.bound,
                  "lags": relax.lags, "acf": relax.rho.tolist(), "acf_se": relax.rho_se.tolist(),
                  "max_lag_s": (relax.rho.size - 1) * dt, "acf_at_max_lag": float(relax.rho[-1]),
                  "method": f"decay of phi's autocorrelation over {windows} windows of "
                            f"{cells_m} cells"}  # fmt: skip
    curves, species_settle = settle["curves"], {}
    if network is not None:
        species_settle = {s: r.time for s, r in zip(network.species, settle["species"],
                                                     strict=True)}  # fmt: skip
        curves["species"] = {s: np.asarray(curves["species"])[j].tolist()
                             for j, s in enumerate(network.species)}  # fmt: skip
        curves["final"] = dict(zip(network.species, curves["final"], strict=True))
    result = FixedInputs(
        SIMULATED_METHOD, settle["occupancy"], settle["occupancy_se"], settle["settled"],
        settle["phi"], settle["network"], species_settle, curves, t, relaxation,
        hazards, memory, switch, events, species_law, stopped, stopped_state, oscillation,
        int(n), notes, spent,
    )  # fmt: skip
    result.curves["wall_s"] = settle_wall
    return result


def _settling(
    times: np.ndarray,
    phi: np.ndarray,
    counts: list[np.ndarray | None],
    group: np.ndarray,
    g_count: int,
    rel: float,
    counters: list[int] | None = None,
) -> dict[str, Any]:
    """Settling and occupancy of every grid point from a run's samples (``phi``: cells x T).
    The noise bands share a family-wise level of 5 % over every curve tested (each point's phi
    and species), so that a run at its plateau is not taken for a drifting one by chance.
    ``counters``: species columns reported but not waited for (:func:`counter_species`)."""
    skip = set(counters or ())
    has_counts = counts[0] is not None
    c = np.stack([k for k in counts if k is not None], 2) if has_counts else None  # (cells, S, T)
    alpha = 0.05 / (g_count * (1 + (c.shape[1] if c is not None else 0)))
    out: dict[str, Any] = {k: np.zeros(g_count) for k in
                           ("occupancy", "occupancy_se", "phi", "network")}  # fmt: skip
    out["settled"] = np.zeros(g_count, dtype=bool)
    out["species"], out["curves"] = {}, {}
    for g in range(g_count):
        rows = group == g
        s_phi = settling_from_cells(times, phi[rows], rel, alpha)
        out["occupancy"][g], out["occupancy_se"][g] = s_phi.final, s_phi.final_se
        out["phi"][g] = s_phi.time
        settled = s_phi.settled
        worst = 0.0
        if c is not None:
            per_species = [
                settling_from_cells(times, c[rows, s], rel, alpha) for s in range(c.shape[1])
            ]
            waited = [r for j, r in enumerate(per_species) if j not in skip]
            worst = max((r.time for r in waited), default=0.0)
            settled = settled and all(r.settled for r in waited)
            if g == 0:
                out["species"] = per_species
                out["curves"] = {"times": times.tolist(),
                                 "species": c[rows].mean(0).tolist(),
                                 "final": [s.final for s in per_species],
                                 "phi": phi[rows].mean(0).tolist(), "phi_final": s_phi.final}  # fmt: skip
        elif g == 0:
            out["curves"] = {"times": times.tolist(), "phi": phi[rows].mean(0).tolist(),
                             "phi_final": s_phi.final}  # fmt: skip
        out["network"][g] = worst
        out["settled"][g] = settled
    if not has_counts:
        out["network"] = None
    return out


__all__ = [
    "RANGE_SHARE",
    "SAMPLES",
    "SETTLING_BUDGET",
    "simulate_fixed_inputs",
]

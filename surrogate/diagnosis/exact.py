"""Items 3, 4 and 6 of the inspection from the generator of an enumerable network: the
stationary occupancy, the settling of the law from the file's counts, the exact hazard against
the age and phi's exact autocorrelation (no simulation).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.ctmc.lumped import (
    lumped_age_psi,
    lumped_psi,
    relaxation_time,
    stationary_distribution,
)
from surrogate.diagnosis.fixed import EXACT_METHOD, FixedInputs, oscillation_dict
from surrogate.diagnosis.options import InspectOptions
from surrogate.diagnosis.population import Grid
from surrogate.evaluate.dynamics import oscillation_from_acf, settling_time
from surrogate.models.network import NetworkInternalModel


def exact_fixed_inputs(
    network: NetworkInternalModel, grid: Grid, options: InspectOptions, dt: float
) -> FixedInputs:
    """Items 3, 4 and 6 from the generator of an enumerable network (no simulation)."""
    space = network.state_space
    assert space is not None
    q = network.generator(torch.as_tensor(grid.x, dtype=torch.float32))  # (G, K, K)
    pi = stationary_distribution(q)
    states = space.states.to(torch.float64)
    lump = network.phi((space.states,)).to(torch.float64)
    occupancy = (pi @ lump).numpy()
    tau = relaxation_time(q).numpy()
    # settling from the file's counts: the law p0 exp(Q t) on a grid of times, doubled
    g_count, k = pi.shape
    rel = options.settle_tolerance
    finite = tau[np.isfinite(tau)]
    horizon = min(max(8 * float(finite.max()) if finite.size else 0.0, options.min_time),
                  options.max_time)  # fmt: skip
    while True:
        steps = 512
        step = torch.linalg.matrix_exp(q * (horizon / steps))
        law = torch.zeros(g_count, k, dtype=torch.float64)
        law[:, 0] = 1.0  # states[0] is the initial state
        laws = [law]
        for _ in range(steps):
            law = torch.einsum("gk,gkj->gj", law, step)
            laws.append(law)
        laws_t = torch.stack(laws)  # (T, G, K)
        means = (laws_t @ states).numpy()  # (T, G, S)
        phi = (laws_t @ lump).numpy()  # (T, G)
        final_means, final_phi = (pi @ states).numpy(), occupancy
        times = np.linspace(0.0, horizon, steps + 1)
        zero = np.zeros(times.size)
        settle_phi = np.array([settling_time(times, phi[:, g], zero, final_phi[g], rel_tol=rel)
                               for g in range(g_count)])  # fmt: skip
        settle_species = np.array([[settling_time(times, means[:, g, s], zero,
                                                  final_means[g, s], rel_tol=rel)
                                    for s in range(states.shape[1])]
                                   for g in range(g_count)])  # fmt: skip
        settled = np.maximum(settle_phi, settle_species.max(1)) <= horizon / 2
        if settled.all() or horizon >= options.max_time:
            break
        horizon = min(2 * horizon, options.max_time)
    # memory at the median inputs: the exact hazard against the age
    q0 = q[:1]
    tau0 = float(tau[0]) if math.isfinite(tau[0]) else dt
    ages = int(min(max(math.ceil(5 * tau0 / dt), 16), 2000))
    age_psi = lumped_age_psi(q0, lump > 0, dt, ages)[0].numpy()  # (2, A + 1)
    psi = lumped_psi(q0, lump > 0, dt)[0].numpy()
    hazards: list[dict[str, Any] | None] = []
    effects = []
    for v in (0, 1):
        h = age_psi[v] if v == 0 else 1.0 - age_psi[v]
        pooled = psi[v] if v == 0 else 1.0 - psi[v]
        mass = occupancy[0] if v == 1 else 1.0 - occupancy[0]
        if not (mass > 0 and pooled > 0 and np.isfinite(h).all()):
            hazards.append(None)
            continue
        effect = float(np.abs(h - pooled).max() / pooled)
        flat = settling_time(np.arange(h.size), h, np.zeros(h.size), float(h[-1]), rel_tol=rel)
        effects.append(effect)
        hazards.append({"age_s": (np.arange(h.size) * dt).tolist(), "rows": None,
                        "hazard": h.tolist(), "se": None, "pooled": float(pooled),
                        "chi2": None, "df": None, "p_value": None, "effect": effect,
                        "flat_from_s": float(flat) * dt})  # fmt: skip
    memory = None if len(effects) < 2 else max(effects) > options.memory_effect
    # phi's exact autocorrelation at lags 0..ages windows: cov(l) = sum pi f P^l f
    one = torch.linalg.matrix_exp(q0[0] * dt)
    f = lump - float(occupancy[0])
    ahead, cov = f.clone(), []
    for _ in range(ages + 1):
        cov.append(float((pi[0] * f * ahead).sum()))
        ahead = one @ ahead
    oscillation = None
    if cov[0] > 0:
        rho = np.asarray(cov) / cov[0]
        oscillation = oscillation_dict(
            oscillation_from_acf(rho, None, dt, options.oscillation_depth), dt
        )
        if oscillation["detected"] and g_count > 1:
            oscillation["over_range"] = [
                _exact_period(q[g], pi[g], lump, float(occupancy[g]), float(tau[g]), dt,
                              options.oscillation_depth) | {"at": grid.describe(g)}
                for g in range(1, g_count)
            ]  # fmt: skip
    switch = np.array([psi[0], 1.0 - psi[1]])
    median_inputs = network.kinetic_inputs(torch.as_tensor(grid.x[:1], dtype=torch.float32))
    a0 = network.kinetics.torch_propensity(space.states, median_inputs.expand(k, -1)).sum(1)
    events = float((pi[0] * a0).sum()) * dt
    dead = a0 <= 0
    stopped = float(pi[0][dead].sum())
    stopped_state = None
    if bool(dead.any()):
        where = int(torch.argmax(torch.where(dead, pi[0], -1.0)))
        stopped_state = dict(zip(network.species, space.states[where].tolist(), strict=True))
    species_law = {s: (space.states[:, j].numpy(), pi[0].numpy())
                   for j, s in enumerate(network.species)}  # fmt: skip
    curves = {"times": times.tolist(), "species": {s: means[:, 0, j].tolist()
                                                   for j, s in enumerate(network.species)},
              "final": {s: float(final_means[0, j]) for j, s in enumerate(network.species)},
              "phi": phi[:, 0].tolist(), "phi_final": float(final_phi[0])}  # fmt: skip
    relaxation = {"tau_s": float(tau[0]), "se": 0.0, "bound": "",
                  "method": "1 / spectral gap of the generator"}  # fmt: skip
    return FixedInputs(EXACT_METHOD, occupancy, np.zeros_like(occupancy), settled, settle_phi,
                       settle_species.max(1),
                       {s: float(settle_species[0, j]) for j, s in enumerate(network.species)},
                       curves, horizon, relaxation, hazards, memory, switch, events,
                       species_law, stopped, stopped_state, oscillation)  # fmt: skip


def _exact_period(
    q: Tensor, pi: Tensor, lump: Tensor, occupancy: float, tau: float, dt: float, depth: float
) -> dict[str, Any]:  # fmt: skip
    """Whether phi oscillates at one point of the grid and its period, from the generator
    ``q`` (``K x K``) and its stationary law ``pi``: the exact autocorrelation over the lags
    :func:`exact_fixed_inputs` takes at the median (five relaxation times, 16 to 2,000)."""
    ages = int(min(max(math.ceil(5 * (tau if math.isfinite(tau) else dt) / dt), 16), 2000))
    one = torch.linalg.matrix_exp(q * dt)
    f = lump - occupancy
    ahead, cov = f.clone(), []
    for _ in range(ages + 1):
        cov.append(float((pi * f * ahead).sum()))
        ahead = one @ ahead
    if not cov[0] > 0:
        return {"detected": False, "period_s": None, "q90_s": None}
    found = oscillation_from_acf(np.asarray(cov) / cov[0], None, dt, depth)
    period = float(found.period_s)
    return {"detected": bool(found.detected),
            "period_s": period if math.isfinite(period) else None, "q90_s": None}  # fmt: skip


__all__ = [
    "exact_fixed_inputs",
]

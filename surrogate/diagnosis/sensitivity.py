"""The network (the inspection's item 1): species, parameters, and for each input the reactions
its propensities feed and its sensitivity over the network states the population runs sampled.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.diagnosis.options import InspectOptions
from surrogate.diagnosis.population import Grid, Population
from surrogate.models.network import NetworkInternalModel
from surrogate.sbml import SbmlModel


def propensity_change(kinetics: Any, states: Tensor, low: Tensor, high: Tensor) -> np.ndarray:
    """The sensitivity of every reaction's propensity to a change of the inputs from ``low``
    to ``high`` (``(P,)`` each), over ``states`` (``m x S`` counts):
    ``sum_s |a_r(s, high) - a_r(s, low)| / sum_s (a_r(s, low) + a_r(s, high)) / 2``, 0 where the
    reaction never fires in those states. ``(R,)``."""
    m = states.shape[0]
    a_low = kinetics.torch_propensity(states, low.reshape(1, -1).expand(m, -1))
    a_high = kinetics.torch_propensity(states, high.reshape(1, -1).expand(m, -1))
    change = (a_high - a_low).abs().sum(0)
    mean = ((a_low + a_high) / 2).sum(0)
    return torch.where(mean > 0, change / mean.clamp_min(1e-300), 0.0).numpy()


def _fires(
    kinetics: Any, states: Tensor, low: Tensor, high: Tensor, enters: list[str],
    reactions: tuple[str, ...],
) -> bool:  # fmt: skip
    """Whether some reaction of ``enters`` has a positive propensity in some of ``states`` at
    ``low`` or ``high`` inputs."""
    m = states.shape[0]
    columns = [reactions.index(r) for r in enters]
    both = [kinetics.torch_propensity(states, x.reshape(1, -1).expand(m, -1))[:, columns]
            for x in (low, high)]  # fmt: skip
    return bool(any((a > 0).any() for a in both))


def describe_network(
    network: NetworkInternalModel, population: Population, grid: Grid, options: InspectOptions
) -> dict[str, Any]:
    """Item 1: species, parameters, and what each input feeds and whether it has an effect."""
    kinetics = network.kinetics
    reactions = network.reactions.reaction_names
    sbml = network.network if isinstance(network.network, SbmlModel) else None
    initial = network.initial_counts.tolist()
    out: dict[str, Any] = {
        "species": {s: int(c) for s, c in zip(network.species, initial, strict=True)},
        "reactions": list(reactions),
        "global_parameters": dict(sbml.parameters) if sbml else {},
        "local_parameters": dict(sbml.local_parameters) if sbml else {},
        "file_inputs": bool(sbml),
    }
    states = population.states
    assert states is not None and population.kinetic is not None
    kin = population.kinetic
    q = options.quantiles
    low, high = np.quantile(kin, q[0], axis=0), np.quantile(kin, q[1], axis=0)
    median = np.median(kin, axis=0)
    as_tensor = lambda v: torch.as_tensor(v, dtype=torch.float64)  # noqa: E731
    inputs = []
    for j, name in enumerate(kinetics.input_names):
        enters = [reactions[r] for r, e in enumerate(kinetics.propensity_exprs)
                  if j in e.inputs_used()]  # fmt: skip
        lo, hi = median.copy(), median.copy()
        lo[j], hi[j] = low[j], high[j]
        sens = propensity_change(kinetics, states, as_tensor(lo), as_tensor(hi))
        effect = {reactions[r]: float(sens[r]) for r in range(len(reactions))
                  if reactions[r] in enters}  # fmt: skip
        flags = []
        if not enters:
            flags.append("feeds no reaction")
        elif not high[j] > low[j]:
            flags.append("one value over the fields' range")
        elif not _fires(kinetics, states, as_tensor(lo), as_tensor(hi), enters, reactions):
            which = "its reactions never fire" if len(enters) > 1 else "its reaction never fires"
            flags.append(
                f"no effect seen: {which} in the states sampled (propensity 0 at "
                "both ends of the range: a species it needs is absent or used up)"
            )
        elif max(effect.values()) < options.effect_threshold:
            flags.append("no effect on its reactions' propensities in the states sampled")
        inputs.append({"name": name, "low": float(low[j]), "median": float(median[j]),
                       "high": float(high[j]), "reactions": enters, "sensitivity": effect,
                       "flags": flags})  # fmt: skip
    out["inputs"] = inputs
    # the body's inputs, through the model's features and input formulas
    body = []
    for i, name in enumerate(grid.names):
        xl, xh = grid.median.copy(), grid.median.copy()
        xl[i], xh[i] = grid.low[i], grid.high[i]
        both = network.kinetic_inputs(torch.as_tensor(np.stack([xl, xh]), dtype=torch.float32))
        sens = propensity_change(kinetics, states, both[0], both[1])
        body.append({"name": name, "low": float(grid.low[i]), "high": float(grid.high[i]),
                     "sensitivity": {reactions[r]: float(sens[r]) for r in range(len(reactions))
                                     if sens[r] > 0},
                     "effect": float(sens.max()) if sens.size else 0.0})  # fmt: skip
    out["body_inputs"] = body
    return out


__all__ = [
    "describe_network",
    "propensity_change",
]

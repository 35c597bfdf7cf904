"""Flagella / motor population CTMC of one cell: species S (semicoiled, CW), C (curly, CW),
N (normal, CCW) with reactions S -> C (mu), C -> N (k+), S -> N (k+), N -> S (k-).

The cell RUNs iff N >= 2 and S == 0. Motors are independent first-order units, so the state
after a window dt can be sampled exactly either with the general SSA or from each motor's
transition matrix exp(Q dt) (``model.motor_sampler``); both are exact in distribution.
"""

from __future__ import annotations

import torch
from torch import Tensor

from surrogate.ctmc import (
    ReactionNetwork,
    gillespie,
    sample_counts,
    unit_generator,
    unit_transition_matrix,
)
from surrogate.models.ecoli.parameters import EcoliParameters

SPECIES = ("S", "C", "N")
S, C, N = 0, 1, 2

FLAGELLA_NETWORK = ReactionNetwork.from_reactions(
    SPECIES,
    [
        ("S->C", {"S": 1}, {"C": 1}),  # semicoiled -> curly, fixed rate mu
        ("C->N", {"C": 1}, {"N": 1}),  # CW -> CCW at k+
        ("S->N", {"S": 1}, {"N": 1}),  # CW -> CCW at k+
        ("N->S", {"N": 1}, {"S": 1}),  # CCW -> CW at k-
    ],
)


def rate_constants(k_plus: Tensor, k_minus: Tensor, p: EcoliParameters) -> Tensor:
    """Per-cell rate constants (n, 4) of the flagella network, in reaction order."""
    mu = torch.full_like(k_plus, p.mu)
    return torch.stack([mu, k_plus, k_plus, k_minus], dim=-1)


def is_run(counts: Tensor) -> Tensor:
    """phi_RUN(s) = (N >= 2) and (S == 0), for counts (n, 3) -> bool (n,)."""
    return (counts[..., N] >= 2) & (counts[..., S] == 0)


def stationary_motor_distribution(k_plus: Tensor, k_minus: Tensor, p: EcoliParameters) -> Tensor:
    """Stationary distribution (n, 3) of ONE motor at fixed rates.

    Balance: pi_C k+ = pi_S mu and pi_N k- = pi_S (mu + k+), so
    pi ~ (1, mu / k+, (mu + k+) / k-).
    """
    ones = torch.ones_like(k_plus)
    weights = torch.stack([ones, p.mu / k_plus, (p.mu + k_plus) / k_minus], dim=-1)
    return weights / weights.sum(-1, keepdim=True)


def sample_stationary_counts(k_plus: Tensor, k_minus: Tensor, p: EcoliParameters) -> Tensor:
    """Draw each cell's motor counts (n, 3) from the product of per-motor stationary laws."""
    pi = stationary_motor_distribution(k_plus.double(), k_minus.double(), p)
    states = torch.multinomial(pi, p.n_motors, replacement=True)  # (n, n_motors) motor states
    return torch.nn.functional.one_hot(states, 3).sum(1)


def advance_motors(
    counts: Tensor, k_plus: Tensor, k_minus: Tensor, dt: float, p: EcoliParameters
) -> Tensor:
    """Exact sample of the motor counts after a window ``dt`` with rates fixed over it."""
    rates = rate_constants(k_plus.double(), k_minus.double(), p)
    if p.motor_sampler == "ssa":
        return gillespie(FLAGELLA_NETWORK, counts, rates, dt)
    transition = unit_transition_matrix(unit_generator(FLAGELLA_NETWORK, rates), dt)
    return sample_counts(counts, transition)

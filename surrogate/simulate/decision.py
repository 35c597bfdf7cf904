"""Decision layers: what a cell does next (RUN or TUMBLE) given its inputs (m, L).

The outer time loop is shared; only this layer differs between the full model (exact motor
pCTMC + RUN property) and the abstraction (phi' ~ Bernoulli(psi_phi(m, L))).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import torch
from torch import Tensor

from surrogate.models.ecoli import (
    EcoliParameters,
    advance_motors,
    is_run,
    motor_rates,
    sample_stationary_counts,
)

# p(phi' = RUN | phi, m, L) for tensors of one length; a PsiClassifier or a PsiLookupTable.
RunProbability = Callable[[Tensor, Tensor, Tensor], Tensor]


class DecisionLayer(Protocol):
    """The internal layer of a cell, seen from the outer loop."""

    name: str

    def initialize(self, methylation: Tensor, ligand: Tensor) -> Tensor:
        """Draw the initial RUN property (bool, (n,)) for cells adapted to their inputs."""
        ...

    def step(self, run: Tensor, methylation: Tensor, ligand: Tensor, dt: float) -> Tensor:
        """Advance one window ``dt`` with inputs fixed; return the next RUN property (bool)."""
        ...


class FullDecision:
    """Algorithm 1: simulate each cell's motor pCTMC exactly over dt, then evaluate phi_RUN."""

    name = "full"

    def __init__(self, params: EcoliParameters) -> None:
        self.params = params
        self.counts: Tensor | None = None  # motor counts (n, 3): S, C, N

    def initialize(self, methylation: Tensor, ligand: Tensor) -> Tensor:
        """Motors drawn from their stationary law at each cell's own (m, L)."""
        k_plus, k_minus = motor_rates(methylation, ligand, self.params)
        self.counts = sample_stationary_counts(k_plus, k_minus, self.params)
        return is_run(self.counts)

    def step(self, run: Tensor, methylation: Tensor, ligand: Tensor, dt: float) -> Tensor:
        """Exact motor window (SSA or per-motor transition matrices), then phi_RUN."""
        if self.counts is None:
            raise RuntimeError("FullDecision.step called before initialize()")
        k_plus, k_minus = motor_rates(methylation, ligand, self.params)
        self.counts = advance_motors(self.counts, k_plus, k_minus, dt, self.params)
        return is_run(self.counts)


class AbstractDecision:
    """Algorithm 2: phi' ~ Bernoulli(psi_phi(m, L)) with a learned run probability."""

    name = "abstract"

    def __init__(self, run_probability: RunProbability, params: EcoliParameters) -> None:
        self.run_probability = run_probability
        self.params = params

    def initialize(self, methylation: Tensor, ligand: Tensor) -> Tensor:
        """Same initial law as the full model (stationary motors -> phi_RUN), for a fair start."""
        k_plus, k_minus = motor_rates(methylation, ligand, self.params)
        return is_run(sample_stationary_counts(k_plus, k_minus, self.params))

    def step(self, run: Tensor, methylation: Tensor, ligand: Tensor, dt: float) -> Tensor:
        """One Bernoulli draw per cell from the classifier's probability."""
        p = self.run_probability(run, methylation, ligand)
        return torch.rand_like(p) < p

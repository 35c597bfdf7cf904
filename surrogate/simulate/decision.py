"""Decision layers: what a cell does next (RUN or TUMBLE) given its inputs (m, L).

The outer time loop is shared; only this layer differs between the full model (exact motor
pCTMC + RUN property) and the abstraction (phi' ~ Bernoulli(psi_phi(m, L))).

Besides the plain protocol (``initialize`` / ``step``), the two built-in layers offer a *fused*
form that :class:`~surrogate.simulate.loop.Simulator` inlines into its one-function-per-step
kernel (and can ``torch.compile``): ``fused_step`` is a pure function of tensors that takes its
random numbers as inputs, so the whole step has no host sync and a fixed number of ops.
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
from surrogate.models.ecoli.motors import (
    MOTOR_DTYPE,
    counts_from_states,
    is_run_states,
    motor_thresholds,
    run_flag_from_states,
    sample_motor_states,
    sample_stationary_states,
    step_motor_states,
)

# p(phi' = RUN | phi, m, L) for tensors of one length; a PsiClassifier or a PsiLookupTable.
RunProbability = Callable[[Tensor, Tensor, Tensor], Tensor]

# per-cell tensors a fused decision carries from step to step (e.g. motor states)
DecisionState = tuple[Tensor, ...]


class DecisionLayer(Protocol):
    """The internal layer of a cell, seen from the outer loop."""

    name: str

    def initialize(self, methylation: Tensor, ligand: Tensor) -> Tensor:
        """Draw the initial RUN property (bool, (n,)) for cells adapted to their inputs."""
        ...

    def step(self, run: Tensor, methylation: Tensor, ligand: Tensor, dt: float) -> Tensor:
        """Advance one window ``dt`` with inputs fixed; return the next RUN property (bool)."""
        ...


class FusedDecision(Protocol):
    """Optional extension of :class:`DecisionLayer` that the simulator can fuse into its step.

    ``fused_uniforms`` float32 and ``fused_uniforms64`` float64 uniform rows (each of length n)
    are drawn by the simulator per step and passed in; ``fused_step`` must be pure (no host
    sync, no RNG, no state mutation). It gets phi before the window as float 0/1 (plus
    ``log_terms`` = ln TarTerm + ln TsrTerm of L, shared with the OU drift) and returns (phi
    after the window as float 0/1, next state, aux): flags travel as numbers because compiled
    CPU kernels handle boolean tensors with scalar loops. The simulator stores the state with
    ``set_fused_state`` and drops ``aux`` (intermediate tensors returned only so that
    ``torch.compile`` materialises them once per step instead of recomputing them inside every
    consumer loop).
    """

    fusable: bool
    fused_uniforms: int
    fused_uniforms64: int

    def fused_state(self) -> DecisionState: ...

    def set_fused_state(self, state: DecisionState) -> None: ...

    def fused_step(
        self,
        run: Tensor,
        methylation: Tensor,
        ligand: Tensor,
        log_terms: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: DecisionState,
    ) -> tuple[Tensor, DecisionState, tuple[Tensor, ...]]: ...


def rates_from_log_terms(
    methylation: Tensor, log_terms: Tensor, p: EcoliParameters
) -> tuple[Tensor, Tensor]:
    """(k+, k-) in float64 from m and ln TarTerm + ln TsrTerm (shared with the OU drift).

    Same formulas as :func:`surrogate.models.ecoli.motor_rates` (MWC activity, CheY-P, dG),
    with the receptor terms computed once per step by the caller.
    """
    free_energy = p.eps0 + p.eps1 * methylation + log_terms
    yp = p.alpha * torch.sigmoid(-free_energy)
    dg = (p.g0 / 4.0 - p.g1 / 2.0 * yp / (yp + p.k_d)).to(torch.float64)
    return p.omega * torch.exp(dg), p.omega * torch.exp(-dg)


class FullDecision:
    """Algorithm 1: simulate each cell's motor pCTMC exactly over dt, then evaluate phi_RUN.

    With ``motor_sampler=transition_matrix`` every motor keeps its own state (``motors``,
    (M, n) float32: 0 = S, 1 = C, 2 = N) and moves by its closed-form exp(Q dt) with one uniform
    per motor and window (fixed cost, fusable). With ``ssa`` the counts (n, 3) advance by the
    general Gillespie SSA (an event loop with host syncs; not fusable).
    """

    name = "full"
    fused_uniforms = 0

    def __init__(self, params: EcoliParameters) -> None:
        self.params = params
        self.motors: Tensor | None = None  # (M, n) float32 per-motor states (transition_matrix)
        self._counts: Tensor | None = None  # (n, 3) motor counts S, C, N (ssa)

    @property
    def fusable(self) -> bool:
        """Whether the simulator may inline :meth:`fused_step` (closed-form sampler only)."""
        return self.params.motor_sampler != "ssa"

    @property
    def fused_uniforms64(self) -> int:
        """One float64 uniform per motor and window."""
        return int(self.params.n_motors)

    @property
    def counts(self) -> Tensor | None:
        """Motor counts (n, 3): S, C, N."""
        if self.motors is not None:
            return counts_from_states(self.motors)
        return self._counts

    @counts.setter
    def counts(self, counts: Tensor | None) -> None:
        if counts is None or not self.fusable:
            self._counts, self.motors = counts, None
            return
        # motors of a cell are exchangeable: lay the counts out as states in any order
        m = int(self.params.n_motors)
        if counts.dim() != 2 or counts.shape[1] != 3 or bool((counts.sum(1) != m).any()):
            raise ValueError(f"motor counts must be (n, 3) with rows summing to n_motors={m}")
        cum = counts.to(torch.int64).cumsum(-1)  # (n, 3)
        slots = torch.arange(m, device=counts.device)
        states = (slots[:, None, None] >= cum[None, :, :]).sum(-1)  # (M, n)
        self.motors = states.clamp_max(2).to(MOTOR_DTYPE).contiguous()
        self._counts = None

    def initialize(self, methylation: Tensor, ligand: Tensor) -> Tensor:
        """Motors drawn from their stationary law at each cell's own (m, L)."""
        k_plus, k_minus = motor_rates(methylation, ligand, self.params)
        if self.fusable:
            self.motors = sample_stationary_states(k_plus, k_minus, self.params)
            self._counts = None
            return is_run_states(self.motors)
        self._counts = sample_stationary_counts(k_plus, k_minus, self.params)
        self.motors = None
        return is_run(self._counts)

    def step(self, run: Tensor, methylation: Tensor, ligand: Tensor, dt: float) -> Tensor:
        """Exact motor window (SSA or per-motor transition matrices), then phi_RUN."""
        if self.motors is None and self._counts is None:
            raise RuntimeError("FullDecision.step called before initialize()")
        k_plus, k_minus = motor_rates(methylation, ligand, self.params)
        if self.motors is not None:
            u = torch.rand(self.motors.shape, dtype=torch.float64, device=self.motors.device)
            self.motors = step_motor_states(self.motors, k_plus, k_minus, dt, self.params.mu, u)
            return is_run_states(self.motors)
        self._counts = advance_motors(self._counts, k_plus, k_minus, dt, self.params)
        return is_run(self._counts)

    # fused form -----------------------------------------------------------------------------
    def fused_state(self) -> DecisionState:
        """The per-motor states."""
        if self.motors is None:
            raise RuntimeError("FullDecision: no per-motor state (not initialised, or ssa)")
        return (self.motors,)

    def set_fused_state(self, state: DecisionState) -> None:
        """Store the per-motor states returned by :meth:`fused_step`."""
        (self.motors,) = state

    def fused_step(
        self,
        run: Tensor,
        methylation: Tensor,
        ligand: Tensor,
        log_terms: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: DecisionState,
    ) -> tuple[Tensor, DecisionState, tuple[Tensor, ...]]:
        """Pure: rates from (m, L), one exact window of every motor, phi_RUN."""
        k_plus, k_minus = rates_from_log_terms(methylation, log_terms, self.params)
        # per-cell thresholds as ONE (5, n) tensor, returned as an aux output: a compiled step
        # then materialises them once instead of recomputing them for every motor
        thresholds = torch.stack(motor_thresholds(k_plus, k_minus, dt, self.params.mu))
        motors = sample_motor_states(state[0], thresholds, u64)
        return run_flag_from_states(motors), (motors,), (thresholds,)


class AbstractDecision:
    """Algorithm 2: phi' ~ Bernoulli(psi_phi(m, L)) with a learned run probability."""

    name = "abstract"
    fusable = True
    fused_uniforms = 1
    fused_uniforms64 = 0

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

    # fused form -----------------------------------------------------------------------------
    def fused_state(self) -> DecisionState:
        """No per-cell state."""
        return ()

    def set_fused_state(self, state: DecisionState) -> None:
        """Nothing to store."""

    def fused_step(
        self,
        run: Tensor,
        methylation: Tensor,
        ligand: Tensor,
        log_terms: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: DecisionState,
    ) -> tuple[Tensor, DecisionState, tuple[Tensor, ...]]:
        """Pure: phi' = [u < psi_phi(m, L)] with the uniform ``u[0]``."""
        p = self.run_probability(run, methylation, ligand)
        return (u[0] < p).to(torch.float32), (), ()


def is_fusable(decision: object) -> bool:
    """Whether ``decision`` implements the fused protocol and allows it now."""
    return bool(getattr(decision, "fusable", False)) and hasattr(decision, "fused_step")


__all__ = [
    "AbstractDecision",
    "DecisionLayer",
    "DecisionState",
    "FullDecision",
    "FusedDecision",
    "RunProbability",
    "is_fusable",
    "rates_from_log_terms",
]

"""The E. coli internal model: the flagella/motor population CTMC driven by (m, L).

Inputs ``x = (m, L)``: the cell's methylation and the ligand at its position. The network's
rates depend on them only through the receptor free energy F(m, L) (equivalently CheY-P, or the
motor free-energy difference dG = ln(k+ / omega)), so those are offered as features, and dG is
the *signal*: the exact lumped psi and the default abstraction are functions of it alone.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from surrogate.ctmc import gillespie
from surrogate.ctmc.lumped import lumped_age_psi, lumped_class_step
from surrogate.models.base import InternalState, Randoms
from surrogate.models.ecoli import formulas
from surrogate.models.ecoli.motors import (
    FLAGELLA_NETWORK,
    N,
    class_index,
    class_probability_after,
    counts_from_states,
    exact_run_probability,
    is_run,
    motor_classes,
    motor_thresholds,
    motor_transition_matrix,
    population_space,
    rate_constants,
    run_flag_from_states,
    run_probability_after,
    sample_motor_states,
    sample_stationary_counts,
    sample_stationary_states,
    states_from_counts,
)
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli.signalling import rates_from_delta_g

INPUTS = ("m", "L")
FEATURES = ("F", "cheyp", "dG")


class MotorInternalModel:
    """Four (``n_motors``) independent flagellar motors per cell, S -> C (mu), C -> N (k+),
    S -> N (k+), N -> S (k-), with k+- = omega exp(+-dG(m, L)); phi = RUN iff N >= 2 and S == 0.

    With ``motor_sampler=transition_matrix`` (default) every motor keeps its own state (state =
    ``(motors,)``, ``n_motors x n`` float32: 0 = S, 1 = C, 2 = N) and moves by its closed-form
    exp(Q dt), one float64 uniform per motor and window: exact, fixed cost, fusable. With ``ssa``
    the counts (state = ``(counts,)``, ``n x 3``) advance by the general batched Gillespie SSA
    (exact, event loop with host syncs, not fusable).

    Example:
        >>> model = MotorInternalModel(EcoliParameters())
        >>> x = torch.tensor([[2.2, 0.0]])
        >>> state = model.initial_state(x)
        >>> model.phi(model.advance(state, x, 0.05)).shape
        torch.Size([1])
    """

    input_names = INPUTS
    feature_names = FEATURES
    signal_names = ("dG",)
    lump_names = ("tumble", "run")

    def __init__(self, params: EcoliParameters) -> None:
        self.params = params
        self.fusable = params.motor_sampler != "ssa"
        self.randoms = Randoms(uniform64=int(params.n_motors) if self.fusable else 0)
        # dG over CheY-P in [0, alpha]: the whole range the signal can take
        c = formulas.constants(params)
        self.signal_bounds = {"dG": (formulas.delta_g(params.alpha, c), formulas.delta_g(0.0, c))}
        # K lumps: (phi, number of CCW motors), e.g. "run/3 CCW"
        keys = motor_classes(params.n_motors)
        self.class_names = tuple(f"{self.lump_names[r]}/{c} CCW" for r, c in keys)
        self.class_lumps = tuple(r for r, _ in keys)
        self._class_index = class_index(params.n_motors)

    # -- inputs and features -----------------------------------------------------------------
    def features(self, x: Tensor, names: Sequence[str]) -> Tensor:
        """Columns ``names`` (any of m, L, F, cheyp, dG) at inputs ``x`` (``n x 2``)."""
        unknown = [n for n in names if n not in INPUTS + FEATURES]
        if unknown:
            raise KeyError(f"unknown feature(s) {unknown}; known: {list(INPUTS + FEATURES)}")
        cols = {"m": x[:, 0], "L": x[:, 1]}
        if any(n in FEATURES for n in names):  # F -> CheY-P -> dG, each computed once
            c = formulas.constants(self.params)
            terms = formulas.log_receptor_terms(cols["L"], c)
            cols["F"], _, cols["cheyp"], cols["dG"] = formulas.signal(cols["m"], terms, c)
        return torch.stack([cols[n] for n in names], -1)

    def rates(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(k+, k-) ``(n,)`` float64 at inputs ``x``."""
        return rates_from_delta_g(self.features(x, ("dG",))[:, 0], self.params)

    # -- the window ----------------------------------------------------------------------------
    def initial_state(self, x: Tensor) -> InternalState:
        """Every motor from its own stationary law at the cell's (m, L)."""
        k_plus, k_minus = self.rates(x)
        if self.fusable:
            return (sample_stationary_states(k_plus, k_minus, self.params),)
        return (sample_stationary_counts(k_plus, k_minus, self.params),)

    def advance(self, state: InternalState, x: Tensor, dt: float) -> InternalState:
        """One exact window (per-motor transition matrices, or the SSA on the counts)."""
        if self.fusable:
            u64 = torch.rand(state[0].shape, dtype=torch.float64, device=state[0].device)
            return self.fused_advance(state, x, dt, state[0].new_empty(0), u64)[0]
        k_plus, k_minus = self.rates(x)
        rates = rate_constants(k_plus, k_minus, self.params)
        return (gillespie(FLAGELLA_NETWORK, state[0], rates, dt),)

    def fused_advance(
        self, state: InternalState, x: Tensor, dt: float, u: Tensor, u64: Tensor | None
    ) -> tuple[InternalState, tuple[Tensor, ...]]:
        """Pure: rates from (m, L), one exact window of every motor (``u64``: one uniform per
        motor). The per-cell thresholds are returned as one ``5 x n`` aux tensor, so a compiled
        step materialises them once instead of recomputing them for every motor."""
        if not self.fusable:
            raise RuntimeError("motor_sampler=ssa has no fused window")
        k_plus, k_minus = self.rates(x)
        thresholds = torch.stack(motor_thresholds(k_plus, k_minus, dt, self.params.mu))
        assert u64 is not None  # self.randoms asks for uniform64 rows
        return (sample_motor_states(state[0], thresholds, u64),), (thresholds,)

    def phi(self, state: InternalState) -> Tensor:
        """RUN (N >= 2 and S == 0) as float 0/1 ``(n,)``."""
        if self.fusable:
            return run_flag_from_states(state[0])
        return is_run(state[0]).to(torch.float32)

    def concat_states(self, states: Sequence[InternalState]) -> InternalState:
        """Per-motor states ``(M, n)`` are joined along cells (dim 1), counts ``(n, 3)`` dim 0."""
        dim = 1 if self.fusable else 0
        return (torch.cat([s[0] for s in states], dim=dim),)

    def counts(self, state: InternalState) -> Tensor:
        """Motor counts ``n x 3`` (S, C, N) of a state."""
        return counts_from_states(state[0]) if self.fusable else state[0]

    def state_from_counts(self, counts: Tensor) -> InternalState:
        """A state with the given motor counts (``n x 3``; motors are exchangeable)."""
        m = int(self.params.n_motors)
        if counts.dim() != 2 or counts.shape[1] != 3 or bool((counts.sum(1) != m).any()):
            raise ValueError(f"motor counts must be (n, 3) with rows summing to n_motors={m}")
        if not self.fusable:
            return (counts.to(torch.int64),)
        return (states_from_counts(counts, m).contiguous(),)

    def classes(self, state: InternalState) -> Tensor:
        """Each cell's class (index into :attr:`class_names`: its phi and number of CCW
        motors) ``(n,)`` int64."""
        counts = self.counts(state).long()
        index = self._class_index.to(counts.device)
        return index[is_run(counts).long(), counts[:, N]]

    def expected_class_next(self, state: InternalState, x: Tensor, dt: float) -> Tensor:
        """Exact P(class after a window ``dt`` | this state, inputs ``x``) ``n x C`` float64:
        the K-lumps chain's expected label (:func:`class_probability_after`)."""
        motors = state[0] if self.fusable else states_from_counts(state[0], self.params.n_motors)
        k_plus, k_minus = self.rates(x)
        transition = motor_transition_matrix(k_plus, k_minus, dt, self.params.mu)
        return class_probability_after(motors, transition, self._class_index)

    def expected_phi_next(self, state: InternalState, x: Tensor, dt: float) -> Tensor:
        """Exact P(RUN after a window ``dt`` | this state, inputs ``x``) ``(n,)`` float64: each
        motor's row of its closed-form exp(Q dt) at the cell's rates (the expected label of
        the window, :func:`~surrogate.models.ecoli.motors.run_probability_after`)."""
        motors = state[0] if self.fusable else states_from_counts(state[0], self.params.n_motors)
        k_plus, k_minus = self.rates(x)
        return run_probability_after(
            motors, motor_transition_matrix(k_plus, k_minus, dt, self.params.mu)
        )

    # -- exact lumped psi ------------------------------------------------------------------------
    def exact_psi(self, signal: Tensor, dt: float) -> Tensor:
        """Exact P(RUN after dt | TUMBLE / RUN now) ``n x 2`` at signals dG (``n x 1``)."""
        k_plus, k_minus = rates_from_delta_g(signal[:, 0], self.params)
        return exact_run_probability(k_plus, k_minus, dt, self.params)

    def exact_age_psi(self, signal: Tensor, dt: float, max_steps: int) -> Tensor:
        """Exact P(RUN after dt | TUMBLE / RUN now, k windows since the last switch),
        ``n x 2 x (max_steps + 1)``, at signals dG (``n x 1``) (adapted cells; see
        :func:`surrogate.ctmc.lumped.lumped_age_psi`)."""
        k_plus, k_minus = rates_from_delta_g(signal[:, 0], self.params)
        space = population_space(self.params.n_motors)
        q = space.generator(rate_constants(k_plus.double(), k_minus.double(), self.params))
        return lumped_age_psi(q, is_run(space.states), dt, max_steps)

    def exact_class_step(self, signal: Tensor, dt: float) -> Tensor:
        """Exact one-window class-to-class law of adapted cells ``n x C x C`` float64 at
        signals dG (``n x 1``) (:func:`surrogate.ctmc.lumped.lumped_class_step`)."""
        k_plus, k_minus = rates_from_delta_g(signal[:, 0], self.params)
        space = population_space(self.params.n_motors)
        q = space.generator(rate_constants(k_plus.double(), k_minus.double(), self.params))
        states = space.states
        classes = self._class_index[is_run(states).long(), states[:, N]]
        return lumped_class_step(q, classes, len(self.class_names), dt)

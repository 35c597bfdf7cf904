"""Flagella / motor population CTMC of one cell: species S (semicoiled, CW), C (curly, CW),
N (normal, CCW) with reactions S -> C (mu), C -> N (k+), S -> N (k+), N -> S (k-).

The cell RUNs iff N >= 2 and S == 0. Motors are independent first-order units, so the state
after a window dt can be sampled exactly either with the general SSA or from each motor's
transition matrix exp(Q dt) (``model.motor_sampler``); both are exact in distribution.

Closed form of exp(Q dt) for one motor
--------------------------------------
With A = mu + k+ (exit rate of S) and B = k+ + k- (the CW <-> CCW relaxation rate), the
generator's eigenvalues are 0, -A and -B (its characteristic polynomial is
lambda (lambda + A)(lambda + B)), so they are always real. Two facts give P = exp(Q dt):

* CW = {S, C} is lumpable: both S and C leave for N at rate k+, so CW/CCW is a two-state chain
  and P_SN = P_CN = (k+/B)(1 - e^{-B dt}), P_NN = 1 - (k-/B)(1 - e^{-B dt}).
* S is entered only from N, so p_S(t) = p_S(0) e^{-A t} + int_0^t e^{-A (t-s)} k- p_N(s) ds,
  with p_N(s) from the two-state chain. With g = (1 - e^{-A dt}) / A and
  f = (e^{-B dt} - e^{-A dt}) / (A - B) (> 0; = dt e^{-A dt} when A = B):
  P_SS = e^{-A dt} + (k+ k- / B)(g - f), P_CS = (k+ k- / B)(g - f), P_NS = (k+ k- / B) g + (k-^2 / B) f.

Every term is evaluated with ``expm1`` in float64 and no difference of nearly equal large
numbers, so it is accurate to ~1e-16 absolute for any rates (k+ ~ 3e4/s makes B dt ~ 1500;
e^{-1500} underflows harmlessly to 0). It is checked against ``scipy.linalg.expm`` in the tests.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from surrogate.ctmc import (
    ReactionNetwork,
    gillespie,
    sample_counts,
    unit_generator,
    unit_transition_matrix,
)
from surrogate.ctmc.lumped import StateSpace, lumped_psi
from surrogate.models.ecoli import formulas
from surrogate.models.ecoli.formulas import C, N, S
from surrogate.models.ecoli.parameters import EcoliParameters

SPECIES = ("S", "C", "N")
MOTOR_DTYPE = torch.float32  # dtype of per-motor state tensors (values 0., 1., 2.)

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


def is_run_states(motors: Tensor) -> Tensor:
    """phi_RUN from per-motor states ``motors`` (M, n) (0 = S, 1 = C, 2 = N) -> bool (n,)."""
    return run_flag_from_states(motors) > 0


def run_flag_from_states(motors: Tensor) -> Tensor:
    """phi_RUN as float 0/1 (n,) (no boolean algebra: cheaper in compiled kernels): the N count
    as a sum of :func:`~surrogate.models.ecoli.formulas.ccw` and "no S" from the lowest state,
    plain float reductions along the motor axis (several times faster eagerly than counting
    boolean masks)."""
    return formulas.run_flag(formulas.ccw(motors).sum(0), motors.amin(0))


def counts_from_states(motors: Tensor) -> Tensor:
    """Motor counts (n, 3) (S, C, N) from per-motor states (M, n)."""
    return torch.stack([(motors == s).sum(0) for s in (S, C, N)], dim=-1)


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


def sample_stationary_states(k_plus: Tensor, k_minus: Tensor, p: EcoliParameters) -> Tensor:
    """Per-motor states (M, n), each motor drawn independently from its stationary law.

    States are stored as float32 0., 1., 2. (S, C, N): compiled kernels compare and blend them
    in the same SIMD lanes as the float thresholds (uint8 forces scalar byte stores).
    """
    pi = stationary_motor_distribution(k_plus.double(), k_minus.double(), p)  # (n, 3)
    u = torch.rand((p.n_motors, pi.shape[0]), dtype=torch.float64, device=pi.device)
    # inverse CDF; 1 - u in (0, 1] so a state of probability 0 is never drawn
    v = 1.0 - u
    c1, c2 = pi[:, S], pi[:, S] + pi[:, C]
    return ((v > c1).to(MOTOR_DTYPE) + (v > c2).to(MOTOR_DTYPE)).contiguous()


def motor_transition_terms(
    k_plus: Tensor, k_minus: Tensor, dt: float, mu: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The six independent entries of one motor's exp(Q dt), elementwise, in float64:
    (P_SS, P_CS, P_NS, P_SN = P_CN, P_NN, 1 - P_NN). P_xC = 1 - P_xS - P_xN.

    See the module docstring for the derivation (the formula:
    :func:`surrogate.models.ecoli.formulas.motor_transition_terms`); accurate to ~1e-16
    absolute for any rates.
    """
    return formulas.motor_transition_terms(k_plus, k_minus, dt, mu)


def motor_transition_matrix(k_plus: Tensor, k_minus: Tensor, dt: float, mu: float) -> Tensor:
    """exp(Q dt) of one motor, (..., 3, 3) float64 row-stochastic (states S, C, N), closed form."""
    p_ss, p_cs, p_ns, to_n, p_nn, from_n = motor_transition_terms(k_plus, k_minus, dt, mu)
    p_ns = torch.minimum(p_ns, from_n)
    rows = [
        torch.stack([p_ss, (1.0 - p_ss - to_n).clamp_min(0.0), to_n], -1),
        torch.stack([p_cs, (1.0 - p_cs - to_n).clamp_min(0.0), to_n], -1),
        torch.stack([p_ns, from_n - p_ns, p_nn], -1),
    ]
    return torch.stack(rows, -2)


def motor_thresholds(
    k_plus: Tensor, k_minus: Tensor, dt: float, mu: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Cumulative thresholds for sampling one motor's next state with one uniform u in [0, 1).

    A motor in state s moves to S if u < t1[s], to C if t1[s] <= u < t2[s], else to N, where
    t1 = P_sS and t2 = P_sS + P_sC = 1 - P_sN. Returns (t1_S, t1_C, t1_N, t2_CW, t2_N): t2 is
    1 - P_SN = 1 - P_CN for both CW states (lumpability) and 1 - P_NN for N.
    """
    return formulas.motor_thresholds(k_plus, k_minus, dt, mu)


def sample_motor_states(motors: Tensor, thresholds: Tensor, u: Tensor) -> Tensor:
    """Next state of every motor from per-cell thresholds, one uniform per motor.

    ``motors`` (M, n) states 0 = S, 1 = C, 2 = N (float, see :data:`MOTOR_DTYPE`);
    ``thresholds`` (5, n) = the rows of :func:`motor_thresholds` stacked; ``u`` (M, n) uniforms
    in [0, 1) (float64 gives the probabilities a 2^-53 resolution). Pure, fixed cost, no host
    sync: :func:`surrogate.models.ecoli.formulas.next_motor_state` over every motor.
    """
    return formulas.next_motor_state(motors, u.to(thresholds.dtype), *thresholds.unbind(0))


def motor_laws_after(motors: Tensor, transition: Tensor) -> Tensor:
    """Each motor's law over (S, C, N) after the window, ``M x n x 3``: its cell's
    ``transition`` row (``n x 3 x 3``) at its state (``motors``, ``M x n``)."""
    index = motors.long()  # (M, n)
    rows = transition.unsqueeze(0).expand(index.shape[0], -1, -1, -1)
    return rows.gather(2, index[..., None, None].expand(*index.shape, 1, 3)).squeeze(2)


def run_probability_after(motors: Tensor, transition: Tensor) -> Tensor:
    """P(RUN after the window | every motor's state now), ``(n,)`` float64: the expected RUN
    flag of the next window given the current configuration (a Rao-Blackwellised label).

    Motors move independently, motor i by the row of its cell's ``transition`` (``n x 3 x 3``,
    exp(Q dt)) at its state; RUN = no motor in S and at least two in N. With a_i = P(C) and
    b_i = P(N) after the window, P(RUN) = prod(a_i + b_i) - prod(a_i) - sum_i b_i prod_{j!=i} a_j,
    accumulated motor by motor (the generating polynomial's coefficients of N^0 and N^1).

    Args:
        motors: per-motor states ``M x n`` (0 = S, 1 = C, 2 = N), any dtype.
        transition: each cell's one-motor transition matrix ``n x 3 x 3`` (rows S, C, N).
    """
    after = motor_laws_after(motors, transition)
    no_s = torch.ones_like(after[0, :, 0])
    none_n = torch.ones_like(no_s)
    one_n = torch.zeros_like(no_s)
    for a, b in zip(after[..., C], after[..., N], strict=True):
        one_n = one_n * a + none_n * b
        none_n = none_n * a
        no_s = no_s * (a + b)
    return (no_s - none_n - one_n).clamp(0.0, 1.0)


def class_probability_after(motors: Tensor, transition: Tensor, index: Tensor) -> Tensor:
    """P(class after the window | every motor's state now) ``n x C`` float64: the K-lumps
    chain's expected label (see :func:`run_probability_after`), class = (phi, number of CCW
    motors) through ``index`` (:func:`class_index`).

    The law of (number in N, any in S) after the window, accumulated motor by motor over the
    ``2 x (M + 1)`` pairs (M multiply-adds of ``n x (M + 1)`` tensors).

    Args:
        motors: per-motor states ``M x n`` (0 = S, 1 = C, 2 = N), any dtype.
        transition: each cell's one-motor transition matrix ``n x 3 x 3`` (rows S, C, N).
        index: ``2 x (M + 1)`` int64 class of (phi, number of CCW motors), -1 where none.
    """
    after = motor_laws_after(motors, transition)
    m = after.shape[0]
    n = after.shape[1]
    # law[:, k, s]: k motors in N so far, s = 1 if any in S
    law = after.new_zeros(n, m + 1, 2)
    law[:, 0, 0] = 1.0
    for p in after:  # (n, 3): this motor's law after the window
        shifted = torch.zeros_like(law)
        shifted[:, 1:] = law[:, :-1] * p[:, N, None, None]
        to_s = law.sum(2) * p[:, S, None]  # any S from here on
        law = shifted + law * p[:, C, None, None]
        law[:, :, 1] += to_s
    n_ccw = torch.arange(m + 1, device=after.device)
    run = torch.stack([(n_ccw >= 2) & True, torch.zeros_like(n_ccw, dtype=torch.bool)], 1)
    classes = index.to(after.device)[run.long(), n_ccw[:, None].expand(-1, 2)]  # (M + 1, 2)
    out = after.new_zeros(n, int(index.max()) + 1)
    valid = classes >= 0
    out.index_add_(1, classes[valid], law[:, valid])
    return out


def states_from_counts(counts: Tensor, n_motors: int) -> Tensor:
    """Per-motor states ``M x n`` (float, see :data:`MOTOR_DTYPE`) with the given counts
    ``n x 3`` (S, C, N; motors are exchangeable, so any order of them)."""
    cum = counts.to(torch.int64).cumsum(-1)  # (n, 3)
    slots = torch.arange(int(n_motors), device=counts.device)
    return (slots[:, None, None] >= cum[None, :, :]).sum(-1).clamp_max(2).to(MOTOR_DTYPE)


def step_motor_states(
    motors: Tensor, k_plus: Tensor, k_minus: Tensor, dt: float, mu: float, u: Tensor
) -> Tensor:
    """Exact sample of every motor's state after ``dt`` at fixed rates, one uniform per motor.

    ``motors`` (M, n) states 0 = S, 1 = C, 2 = N, ``k_plus``/``k_minus`` (n,), ``u`` (M, n)
    uniforms in [0, 1) (float64 for a 2^-53 resolution of the probabilities).
    """
    thresholds = torch.stack(motor_thresholds(k_plus, k_minus, dt, mu))
    return sample_motor_states(motors, thresholds, u)


def advance_motors(
    counts: Tensor, k_plus: Tensor, k_minus: Tensor, dt: float, p: EcoliParameters
) -> Tensor:
    """Exact sample of the motor counts after a window ``dt`` with rates fixed over it.

    ``transition_matrix``: each motor moves by its closed-form exp(Q dt) (``sample_counts``);
    ``ssa``: the general Gillespie SSA on the network.
    """
    if p.motor_sampler == "ssa":
        rates = rate_constants(k_plus.double(), k_minus.double(), p)
        return gillespie(FLAGELLA_NETWORK, counts, rates, dt)
    transition = motor_transition_matrix(k_plus, k_minus, dt, p.mu)
    return sample_counts(counts, transition)


def generic_transition_matrix(
    k_plus: Tensor, k_minus: Tensor, dt: float, p: EcoliParameters
) -> Tensor:
    """exp(Q dt) by the generic path (generator + ``torch.linalg.matrix_exp``), for checks."""
    rates = rate_constants(k_plus.double(), k_minus.double(), p)
    return unit_transition_matrix(unit_generator(FLAGELLA_NETWORK, rates), dt)


@functools.lru_cache(maxsize=8)
def motor_classes(n_motors: int) -> tuple[tuple[int, int], ...]:
    """The K-lumps classes of a cell's motors: every reachable (phi, number of CCW motors),
    sorted (tumbles first). With 4 motors: tumble with 0-3 CCW, run with 2-4 CCW (7 classes)."""
    states = population_space(n_motors).states
    return tuple(sorted({(int(r), int(s[N])) for r, s in zip(is_run(states), states, strict=True)}))


def class_index(n_motors: int) -> Tensor:
    """``2 x (n_motors + 1)`` int64: the class of (phi, number of CCW motors), -1 if none."""
    index = torch.full((2, int(n_motors) + 1), -1, dtype=torch.int64)
    for k, (run, n_ccw) in enumerate(motor_classes(n_motors)):
        index[run, n_ccw] = k
    return index


def population_space(n_motors: int) -> StateSpace:
    """The motor population's states (counts S, C, N summing to ``n_motors``): 15 for 4 motors."""
    return StateSpace.enumerate(FLAGELLA_NETWORK, torch.tensor([0, 0, int(n_motors)]))


def exact_run_probability(k_plus: Tensor, k_minus: Tensor, dt: float, p: EcoliParameters) -> Tensor:
    """Exact lumped P(RUN after dt | TUMBLE / RUN now), ``n x 2``, at rates ``k_plus``/``k_minus``
    (``(n,)``): the motor population's generator, started from its stationary law restricted to
    the current lump (:func:`surrogate.ctmc.lumped.lumped_psi`)."""
    space = population_space(p.n_motors)
    q = space.generator(rate_constants(k_plus.double(), k_minus.double(), p))
    return lumped_psi(q, is_run(space.states), dt)

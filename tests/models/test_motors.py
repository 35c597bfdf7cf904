"""The closed-form motor sampler: exp(Q dt) against high-precision references, and the sampled
motor states against the exact law and against the general SSA.

Statistical checks reuse the helpers of ``tests/ctmc`` with fixed seeds: chi-square p > 1e-3
after merging bins with expected count < 5 (a correct sampler fails with probability 1e-3 had
the seed been random) and a total-variation bound exceeded with probability <= 1e-6.
"""

from __future__ import annotations

import itertools
import math

import mpmath
import numpy as np
import pytest
import scipy.linalg
import torch

from surrogate.ctmc import gillespie
from surrogate.models.ecoli import EcoliParameters, motor_rates
from surrogate.models.ecoli.internal import MotorInternalModel
from surrogate.models.ecoli.motors import (
    FLAGELLA_NETWORK,
    MOTOR_DTYPE,
    counts_from_states,
    generic_transition_matrix,
    is_run,
    is_run_states,
    motor_classes,
    motor_thresholds,
    motor_transition_matrix,
    rate_constants,
    run_flag_from_states,
    sample_motor_states,
    sample_stationary_states,
    step_motor_states,
)

from ..ctmc.test_ssa import N_CHAINS, P_MIN, assert_matches_distribution, state_counts
from ..ctmc.test_transition import (
    RATE_CASES,
    merged_contingency_pvalue,
    multinomial_sum_distribution,
)

P = EcoliParameters()
DT = 0.05
# k+ from omega e^-10 to omega e^10 (the model's whole range, ~6e-5 .. 2.9e4 /s) and beyond,
# k- independently; plus the degenerate case k- = mu (the two non-zero eigenvalues coincide)
GRID = np.logspace(-5, 4.6, 25)
RATES = [(kp, km) for kp in GRID for km in GRID] + [(1.0, 5.0), (3e4, 5.0), (2.0, 5.0 + 1e-13)]


def _rates(pairs) -> tuple[torch.Tensor, torch.Tensor]:
    kp, km = zip(*pairs, strict=True)
    return torch.tensor(kp, dtype=torch.float64), torch.tensor(km, dtype=torch.float64)


def _generator(kp: float, km: float, mu: float = P.mu) -> list[list[float]]:
    return [[-(mu + kp), mu, kp], [0.0, -kp, kp], [km, 0.0, -km]]


@pytest.mark.parametrize("dt", [0.002, DT, 1.0])
def test_closed_form_matches_50_digit_expm(dt: float) -> None:
    """Against mpmath's expm at 50 digits: ~1e-16 absolute everywhere, stiff rates included."""
    pairs = RATES[::7] + RATES[-3:]
    p = motor_transition_matrix(*_rates(pairs), dt, P.mu)
    mpmath.mp.dps = 50
    worst = 0.0
    for (kp, km), got in zip(pairs, p, strict=True):
        ref = mpmath.expm(mpmath.matrix(_generator(kp, km)) * dt)
        ref = np.array(ref.tolist(), dtype=float)
        worst = max(worst, float(np.abs(got.numpy() - ref).max()))
    assert worst < 1e-14, worst


def test_closed_form_matches_scipy_and_torch_expm() -> None:
    """Against scipy.linalg.expm and torch.linalg.matrix_exp over the whole rate grid; those are
    accurate to ~1e-12 (their scaling-and-squaring round-off at B dt ~ 1500), hence 1e-10."""
    kp, km = _rates(RATES)
    p = motor_transition_matrix(kp, km, DT, P.mu)
    assert p.dtype == torch.float64
    assert (p >= 0).all()
    torch.testing.assert_close(p.sum(-1), torch.ones(len(RATES), 3, dtype=torch.float64))
    generic = generic_transition_matrix(kp, km, DT, P)
    torch.testing.assert_close(p, generic, rtol=0, atol=1e-10)
    for i in range(0, len(RATES), 5):
        ref = scipy.linalg.expm(np.array(_generator(*RATES[i])) * DT)
        np.testing.assert_allclose(p[i].numpy(), ref, rtol=0, atol=1e-10)


def test_thresholds_are_cumulative_rows() -> None:
    kp, km = _rates(RATES)
    p = motor_transition_matrix(kp, km, DT, P.mu)
    t1_s, t1_c, t1_n, t2_cw, t2_n = motor_thresholds(kp, km, DT, P.mu)
    torch.testing.assert_close(torch.stack([t1_s, t1_c, t1_n], -1), p[..., 0], rtol=0, atol=0)
    torch.testing.assert_close(t2_cw, 1.0 - p[:, 0, 2], rtol=0, atol=1e-15)
    torch.testing.assert_close(t2_cw, 1.0 - p[:, 1, 2], rtol=0, atol=1e-15)
    torch.testing.assert_close(t2_n, 1.0 - p[:, 2, 2], rtol=0, atol=1e-15)
    assert bool((t1_s <= t2_cw).all() and (t1_c <= t2_cw).all() and (t1_n <= t2_n).all())


def _motors(start: tuple[int, int, int], n: int) -> torch.Tensor:
    """(M, n) motor states with ``start`` = (S, C, N) counts in every cell."""
    states = [s for s, c in enumerate(start) for _ in range(c)]
    return torch.tensor(states, dtype=MOTOR_DTYPE)[:, None].expand(-1, n).contiguous()


@pytest.mark.parametrize("case", list(RATE_CASES))
def test_per_motor_sampler_matches_the_exact_law(case: str) -> None:
    """Counts after one window, from (S, C, N) = (1, 1, 2): the exact law is the sum of
    per-motor multinomials with the closed-form P."""
    kp, km = RATE_CASES[case]
    start = (1, 1, 2)
    n = N_CHAINS
    k_plus = torch.full((n,), kp, dtype=torch.float64)
    k_minus = torch.full((n,), km, dtype=torch.float64)
    gen = torch.Generator().manual_seed(31)
    u = torch.rand((sum(start), n), dtype=torch.float64, generator=gen)
    new = step_motor_states(_motors(start, n), k_plus, k_minus, DT, P.mu, u)
    p = motor_transition_matrix(k_plus[:1], k_minus[:1], DT, P.mu)[0].numpy()
    states, law = multinomial_sum_distribution(start, p)
    assert_matches_distribution(counts_from_states(new), states, law)


@pytest.mark.parametrize("case", list(RATE_CASES))
def test_per_motor_sampler_agrees_with_the_ssa(case: str) -> None:
    """Two-sample chi-square of the counts after 4 windows: closed-form sampler vs Gillespie."""
    kp, km = RATE_CASES[case]
    start = (1, 1, 2)
    n = N_CHAINS
    k_plus = torch.full((n,), kp, dtype=torch.float64)
    k_minus = torch.full((n,), km, dtype=torch.float64)
    torch.manual_seed(41)
    motors = _motors(start, n)
    for _ in range(4):
        u = torch.rand(motors.shape, dtype=torch.float64)
        motors = step_motor_states(motors, k_plus, k_minus, DT, P.mu, u)
    counts = torch.tensor(start).expand(n, -1)
    rates = rate_constants(k_plus, k_minus, P)
    gen = torch.Generator().manual_seed(42)
    for _ in range(4):
        counts = gillespie(FLAGELLA_NETWORK, counts, rates, DT, gen)
    states = [s for s in itertools.product(range(5), repeat=3) if sum(s) == sum(start)]
    by_closed_form = state_counts(counts_from_states(motors), states)
    by_ssa = state_counts(counts, states)
    pvalue, bins = merged_contingency_pvalue(by_closed_form, by_ssa)
    if case == "fast":  # all motors in N up to ~1e-5 (see tests/ctmc/test_transition.py)
        assert bins == 1
        assert by_closed_form[states.index((0, 0, 4))] >= n - 20
    else:
        assert bins >= 3
        assert pvalue > P_MIN, f"two-sample chi-square p = {pvalue:.3g} over {bins} bins"


def test_eager_and_compiled_formulations_are_identical(monkeypatch) -> None:
    """sample_motor_states gathers eagerly and blends with where under torch.compile."""
    n = 5000
    gen = torch.Generator().manual_seed(3)
    motors = torch.randint(0, 3, (6, n), generator=gen).to(MOTOR_DTYPE)
    kp = torch.exp(torch.empty(n, dtype=torch.float64).uniform_(-10, 10, generator=gen))
    thresholds = torch.stack(motor_thresholds(kp, 1.69 / kp, DT, P.mu))
    u = torch.rand((6, n), dtype=torch.float64, generator=gen)
    eager = sample_motor_states(motors, thresholds, u)
    monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
    blended = sample_motor_states(motors, thresholds, u)
    assert torch.equal(eager, blended)


def test_run_property_from_states_and_counts() -> None:
    motors = torch.tensor(list(itertools.product(range(3), repeat=4)), dtype=MOTOR_DTYPE).T
    counts = counts_from_states(motors)
    expected = is_run(counts)
    assert torch.equal(is_run_states(motors), expected)
    assert torch.equal(run_flag_from_states(motors), expected.to(MOTOR_DTYPE))
    assert expected.any() and not expected.all()


def test_stationary_states_follow_the_stationary_law() -> None:
    torch.manual_seed(5)
    n = 50_000
    m = torch.full((n,), 2.2, dtype=torch.float64)
    L = torch.zeros(n, dtype=torch.float64)
    k_plus, k_minus = motor_rates(m, L, P)
    motors = sample_stationary_states(k_plus, k_minus, P)
    assert motors.shape == (P.n_motors, n) and motors.dtype == MOTOR_DTYPE
    w = np.array([1.0, P.mu / k_plus[0].item(), (P.mu + k_plus[0].item()) / k_minus[0].item()])
    pi = w / w.sum()
    observed = np.bincount(motors.long().reshape(-1).numpy(), minlength=3) / motors.numel()
    se = np.sqrt(pi * (1 - pi) / motors.numel())
    assert np.all(np.abs(observed - pi) < 5 * se)


def test_internal_model_counts_round_trip() -> None:
    torch.manual_seed(6)
    internal = MotorInternalModel(P)
    x = torch.stack([torch.full((1000,), 2.2), torch.zeros(1000)], -1)
    state = internal.initial_state(x)
    counts = internal.counts(state)
    assert counts.shape == (1000, 3) and bool((counts.sum(1) == P.n_motors).all())
    assert torch.equal(internal.phi(state) > 0, is_run(counts))
    assert torch.equal(internal.counts(internal.state_from_counts(counts.flip(0))), counts.flip(0))
    ssa = MotorInternalModel(EcoliParameters(motor_sampler="ssa"))
    (ssa_counts,) = ssa.initial_state(x)
    assert not ssa.fusable and ssa_counts.shape == (1000, 3)


def test_internal_rates_are_the_model_rates() -> None:
    """The rates the simulation uses come from the same formula chain as motor_rates."""
    gen = torch.Generator().manual_seed(7)
    m = 8.0 * torch.rand(10_000, generator=gen)
    L = 0.2 * torch.rand(10_000, generator=gen)
    k_plus, k_minus = MotorInternalModel(P).rates(torch.stack([m, L], -1))
    ref_plus, ref_minus = motor_rates(m, L, P)
    assert k_plus.dtype == torch.float64
    assert torch.equal(k_plus, ref_plus) and torch.equal(k_minus, ref_minus)


@pytest.mark.parametrize(("m", "L"), [(2.2, 0.0), (2.4, 0.0), (2.6, 0.02)])
def test_fused_window_agrees_with_the_ssa_window(m: float, L: float) -> None:
    """The internal model's fused window (closed form, as the simulator runs it) against the
    SSA sampler: motor counts after 10 windows at fixed inputs, two-sample chi-square."""
    n = N_CHAINS
    x = torch.stack([torch.full((n,), m), torch.full((n,), L)], -1)
    torch.manual_seed(8)
    fused = MotorInternalModel(P)
    state = fused.initial_state(x)
    ssa = MotorInternalModel(EcoliParameters(motor_sampler="ssa"))
    ssa_state = (fused.counts(state),)  # the same start
    for _ in range(10):
        u64 = torch.rand((P.n_motors, n), dtype=torch.float64)
        state, _ = fused.fused_advance(state, x, DT, torch.empty(0, n), u64)
        ssa_state = ssa.advance(ssa_state, x, DT)
    states = [s for s in itertools.product(range(5), repeat=3) if sum(s) == P.n_motors]
    pvalue, bins = merged_contingency_pvalue(
        state_counts(fused.counts(state), states), state_counts(ssa.counts(ssa_state), states)
    )
    assert bins >= 3
    assert pvalue > P_MIN, f"two-sample chi-square p = {pvalue:.3g} over {bins} bins"


# ----------------------------------------------------------------------------------------------
# expected labels


def test_run_probability_after_is_the_sum_over_every_end_configuration() -> None:
    """P(RUN after | motors now) against brute force: every one of the 3^M end configurations
    weighted by the product of the motors' transition rows, summed where RUN holds."""
    from surrogate.models.ecoli.motors import run_probability_after

    gen = torch.Generator().manual_seed(0)
    n, m = 64, 4
    motors = torch.randint(0, 3, (m, n), generator=gen).to(MOTOR_DTYPE)
    kp, km = _rates(RATES[:: max(1, len(RATES) // n)][:n])
    transition = motor_transition_matrix(kp, km, DT, P.mu)
    got = run_probability_after(motors, transition)
    want = torch.zeros(n, dtype=torch.float64)
    cells = torch.arange(n)
    for ends in itertools.product(range(3), repeat=m):
        weight = torch.ones(n, dtype=torch.float64)
        for i, end in enumerate(ends):
            weight = weight * transition[cells, motors[i].long(), end]
        run = ends.count(2) >= 2 and 0 not in ends
        want += weight if run else 0.0
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)


def test_expected_labels_average_to_the_outcomes() -> None:
    """From one set of states, the mean of 40 sampled windows' RUN flags per cell agrees with
    the expected label within 5 standard errors, pooled per origin and per cell."""
    model = MotorInternalModel(P)
    gen = torch.Generator().manual_seed(1)
    n = 4000
    x = torch.stack([2.2 + 0.4 * torch.randn(n, generator=gen), torch.zeros(n)], 1)
    torch.manual_seed(1)
    state = model.initial_state(x)
    expected = model.expected_phi_next(state, x, DT)
    outcomes = torch.stack([model.phi(model.advance(state, x, DT)) for _ in range(40)]).double()
    phi = model.phi(state)
    for origin in (0, 1):
        rows = phi == origin
        mean, p = outcomes[:, rows].mean(), expected[rows].mean()
        se = math.sqrt(float((expected[rows] * (1 - expected[rows])).sum()) / 40) / int(rows.sum())
        assert abs(float(mean - p)) < 5 * se, (origin, float(mean), float(p), se)
    # and it carries information beyond the origin: the per-cell frequencies follow it
    per_cell = outcomes.mean(0)
    assert float(torch.corrcoef(torch.stack([per_cell, expected]))[0, 1]) > 0.9


def test_expected_labels_from_counts_equal_those_from_states() -> None:
    """The SSA motor sampler (counts) gives the same expected labels as per-motor states."""
    x = torch.tensor([[2.0, 0.0], [2.4, 0.01], [1.8, 0.0]]).repeat(20, 1)
    states = MotorInternalModel(P)
    counts = MotorInternalModel(EcoliParameters(motor_sampler="ssa"))
    torch.manual_seed(2)
    state = states.initial_state(x)
    by_counts = (counts_from_states(state[0]),)
    torch.testing.assert_close(
        states.expected_phi_next(state, x, DT), counts.expected_phi_next(by_counts, x, DT)
    )


def test_expected_class_laws_are_the_sum_over_every_end_configuration() -> None:
    """K lumps' expected label: P(class after the window | every motor now) equals the brute
    sum over the 3^M end configurations mapped to (phi, number of CCW motors), to 1e-12; its
    lumps sum to the expected RUN label; and from counts it is the same as from states."""
    model = MotorInternalModel(P)
    gen = torch.Generator().manual_seed(3)
    n = 300
    x = torch.stack([2.2 + 0.5 * torch.randn(n, generator=gen), torch.zeros(n)], 1)
    torch.manual_seed(3)
    state = model.initial_state(x)
    got = model.expected_class_next(state, x, DT)
    kp, km = model.rates(x)
    transition = motor_transition_matrix(kp, km, DT, P.mu)
    motors, cells = state[0], torch.arange(n)
    keys = list(motor_classes(P.n_motors))
    want = torch.zeros(n, len(keys), dtype=torch.float64)
    for ends in itertools.product(range(3), repeat=P.n_motors):
        weight = torch.ones(n, dtype=torch.float64)
        for i, end in enumerate(ends):
            weight = weight * transition[cells, motors[i].long(), end]
        run = int(ends.count(2) >= 2 and 0 not in ends)
        want[:, keys.index((run, ends.count(2)))] += weight
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)
    run_classes = torch.tensor(model.class_lumps, dtype=torch.bool)
    torch.testing.assert_close(got[:, run_classes].sum(1), model.expected_phi_next(state, x, DT))
    by_counts = MotorInternalModel(EcoliParameters(motor_sampler="ssa"))
    torch.testing.assert_close(
        by_counts.expected_class_next((counts_from_states(state[0]),), x, DT), got
    )

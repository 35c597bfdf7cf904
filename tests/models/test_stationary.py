"""Stationary behaviour of the motor pCTMC at fixed inputs (m, L), through the model's sampler."""

from __future__ import annotations

import math

import pytest
import torch

from surrogate.models.ecoli import EcoliParameters, advance_motors, is_run, motor_rates
from surrogate.models.ecoli.signalling import adapted_methylation

CASES = [(0.0, None), (0.05, None), (0.0, 2.0), (0.02, 2.8)]  # (L, m); m None = adapted m0(L)


@pytest.mark.parametrize("sampler", ["transition_matrix", "ssa"])
@pytest.mark.parametrize(("L", "m"), CASES)
def test_stationary_cw_bias_and_run_probability(sampler: str, L: float, m: float | None) -> None:
    torch.manual_seed(11)
    p = EcoliParameters(motor_sampler=sampler)
    n = 10_000
    Lt = torch.full((n,), L, dtype=torch.float64)
    mt = adapted_methylation(Lt, p) if m is None else torch.full((n,), m, dtype=torch.float64)
    k_plus, k_minus = motor_rates(mt, Lt, p)
    counts = torch.zeros(n, 3, dtype=torch.int64)
    counts[:, 2] = p.n_motors  # all CCW (N): far from stationary
    # 5 s of windows: relaxation times are 1/(k+ + k-) <= 0.6 s and 1/mu = 0.2 s (e^-8 left)
    for _ in range(100):
        counts = advance_motors(counts, k_plus, k_minus, 0.05, p)
    bias = (k_minus / (k_plus + k_minus))[0].item()
    cw = counts[:, :2].sum().item() / (n * p.n_motors)
    # motors of different cells are independent and each motor's CW indicator is Bernoulli(bias)
    # at stationarity: 5 binomial standard errors (two-sided false alarm ~6e-7)
    se = math.sqrt(bias * (1 - bias) / (n * p.n_motors))
    assert cw == pytest.approx(bias, abs=5 * se + 1e-12)
    # P(RUN) from the product of per-motor stationary laws pi ~ (1, mu/k+, (mu+k+)/k-):
    # RUN iff S == 0 and N >= 2, i.e. all motors in C or N with at least two in N
    kp, km = k_plus[0].item(), k_minus[0].item()
    w = [1.0, p.mu / kp, (p.mu + kp) / km]
    _, pi_c, pi_n = (x / sum(w) for x in w)
    M = p.n_motors
    p_run = sum(math.comb(M, j) * pi_n**j * pi_c ** (M - j) for j in range(2, M + 1))
    run = is_run(counts).double().mean().item()
    assert run == pytest.approx(p_run, abs=5 * math.sqrt(p_run * (1 - p_run) / n) + 1e-12)

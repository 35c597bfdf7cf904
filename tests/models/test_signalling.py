"""Signalling layer: values from the parameter sheet, adaptation, OU relaxation."""

from __future__ import annotations

import math

import pytest
import torch

from surrogate.models.ecoli import (
    EcoliParameters,
    adapted_methylation,
    cheyp,
    cw_bias,
    motor_rates,
    ou_step,
)

P = EcoliParameters()


def test_constants_from_parameter_sheet() -> None:
    # ecoli-parameters.md: m0(0) ~ 2.199, sigma_m ~ 0.0213, CW bias ~ 0.22 at Yp* = 2.7
    assert adapted_methylation(torch.tensor(0.0, dtype=torch.float64), P).item() == pytest.approx(
        2.1987, abs=5e-4
    )
    assert P.sigma_m == pytest.approx(0.1 / (8.55 * (1 - 2.7 / 6.0)), rel=1e-12)
    assert P.sigma_m == pytest.approx(0.0213, abs=1e-4)
    x = 2.7 / (2.7 + 3.06)
    assert P.cw_bias_adapted == pytest.approx(1 / (1 + math.exp(2 * (10 - 20 * x))), rel=1e-12)
    assert P.cw_bias_adapted == pytest.approx(0.2227, abs=5e-4)


def test_yp_formula_against_hand_computation() -> None:
    m, L = 2.5, 0.03
    tar = ((1 + L / 0.02) / (1 + L / 0.5)) ** 6
    tsr = ((1 + L / 100.0) / (1 + L / 1e6)) ** 13  # K_TSR_on in the denominator (typo fixed)
    expected = 6.0 / (1 + math.exp(19 - 8.55 * m) * tar * tsr)
    got = cheyp(
        torch.tensor(m, dtype=torch.float64), torch.tensor(L, dtype=torch.float64), P
    ).item()
    assert got == pytest.approx(expected, rel=1e-12)


def test_motor_rates() -> None:
    L = torch.tensor([0.0, 0.01, 0.1], dtype=torch.float64)
    m = torch.tensor([0.0, 2.2, 4.0], dtype=torch.float64)
    kp, km = motor_rates(m, L, P)
    assert torch.allclose(kp * km, torch.full_like(kp, 1.3**2))  # k+ k- = omega^2
    # m = 0 at L = 0: Yp ~ 0, so k+ ~ omega e^10 ~ 2.86e4 /s (far above 1/dt)
    assert kp[0].item() == pytest.approx(1.3 * math.exp(10.0), rel=1e-3)
    # at the adapted level the CW bias k-/(k+ + k-) is mb0
    m0 = adapted_methylation(L, P)
    kp, km = motor_rates(m0, L, P)
    assert torch.allclose(km / (kp + km), torch.full_like(kp, P.cw_bias_adapted), rtol=1e-10)
    assert torch.allclose(cw_bias(m0, L, P), torch.full_like(kp, P.cw_bias_adapted), rtol=1e-10)


@pytest.mark.parametrize("L", [0.0, 1e-3, 0.02, 0.1, 1.0])
def test_adapted_methylation_gives_adapted_cheyp(L: float) -> None:
    Lt = torch.tensor(L, dtype=torch.float64)
    assert cheyp(adapted_methylation(Lt, P), Lt, P).item() == pytest.approx(2.7, rel=1e-10)


def test_m0_increases_with_ligand() -> None:
    L = torch.linspace(0, 0.1, 50, dtype=torch.float64)
    assert bool((adapted_methylation(L, P).diff() > 0).all())


def _relax(m: torch.Tensor, L: torch.Tensor, seconds: float, dt: float = 0.05) -> torch.Tensor:
    for _ in range(round(seconds / dt)):
        m = ou_step(m, L, dt, P, torch.randn_like(m))
    return m


def test_methylation_relaxes_to_m0_and_yp_to_adapted_level() -> None:
    torch.manual_seed(0)
    n, L = 20_000, 0.05
    Lt = torch.full((n,), L, dtype=torch.float64)
    m0 = adapted_methylation(Lt[:1], P).item()
    m = torch.full((n,), m0 + 0.5, dtype=torch.float64)  # far out of adaptation
    m = _relax(m, Lt, 10 * P.tau)  # 10 tau: the initial offset decays to 0.5 e^-10 ~ 2e-5
    # mean: s.e. = sigma_m / sqrt(n) ~ 1.5e-4; 5 s.e. plus the remaining offset
    assert m.mean().item() == pytest.approx(m0, abs=5 * P.sigma_m / math.sqrt(n) + 1e-4)
    # stationary s.d. of the OU is sigma_m (Euler bias O(dt/tau) ~ 0.2 %); s.e. of an s.d. ~ sd/sqrt(2n)
    assert m.std().item() == pytest.approx(P.sigma_m, rel=0.005 + 5 / math.sqrt(2 * n))
    yp = cheyp(m, Lt, P)
    # Yp is near-linear over +-sigma_m: |dYp/dm| sigma_m ~ 0.27 uM per cell, s.e. ~ 0.27/sqrt(n)
    assert yp.mean().item() == pytest.approx(2.7, abs=0.02)


def test_adaptation_after_a_step_in_ligand() -> None:
    torch.manual_seed(1)
    n = 5_000
    m = adapted_methylation(torch.zeros(n, dtype=torch.float64), P)
    L = torch.full((n,), 0.1, dtype=torch.float64)
    # attractant step: CheY-P collapses (cells run), then methylation restores it
    assert cheyp(m, L, P).mean().item() < 0.1 * 2.7
    m = _relax(m, L, 10 * P.tau)
    assert cheyp(m, L, P).mean().item() == pytest.approx(2.7, abs=0.02)
    # and the removal of attractant overshoots upwards before adapting back
    L0 = torch.zeros_like(L)
    assert cheyp(m, L0, P).mean().item() > 5.0
    m = _relax(m, L0, 10 * P.tau)
    assert cheyp(m, L0, P).mean().item() == pytest.approx(2.7, abs=0.02)


def test_ou_clamps_to_reference_range() -> None:
    m = torch.tensor([-1.0, 9.0], dtype=torch.float64)
    out = ou_step(
        m, torch.zeros(2, dtype=torch.float64), 0.05, P, torch.zeros(2, dtype=torch.float64)
    )
    assert out.min().item() >= 0.0 and out.max().item() <= 8.0

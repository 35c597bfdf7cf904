"""Receptor signalling: MWC activity, CheY-P, motor switching rates, adapted methylation, OU step.

Every formula is written once here; composite functions call the pieces, so the fused simulation
step, the exact lumped psi and the abstraction's features all share them. All functions are
elementwise over tensors of any shape (cells in the batch dimension). Formulas:
``ecoli-parameters.md`` (Sneddon et al. 2012); the paper's Yp formula has a typo in the TSR
factor, corrected here (K_TSR_on in the TSR denominator).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from surrogate.models.ecoli.parameters import EcoliParameters


def log_receptor_terms(ligand: Tensor, p: EcoliParameters) -> Tensor:
    """ln(TarTerm(L)) + ln(TsrTerm(L)), with TarTerm = ((1 + L/K_off) / (1 + L/K_on))^n_TAR."""
    tar = p.n_tar * (torch.log1p(ligand / p.k_tar_off) - torch.log1p(ligand / p.k_tar_on))
    tsr = p.n_tsr * (torch.log1p(ligand / p.k_tsr_off) - torch.log1p(ligand / p.k_tsr_on))
    return tar + tsr


def free_energy(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> Tensor:
    """Receptor-cluster free energy F(m, L) = eps0 + eps1 m + ln TarTerm + ln TsrTerm (kT)."""
    return p.eps0 + p.eps1 * methylation + log_receptor_terms(ligand, p)


def cheyp_from_free_energy(energy: Tensor, p: EcoliParameters) -> Tensor:
    """Yp = alpha a with the MWC activity a = 1 / (1 + exp(F)) (uM)."""
    return p.alpha * torch.sigmoid(-energy)  # stable for large |F|


def activity(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> Tensor:
    """MWC cluster activity a(m, L) = 1 / (1 + exp(F(m, L)))."""
    return torch.sigmoid(-free_energy(methylation, ligand, p))


def cheyp(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> Tensor:
    """CheY-P concentration Yp(m, L) = alpha * a(m, L) in uM."""
    return cheyp_from_free_energy(free_energy(methylation, ligand, p), p)


def delta_g(yp: Tensor, p: EcoliParameters) -> Tensor:
    """dG = g0/4 - (g1/2) Yp / (Yp + K_D) (kT): the motor's CW/CCW free-energy difference."""
    return p.g0 / 4.0 - p.g1 / 2.0 * yp / (yp + p.k_d)


def rates_from_delta_g(dg: Tensor, p: EcoliParameters) -> tuple[Tensor, Tensor]:
    """(k+, k-) = omega exp(+-dG) in 1/s, float64 (k+ reaches ~3e4/s at Yp = 0)."""
    dg = dg.to(torch.float64)
    return p.omega * torch.exp(dg), p.omega * torch.exp(-dg)


def motor_rates(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> tuple[Tensor, Tensor]:
    """Motor switching rates (k_plus: CW -> CCW, k_minus: CCW -> CW) in 1/s, float64."""
    return rates_from_delta_g(delta_g(cheyp(methylation, ligand, p), p), p)


def cw_bias(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> Tensor:
    """Stationary CW bias of one motor, k- / (k+ + k-) = 1 / (1 + exp(2 dG))."""
    return torch.sigmoid(-2.0 * delta_g(cheyp(methylation, ligand, p), p))


def adapted_methylation(ligand: Tensor, p: EcoliParameters) -> Tensor:
    """m0(L): the methylation level at which Yp(m0, L) = Yp* (full adaptation).

    m0(L) = [ln(alpha/Yp* - 1) - eps0 - ln TarTerm(L) - ln TsrTerm(L)] / eps1 (~2.199 at L = 0).
    """
    return (
        math.log(p.alpha / p.yp_adapted - 1.0) - p.eps0 - log_receptor_terms(ligand, p)
    ) / p.eps1


def ou_step(
    methylation: Tensor, ligand: Tensor, dt: float, p: EcoliParameters, noise: Tensor
) -> Tensor:
    """One Euler-Maruyama step of the methylation OU process, clamped to [m_min, m_max].

    m += (m0(L) - m) dt / tau + sigma_m sqrt(2 dt / tau) * noise, with ``noise`` ~ N(0, 1).
    Pure (returns a new tensor).
    """
    drift = (adapted_methylation(ligand, p) - methylation) * (dt / p.tau)
    diffusion = p.sigma_m * math.sqrt(2.0 * dt / p.tau) * noise
    return (methylation + drift + diffusion).clamp(p.m_min, p.m_max)

"""Receptor signalling: MWC activity, CheY-P, motor switching rates, adapted methylation, OU step.

The torch step's functions of (m, L) and the model's parameters: each evaluates the scalar
formulas of :mod:`surrogate.models.ecoli.formulas` (the one source the compiled kernel is made
from too) over tensors with the parameters' :func:`~surrogate.models.ecoli.formulas.constants`;
composite functions call the pieces, so the fused simulation step, the exact lumped psi and the
abstraction's features all share them. All functions are elementwise over tensors of any shape
(cells in the batch dimension).
"""

from __future__ import annotations

import torch
from torch import Tensor

from surrogate.models.ecoli import formulas
from surrogate.models.ecoli.formulas import constants
from surrogate.models.ecoli.parameters import EcoliParameters


def log_receptor_terms(ligand: Tensor, p: EcoliParameters) -> Tensor:
    """ln(TarTerm(L)) + ln(TsrTerm(L)), with TarTerm = ((1 + L/K_off) / (1 + L/K_on))^n_TAR."""
    return formulas.log_receptor_terms(ligand, constants(p))


def free_energy(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> Tensor:
    """Receptor-cluster free energy F(m, L) = eps0 + eps1 m + ln TarTerm + ln TsrTerm (kT)."""
    c = constants(p)
    return formulas.free_energy(methylation, formulas.log_receptor_terms(ligand, c), c)


def cheyp_from_free_energy(energy: Tensor, p: EcoliParameters) -> Tensor:
    """Yp = alpha a with the MWC activity a = 1 / (1 + exp(F)) (uM)."""
    return formulas.cheyp(formulas.activity(energy), constants(p))


def activity(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> Tensor:
    """MWC cluster activity a(m, L) = 1 / (1 + exp(F(m, L)))."""
    return formulas.activity(free_energy(methylation, ligand, p))


def cheyp(methylation: Tensor, ligand: Tensor, p: EcoliParameters) -> Tensor:
    """CheY-P concentration Yp(m, L) = alpha * a(m, L) in uM."""
    return cheyp_from_free_energy(free_energy(methylation, ligand, p), p)


def delta_g(yp: Tensor, p: EcoliParameters) -> Tensor:
    """dG = g0/4 - (g1/2) Yp / (Yp + K_D) (kT): the motor's CW/CCW free-energy difference."""
    return formulas.delta_g(yp, constants(p))


def rates_from_delta_g(dg: Tensor, p: EcoliParameters) -> tuple[Tensor, Tensor]:
    """(k+, k-) = omega exp(+-dG) in 1/s, float64 (k+ reaches ~3e4/s at Yp = 0)."""
    return formulas.rates(dg, p.omega)


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
    c = constants(p)
    return formulas.adapted_methylation(formulas.log_receptor_terms(ligand, c), c)


def ou_step(
    methylation: Tensor, ligand: Tensor, dt: float, p: EcoliParameters, noise: Tensor
) -> Tensor:
    """One Euler-Maruyama step of the methylation OU process, clamped to [m_min, m_max].

    m += (m0(L) - m) dt / tau + sigma_m sqrt(2 dt / tau) * noise, with ``noise`` ~ N(0, 1).
    Pure (returns a new tensor).
    """
    c = constants(p, dt)
    return formulas.ou_step(methylation, formulas.log_receptor_terms(ligand, c), noise, c)

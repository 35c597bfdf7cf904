"""E. coli chemotaxis: receptor signalling, methylation OU process and the flagella/motor pCTMC.

:class:`EcoliModel` is the plug-in (``model=ecoli``): :class:`MotorInternalModel` (the motors)
plus :class:`ChemotacticBody` (run-and-tumble movement, OU methylation).
"""

from __future__ import annotations

from surrogate.models.ecoli.body import ChemotacticBody
from surrogate.models.ecoli.internal import MotorInternalModel
from surrogate.models.ecoli.model import EcoliModel
from surrogate.models.ecoli.motors import (
    FLAGELLA_NETWORK,
    advance_motors,
    exact_run_probability,
    is_run,
    sample_stationary_counts,
    stationary_motor_distribution,
)
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli.reference import PAPER_QUANTITIES, PAPER_TABLE1, paper_table1_frame
from surrogate.models.ecoli.signalling import (
    activity,
    adapted_methylation,
    cheyp,
    cw_bias,
    free_energy,
    motor_rates,
    ou_step,
)
from surrogate.models.perturbation import DiscJump, random_in_disc

__all__ = [
    "FLAGELLA_NETWORK",
    "PAPER_QUANTITIES",
    "PAPER_TABLE1",
    "ChemotacticBody",
    "DiscJump",
    "EcoliModel",
    "EcoliParameters",
    "MotorInternalModel",
    "activity",
    "adapted_methylation",
    "advance_motors",
    "cheyp",
    "cw_bias",
    "exact_run_probability",
    "free_energy",
    "is_run",
    "motor_rates",
    "ou_step",
    "paper_table1_frame",
    "random_in_disc",
    "sample_stationary_counts",
    "stationary_motor_distribution",
]

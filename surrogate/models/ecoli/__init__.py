"""E. coli chemotaxis: receptor signalling, methylation OU process and the flagella/motor pCTMC."""

from __future__ import annotations

from surrogate.models.ecoli.motors import (
    FLAGELLA_NETWORK,
    advance_motors,
    is_run,
    sample_stationary_counts,
    stationary_motor_distribution,
)
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli.signalling import (
    activity,
    adapted_methylation,
    cheyp,
    cw_bias,
    motor_rates,
    ou_step,
)

__all__ = [
    "FLAGELLA_NETWORK",
    "EcoliParameters",
    "activity",
    "adapted_methylation",
    "advance_motors",
    "cheyp",
    "cw_bias",
    "is_run",
    "motor_rates",
    "ou_step",
    "sample_stationary_counts",
    "stationary_motor_distribution",
]

"""Agent models: the protocols the engine uses (:mod:`surrogate.models.base`), a generic
network-based internal model, and one subpackage per concrete model (``ecoli``).

Importing this package does not import a concrete model; configs select one by ``_target_``.
"""

from __future__ import annotations

from surrogate.models.base import (
    AgentBody,
    BodyState,
    InternalModel,
    InternalState,
    Model,
    Perturbation,
    Randoms,
    check_options,
)
from surrogate.models.network import NetworkInternalModel

__all__ = [
    "AgentBody",
    "BodyState",
    "InternalModel",
    "InternalState",
    "Model",
    "NetworkInternalModel",
    "Perturbation",
    "Randoms",
    "check_options",
]

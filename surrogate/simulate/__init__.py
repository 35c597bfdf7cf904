"""Population simulation: one outer time loop over any agent model, with a pluggable decision
layer (the full internal model, its exact lumped psi, or a learned abstraction, with or without
a switch clock, or a chain over finer classes: K lumps)."""

from __future__ import annotations

from surrogate.simulate.classes import ClassDecision, ClassTable
from surrogate.simulate.decision import (
    AbstractDecision,
    DecisionLayer,
    ExactDecision,
    ExactPsi,
    FullDecision,
)
from surrogate.simulate.loop import PopulationState, Simulator, StepRecord
from surrogate.simulate.memory import MemoryDecision
from surrogate.simulate.population import PopulationSummary, simulate_population

__all__ = [
    "AbstractDecision",
    "ClassDecision",
    "ClassTable",
    "DecisionLayer",
    "ExactDecision",
    "ExactPsi",
    "FullDecision",
    "MemoryDecision",
    "PopulationState",
    "PopulationSummary",
    "Simulator",
    "StepRecord",
    "simulate_population",
]

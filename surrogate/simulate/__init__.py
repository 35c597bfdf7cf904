"""Population simulation: one outer time loop with a pluggable decision layer."""

from __future__ import annotations

from surrogate.simulate.decision import AbstractDecision, DecisionLayer, FullDecision
from surrogate.simulate.loop import PopulationState, Simulator, StepRecord
from surrogate.simulate.population import PopulationSummary, simulate_population

__all__ = [
    "AbstractDecision",
    "DecisionLayer",
    "FullDecision",
    "PopulationState",
    "PopulationSummary",
    "Simulator",
    "StepRecord",
    "simulate_population",
]

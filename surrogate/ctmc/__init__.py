"""Population continuous-time Markov chains: reaction networks and exact window samplers.

``gillespie`` simulates any mass-action network exactly (event by event, batched over cells);
``unit_generator`` / ``unit_transition_matrix`` / ``sample_counts`` sample networks of independent
first-order units exactly in one step per window, whatever the rates.
"""

from __future__ import annotations

from surrogate.ctmc.network import ReactionNetwork
from surrogate.ctmc.ssa import gillespie
from surrogate.ctmc.transition import sample_counts, unit_generator, unit_transition_matrix

__all__ = [
    "ReactionNetwork",
    "gillespie",
    "sample_counts",
    "unit_generator",
    "unit_transition_matrix",
]

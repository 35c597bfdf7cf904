"""Population continuous-time Markov chains: reaction networks and exact window samplers.

``gillespie`` simulates any mass-action network exactly (event by event, batched over cells), or
general kinetics (``Kinetics``, e.g. read from SBML) through its ``propensity`` hook;
``CompiledSSA`` runs the same kinetics per cell in compiled code (numba) for networks with
thousands of events per cell per window;
``unit_generator`` / ``unit_transition_matrix`` / ``sample_counts`` sample networks of independent
first-order units exactly in one step per window, whatever the rates.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from surrogate.ctmc.kinetics import Expr, Kinetics, mass_action_kinetics
from surrogate.ctmc.network import ReactionNetwork
from surrogate.ctmc.ssa import gillespie
from surrogate.ctmc.transition import sample_counts, unit_generator, unit_transition_matrix

if TYPE_CHECKING:
    from surrogate.ctmc.compiled import CellStreams, CompiledSSA

__all__ = [
    "CellStreams",
    "CompiledSSA",
    "Expr",
    "Kinetics",
    "ReactionNetwork",
    "gillespie",
    "mass_action_kinetics",
    "sample_counts",
    "unit_generator",
    "unit_transition_matrix",
]


def __getattr__(name: str) -> Any:
    """Import the compiled SSA (and numba, ~0.6 s) only when it is first used."""
    if name in ("CellStreams", "CompiledSSA"):
        from surrogate.ctmc import compiled

        return getattr(compiled, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Read SBML models as stochastic reaction networks with general kinetics (python-libsbml).

``read_sbml(path, inputs=[...])`` returns an :class:`SbmlModel` whose ``kinetics`` runs on both
SSA backends: ``surrogate.ctmc.gillespie(..., propensity=model.torch_propensity)`` (batched, any
device) and ``surrogate.ctmc.CompiledSSA(model.kinetics)`` (numba, per cell).
"""

from __future__ import annotations

from surrogate.sbml.errors import SbmlError, SbmlWarning
from surrogate.sbml.reader import SbmlModel, SbmlReaction, read_sbml, read_sbml_string

__all__ = [
    "SbmlError",
    "SbmlModel",
    "SbmlReaction",
    "SbmlWarning",
    "read_sbml",
    "read_sbml_string",
]

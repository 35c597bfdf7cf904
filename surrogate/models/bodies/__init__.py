"""A small library of agent bodies for models written as a yaml and an SBML file.

Each body is selected by ``kind`` in the model's ``body`` settings; the other keys are its
parameters (documented in each module), refused by name when unknown or of the wrong type:

* ``chemotaxis``: the run-and-tumble E. coli body with its methylation adaptation, inputs
  ``(m, L)``, derived ``F`` and ``activity`` (:mod:`.chemotaxis`);
* ``walker``: a 2-D walker whose speed depends on phi, input ``L`` (:mod:`.walker`);
* ``static``: an agent that stays where it is, input ``L`` (:mod:`.static`).

Every body hands its internal model ``x`` with columns ``variable_names`` (``L`` is always the
field's value where the agent is) and offers ``derived`` variables computed from them.
"""

from surrogate.models.bodies.chemotaxis import RunAndTumbleBody
from surrogate.models.bodies.registry import BODY_KINDS, LibraryBody, build_body
from surrogate.models.bodies.static import StaticAgent
from surrogate.models.bodies.walker import Walker

__all__ = ["BODY_KINDS", "LibraryBody", "RunAndTumbleBody", "StaticAgent", "Walker", "build_body"]

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

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from surrogate.errors import ConfigError
from surrogate.models.bodies.chemotaxis import RunAndTumbleBody
from surrogate.models.bodies.static import StaticAgent
from surrogate.models.bodies.walker import Walker

#: body kinds and their classes
BODY_KINDS: dict[str, type] = {
    "chemotaxis": RunAndTumbleBody,
    "walker": Walker,
    "static": StaticAgent,
}


def build_body(options: Mapping[str, Any], where: str = "model.body") -> Any:
    """The library body ``options["kind"]`` with the other options as its parameters."""
    if not isinstance(options, Mapping):
        raise ConfigError(f"{where} must be a mapping with a `kind` ({sorted(BODY_KINDS)}), got "
                          f"{options!r}")  # fmt: skip
    params = dict(options)
    kind = params.pop("kind", None)
    if kind not in BODY_KINDS:
        raise ConfigError(f"{where}.kind must be one of {sorted(BODY_KINDS)}, got {kind!r}")
    return BODY_KINDS[kind](params, where)


__all__ = ["BODY_KINDS", "RunAndTumbleBody", "StaticAgent", "Walker", "build_body"]

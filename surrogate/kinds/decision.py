"""The decision layers and their modes (``decision.name``, ``decision.mode``) as objects:
:class:`DecisionKind`, :class:`DecisionMode`, :func:`decision_kind`; and a decision group's
keys as they enter a run's identity (:func:`decision_identity`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from surrogate.errors import ConfigError


@dataclass(frozen=True)
class DecisionMode:
    """How a decision layer evaluates its law (``decision.mode``)."""

    name: str
    #: a table over the inputs (lookup), not the classifier or the exact law every step
    table: bool


@dataclass(frozen=True)
class DecisionKind:
    """A run's decision layer (``decision.name``): the full model, the learned abstraction
    (located by its train settings) or the model's exact lumped law."""

    name: str
    #: its ``decision.mode`` choices, the first the default where none is given
    modes: tuple[DecisionMode, ...] = ()
    #: the learned abstraction: the run needs its fit (decision=abstract)
    learned: bool = False
    #: the model's exact lumped law (decision=exact)
    exact: bool = False

    @property
    def full(self) -> bool:
        """The full model runs itself (decision=full): no mode, no chain."""
        return not (self.learned or self.exact)

    def mode(self, value: object) -> DecisionMode:
        """``decision.mode`` validated for this layer."""
        for mode in self.modes:
            if mode.name == value:
                return mode
        raise ConfigError(
            f"decision.mode must be one of {[m.name for m in self.modes]} for "
            f"decision={self.name}, got {value!r}"
        )


LOOKUP = DecisionMode("lookup", table=True)
DECISION_KINDS = {
    "full": DecisionKind("full"),
    "abstract": DecisionKind("abstract", (LOOKUP, DecisionMode("classifier", False)), learned=True),
    "exact": DecisionKind("exact", (LOOKUP, DecisionMode("direct", False)), exact=True),
}


def decision_kind(name: object) -> DecisionKind:
    """``decision.name`` validated: its kind."""
    if not isinstance(name, str) or name not in DECISION_KINDS:
        raise ConfigError(
            f"decision.name must be one of {list(DECISION_KINDS)} (select with "
            f"decision=full|abstract|exact), got {name!r}"
        )
    return DECISION_KINDS[name]


def mode_kind(name: str) -> DecisionMode:
    """A decision mode by name (one of the layers' modes, e.g. a caller's ``"lookup"``)."""
    for kind in DECISION_KINDS.values():
        for mode in kind.modes:
            if mode.name == name:
                return mode
    raise ValueError(f"unknown decision mode {name!r}")


def decision_identity(config: Mapping[str, Any]) -> dict[str, Any]:
    """A decision group's keys as they enter a run's identity: ``lumps`` only where it names
    another chain than the two-state one, so runs keep the identity they had before K lumps
    (the key is read by decision=exact only, and compared as given)."""
    if config.get("lumps", "phi") == "phi":
        return {k: v for k, v in config.items() if k != "lumps"}
    return dict(config)

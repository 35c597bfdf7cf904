"""The contract of a field that is state: the simulator owns its time and steps it with the cells.

A given field (:class:`~surrogate.fields.Field`) is a function L(r, t). A coupled field also
holds a state that the population changes: :class:`~surrogate.simulate.Simulator` resets it
when it draws the population's initial state and, after every step of the agents, calls
:meth:`CoupledField.step` with the agents' positions and phi. Its ``__call__(position, t)`` reads
the current state (``t`` is the simulator's time, which the field's own clock equals), so the
bodies read it as any field and need no change.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from surrogate.fields import Field

__all__ = ["CoupledField", "is_coupled"]


class CoupledField(Field):
    """Base of the fields the agents change (see the module docstring)."""

    #: the current state (what :meth:`reset` or :meth:`step` last returned), which the simulator
    #: keeps in its population state
    state: Any

    def reset(self, device: torch.device | str = "cpu") -> Any:
        """Set the state to its initial value on ``device``; return the state."""
        raise NotImplementedError

    def step(self, position: Tensor, phi: Tensor, dt: float) -> Any:
        """Advance the state by ``dt`` with the agents at ``position`` (``(n, 2)``) and their
        phi (``(n,)``) after the agents' step; return the new state."""
        raise NotImplementedError

    def validate(self, dt: float) -> None:
        """Refuse a time step the field cannot be advanced with (ConfigError naming why)."""

    def check(self) -> str | None:
        """What is wrong with the state (e.g. NaN), or None."""
        return None

    def memory_bytes(self) -> int:
        """Memory the state and its step need (bytes), for the checks before a run."""
        return 0


def is_coupled(field: Any) -> bool:
    """Whether ``field`` is a coupled field."""
    return isinstance(field, CoupledField)

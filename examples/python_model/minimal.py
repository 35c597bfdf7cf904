"""The smallest internal model the engine takes: the required protocol and nothing else.

A telegraph switch per cell: OFF -> ON at ``k_on * s`` (``s``: the inducer the body reads from
the field), ON -> OFF at ``k_off``; phi = ON. :class:`TelegraphInternal` writes only what
:class:`~surrogate.models.base.InternalModel` requires (``input_names``, ``signal_names``,
``lump_names``, ``initial_state``, ``advance``, ``phi``) and declares none of the optional
capabilities (:mod:`surrogate.models.capabilities`): no derived features, no pure window (the
simulator runs the eager ``advance``), no ``concat_states`` (the engine concatenates the state's
tensors), no exact psi (``decision=exact`` is refused; train scores the abstraction against
binned frequencies of a full-model run), no signal bounds, no expected labels, no cost estimate.
Its body is the gene switch's :class:`~examples.python_model.gene_switch.Walker`;
``tests/examples/test_minimal_model.py`` runs it through collect, train and simulate.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from examples.python_model.gene_switch import Walker
from surrogate.errors import ConfigError
from surrogate.models import Model


class TelegraphInternal:
    """A two-state switch per cell, advanced exactly over a window (its own RNG).

    Args:
        k_on: OFF -> ON rate per unit of inducer (1/s).
        k_off: ON -> OFF rate (1/s).
    """

    input_names = ("s",)
    signal_names = ("s",)
    lump_names = ("off", "on")

    def __init__(self, k_on: float, k_off: float) -> None:
        self.k_on, self.k_off = float(k_on), float(k_off)

    def _stationary(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """P(ON) at stationarity and the total switching rate, both ``(n,)``."""
        on = self.k_on * x[:, 0].clamp_min(0.0)
        total = on + self.k_off
        return on / total, total

    def initial_state(self, x: Tensor) -> tuple[Tensor]:
        """ON with its stationary probability at inputs ``x`` (``n x 1``): a state ``(phi,)``."""
        p_on, _ = self._stationary(x)
        return ((torch.rand_like(p_on) < p_on).to(torch.float32),)

    def advance(self, state: tuple[Tensor], x: Tensor, dt: float) -> tuple[Tensor]:
        """The exact state after ``dt`` at inputs ``x``: P(ON) relaxes to its stationary value
        at the total rate."""
        (phi,) = state
        p_on, total = self._stationary(x)
        decay = torch.exp(-total * dt)
        p = torch.where(phi > 0, p_on + (1 - p_on) * decay, p_on * (1 - decay))
        return ((torch.rand_like(p) < p).to(torch.float32),)

    def phi(self, state: tuple[Tensor]) -> Tensor:
        """ON as float 0/1 ``(n,)``."""
        return state[0]


class TelegraphModel(Model):
    """The telegraph switch in the gene switch's walker (every constant a config key)."""

    name = "telegraph"

    def __init__(
        self,
        k_on: float = 50.0,
        k_off: float = 2.0,
        speed_on: float = 0.02,
        speed_off: float = 0.005,
        rotation: float = 0.5,
        perturbation: Mapping[str, Any] | None = None,
    ) -> None:
        if min(k_on, k_off, speed_on, speed_off, rotation) <= 0:
            raise ConfigError("telegraph: rates and speeds must be positive")
        self.internal = TelegraphInternal(k_on, k_off)
        self.body = Walker(speed_on, speed_off, rotation)
        self.perturbation_options = dict(perturbation or {"radius": 3.0})

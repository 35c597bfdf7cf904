"""A static agent: a cell that stays where it is and reads the field there.

State: ``position`` (``n x 2``, mm, fixed), ``time_on`` and ``elapsed`` (``(n,)``, s). It hands
its internal model the field's value at its position, ``x = (L,)`` (a dynamic field changes it
over time). Observable: ``on_fraction``, the share of the time since the start spent with
phi = 1. Collect's perturbation: jumps to random points of a disc around the peak (the only
way a static agent sees other inputs).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from surrogate.fields import Field
from surrogate.models.base import BodyState, Randoms, check_options
from surrogate.models.perturbation import PERTURBATION_DEFAULTS, DiscJump, disc_jump, disc_options

#: parameters of the static agent and their defaults
STATIC_DEFAULTS: dict[str, Any] = {"perturbation": {"radius": 4.0, "sampling": "radius"}}


class StaticAgent:
    """An agent that does not move (see the module docstring).

    Args:
        options: :data:`STATIC_DEFAULTS` keys.
        where: the setting's name in messages.

    Example:
        >>> from surrogate.fields import ConstantField
        >>> agent = StaticAgent()
        >>> state = agent.initial_state(2, torch.tensor([0.0, 0.0]), ConstantField(0.1), 0.05)
        >>> agent.inputs(state, ConstantField(0.1), 0.0)[:, 0]
        tensor([0.1000, 0.1000])
    """

    #: a start position is [x, y] (mm)
    start_size = 2
    observable_names = ("on_fraction",)
    variable_names = ("L",)
    randoms = Randoms()
    adapt_randoms = Randoms()

    def __init__(self, options: Mapping[str, Any] | None = None, where: str = "model.body") -> None:
        o = check_options({} if options is None else options, STATIC_DEFAULTS, where)
        self.perturbation_options = check_options(
            {} if o["perturbation"] is None else o["perturbation"],
            PERTURBATION_DEFAULTS,
            f"{where}.perturbation",
        )
        disc_options(self.perturbation_options, f"{where}.perturbation")
        self.where = where
        self.derived: dict[str, Any] = {}

    def validate(self, dt: float) -> None:
        """Any positive dt works."""

    def initial_state(self, n_cells: int, start: Tensor, field: Field, dt: float) -> BodyState:
        """Agents at ``start`` (one point or ``n x 2``), no time counted yet."""
        position = start.to(torch.float32).reshape(-1, 2).expand(n_cells, 2).clone()
        zeros = torch.zeros(n_cells, device=position.device)
        return {"position": position, "time_on": zeros, "elapsed": zeros.clone()}

    def inputs(self, state: BodyState, field: Field, t: float) -> Tensor:
        """``x = (L(r, t),)``, ``n x 1``."""
        return field(state["position"], t)[:, None]

    def adapt(self, state: BodyState, x: Tensor, dt: float, u: Tensor, z: Tensor) -> BodyState:
        """No slow internal process."""
        return state

    def move(
        self,
        state: BodyState,
        phi_before: Tensor,
        phi_after: Tensor,
        x: Tensor,
        dt: float,
        u: Tensor,
        z: Tensor,
        extra: Tensor | None,
    ) -> BodyState:
        """Stay; count the step's time and its time with phi = 1."""
        return {"position": state["position"], "time_on": state["time_on"] + phi_after * dt,
                "elapsed": state["elapsed"] + dt}  # fmt: skip

    def sample_extra(self, n_cells: int, device: torch.device) -> None:
        """Nothing beyond :attr:`randoms`."""
        return None

    def observables(self, state: BodyState, field: Field) -> dict[str, Tensor]:
        """The share of the elapsed time each agent spent with phi = 1 (0 before any step)."""
        elapsed = state["elapsed"]
        return {"on_fraction": state["time_on"] / elapsed.clamp_min(1e-30)}

    def observable_label(self, name: str) -> str:
        """Figure label of an observable."""
        return {"on_fraction": "time share with phi = 1"}.get(name, name)

    def check_inputs(self, x: Tensor) -> str | None:
        """The field's values must be finite."""
        return None if bool(torch.isfinite(x).all()) else "the field returned NaN/inf values"

    def perturbation(self, field: Field, options: Mapping[str, Any]) -> DiscJump:
        """Jumps into a disc around the field's peak."""
        return disc_jump(field, options, f"{self.where}.perturbation")

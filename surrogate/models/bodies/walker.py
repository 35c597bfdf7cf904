"""A walker whose speed depends on phi: a 2-D swimmer for any internal network.

State: ``position`` (``n x 2``, mm) and ``heading`` (``(n,)``, rad). Each step it moves
``speed_on * dt`` (phi = 1) or ``speed_off * dt`` (phi = 0) along its heading, which diffuses
with rotational diffusion coefficient ``rotation`` (rad^2/s). It hands its internal model the
field's value where it is, ``x = (L,)``. Observable: the distance from the field's peak (mm).
Collect's perturbation: jumps to random points of a disc around the peak (``perturbation``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import torch
from torch import Tensor

from surrogate.fields import Field
from surrogate.models.base import BodyState, Randoms, check_options
from surrogate.models.bodies.options import number
from surrogate.models.perturbation import PERTURBATION_DEFAULTS, DiscJump, disc_jump, disc_options

#: parameters of the walker and their defaults (units: mm, s, rad)
WALKER_DEFAULTS: dict[str, Any] = {
    "speed_on": 0.02,  # mm/s while phi = 1
    "speed_off": 0.0,  # mm/s while phi = 0
    "rotation": 0.5,  # rad^2/s, rotational diffusion of the heading
    "perturbation": {"radius": 4.0, "sampling": "radius"},
}


class Walker:
    """A walker whose speed is ``speed_on`` when phi = 1 and ``speed_off`` when phi = 0.

    Args:
        options: :data:`WALKER_DEFAULTS` keys (unknown keys and wrong types are refused, named
            under ``where``).
        where: the setting's name in messages (e.g. ``"model.body"``).

    Example:
        >>> from surrogate.fields import GaussianField
        >>> walker, field = Walker({"speed_on": 0.03}), GaussianField()
        >>> state = walker.initial_state(4, torch.tensor([1.0, 0.0]), field, 0.05)
        >>> walker.inputs(state, field, 0.0).shape  # the field's value L per cell
        torch.Size([4, 1])
    """

    #: a start position is [x, y] (mm)
    start_size = 2
    observable_names = ("distance",)
    #: histogram grids of the observables (lo, hi, width): 0-20 mm in 2 um bins
    histogram_grids: ClassVar[dict[str, tuple[float, float, float]]] = {
        "distance": (0.0, 20.0, 0.002)
    }
    variable_names = ("L",)
    randoms = Randoms(normal=1)
    adapt_randoms = Randoms()

    def __init__(self, options: Mapping[str, Any] | None = None, where: str = "model.body") -> None:
        o = check_options({} if options is None else options, WALKER_DEFAULTS, where)
        self.speed_on = number(o, "speed_on", where)
        self.speed_off = number(o, "speed_off", where)
        self.rotation = number(o, "rotation", where)
        self.perturbation_options = check_options(
            {} if o["perturbation"] is None else o["perturbation"],
            PERTURBATION_DEFAULTS,
            f"{where}.perturbation",
        )
        disc_options(self.perturbation_options, f"{where}.perturbation")
        self.where = where
        self.derived: dict[str, Any] = {}

    def validate(self, dt: float) -> None:
        """Any positive dt works (the heading's diffusion is exact per step)."""

    def initial_state(self, n_cells: int, start: Tensor, field: Field, dt: float) -> BodyState:
        """Walkers at ``start`` (one point or ``n x 2``) with uniform headings."""
        position = start.to(torch.float32).reshape(-1, 2).expand(n_cells, 2).clone()
        heading = (2 * math.pi) * torch.rand(n_cells, device=position.device)
        return {"position": position, "heading": heading}

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
        """Turn by a N(0, rotation dt) angle, then move at the speed of phi after the window."""
        speed = self.speed_off + (self.speed_on - self.speed_off) * phi_after
        heading = state["heading"] + math.sqrt(self.rotation * dt) * z[0]
        px = state["position"][:, 0] + torch.cos(heading) * (speed * dt)
        py = state["position"][:, 1] + torch.sin(heading) * (speed * dt)
        return {"position": torch.stack([px, py], -1), "heading": heading}

    def sample_extra(self, n_cells: int, device: torch.device) -> None:
        """Nothing beyond :attr:`randoms`."""
        return None

    def observables(self, state: BodyState, field: Field) -> dict[str, Tensor]:
        """Each walker's distance from the field's peak (mm)."""
        return {"distance": field.distance_from_peak(state["position"])}

    def observable_label(self, name: str) -> str:
        """Figure label of an observable."""
        return {"distance": "distance from the peak (mm)"}.get(name, name)

    def check_inputs(self, x: Tensor) -> str | None:
        """The field's values must be finite."""
        return None if bool(torch.isfinite(x).all()) else "the field returned NaN/inf values"

    def perturbation(self, field: Field, options: Mapping[str, Any]) -> DiscJump:
        """Jumps into a disc around the field's peak (the shared
        :class:`~surrogate.models.perturbation.DiscJump`)."""
        return disc_jump(field, options, f"{self.where}.perturbation")

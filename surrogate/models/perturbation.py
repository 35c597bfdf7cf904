"""Collect's generic perturbation for bodies with a 2-D ``position``: jumps to random points of
a disc around the field's peak (:class:`DiscJump`), with its options read and refused by name
(:func:`disc_options`). Any body whose state has ``position`` (``n x 2``, mm) can offer it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.fields import Field
from surrogate.models.base import BodyState, check_options
from surrogate.validation import yaml_hint

__all__ = [
    "PERTURBATION_DEFAULTS",
    "SAMPLINGS",
    "DiscJump",
    "disc_jump",
    "disc_options",
    "random_in_disc",
]

#: collect's perturbation: jumps to random points of a disc around the field's peak
PERTURBATION_DEFAULTS: dict[str, Any] = {"radius": 4.0, "sampling": "radius"}
SAMPLINGS = ("radius", "area")


def random_in_disc(
    n: int, centre: tuple[float, float], radius: float, device: torch.device, sampling: str
) -> Tensor:
    """``n`` random points (mm, ``n x 2``) in a disc: distance from the centre uniform in
    [0, radius] (``radius``: more points near the peak, where the fields' high L lives) or uniform
    over the disc's area (``area``)."""
    u = torch.rand(n, device=device)
    r = radius * (u if sampling == "radius" else torch.sqrt(u))
    theta = torch.rand(n, device=device) * (2 * math.pi)
    offset = torch.stack([r * torch.cos(theta), r * torch.sin(theta)], -1)
    return offset + torch.tensor(centre, device=device)


class DiscJump:
    """Perturbation: cells start uniformly in a disc around the field's peak and jump to random
    points of it; the rest of their state is kept (the E. coli body's methylation is then out of
    adaptation with the new L while it relaxes): the "sporadic perturbation" of the paper's data
    collection."""

    def __init__(self, field: Field, radius: float, sampling: str) -> None:
        self.centre = field.peak
        self.radius = float(radius)
        self.sampling = sampling

    def start(self, n_cells: int, device: torch.device) -> Tensor:
        """Start positions ``n x 2``."""
        return random_in_disc(n_cells, self.centre, self.radius, device, self.sampling)

    def apply(self, state: BodyState, mask: Tensor) -> BodyState:
        """Move the cells where ``mask`` is true to random points of the disc."""
        target = self.start(mask.shape[0], mask.device)
        position = torch.where(mask.unsqueeze(-1), target, state["position"])
        return {**state, "position": position}


def disc_jump(field: Field, options: Mapping[str, Any], where: str) -> DiscJump:
    """The :class:`DiscJump` of ``options`` around ``field``'s peak (see :func:`disc_options`)."""
    return DiscJump(field, *disc_options(options, where))


def disc_options(options: Mapping[str, Any], where: str) -> tuple[float, str]:
    """``(radius, sampling)`` of a disc perturbation's ``options`` (``radius`` mm > 0,
    ``sampling`` radius|area), each refused by its name under ``where`` (e.g.
    ``"model.perturbation"``)."""
    o = check_options(options, PERTURBATION_DEFAULTS, where)
    radius = o["radius"]
    if (isinstance(radius, bool) or not isinstance(radius, int | float)
            or not 0 < radius < math.inf):  # fmt: skip
        raise ConfigError(f"{where}.radius must be a finite number > 0 mm, got {radius!r}"
                          f"{yaml_hint(radius)}")  # fmt: skip
    if o["sampling"] not in SAMPLINGS:
        raise ConfigError(
            f"{where}.sampling must be one of {list(SAMPLINGS)}, got {o['sampling']!r}"
        )
    return float(radius), str(o["sampling"])

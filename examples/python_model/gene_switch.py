"""The template for a new Python model: a gene switch with dimerisation inside a walker that
moves faster when the switch is ON, written against the protocols of :mod:`surrogate.models.base`
only (no E. coli code) and selected by ``model._target_`` (README.md in this folder). Copy this
file to start a model of your own: a :class:`~surrogate.models.Model` subclass whose constructor
takes the config's keys and sets ``internal`` (here the generic reaction-network adapter),
``body`` (here :class:`Walker`) and ``perturbation_options``. The same gene switch written as a
yaml beside an SBML file, in the library's walker body, is ``examples/gene_switch``;
``tests/examples/test_python_model.py`` runs this one through every stage.

Internal network (8 protein molecules per cell, conserved): inactive I, active monomer P, dimer
D. I -> P at ``k_act * s`` (``s``: the inducer concentration the body reads from the field),
P -> I at ``k_deact``, 2P -> D at ``k_dim``, D -> 2P at ``k_undim``. ON iff D >= 2. The state
space has 25 states, so the exact lumped psi exists.

Body: position and heading; speed ``speed_on`` when ON, ``speed_off`` when OFF; the heading
diffuses (rotational diffusion ``rotation`` rad^2/s). Observable: distance from the field's peak.
Perturbation: jumps to random points of a disc around the peak.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import torch
from torch import Tensor

from surrogate.ctmc import ReactionNetwork
from surrogate.errors import ConfigError
from surrogate.fields import Field
from surrogate.models import Model, NetworkInternalModel, Randoms, check_options

NETWORK = ReactionNetwork.from_reactions(
    ["I", "P", "D"],
    [
        ("activate", {"I": 1}, {"P": 1}),
        ("deactivate", {"P": 1}, {"I": 1}),
        ("dimerise", {"P": 2}, {"D": 1}),
        ("split", {"D": 1}, {"P": 2}),
    ],
)


class Jump:
    """Cells start in, and jump to, random points of a disc around the field's peak."""

    def __init__(self, field: Field, radius: float) -> None:
        self.centre, self.radius = field.peak, radius

    def start(self, n_cells: int, device: torch.device) -> Tensor:
        r = self.radius * torch.sqrt(torch.rand(n_cells, device=device))
        theta = 2 * math.pi * torch.rand(n_cells, device=device)
        return torch.stack([r * torch.cos(theta), r * torch.sin(theta)], -1) + torch.tensor(
            self.centre, device=device
        )

    def apply(self, state: dict[str, Tensor], mask: Tensor) -> dict[str, Tensor]:
        target = self.start(mask.shape[0], mask.device)
        return {**state, "position": torch.where(mask[:, None], target, state["position"])}


class Walker:
    """A 2-D walker: faster when ON, rotational diffusion, no slow internal process."""

    observable_names = ("distance",)
    start_size = 2  # a start position is [x, y] (mm); default: any list, the body reads it
    histogram_grids: ClassVar[dict[str, tuple[float, float, float]]] = {
        "distance": (0.0, 20.0, 0.002)
    }  # (lo, hi, width) in mm; default: from the data
    randoms = Randoms(normal=1)
    adapt_randoms = Randoms()

    def __init__(self, speed_on: float, speed_off: float, rotation: float) -> None:
        self.speed_on, self.speed_off, self.rotation = speed_on, speed_off, rotation

    def initial_state(self, n_cells: int, start: Tensor, field: Field, dt: float) -> dict:
        position = start.to(torch.float32).reshape(-1, 2).expand(n_cells, 2).clone()
        heading = 2 * math.pi * torch.rand(n_cells, device=position.device)
        return {"position": position, "heading": heading}

    def inputs(self, state: dict, field: Field, t: float) -> Tensor:
        return field(state["position"], t)[:, None]

    def adapt(self, state: dict, x: Tensor, dt: float, u: Tensor, z: Tensor) -> dict:
        return state

    def move(self, state, phi_before, phi_after, x, dt, u, z, extra) -> dict:
        speed = self.speed_off + (self.speed_on - self.speed_off) * phi_after
        heading = state["heading"] + math.sqrt(self.rotation * dt) * z[0]
        step = torch.stack([torch.cos(heading), torch.sin(heading)], -1) * (speed * dt)[:, None]
        return {"position": state["position"] + step, "heading": heading}

    def sample_extra(self, n_cells: int, device: torch.device) -> None:
        return None

    def observables(self, state: dict, field: Field) -> dict[str, Tensor]:
        return {"distance": field.distance_from_peak(state["position"])}

    def check_inputs(self, x: Tensor) -> str | None:
        return None if bool(torch.isfinite(x).all()) else "NaN/inf inducer"

    def perturbation(self, field: Field, options: Mapping[str, Any]) -> Jump:
        o = check_options(options, {"radius": 3.0}, "model.perturbation")
        return Jump(field, float(o["radius"]))


class GeneSwitchModel(Model):
    """The gene switch in a walker (see the module docstring); every constant is a keyword
    argument, so every key of the ``model`` config but ``_target_``."""

    name = "gene_switch"

    def __init__(  # noqa: PLR0913  # every constant is a key of the model config
        self,
        k_act: float = 50.0,
        k_deact: float = 2.0,
        k_dim: float = 1.0,
        k_undim: float = 1.0,
        molecules: int = 8,
        threshold: int = 2,
        speed_on: float = 0.02,
        speed_off: float = 0.005,
        rotation: float = 0.5,
        perturbation: Mapping[str, Any] | None = None,
    ) -> None:
        if min(k_act, k_deact, k_dim, k_undim, speed_on, speed_off, rotation) <= 0:
            raise ConfigError("gene_switch: rate constants and speeds must be positive")
        rates = torch.tensor([k_act, k_deact, k_dim, k_undim], dtype=torch.float64)

        def rate_constants(signal: Tensor) -> Tensor:
            scale = torch.ones(signal.shape[0], 4, dtype=torch.float64, device=signal.device)
            scale[:, 0] = signal[:, 0].to(torch.float64)  # activation follows the inducer
            return scale * rates.to(signal.device)

        self.internal = NetworkInternalModel(
            NETWORK,
            input_names=("s",),
            rate_constants=rate_constants,
            lump=lambda counts: counts[:, 2] >= threshold,
            initial_counts=[molecules, 0, 0],
            lump_names=("off", "on"),
        )
        self.body = Walker(speed_on, speed_off, rotation)
        self.perturbation_options = dict(perturbation or {"radius": 3.0})

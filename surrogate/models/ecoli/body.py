"""The E. coli body: a run-and-tumble swimmer in a 2-D ligand field with OU methylation.

State: ``position`` (``n x 2``, mm), ``heading`` (``(n,)``, rad) and the methylation ``m``
(``(n,)``), the cell's chemical memory, which follows an Ornstein-Uhlenbeck process towards the
adapted level m0(L) (paper, Eq. 3; Euler-Maruyama with the reference code's clamp). It hands the
motors ``x = (m, L(r, t))``. RUN: move ``speed * dt`` along the heading; TUMBLE: stay and turn by a
Gamma(shape, scale) angle with a random sign, at every step spent tumbling (paper, Algorithm 1;
``per_step``) or once per tumble (reference code; ``per_tumble``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import torch
from torch import Tensor

from surrogate.fields import Field
from surrogate.models.base import BodyState, Randoms
from surrogate.models.ecoli import formulas
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli.signalling import adapted_methylation, ou_step

# re-exported: these lived here before the walker and static bodies shared them
from surrogate.models.perturbation import (  # noqa: F401
    PERTURBATION_DEFAULTS,
    SAMPLINGS,
    DiscJump,
    disc_jump,
    disc_options,
    random_in_disc,
)

# integer Gamma shapes up to this are drawn as sums of exponentials (k uniforms per cell)
MAX_GAMMA_UNIFORMS = 16


class ChemotacticBody:
    """Run-and-tumble body of an E. coli cell (see the module docstring).

    Example:
        >>> from surrogate.fields import GaussianField
        >>> body, field = ChemotacticBody(EcoliParameters()), GaussianField()
        >>> state = body.initial_state(3, torch.tensor([2.0, 0.0]), field, 0.05)
        >>> body.inputs(state, field, 0.0).shape   # (m, L) per cell
        torch.Size([3, 2])
    """

    #: a start position is [x, y] (mm)
    start_size = 2
    observable_names = ("distance",)
    #: histogram grids of the observables (lo, hi, width): 0-20 mm in 2 um bins
    histogram_grids: ClassVar[dict[str, tuple[float, float, float]]] = {
        "distance": (0.0, 20.0, 0.002)
    }

    def __init__(self, params: EcoliParameters) -> None:
        self.params = params
        shape = float(params.tumble_shape)
        self.gamma_k = int(shape) if shape.is_integer() and shape <= MAX_GAMMA_UNIFORMS else 0
        self.tumble_scale = math.radians(params.tumble_scale_deg)
        self.per_tumble = params.tumble_mode == "per_tumble"
        # Gamma angle (gamma_k rows, unless drawn by sample_extra) and its sign; OU noise
        self.randoms = Randoms(uniform=self.gamma_k + 1, normal=1)
        self.adapt_randoms = Randoms(normal=1)

    def initial_state(self, n_cells: int, start: Tensor, field: Field, dt: float) -> BodyState:
        """Cells at ``start`` (one point or ``n x 2``) with uniform headings and m drawn from the
        OU's stationary law at L(start), m0(L) + sigma_m N(0, 1)."""
        p = self.params
        position = start.to(torch.float32).reshape(-1, 2).expand(n_cells, 2).clone()
        heading = torch.rand(n_cells, device=position.device) * (2 * math.pi)
        ligand = field(position, 0.0)
        noise = torch.randn(n_cells, device=position.device)
        m = (adapted_methylation(ligand, p) + p.sigma_m * noise).clamp(p.m_min, p.m_max)
        return {"position": position, "heading": heading, "m": m}

    def inputs(self, state: BodyState, field: Field, t: float) -> Tensor:
        """``x = (m, L(r, t))``, ``n x 2``."""
        return torch.stack([state["m"], field(state["position"], t)], -1)

    def adapt(self, state: BodyState, x: Tensor, dt: float, u: Tensor, z: Tensor) -> BodyState:
        """One OU step of the methylation at L = ``x[:, 1]``."""
        return {**state, "m": ou_step(state["m"], x[:, 1], dt, self.params, z[0])}

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
        """RUN: move along the heading; TUMBLE: stay and turn; then the OU step.

        ``u`` holds ``gamma_k`` rows for the Gamma angle (unless ``extra`` holds the angles) and
        one row for its sign; flags are float 0/1 (see :mod:`surrogate.models.base`).
        """
        position, heading = state["position"], state["heading"]
        c = formulas.constants(self.params, dt)
        # x and y as separate columns keep a compiled kernel in SIMD lanes
        px, py = formulas.run_step(position[:, 0], position[:, 1], heading, phi_after, c)
        turning = formulas.turning(phi_before, phi_after, self.per_tumble)
        if extra is None:  # Gamma(k, scale) from the first gamma_k rows of u
            extra = formulas.tumble_angle(u, 0, self.gamma_k, c[formulas.TUMBLE_SCALE])
        turned = formulas.turn(heading, extra, u[-1], c)
        moved = {
            "position": torch.stack([px, py], -1),
            "heading": torch.where(turning > 0, turned, heading),
            "m": state["m"],
        }
        return self.adapt(moved, x, dt, u, z)

    def sample_extra(self, n_cells: int, device: torch.device) -> Tensor | None:
        """Gamma tumble angles ``(n,)`` for a non-integer shape (else None)."""
        if self.gamma_k:
            return None
        p = self.params
        gamma = torch.distributions.Gamma(
            torch.tensor(float(p.tumble_shape), device=device),
            torch.tensor(1.0 / self.tumble_scale, device=device),
        )
        return gamma.sample((n_cells,))

    def observables(self, state: BodyState, field: Field) -> dict[str, Tensor]:
        """Each cell's distance from the field's peak (mm)."""
        return {"distance": field.distance_from_peak(state["position"])}

    def check_inputs(self, x: Tensor) -> str | None:
        """Ligand concentrations must be finite and non-negative."""
        ligand = x[:, 1]
        lowest = float(ligand.min()) if ligand.numel() else 0.0
        if not math.isfinite(lowest) or not bool(torch.isfinite(ligand).all()):
            return "the field returned NaN/inf concentrations"
        if lowest < 0:
            return f"the field returned negative concentrations (lowest {lowest:.3g} mM)"
        return None

    def perturbation(self, field: Field, options: Mapping[str, Any]) -> DiscJump:
        """Jumps into a disc of ``radius`` (mm) around the peak, distance uniform in radius
        (``sampling: radius``) or over the area (``area``)."""
        return disc_jump(field, options, "model.perturbation")

"""The one outer time loop for a population (Algorithms 1 and 2 of the paper).

Per step, for all cells at once: L <- L(r, t); phi <- decision(phi, m, L); RUN: r += v dt,
TUMBLE: rotate the heading by a Gamma-distributed angle; m <- OU(m, L, dt); t += dt.
Cells live in the batch dimension; the only Python loop is over time steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from surrogate.errors import NumericalError
from surrogate.fields import Field
from surrogate.models.ecoli import EcoliParameters, adapted_methylation, ou_step
from surrogate.simulate.decision import DecisionLayer


@dataclass
class PopulationState:
    """Per-cell state, cells in the first dimension."""

    position: Tensor  # (n, 2) mm
    heading: Tensor  # (n,) rad
    methylation: Tensor  # (n,)
    run: Tensor  # (n,) bool: phi_RUN of the last window
    segment_steps: Tensor  # (n,) int32: steps spent in the current run/tumble segment
    segment_complete: Tensor  # (n,) bool: the current segment began with a switch (not censored)
    step: int = 0

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return self.position.shape[0]


@dataclass
class StepRecord:
    """What one step saw and did (used by collect and by recorders)."""

    ligand: Tensor  # L(r, t) at the start of the step
    methylation: Tensor  # m used by the decision
    run_before: Tensor  # phi before the window
    run_after: Tensor  # phi after the window
    ended_length: Tensor  # int32: +k run of k steps ended, -k tumble ended, 0 none


class Simulator:
    """Steps a population through a field with a pluggable decision layer."""

    def __init__(
        self,
        decision: DecisionLayer,
        field: Field,
        params: EcoliParameters,
        dt: float,
        device: str | torch.device = "cpu",
        check_finite: bool = True,
    ) -> None:
        self.decision = decision
        self.field = field
        self.params = params
        self.dt = float(dt)
        self.device = torch.device(device)
        self.check_finite = check_finite
        self._run_step = params.speed * self.dt
        self._tumble = torch.distributions.Gamma(
            torch.tensor(params.tumble_shape, device=self.device),
            torch.tensor(1.0 / math.radians(params.tumble_scale_deg), device=self.device),
        )

    # ------------------------------------------------------------------------------------
    def initial_state(
        self,
        n_cells: int,
        start: Sequence[float] | Tensor = (2.0, 0.0),
        equilibration_time: float = 0.0,
    ) -> PopulationState:
        """Cells at ``start`` (one point, or per-cell positions (n, 2)) with uniform random
        headings, internal state adapted to L(start).

        m ~ m0(L) + sigma_m N(0, 1) (the OU's stationary law at constant L), motors from their
        stationary law, then ``equilibration_time`` seconds of internal dynamics at a fixed
        position so the decision layer's own state settles.
        """
        p = self.params
        position = torch.as_tensor(start, dtype=torch.float32, device=self.device)
        position = position.reshape(-1, 2).expand(n_cells, 2).clone()
        heading = torch.rand(n_cells, device=self.device) * (2 * math.pi)
        ligand = self.field(position, 0.0)
        m = adapted_methylation(ligand, p) + p.sigma_m * torch.randn(n_cells, device=self.device)
        m = m.clamp_(p.m_min, p.m_max)
        run = self.decision.initialize(m, ligand)
        for _ in range(round(equilibration_time / self.dt)):
            run = self.decision.step(run, m, ligand, self.dt)
            m = ou_step(m, ligand, self.dt, p, torch.randn_like(m))
        return PopulationState(
            position=position,
            heading=heading,
            methylation=m,
            run=run,
            segment_steps=torch.zeros(n_cells, dtype=torch.int32, device=self.device),
            segment_complete=torch.zeros(n_cells, dtype=torch.bool, device=self.device),
        )

    # ------------------------------------------------------------------------------------
    def step(self, state: PopulationState) -> StepRecord:
        """Advance every cell by one time step dt, in place; return what the step saw."""
        p, dt = self.params, self.dt
        t = state.step * dt
        ligand = self.field(state.position, t)
        m = state.methylation
        if self.check_finite and not bool(torch.isfinite(ligand).all()):
            raise NumericalError(f"the field returned NaN/inf concentrations at t={t:g} s")
        run_before = state.run
        run = self.decision.step(run_before, m, ligand, dt)

        # RUN: move along the heading; TUMBLE: stay and turn.
        step_len = run.to(m.dtype) * self._run_step
        direction = torch.stack([torch.cos(state.heading), torch.sin(state.heading)], dim=-1)
        state.position = state.position + direction * step_len.unsqueeze(-1)
        turning = ~run if p.tumble_mode == "per_step" else (run_before & ~run)
        angle = self._tumble.sample((state.n_cells,))
        sign = torch.where(torch.rand_like(angle) < 0.5, -1.0, 1.0)
        state.heading = torch.where(turning, state.heading + sign * angle, state.heading)
        state.heading = torch.remainder(state.heading, 2 * math.pi)

        state.methylation = ou_step(m, ligand, dt, p, torch.randn_like(m))

        # Run/tumble segments: a segment ends when phi switches; the first one is left-censored.
        switched = run != run_before
        length = state.segment_steps + 1  # steps of the finished segment, incl. the last window
        ended = switched & state.segment_complete
        signed = torch.where(run_before, length, -length)
        ended_length = torch.where(ended, signed, torch.zeros_like(signed))
        # the new segment's first window is this one (phi after it is the new state)
        state.segment_steps = torch.where(switched, torch.zeros_like(length), length)
        state.segment_complete = state.segment_complete | switched
        state.run = run
        state.step += 1
        return StepRecord(ligand, m, run_before, run, ended_length)

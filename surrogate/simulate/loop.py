"""The one outer time loop for a population (Algorithms 1 and 2 of the paper).

Per step, for all cells at once: L <- L(r, t); phi <- decision(phi, m, L); RUN: r += v dt,
TUMBLE: rotate the heading by a Gamma-distributed angle; m <- OU(m, L, dt); t += dt.
Cells live in the batch dimension; the only Python loop is over time steps.

Performance design (see ``surrogate.bench``):

* The random numbers of a step are drawn up front in at most three calls (float32 uniforms
  (k, n), float64 motor uniforms (M, n), normals (n,)); everything else is ONE pure function of
  tensors (:meth:`Simulator._fused_step`): field, decision, movement, tumble, OU and segment
  bookkeeping, with no host sync and a fixed number of ops. ``compile=True`` runs it through
  ``torch.compile`` (fused C++/OpenMP loops on the CPU, Triton on CUDA); if compiling fails the
  simulator falls back to the same function run eagerly, with a warning.
* Flags (RUN before/after, segment complete) enter and leave the kernel as uint8 views of the
  bool tensors and are 0/1 numbers inside: compiled CPU kernels handle bool tensors with
  scalar loops (measured ~50x slower than the same logic in arithmetic).
* Gamma(k, scale) tumble angles with an integer shape k are -scale * ln(prod of k uniforms)
  (a sum of k exponentials, exact); a non-integer shape falls back to torch's Gamma sampler.
* No per-step NaN check: NaN/inf from the field propagates into the methylation (and positions)
  and :meth:`Simulator.check_state` finds it at record times (``simulate_population``).
"""

from __future__ import annotations

import math
import time
import types
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import NumericalError
from surrogate.fields import Field
from surrogate.models.ecoli import EcoliParameters, adapted_methylation, ou_step
from surrogate.models.ecoli.signalling import log_receptor_terms
from surrogate.simulate.decision import DecisionLayer, is_fusable

# integer Gamma shapes up to this are drawn as sums of exponentials (k uniforms per cell)
MAX_GAMMA_UNIFORMS = 16


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


def _private_copy(method: Callable[..., Any]) -> Callable[..., Any]:
    """The bound ``method`` re-bound to a copy of its function with its own code object.

    ``torch.compile`` keeps its cache (and its recompile limit) per code object; a private copy
    per simulator means many simulators (other fields, sizes, parameters) never evict or
    exhaust each other's compiled steps.
    """
    func = method.__func__  # type: ignore[attr-defined]
    copy = types.FunctionType(
        func.__code__.replace(),
        func.__globals__,
        func.__name__,
        func.__defaults__,
        func.__closure__,
    )
    copy.__qualname__ = func.__qualname__
    return types.MethodType(copy, method.__self__)  # type: ignore[attr-defined]


class Simulator:
    """Steps a population through a field with a pluggable decision layer.

    Args:
        decision: the decision layer (``FullDecision``, ``AbstractDecision`` or any object with
            ``initialize``/``step``; the built-in ones are fused into the step kernel).
        field: the ligand field L(r, t).
        params: model constants.
        dt: time step (s).
        device: where all per-cell tensors live.
        check_finite: let :meth:`check_state` raise on NaN/inf (called at record times).
        compile: run the step kernel through ``torch.compile`` (the first steps pay the
            compile time, seconds; :meth:`warm_up` does it up front; falls back to eager with a
            warning if compiling fails, see ``compile_error``).
    """

    def __init__(
        self,
        decision: DecisionLayer,
        field: Field,
        params: EcoliParameters,
        dt: float,
        device: str | torch.device = "cpu",
        check_finite: bool = True,
        compile: bool = False,
    ) -> None:
        self.decision = decision
        self.field = field
        self.params = params
        self.dt = float(dt)
        self.device = torch.device(device)
        self.check_finite = check_finite
        self._run_step = params.speed * self.dt
        self._tumble_scale = math.radians(params.tumble_scale_deg)
        shape = float(params.tumble_shape)
        self._gamma_k = int(shape) if shape.is_integer() and shape <= MAX_GAMMA_UNIFORMS else 0
        self._tumble = torch.distributions.Gamma(
            torch.tensor(params.tumble_shape, device=self.device),
            torch.tensor(1.0 / self._tumble_scale, device=self.device),
        )
        self._m0_const = math.log(params.alpha / params.yp_adapted - 1.0) - params.eps0
        self._ou_rate = self.dt / params.tau
        self._ou_noise = params.sigma_m * math.sqrt(2.0 * self.dt / params.tau)
        self._checked_step = 0  # step up to which check_state found the state finite
        # a run-probability function's own per-call NaN check would cost a host sync per step;
        # the loop checks its state at record times instead (check_state)
        run_probability = getattr(decision, "run_probability", None)
        if getattr(run_probability, "check_finite", False):
            run_probability.check_finite = False  # type: ignore[union-attr]
        # compiled kernels (per simulator, see _private_copy); None = eager
        self.compile = bool(compile)
        self.compile_error: str | None = None
        self._kernels: dict[str, Callable[..., Any]] = {}
        if self.compile:
            for name in ("_fused_step", "_advance"):
                self._kernels[name] = torch.compile(_private_copy(getattr(self, name)))

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
        self._checked_step = 0
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
        t = state.step * self.dt
        m, run_before = state.methylation, state.run
        decision = self.decision
        fused = is_fusable(decision)
        u, u64, z, angle = self.draw_randoms(state.n_cells)
        # flags enter and leave the kernels as uint8 (free views of the bool tensors): compiled
        # CPU kernels handle bool loads/stores/blends with scalar loops, bytes in SIMD lanes
        run8, complete8 = _as_bytes(run_before), _as_bytes(state.segment_complete)
        if fused:
            out = self._run(
                "_fused_step",
                state.position, state.heading, m, run8, state.segment_steps, complete8,
                decision.fused_state(), u, u64, z, angle, t,
            )  # fmt: skip
            position, heading, m_next, run8, seg_steps, complete8, ended, ligand, dstate, _ = out
            decision.set_fused_state(dstate)  # type: ignore[attr-defined]
            run = run8.view(torch.bool)
        else:
            ligand = self.field(state.position, t)
            run = decision.step(run_before, m, ligand, self.dt)
            position, heading, m_next, seg_steps, complete8, ended = self._run(
                "_advance",
                state.position, state.heading, m, run8, run.to(torch.float32),
                state.segment_steps, complete8, ligand, None, u, z, angle,
            )  # fmt: skip
        state.position, state.heading, state.methylation = position, heading, m_next
        state.run, state.segment_steps = run, seg_steps
        state.segment_complete = complete8.view(torch.bool)
        state.step += 1
        return StepRecord(ligand, m, run_before, run, ended)

    def draw_randoms(self, n: int) -> tuple[Tensor, Tensor | None, Tensor, Tensor | None]:
        """All random numbers of one step, in at most four calls: float32 uniforms (k, n)
        (decision, Gamma angle, sign), float64 motor uniforms (M, n) or None, normals (n,),
        and the tumble angles (n,) only for a non-integer Gamma shape (else None)."""
        dev, decision = self.device, self.decision
        fused = is_fusable(decision)
        n_dec = decision.fused_uniforms if fused else 0  # type: ignore[attr-defined]
        n64 = decision.fused_uniforms64 if fused else 0  # type: ignore[attr-defined]
        u = torch.rand((n_dec + self._gamma_k + 1, n), device=dev)
        u64 = torch.rand((n64, n), dtype=torch.float64, device=dev) if n64 else None
        z = torch.randn(n, device=dev)
        angle = None if self._gamma_k else self._tumble.sample((n,))
        return u, u64, z, angle

    def _run(self, name: str, *args: Any) -> Any:
        """Call kernel ``name`` compiled if enabled (falling back to eager on failure)."""
        kernel = self._kernels.get(name)
        if kernel is not None:
            try:
                return kernel(*args)
            except Exception as exc:  # a compiler/backend failure: same function, eagerly
                self.compile_error = f"{type(exc).__name__}: {exc}"
                self._kernels.clear()
                warnings.warn(
                    f"torch.compile of the simulation step failed ({self.compile_error}); "
                    "running it eagerly",
                    RuntimeWarning,
                    stacklevel=3,
                )
        return getattr(self, name)(*args)

    def warm_up(self, state: PopulationState) -> float:
        """Compile (if enabled) by running the fused kernel on ``state`` without changing it or
        the decision layer (the kernel is pure; only the RNG stream advances); return seconds.

        Three calls: dynamo specialises on the first time value and generalises on the next.
        A decision layer that is not fusable has nothing to warm up (its ``_advance`` kernel
        compiles on the first step).
        """
        if not is_fusable(self.decision):
            return 0.0
        t0 = time.perf_counter()
        run8, complete8 = _as_bytes(state.run), _as_bytes(state.segment_complete)
        for k in range(3):
            u, u64, z, angle = self.draw_randoms(state.n_cells)
            self._run(
                "_fused_step",
                state.position, state.heading, state.methylation, run8, state.segment_steps,
                complete8, self.decision.fused_state(), u, u64, z, angle,  # type: ignore[attr-defined]
                (state.step + k) * self.dt,
            )  # fmt: skip
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter() - t0

    # ------------------------------------------------------------------------------------
    def check_state(self, state: PopulationState) -> None:
        """Raise :class:`NumericalError` if any position or methylation is NaN/inf.

        One host sync. NaN/inf concentrations from the field reach the methylation through the
        OU drift in the same step, so checking at every record time catches them; the message
        names the window since the last successful check.
        """
        if not self.check_finite:
            return
        finite = torch.isfinite(state.methylation).all() & torch.isfinite(state.position).all()
        if not bool(finite):
            t0, t1 = self._checked_step * self.dt, state.step * self.dt
            raise NumericalError(
                f"NaN/inf in the cells' methylation or positions between t={t0:g} s and "
                f"t={t1:g} s: the field returned NaN/inf concentrations or the dynamics "
                "diverged there"
            )
        self._checked_step = state.step

    # ------------------------------------------------------------------------------------
    # pure step kernels (no host sync, no RNG, no mutation): eager or torch.compile'd.
    # Flags are uint8 on input/output and float 0/1 inside (see step()).
    def _fused_step(
        self,
        position: Tensor,
        heading: Tensor,
        m: Tensor,
        run8: Tensor,
        segment_steps: Tensor,
        complete8: Tensor,
        dstate: tuple[Tensor, ...],
        u: Tensor,
        u64: Tensor | None,
        z: Tensor,
        angle: Tensor | None,
        t: float,
    ) -> tuple[Any, ...]:
        """Algorithm 1/2 for one step with a fused decision layer."""
        ligand = self.field(position, t)
        log_terms = log_receptor_terms(ligand, self.params)
        k = self.decision.fused_uniforms  # type: ignore[attr-defined]
        run_before = run8.to(torch.float32)
        run_next, dstate, aux = self.decision.fused_step(  # type: ignore[attr-defined]
            run_before, m, ligand, log_terms, self.dt, u[:k], u64, dstate
        )
        run_next = run_next.to(torch.float32)
        out = self._advance(
            position, heading, m, run8, run_next, segment_steps, complete8, ligand, log_terms,
            u[k:], z, angle,
        )  # fmt: skip
        position, heading, m_next, segment_steps, complete8, ended = out
        return (
            position, heading, m_next, run_next.to(torch.uint8), segment_steps, complete8, ended,
            ligand, dstate, aux,
        )  # fmt: skip

    def _advance(
        self,
        position: Tensor,
        heading: Tensor,
        m: Tensor,
        run8: Tensor,
        run: Tensor,
        segment_steps: Tensor,
        complete8: Tensor,
        ligand: Tensor,
        log_terms: Tensor | None,
        u: Tensor,
        z: Tensor,
        angle: Tensor | None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Everything after the decision: move/turn, OU step, run/tumble segment bookkeeping.

        ``run8`` is phi before the window (uint8), ``run`` after it (float 0/1). ``u`` holds the
        tumble's uniforms: ``gamma_k`` rows for the Gamma angle (unless ``angle`` is given) and
        one row for its sign. Flag logic is arithmetic on 0/1 numbers (see step()).
        """
        p = self.params
        run_before = run8.to(torch.float32)
        # RUN: move along the heading; TUMBLE: stay and turn (x and y as separate columns keep a
        # compiled kernel in SIMD lanes)
        step_len = run * self._run_step
        x = position[:, 0] + torch.cos(heading) * step_len
        y = position[:, 1] + torch.sin(heading) * step_len
        position = torch.stack([x, y], dim=-1)
        turning = (1.0 - run) if p.tumble_mode == "per_step" else run_before * (1.0 - run)
        if angle is None:
            # Gamma(k, scale) = scale * (sum of k Exp(1)) = -scale * ln(prod of k uniforms);
            # 1 - u lies in (0, 1], and a product of <= 4 of them stays a normal float32.
            logs = [
                torch.log(torch.prod(1.0 - u[i : min(i + 4, self._gamma_k)], dim=0))
                for i in range(0, self._gamma_k, 4)
            ]
            angle = sum(logs[1:], logs[0]) * (-self._tumble_scale)
        signed = torch.where(u[-1] < 0.5, -angle, angle)
        turned = torch.remainder(heading + signed, 2 * math.pi)
        heading = torch.where(turning > 0, turned, heading)

        # OU step of the methylation, m0(L) from the same receptor terms as the decision
        if log_terms is None:
            log_terms = log_receptor_terms(ligand, p)
        m0 = (self._m0_const - log_terms) / p.eps1
        drift = (m0 - m) * self._ou_rate
        m_next = (m + drift + self._ou_noise * z).clamp(p.m_min, p.m_max)

        # Run/tumble segments: a segment ends when phi switches; the first one is left-censored.
        # int32 arithmetic on 0/1 flags: switched, complete (segment began with a switch).
        switched = (run != run_before).to(torch.int32)
        complete = complete8.to(torch.int32)
        length = segment_steps + 1  # steps of the finished segment, incl. the last window
        sign = 2 * run8.to(torch.int32) - 1  # +1: a run ended, -1: a tumble ended
        ended_length = switched * complete * sign * length
        # the new segment's first window is this one (phi after it is the new state)
        segment_steps = length * (1 - switched)
        complete8 = torch.maximum(complete, switched).to(torch.uint8)
        return position, heading, m_next, segment_steps, complete8, ended_length


def _as_bytes(flags: Tensor) -> Tensor:
    """A bool tensor as uint8 (a free view); other dtypes are converted."""
    return flags.view(torch.uint8) if flags.dtype == torch.bool else flags.to(torch.uint8)

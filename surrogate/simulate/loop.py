"""The one outer time loop for a population of agents (Algorithms 1 and 2 of the paper).

Per step, for all cells at once: x <- body.inputs(state, field, t); phi <- decision(phi, x);
body.move(state, phi) (movement and slow internal processes); t += dt. Cells live in the batch
dimension; the only Python loop is over time steps. The loop knows no model: the body, the
internal model and the decision layer are plug-ins (:mod:`surrogate.models.base`).

Performance design (see ``surrogate.benchmarks.loop``):

* The random numbers of a step are drawn up front in at most four calls (float32 uniforms,
  float64 uniforms, normals, and a body's ``sample_extra``), their rows declared by each
  component (:class:`~surrogate.models.base.Randoms`); everything else is ONE pure function of
  tensors (:meth:`Simulator._fused_step`): inputs, decision, movement and segment bookkeeping,
  with no host sync and a fixed number of ops. ``compile=True`` runs it through
  ``torch.compile`` (fused C++/OpenMP loops on the CPU, Triton on CUDA); if compiling fails the
  simulator falls back to the same function run eagerly, with a warning.
* A decision layer without a pure form (an SSA with a data-dependent number of events) runs
  eagerly between the inputs and the (still fused) movement kernel.
* Flags (phi before/after, segment complete) enter and leave the kernel as uint8 views of bool
  tensors and are 0/1 numbers inside: compiled CPU kernels handle bool tensors with scalar loops.
* No per-step NaN check: NaN/inf propagates into the state and :meth:`Simulator.check_state`
  finds it at record times, together with the body's own check of the inputs.
"""

from __future__ import annotations

import os
import time
import types
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import CompileError, ConfigError, KernelUnsupported, NumericalError
from surrogate.fields import Field
from surrogate.models.base import BodyState, Model, Randoms
from surrogate.simulate.coupling import check_coupled_run, coupled_blocks, positions_of
from surrogate.simulate.decision import DecisionLayer, is_fusable
from surrogate.simulate.kernel_pack import pack_decision
from surrogate.simulate.precompile import kernel_wanted, wait_for_precompile
from surrogate.simulate.support import (
    SupportMonitor,
    TrainedRange,
    classes_of,
    trained_range_of,
)


@dataclass
class PopulationState:
    """Per-cell state, cells in the first dimension.

    Attributes:
        body: the body's outer state (e.g. position, heading, methylation).
        phi: bool ``(n,)``, the property after the last window (e.g. RUN).
        segment_steps: int32 ``(n,)``, steps spent in the current phi segment.
        segment_complete: bool ``(n,)``, the current segment began with a switch (not censored).
        inputs: ``n x d``, the inputs of the last step (checked at record times), or None.
        step: steps taken.
        fields: the coupled fields' states after the last step (:mod:`surrogate.grid`: the
            field objects hold them and the simulator advances them); empty for given fields.
    """

    body: BodyState
    phi: Tensor
    segment_steps: Tensor
    segment_complete: Tensor
    inputs: Tensor | None = None
    step: int = 0
    fields: tuple[Any, ...] = ()
    #: ids of the tensors :meth:`make_private` copied (the state's own, written in place)
    _own: tuple[int, ...] = field(default=(), repr=False, compare=False)

    def _tensors(self) -> list[Tensor | None]:
        return [*self.body.values(), self.phi, self.segment_steps, self.segment_complete,
                self.inputs]  # fmt: skip

    def make_private(self) -> None:
        """Replace every tensor by a contiguous copy of its own, unless it is one already (a
        compiled per-cell kernel advances them in place, so nothing a caller holds, e.g. a
        :class:`StepRecord` of the torch step or a tensor put into ``body``, changes)."""
        if self._own == tuple(map(id, self._tensors())):
            return

        def copy(t: Tensor) -> Tensor:
            return t.clone(memory_format=torch.contiguous_format)

        self.body = {k: copy(v) for k, v in self.body.items()}
        self.phi, self.segment_steps = copy(self.phi), copy(self.segment_steps)
        self.segment_complete = copy(self.segment_complete)
        self.inputs = None if self.inputs is None else copy(self.inputs)
        self._own = tuple(map(id, self._tensors()))

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return int(self.phi.shape[0])


@dataclass
class StepRecord:
    """What one step saw and did (used by collect and the recorders)."""

    inputs: Tensor  # n x d, x at the start of the step
    phi_before: Tensor  # bool, phi before the window
    phi_after: Tensor  # bool, phi after it
    ended_length: Tensor  # int32: +k a phi=1 segment of k steps ended, -k a phi=0 one, 0 none


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


def use_compile_cache(directory: str | os.PathLike) -> Path:
    """Keep ``torch.compile``'s on-disk caches (inductor's compiled kernels, FX graphs) under
    ``directory``, so every run and sweep job that shares a data directory reuses them across
    processes; an explicit ``TORCHINDUCTOR_CACHE_DIR`` in the environment wins. Returns the
    directory in use."""
    # the user's setting as the process started: torch writes its default into the variable
    # the first time it looks (e.g. while another stage of the same process runs)
    chosen = _USER_COMPILE_CACHE or str(Path(directory).resolve())
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = chosen
    return Path(chosen)


_USER_COMPILE_CACHE = os.environ.get("TORCHINDUCTOR_CACHE_DIR")


def _add(a: Randoms, b: Randoms) -> Randoms:
    return Randoms(a.uniform + b.uniform, a.uniform64 + b.uniform64, a.normal + b.normal)


#: memory one block of random numbers may take; the block covers as many steps as fit (<= 64)
RANDOM_BLOCK_BYTES = 16 << 20
MAX_BLOCK_STEPS = 64


def block_steps(n_cells: int, randoms: Randoms) -> int:
    """Steps per block of random numbers for ``n_cells`` cells: up to 64 while the block stays
    within :data:`RANDOM_BLOCK_BYTES` (one call per block and kind instead of per step)."""
    per_step = n_cells * (4 * randoms.uniform + 8 * randoms.uniform64 + 4 * randoms.normal)
    return max(1, min(MAX_BLOCK_STEPS, RANDOM_BLOCK_BYTES // max(per_step, 1)))


class RandomBlock:
    """Random numbers for ``steps`` consecutive steps, drawn in one call per kind.

    ``take()`` returns the next step's (uniform ``rows x n``, float64 uniform or None, normal)
    views. The numbers depend only on the generator's state, the rows and ``n``, so a replicate
    simulated in a batch draws exactly what it draws alone.
    """

    def __init__(
        self,
        randoms: Randoms,
        n: int,
        device: torch.device,
        generator: torch.Generator | None = None,
        steps: int | None = None,
    ) -> None:
        self.steps = block_steps(n, randoms) if steps is None else steps
        k, r = self.steps, randoms
        kw: dict[str, Any] = {"device": device, "generator": generator}
        self.u = (
            torch.rand((k, r.uniform, n), **kw)
            if r.uniform
            else torch.empty(k, 0, n, device=device)
        )
        self.u64 = (
            torch.rand((k, r.uniform64, n), dtype=torch.float64, **kw) if r.uniform64 else None
        )
        self.z = (
            torch.randn((k, r.normal, n), **kw) if r.normal else torch.empty(k, 0, n, device=device)
        )
        self.n = n
        self.next = 0

    @property
    def exhausted(self) -> bool:
        """Whether every step's numbers were taken."""
        return self.next >= self.steps

    def take_steps(self, k: int) -> tuple[Tensor, Tensor | None, Tensor]:
        """The next ``k`` steps' numbers (``k x rows x n`` views; ``k`` <= steps left)."""
        a = self.next
        self.next += k
        return (
            self.u[a : a + k],
            None if self.u64 is None else self.u64[a : a + k],
            self.z[a : a + k],
        )

    def take(self) -> tuple[Tensor, Tensor | None, Tensor]:
        """The next step's random numbers."""
        k = self.next
        self.next += 1
        return self.u[k], None if self.u64 is None else self.u64[k], self.z[k]


class Simulator:
    """Steps a population of agents through a field with a pluggable decision layer.

    Args:
        model: the agent model (its body moves the cells; its checks run here).
        decision: the decision layer (:class:`~surrogate.simulate.FullDecision`,
            :class:`~surrogate.simulate.AbstractDecision`, ...).
        field: the field L(r, t) the body reads its inputs from.
        dt: time step (s).
        device: where all per-cell tensors live.
        compile: run the step kernel through ``torch.compile`` (the first steps pay the compile
            time; :meth:`warm_up` does it up front without touching the random stream; falls
            back to eager with a warning if compiling fails, see ``compile_error``). Only for
            the torch backend.
        backend: ``torch`` (tensor operations per step, cells in the batch dimension; any
            device), ``numba`` (the model's compiled per-cell kernel, :meth:`Model.cell_kernel`:
            many steps per call, CPU only, the same random numbers as the torch step) or
            ``auto`` (numba where the model has a kernel for this decision layer and field on
            the CPU and ``compile`` is off, else torch; ``backend_note`` says why torch).
            :meth:`advance` uses it; :meth:`step` is always the torch step.
        compile_fallback: with ``compile``, run eagerly (with a warning) where compiling
            fails; False: raise :class:`~surrogate.errors.CompileError` instead (a stage whose
            artefact's identity says ``compile=true`` must not hold an eager run).

    A coupled field (:class:`~surrogate.grid.CoupledField`, e.g. a
    :class:`~surrogate.grid.GridField`) is part of the population's state: reset by
    :meth:`initial_state`, advanced by :meth:`step` after the agents (their uptake and
    secretion at their new positions, then diffusion). With ``compile`` the compiled kernel is
    the agents' step: the field is read before it and stepped after it, eagerly
    (:meth:`_read_outside`); the per-cell kernel takes one step per call, the field read
    before and stepped after each (:meth:`_advance_coupled`).

    Example:
        >>> from surrogate.fields import GaussianField
        >>> from surrogate.models.ecoli import EcoliModel
        >>> from surrogate.simulate import FullDecision
        >>> model = EcoliModel()
        >>> sim = Simulator(model, FullDecision(model.internal), GaussianField(), dt=0.05)
        >>> state = sim.initial_state(10, start=(2.0, 0.0))
        >>> record = sim.step(state)
    """

    def __init__(
        self,
        model: Model,
        decision: DecisionLayer,
        field: Field,
        dt: float,
        device: str | torch.device = "cpu",
        compile: bool = False,
        backend: str = "torch",
        compile_fallback: bool = True,
    ) -> None:
        self.model = model
        self.body = model.body
        self.decision = decision
        self.field = field
        self.dt = float(dt)
        if not self.dt > 0:
            raise ValueError(f"dt must be > 0, got {dt!r}")
        model.validate(self.dt)
        self.device = torch.device(device)
        #: let :meth:`check_state` raise on NaN/inf or bad inputs (at record times); set it
        #: False on the instance to skip the checks
        self.check_finite = True
        self._checked_step = 0  # step up to which check_state found the state sound
        self._block: RandomBlock | None = None
        self.kernel, self.backend_note = _cell_kernel(backend, model, decision, field, self.dt,
                                                      self.device, bool(compile))  # fmt: skip
        self.backend = "torch" if self.kernel is None else "numba"
        self._coupled = coupled_blocks(field)
        for coupled, _ in self._coupled:
            check_coupled_run(coupled, dt=self.dt)
        if self.kernel is not None:  # a compilation in flight fills numba's cache for its calls
            wait_for_precompile()
        self.compile = bool(compile)
        self.compile_fallback = bool(compile_fallback)
        self.compile_error: str | None = None
        self._kernels: dict[str, Callable[..., Any]] = {}
        self._support: SupportMonitor | None = None
        if self.compile and self.kernel is None:
            for name in ("_fused_step", "_advance"):
                self._kernels[name] = torch.compile(_private_copy(getattr(self, name)))

    @property
    def compiled(self) -> bool:
        """Whether the torch step runs through ``torch.compile`` (asked for, the torch loop,
        and not fallen back to eager so far)."""
        return self.compile and self.kernel is None and self.compile_error is None

    @property
    def randoms(self) -> Randoms:
        """Rows of random numbers one step draws: the decision's (first) and the body's."""
        decision = self.decision.randoms if is_fusable(self.decision) else Randoms()
        return _add(decision, self.body.randoms)

    # ------------------------------------------------------------------------------------
    def initial_state(
        self,
        n_cells: int,
        start: Sequence[float] | Tensor,
        equilibration_time: float = 0.0,
        initialize: Callable[[Tensor], Tensor] | None = None,
    ) -> PopulationState:
        """Cells at ``start`` (one point, or one per cell ``n x 2``), adapted to their inputs.

        The body draws its own initial state (e.g. headings, methylation from its stationary
        law), the decision layer its initial phi (the internal model's stationary law at each
        cell's inputs; or ``initialize(x)``'s, which starts the layer itself: a burn-in of the
        full model per cell costs more than an abstraction's whole run); then
        ``equilibration_time`` seconds of internal dynamics (decision and the body's slow
        processes, no movement) let the decision layer's own state settle.
        Coupled fields start from their initial state (the equilibration does not change them).
        """
        for coupled, _ in self._coupled:
            coupled.reset(self.device)
        body = self.body.initial_state(
            n_cells, torch.as_tensor(start, device=self.device), self.field, self.dt
        )
        x = self.body.inputs(body, self.field, 0.0)
        phi = (self.decision.initialize if initialize is None else initialize)(x)
        adapt = self.body.adapt_randoms
        for _ in range(round(equilibration_time / self.dt)):
            phi = self.decision.step(phi, x, self.dt)
            u, _, z = RandomBlock(adapt, n_cells, self.device, steps=1).take()
            body = self.body.adapt(body, x, self.dt, u, z)
            x = self.body.inputs(body, self.field, 0.0)
        self._checked_step = 0
        self._block = None  # the loop's random numbers start after the initial state's
        return PopulationState(
            body=body,
            phi=phi,
            segment_steps=torch.zeros(n_cells, dtype=torch.int32, device=self.device),
            segment_complete=torch.zeros(n_cells, dtype=torch.bool, device=self.device),
            inputs=x,
            fields=tuple(f.state for f, _ in self._coupled),
        )

    # ------------------------------------------------------------------------------------
    def step(self, state: PopulationState) -> StepRecord:
        """Advance every cell by one time step dt, in place; return what the step saw."""
        t = state.step * self.dt
        decision = self.decision
        phi_before = state.phi
        u, u64, z, extra = self.draw_randoms(state.n_cells)
        # flags enter and leave the kernels as uint8 (free views of the bool tensors): compiled
        # CPU kernels handle bool loads/stores/blends with scalar loops, bytes in SIMD lanes
        phi8, complete8 = _as_bytes(phi_before), _as_bytes(state.segment_complete)
        if is_fusable(decision):
            out = self._run(
                "_fused_step",
                state.body, phi8, state.segment_steps, complete8, decision.fused_state(),
                (u, u64, z, extra), t, self._read_outside(state.body, t),
            )  # fmt: skip
            body, phi8, seg_steps, complete8, ended, x, dstate, _ = out
            decision.set_fused_state(dstate)
            phi = phi8.view(torch.bool)
        else:
            x = self.body.inputs(state.body, self.field, t)
            phi = decision.step(phi_before, x, self.dt)
            body, seg_steps, complete8, ended = self._run(
                "_advance",
                state.body, phi8, phi.to(torch.float32), state.segment_steps, complete8, x,
                (u, z, extra),
            )  # fmt: skip
        state.body, state.phi, state.segment_steps = body, phi, seg_steps
        state.segment_complete = complete8.view(torch.bool)
        state.inputs = x
        state.step += 1
        if self._coupled:
            self._step_fields(state)
        return StepRecord(x, phi_before, phi, ended)

    def _read_outside(self, body: BodyState, t: float) -> Tensor | None:
        """The inputs read eagerly, before the step kernel, where the field is coupled; None
        (the kernel reads them) for a given field.

        A coupled field's read is state that changes between steps and, on the CPU, numba's
        exchange (:mod:`surrogate.grid.kernels`), which ``torch.compile`` cannot trace: read
        outside the kernel, it is the eager read to the byte, compiled or not, and the
        compiled kernel is the agents' step alone (the field's own step follows it, eagerly,
        in :meth:`_step_fields`)."""
        if not self._coupled:
            return None
        return self.body.inputs(body, self.field, t)

    def _step_fields(self, state: PopulationState) -> None:
        """Each coupled field's step with its cells' new positions and phi (after the agents'
        step: the exchange of step n enters the field step n + 1 reads)."""
        for coupled, cells in self._coupled:
            position = positions_of(state.body, coupled)
            coupled.step(position[cells], state.phi[cells], self.dt)
        state.fields = tuple(f.state for f, _ in self._coupled)

    def advance(self, state: PopulationState, steps: int, out: Tensor | None = None) -> Tensor:
        """Advance every cell by ``steps`` steps; return each step's ended segment lengths
        (``steps x n`` int32, as :attr:`StepRecord.ended_length`; into ``out`` if given).

        The torch backend calls :meth:`step` per step; the numba backend calls the model's
        kernel once per block of random numbers (the same numbers, in the same order), writing
        into the state's own tensors (:meth:`PopulationState.make_private`)."""
        n = state.n_cells
        if out is None:
            out = torch.empty((steps, n), dtype=torch.int32, device=self.device)
        if self.kernel is None:
            for s in range(steps):
                out[s] = self.step(state).ended_length
            return out
        if self._coupled:
            return self._advance_coupled(state, steps, out)
        state.make_private()
        done = 0
        while done < steps:
            u, u64, z = self.draw_block(n, steps - done)
            k = int(u.shape[0])
            self.kernel.advance(state, out[done : done + k], u, u64, z)
            done += k
        return out

    def _advance_coupled(self, state: PopulationState, steps: int, out: Tensor) -> Tensor:
        """:meth:`advance` on the per-cell kernel in a coupled field: one step per call, the
        inputs read before it (as :meth:`_read_outside` reads them for the torch step) and
        the fields stepped after it (:meth:`_step_fields`), the step's own random numbers."""
        state.make_private()
        for s in range(steps):
            u, u64, z = self.draw_block(state.n_cells, 1)
            # the state's own inputs tensor hands each step's read to the kernel
            x = self._read_outside(state.body, state.step * self.dt)
            assert x is not None  # a coupled field is read outside
            if state.inputs is None:
                state.inputs = x.contiguous()
            else:
                state.inputs.copy_(x)
            self.kernel.advance(state, out[s : s + 1], u, u64, z)
            self._step_fields(state)
        return out

    def draw_randoms(self, n: int) -> tuple[Tensor, Tensor | None, Tensor, Tensor | None]:
        """This step's random numbers: float32 uniforms, float64 uniforms (or None) and normals
        (rows as declared, the decision's first; views into a block drawn every
        :func:`block_steps` steps), and the body's ``sample_extra`` (or None)."""
        u, u64, z = self._current_block(n).take()
        return u, u64, z, self.body.sample_extra(n, self.device)

    def draw_block(self, n: int, max_steps: int) -> tuple[Tensor, Tensor | None, Tensor]:
        """The next up to ``max_steps`` steps' random numbers (``k x rows x n``), the same
        numbers :meth:`draw_randoms` would hand out step by step (to the end of the current
        block at most)."""
        block = self._current_block(n)
        return block.take_steps(min(max_steps, block.steps - block.next))

    def _current_block(self, n: int) -> RandomBlock:
        """The block of random numbers being handed out, a new one once it is used up."""
        if self._block is None or self._block.exhausted or self._block.n != n:
            self._block = self._next_block(n)
        return self._block

    def _next_block(self, n: int) -> RandomBlock:
        """A new block of random numbers for ``n`` cells."""
        return RandomBlock(self.randoms, n, self.device)

    def _run(self, name: str, *args: Any) -> Any:
        """Call kernel ``name`` compiled if enabled (falling back to eager on failure)."""
        kernel = self._kernels.get(name)
        if kernel is not None:
            try:
                return kernel(*args)
            except Exception as exc:  # a compiler/backend failure: same function, eagerly
                self.compile_error = f"{type(exc).__name__}: {exc}"
                self._kernels.clear()
                if not self.compile_fallback:
                    raise CompileError(
                        f"torch.compile of the simulation step failed ({self.compile_error}); "
                        "this run's settings say compile=true, so it is not run eagerly under "
                        "them: run with compile=false"
                    ) from exc
                warnings.warn(
                    f"torch.compile of the simulation step failed ({self.compile_error}); "
                    "running it eagerly",
                    RuntimeWarning,
                    stacklevel=3,
                )
        return getattr(self, name)(*args)

    def warm_up(self, state: PopulationState) -> float:
        """Compile (if enabled) by running the kernel on ``state`` without changing it, the
        decision layer or the random stream (placeholder random numbers); return seconds.

        torch.compile: three calls (dynamo specialises on the first time value and generalises
        on the next). numba: the kernel compiled, or loaded from its cache, on zero cells.
        """
        if self.kernel is not None:
            t0 = time.perf_counter()
            self.kernel.warm_up(state)
            return time.perf_counter() - t0
        if not self._kernels:
            return 0.0
        t0 = time.perf_counter()
        n, r, dev = state.n_cells, self.randoms, self.device
        u = torch.full((r.uniform, n), 0.5, device=dev)
        u64 = (
            torch.full((r.uniform64, n), 0.5, dtype=torch.float64, device=dev)
            if r.uniform64
            else None
        )
        z = torch.zeros((r.normal, n), device=dev)
        extra = self.body.sample_extra(n, dev)
        extra = None if extra is None else torch.ones_like(extra)
        phi8, complete8 = _as_bytes(state.phi), _as_bytes(state.segment_complete)
        for k in range(3):
            t = (state.step + k) * self.dt
            if is_fusable(self.decision):
                self._run(
                    "_fused_step", state.body, phi8, state.segment_steps, complete8,
                    self.decision.fused_state(), (u, u64, z, extra), t,
                    self._read_outside(state.body, t),
                )  # fmt: skip
            else:
                x = self.body.inputs(state.body, self.field, t)
                self._run(
                    "_advance", state.body, phi8, state.phi.to(torch.float32),
                    state.segment_steps, complete8, x, (u, z, extra),
                )  # fmt: skip
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter() - t0

    # ------------------------------------------------------------------------------------
    def support_blocks(
        self,
    ) -> list[tuple[slice, Callable[[Tensor], Tensor] | None, TrainedRange | None]]:
        """Per run of this loop: its cells, its decision's features and its trained range (None
        where the decision is not learned); one run here."""
        decision = self.decision
        return [(slice(0, None), getattr(decision, "featurize", None),
                 trained_range_of(decision))]  # fmt: skip

    def observe_support(self, state: PopulationState) -> None:
        """Count the cells whose abstraction inputs are outside their trained range now
        (:class:`~surrogate.simulate.support.SupportMonitor`; no host sync). The drivers call
        it every record interval (or chunk of steps)."""
        if state.inputs is None:
            return
        if self._support is None:
            blocks = [(c, f, r) for c, f, r in self.support_blocks() if r is not None]
            if not blocks:
                return
            self._support = SupportMonitor(blocks)
        # a K-lumps block checks each cell against its own class's rows
        classes = classes_of(self.decision) if self._support.needs_classes else None
        self._support.observe(state.inputs, state.phi, classes)

    def support_report(self) -> list[dict[str, Any] | None]:
        """Per run (:meth:`support_blocks` order): the monitor's report, None where the run has
        no learned decision or was never observed."""
        blocks = self.support_blocks()
        if self._support is None:
            return [None] * len(blocks)
        reports = iter(self._support.report())
        return [next(reports) if r is not None else None for _, _, r in blocks]

    def check_state(self, state: PopulationState) -> None:
        """Raise :class:`NumericalError` if the body's state is NaN/inf or its last inputs are
        bad (the body's own check, e.g. negative concentrations). One host sync.

        NaN/inf inputs reach the body's state through its slow processes in the same step, so
        checking at every record time catches them; the message names the window since the last
        successful check.
        """
        if not self.check_finite:
            return
        floats = [v for v in state.body.values() if v.dtype.is_floating_point]
        finite = torch.stack([torch.isfinite(v).all() for v in floats]).all()
        problem = None if bool(finite) else "NaN/inf in the cells' state"
        if state.inputs is not None:
            bad_inputs = self.body.check_inputs(state.inputs)
            problem = bad_inputs or problem
        for coupled, _ in self._coupled:
            problem = problem or coupled.check()
        if problem is not None:
            t0, t1 = self._checked_step * self.dt, state.step * self.dt
            when = f"at t={t1:g} s" if t0 == t1 else f"between t={t0:g} s and t={t1:g} s"
            raise NumericalError(
                f"{problem} {when}: the field returned bad values or the dynamics diverged there"
            )
        self._checked_step = state.step

    # ------------------------------------------------------------------------------------
    # pure step kernels (no host sync, no RNG, no mutation): eager or torch.compile'd.
    # Flags are uint8 on input/output and float 0/1 inside (see step()).
    def _fused_step(
        self,
        body: BodyState,
        phi8: Tensor,
        segment_steps: Tensor,
        complete8: Tensor,
        dstate: tuple[Tensor, ...],
        draws: tuple[Tensor, Tensor | None, Tensor, Tensor | None],
        t: float,
        x: Tensor | None = None,
    ) -> tuple[Any, ...]:
        """Algorithm 1/2 for one step with a fused decision layer (reading the inputs at
        ``t`` unless given, as :meth:`_read_outside` gives them for a coupled field);
        ``draws``: the step's random numbers ``u, u64, z, extra`` (:meth:`draw_randoms`)."""
        u, u64, z, extra = draws
        if x is None:
            x = self.body.inputs(body, self.field, t)
        r = self.decision.randoms
        phi_before = phi8.to(torch.float32)
        phi_after, dstate, aux = self.decision.fused_step(
            phi_before, x, self.dt, u[: r.uniform], u64, dstate
        )
        phi_after = phi_after.to(torch.float32)
        body, segment_steps, complete8, ended = self._advance(
            body, phi8, phi_after, segment_steps, complete8, x,
            (u[r.uniform :], z[r.normal :], extra),
        )  # fmt: skip
        return body, phi_after.to(torch.uint8), segment_steps, complete8, ended, x, dstate, aux

    def _advance(
        self,
        body: BodyState,
        phi8: Tensor,
        phi_after: Tensor,
        segment_steps: Tensor,
        complete8: Tensor,
        x: Tensor,
        draws: tuple[Tensor, Tensor, Tensor | None],
    ) -> tuple[BodyState, Tensor, Tensor, Tensor]:
        """Everything after the decision: the body's move, then the phi segment bookkeeping.

        ``phi8`` is phi before the window (uint8), ``phi_after`` after it (float 0/1);
        ``draws`` the body's uniforms, normals and extra draws (``u, z, extra``).
        """
        u, z, extra = draws
        phi_before = phi8.to(torch.float32)
        body = self.body.move(body, phi_before, phi_after, x, self.dt, u, z, extra)
        # A segment ends when phi switches; the first one is left-censored. int32 arithmetic
        # on 0/1 flags: switched, complete (the segment began with a switch).
        switched = (phi_after != phi_before).to(torch.int32)
        complete = complete8.to(torch.int32)
        length = segment_steps + 1  # steps of the finished segment, incl. the last window
        sign = 2 * phi8.to(torch.int32) - 1  # +1: a phi = 1 segment ended, -1: a phi = 0 one
        ended_length = switched * complete * sign * length
        # the new segment's first window is this one (phi after it is the new state)
        segment_steps = length * (1 - switched)
        complete8 = torch.maximum(complete, switched).to(torch.uint8)
        return body, segment_steps, complete8, ended_length


BACKENDS = ("auto", "torch", "numba")


def check_backend(backend: Any) -> str:
    """``backend`` if it is one of :data:`BACKENDS`, else a :class:`ConfigError` naming them."""
    if backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {list(BACKENDS)}, got {backend!r}")
    return str(backend)


def _cell_kernel(
    backend: str,
    model: Model,
    decision: DecisionLayer,
    field: Field,
    dt: float,
    device: torch.device,
    compile: bool = False,
) -> tuple[Any, str | None]:
    """The model's per-cell kernel for ``backend`` (None: the torch step) and, for ``auto``
    falling back to torch, why. ``auto`` with ``compile`` is the compiled torch step (what
    was asked for; the faster one from ~1e4 cells on, see docs/performance.md)."""
    if not kernel_wanted(check_backend(backend), compile):
        return None, ("compile=true asks for torch.compile of the torch step"
                      if backend == "auto" else None)  # fmt: skip
    try:
        if device.type != "cpu":
            raise KernelUnsupported(f"device {device} (the per-cell kernel runs on the CPU)")
        kernel = model.cell_kernel(pack_decision(decision, dt), field, dt)
    except KernelUnsupported as exc:
        if backend == "numba":
            raise KernelUnsupported(
                f"backend=numba cannot run {exc}; use backend=torch (or auto)"
            ) from None
        return None, f"no per-cell kernel for {exc}"
    return kernel, None


def resolve_backend(
    backend: str,
    model: Model,
    decision: DecisionLayer,
    field: Field,
    dt: float,
    device: str | torch.device = "cpu",
    compile: bool = False,
) -> str:
    """The loop backend (``torch`` or ``numba``) a :class:`Simulator` with these arguments
    runs, without building it."""
    kernel, _ = _cell_kernel(backend, model, decision, field, float(dt), torch.device(device),
                             compile)  # fmt: skip
    return "torch" if kernel is None else "numba"


def _as_bytes(flags: Tensor) -> Tensor:
    """A bool tensor as uint8 (a free view); other dtypes are converted."""
    return flags.view(torch.uint8) if flags.dtype == torch.bool else flags.to(torch.uint8)

"""Replicates in one batch: several independent runs simulated as one population tensor.

Small populations pay a per-step cost (Python, kernel launches, random-number calls) that does
not depend on the number of cells. Independent runs of one model - other seeds, the
full-vs-full noise-floor run, other fields, even other decision layers - can share every step
instead: block i of the population is replicate i, with its own field
(:class:`~surrogate.fields.FieldBatch`), its own decision layer
(:class:`~surrogate.simulate.decision_batch.DecisionBatch`) and its own random stream. A
coupled field (:mod:`surrogate.grid`) is a replicate's own state: each replicate gets its own
copy, stepped with its own cells only.

Each replicate draws its initial state from the global generator seeded with its own seed, then
continues on a private ``torch.Generator`` that carries on from exactly that state, drawing its
rows of every step's random numbers in the layout a standalone run would use. So a replicate
sees the same random numbers as the same run simulated alone; eager CPU kernels are
elementwise per cell, which makes an eager batched replicate bit-for-bit the standalone run
(tested), while compiled kernels may round the last bits of a few cells differently (a
vectorised body and a scalar tail), which leaves it identical in distribution. Where a layer
is not fusable (a network's full model stepped eagerly), the batch steps eagerly, one layer
per replicate, each on
its replicate's generator: a replicate's draws then depend on its seed and the batch's
fusability, not on which other replicates run beside it (a fusable layer in such a batch
steps eagerly too, so it is its standalone run in distribution, not bit for bit).
"""

from __future__ import annotations

import copy
import dataclasses
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from surrogate.fields import Field, FieldBatch
from surrogate.grid.coupled import is_coupled
from surrogate.models.base import Model, Randoms
from surrogate.models.capabilities import concat_states_of, histogram_grids_of
from surrogate.simulate.coupling import positions_of
from surrogate.simulate.decision import AbstractDecision, DecisionLayer, is_fusable
from surrogate.simulate.decision_batch import DecisionBatch, global_state, own_stream
from surrogate.simulate.loop import PopulationState, RandomBlock, Simulator
from surrogate.simulate.population import PopulationSummary, steps_between
from surrogate.simulate.profiles import ProfileRecorder
from surrogate.simulate.recorders import (
    BUFFER_BYTES,
    FLUSH_STEPS,
    RecorderSpec,
    RunRecorder,
    records_durations,
)
from surrogate.simulate.support import TrainedRange, trained_range_of


@dataclass
class Replicate:
    """One run of a batch: its decision layer, field, size, seed and start."""

    decision: DecisionLayer
    field: Field
    n_cells: int
    seed: int
    start: Sequence[float] | Tensor = (2.0, 0.0)


class BatchSimulator(Simulator):
    """A :class:`Simulator` over replicates in one population (see the module docstring).

    Consecutive replicates whose decision layers are interchangeable (the same class over the
    same internal model and run probability) are merged into one layer over their cells, so a
    batch of many runs costs about as many tensor operations per step as one run.

    Args:
        model: the agent model shared by every replicate.
        replicates: the runs, in block order; each needs its own decision-layer instance.
        dt, device, compile, backend, compile_fallback: as for :class:`Simulator`.
        check_finite: sets :attr:`Simulator.check_finite`.

    Example:
        >>> from surrogate.fields import GaussianField, LinearField
        >>> from surrogate.models.ecoli import EcoliModel
        >>> from surrogate.simulate import FullDecision
        >>> model = EcoliModel()
        >>> sim = BatchSimulator(model, [
        ...     Replicate(FullDecision(model.internal), GaussianField(), 100, seed=0),
        ...     Replicate(FullDecision(model.internal), LinearField(), 100, seed=1)], dt=0.05)
        >>> state = sim.initial_state(equilibration_time=1.0)
    """

    decision: DecisionBatch
    field: FieldBatch

    def __init__(
        self,
        model: Model,
        replicates: Sequence[Replicate],
        dt: float,
        device: str | torch.device = "cpu",
        check_finite: bool = True,
        compile: bool = False,
        backend: str = "torch",
        compile_fallback: bool = True,
    ) -> None:
        self.replicates = _own_coupled_fields(replicates)
        if not self.replicates:
            raise ValueError("a batch needs at least one replicate")
        sizes = [r.n_cells for r in self.replicates]
        self.groups, members = _decision_blocks(self.replicates)
        group_sizes = [sum(sizes[i] for i in g) for g in self.groups]
        decision = DecisionBatch(members, group_sizes)
        # consecutive replicates in the same field object share one block of the field
        blocks: list[tuple[Field, int]] = []
        for r in self.replicates:
            if blocks and blocks[-1][0] is r.field:
                blocks[-1] = (r.field, blocks[-1][1] + r.n_cells)
            else:
                blocks.append((r.field, r.n_cells))
        field = FieldBatch([f for f, _ in blocks], [n for _, n in blocks])
        super().__init__(model, decision, field, dt, device, compile, backend, compile_fallback)
        self.check_finite = check_finite
        self.sizes = sizes
        self.slices = [slice(a, a + n) for a, n in zip(_offsets(sizes), sizes, strict=True)]
        self._blocks: list[RandomBlock] = []
        self.generators: list[torch.Generator] = []

    def initial_state(
        self,
        n_cells: int | None = None,
        start: Sequence[float] | Tensor | None = None,
        equilibration_time: float = 0.0,
        initialize: Callable[[Tensor], Tensor] | None = None,
    ) -> PopulationState:
        """Every replicate's initial state exactly as a standalone run with its seed draws it
        (equilibration included); then each continues on its own generator. ``initialize``
        is refused: each replicate's layer starts as it does alone."""
        if initialize is not None:
            raise ValueError("a batch of replicates starts each replicate's layer as a "
                             "standalone run does: initialize is not taken")  # fmt: skip
        states, self.generators, layer_states = [], [], []
        for rep in self.replicates:
            torch.manual_seed(int(rep.seed))
            alone = Simulator(self.model, rep.decision, rep.field, self.dt, self.device)
            states.append(alone.initial_state(rep.n_cells, rep.start, equilibration_time))
            # read now: a layer object serving several replicates holds only the last one's
            layer_states.append(rep.decision.fused_state())
            gen = torch.Generator(device=self.device)
            gen.set_state(global_state(self.device))
            self.generators.append(gen)
        if not is_fusable(self.decision):
            # eager layers draw from the global generator: each from its replicate's own
            # (one replicate per layer, _decision_blocks)
            self.decision.generators = [self.generators[g[0]] for g in self.groups]
        internal = self.model.internal
        for member, group in zip(self.decision.members, self.groups, strict=True):
            parts = [layer_states[i] for i in group]
            if any(parts):
                # a layer with its own per-cell state (e.g. a switch clock) concatenates it
                concat = getattr(member, "concat_states", None) or concat_states_of(internal)
                member.set_fused_state(concat(parts))
        self._checked_step = 0
        self._block, self._blocks = None, []
        body = {k: torch.cat([s.body[k] for s in states]) for k in states[0].body}
        return PopulationState(
            body=body,
            phi=torch.cat([s.phi for s in states]),
            segment_steps=torch.cat([s.segment_steps for s in states]),
            segment_complete=torch.cat([s.segment_complete for s in states]),
            inputs=torch.cat([s.inputs for s in states]),  # type: ignore[misc]
            fields=tuple(f.state for f, _ in self._coupled),
        )

    def support_blocks(
        self,
    ) -> list[tuple[slice, Callable[[Tensor], Tensor] | None, TrainedRange | None]]:
        """Per replicate: its cells, its decision's features and its trained range."""
        return [(cells, getattr(rep.decision, "featurize", None), trained_range_of(rep.decision))
                for rep, cells in zip(self.replicates, self.slices, strict=True)]  # fmt: skip

    def _replicate_randoms(self, i: int) -> Randoms:
        decision = self.replicates[i].decision
        r = decision.randoms if is_fusable(self.decision) else Randoms()
        b = self.body.randoms
        return Randoms(r.uniform + b.uniform, r.uniform64 + b.uniform64, r.normal + b.normal)

    def draw_randoms(self, n: int) -> tuple[Tensor, Tensor | None, Tensor, Tensor | None]:
        """Each replicate's rows from its own generator, in its standalone layout (the
        decision's rows right-aligned before the body's), assembled into the batch's."""
        if self._block is None or self._block.exhausted:
            self._block = self._next_block(n)
        u, u64, z = self._block.take()
        extras = [
            self._extra(s.stop - s.start, g)
            for s, g in zip(self.slices, self.generators, strict=True)
        ]
        return u, u64, z, None if extras[0] is None else torch.cat(extras)  # type: ignore[arg-type]

    def _next_block(self, n: int) -> RandomBlock:
        return self._assemble()

    def _assemble(self) -> RandomBlock:
        """The next block of the batch: every replicate's next block placed in its columns.

        A replicate draws its next block when its own is used up (as its standalone run does);
        replicates whose blocks cover different numbers of steps (very different sizes) are
        assembled over the steps all of them have left."""
        if not self._blocks:
            self._blocks = [None] * len(self.slices)  # type: ignore[list-item]
        for i, (s, gen) in enumerate(zip(self.slices, self.generators, strict=True)):
            if self._blocks[i] is None or self._blocks[i].exhausted:
                self._blocks[i] = RandomBlock(self._replicate_randoms(i), s.stop - s.start,
                                              self.device, gen)  # fmt: skip
        k = min(b.steps - b.next for b in self._blocks)
        total, n = self.randoms, sum(self.sizes)
        out = RandomBlock.__new__(RandomBlock)
        out.steps, out.next, out.n = k, 0, n
        out.u = torch.zeros((k, total.uniform, n), device=self.device)
        out.u64 = (torch.zeros((k, total.uniform64, n), dtype=torch.float64, device=self.device)
                   if total.uniform64 else None)  # fmt: skip
        out.z = torch.zeros((k, total.normal, n), device=self.device)
        for block, cols in zip(self._blocks, self.slices, strict=True):
            a = block.next
            for name in ("u", "u64", "z"):
                src, dst = getattr(block, name), getattr(out, name)
                if src is None or dst is None or src.shape[1] == 0:
                    continue
                dst[:, dst.shape[1] - src.shape[1] :, cols] = src[a : a + k]
            block.next += k
        return out

    def _extra(self, m: int, gen: torch.Generator) -> Tensor | None:
        """The body's extra random numbers for one replicate (drawn from the global generator by
        the body), taken from the replicate's generator by swapping states around the call."""
        if self.body.sample_extra(0, self.device) is None:
            return None
        with own_stream(gen, self.device):
            return self.body.sample_extra(m, self.device)


def _own_coupled_fields(replicates: Sequence[Replicate]) -> list[Replicate]:
    """The replicates, each coupled field (:mod:`surrogate.grid`) its replicate's own: a
    replicate whose field object an earlier one already has gets a deep copy (a coupled
    field's state is its cells', so replicates never share one; each starts from the initial
    state at :meth:`BatchSimulator.initial_state`)."""
    seen: set[int] = set()
    out = []
    for rep in replicates:
        if is_coupled(rep.field) and id(rep.field) in seen:
            rep = dataclasses.replace(rep, field=copy.deepcopy(rep.field))
        seen.add(id(rep.field))
        out.append(rep)
    return out


def _groups(decisions: Sequence[DecisionLayer]) -> list[list[int]]:
    """Runs of consecutive interchangeable decision layers (indices)."""
    groups: list[list[int]] = []
    for i, d in enumerate(decisions):
        if groups and _interchangeable(decisions[groups[-1][0]], d):
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def _decision_blocks(
    replicates: Sequence[Replicate],
) -> tuple[list[list[int]], list[DecisionLayer]]:
    """The batch's decision blocks: (replicate indices, decision layer) per block.

    Where any layer is not fusable (the batch steps eagerly), every replicate is its own
    block, stepped on its replicate's generator (merged, several replicates' draws would share
    one stream). Else consecutive interchangeable layers share one block (:func:`_groups`),
    and consecutive blocks of two-state chains over lookup tables of one shape are stacked
    (:func:`_stacked`).
    """
    decisions = [r.decision for r in replicates]
    eager = not all(is_fusable(d) for d in decisions)
    groups = [[i] for i in range(len(replicates))] if eager else _groups(decisions)
    members = [replicates[g[0]].decision for g in groups]
    merged_groups, merged = (groups, members) if eager else _stacked(replicates, groups, members)
    # one layer object in two blocks (replicates apart): the second gets a copy of its own,
    # else the blocks would share one per-cell state (classes, clocks, motor states)
    seen: set[int] = set()
    for k, member in enumerate(merged):
        if id(member) in seen:
            merged[k] = copy.copy(member)
        seen.add(id(member))
    return merged_groups, merged


def _stacked(
    replicates: Sequence[Replicate], groups: list[list[int]], members: list[DecisionLayer]
) -> tuple[list[list[int]], list[DecisionLayer]]:
    """Consecutive blocks of two-state chains over lookup tables of one shape and the same
    features (e.g. the learned abstraction and the exact-psi chain) stacked into one layer
    over a :class:`~surrogate.gp.lookup.StackedPsiLookup`: one featurisation and one
    interpolation per step for all of them, with the same numbers as separate blocks."""
    merged_groups: list[list[int]] = []
    merged: list[DecisionLayer] = []
    k = 0
    while k < len(groups):
        end = k + 1
        while end < len(groups) and _stackable(members[k], members[end]):
            end += 1
        if end - k == 1:
            merged_groups.append(groups[k])
            merged.append(members[k])
        else:
            from surrogate.gp.lookup import StackedPsiLookup

            cells = [sum(replicates[i].n_cells for i in g) for g in groups[k:end]]
            first = members[k]
            table = StackedPsiLookup([m.run_probability for m in members[k:end]], cells)  # type: ignore[attr-defined]
            name = "+".join(dict.fromkeys(m.name for m in members[k:end]))
            merged.append(first.restacked(table, name))  # type: ignore[attr-defined]
            merged_groups.append([i for g in groups[k:end] for i in g])
        k = end
    return merged_groups, merged


def _stackable(a: DecisionLayer, b: DecisionLayer) -> bool:
    """Whether two two-state chains can share one stacked lookup (see
    :func:`_decision_blocks`): same fused protocol, internal model, features and grid."""
    if not (isinstance(a, AbstractDecision) and isinstance(b, AbstractDecision)):
        return False
    # stateful layers share StatefulDecision.fused_step: their window rule is _pure_step
    same_rule = (type(a).fused_step is type(b).fused_step
                 and getattr(type(a), "_pure_step", None) is getattr(type(b), "_pure_step", None))  # fmt: skip
    if not same_rule or a.randoms != b.randoms:
        return False
    if getattr(a, "max_age", None) != getattr(b, "max_age", None):  # switch clocks' caps
        return False
    # a table exists only if its module was imported (the engine does not import gp itself)
    lookup = sys.modules.get("surrogate.gp.lookup")
    table = getattr(lookup, "PsiLookupTable", None)
    ta, tb = a.run_probability, b.run_probability
    if table is None or not (isinstance(ta, table) and isinstance(tb, table)):
        return False
    return (
        a.internal is b.internal
        and a.featurize == b.featurize
        and (ta.shape, ta.input_names, ta.device) == (tb.shape, tb.input_names, tb.device)
        and is_fusable(a)
        and is_fusable(b)
    )


def _interchangeable(a: DecisionLayer, b: DecisionLayer) -> bool:
    """Whether two layers can be one block: the same kind over the same objects, and a run
    probability (if any) declared ``rowwise``. A psi whose rows interact numerically (e.g.
    matmul-based, with code paths by row count) would give a replicate other last bits in a
    block than alone."""
    same = type(a) is type(b) and a.name == b.name
    for attr in ("internal", "run_probability", "table"):  # table: a K-lumps chain's law
        same = same and getattr(a, attr, None) is getattr(b, attr, None)
    psi = getattr(a, "run_probability", None)
    rowwise = psi is None or bool(getattr(psi, "rowwise", False))
    return same and rowwise and is_fusable(a) == is_fusable(b)


def _offsets(sizes: Sequence[int]) -> list[int]:
    out, acc = [], 0
    for n in sizes:
        out.append(acc)
        acc += n
    return out


def simulate_batch(
    simulator: BatchSimulator,
    t_end: float,
    out_dirs: Sequence[str | os.PathLike],
    record_interval: float = 1.0,
    equilibration_time: float = 0.0,
    progress: bool = True,
    *,
    recording: RecorderSpec | None = None,
) -> list[PopulationSummary]:
    """:func:`~surrogate.simulate.simulate_population` for every replicate of a batch at once:
    one loop, one recorder per replicate writing the ordinary run files into its own directory
    (``out_dirs``, in replicate order), each committed only once the whole batch completes.

    The loop time is the batch's (shared by its replicates); a replicate's cells are seeded as
    its standalone run's (its seed also chooses its recorded cells, in place of
    ``recording.seed``). ``recording``: what each replicate's
    :class:`~surrogate.simulate.recorders.RunRecorder` keeps (default: as the class's defaults),
    the body's declared histogram grids under ``recording.histogram_spec``. A replicate in a
    grid field also records its profiles along x (its own field and cells).
    """

    if len(out_dirs) != len(simulator.replicates):
        raise ValueError("simulate_batch needs one output directory per replicate")
    dt = simulator.dt
    n_steps = steps_between(t_end, dt, "t_end")
    every = steps_between(record_interval, dt, "record_interval")
    body, lumps = simulator.body, simulator.model.internal.lump_names
    recording = recording or RecorderSpec()
    grids = {**histogram_grids_of(body), **dict(recording.histogram_spec or {})}
    mode = recording.durations
    t0 = time.perf_counter()
    recorders: list[RunRecorder] = []
    profiles: list[ProfileRecorder | None] = []
    try:
        for rep, out in zip(simulator.replicates, out_dirs, strict=True):
            recorders.append(RunRecorder(
                Path(out), rep.n_cells, dt, body.observable_names, lumps, block_steps=max(every, FLUSH_STEPS),
                device=simulator.device,
                spec=dataclasses.replace(recording, histogram_spec=grids, seed=int(rep.seed))))  # fmt: skip
            profiles.append(ProfileRecorder.of(Path(out), rep.field, rep.n_cells))
        # the whole batch's segment ends, buffered on the device and handed to the replicates'
        # recorders a block at a time (not one call per replicate and step)
        n_total = sum(rep.n_cells for rep in simulator.replicates)
        rows = max(1, min(FLUSH_STEPS, BUFFER_BYTES // (4 * n_total)))
        buffer = torch.zeros(rows, n_total, dtype=torch.int32, device=simulator.device)
        filled, first = 0, 0

        def hand_over() -> None:
            for rec, cells in zip(recorders, simulator.slices, strict=True):
                rec.record_block(first, buffer[:filled, cells])

        with torch.inference_mode():  # cheaper per op than no_grad
            state = simulator.initial_state(equilibration_time=equilibration_time)
            simulator.check_state(state)
            _record(recorders, profiles, simulator, state, 0.0)
            compile_time = simulator.warm_up(state)
            loop_start = time.perf_counter()
            k = 0
            with tqdm(total=n_steps, desc=f"simulate {simulator.decision.name}", unit="step",
                      disable=not progress, mininterval=1.0) as bar:  # fmt: skip
                while k < n_steps:  # to the next record time, or until the buffer is full
                    steps = min(every - k % every, n_steps - k, rows - filled)
                    if filled == 0:
                        first = k
                    simulator.advance(state, steps, out=buffer[filled : filled + steps])
                    filled += steps
                    if filled == rows:
                        if records_durations(mode):
                            hand_over()
                        filled = 0
                    k += steps
                    bar.update(steps)
                    if k % every == 0:
                        simulator.check_state(state)
                        simulator.observe_support(state)
                        _record(recorders, profiles, simulator, state, k * dt)
            if records_durations(mode) and filled:
                hand_over()
            simulator.check_state(state)
            if simulator.device.type == "cuda":
                torch.cuda.synchronize(simulator.device)
            loop_time = time.perf_counter() - loop_start
        facts = [rec.commit() for rec in recorders]
        profile_facts = [p.commit() if p is not None else None for p in profiles]
    except BaseException:
        for rec in [*recorders, *profiles]:
            if rec is not None:
                rec.abort()
        raise
    wall = time.perf_counter() - t0
    support = simulator.support_report()
    return [
        PopulationSummary(
            n_cells=rep.n_cells,
            n_steps=n_steps,
            dt=dt,
            t_end=t_end,
            wall_time_s=wall,
            loop_time_s=loop_time,
            record_times=rec.times,
            compile_time_s=compile_time,
            means=rec.means,
            n_durations=f["n_durations"],
            recording=f,
            outside_training=outside,
            profiles=p,
        )
        for rep, rec, f, outside, p in zip(
            simulator.replicates, recorders, facts, support, profile_facts, strict=True
        )
    ]


def _record(
    recorders: Sequence[Any],
    profiles: Sequence[ProfileRecorder | None],
    simulator: BatchSimulator,
    state: PopulationState,
    t: float,
) -> None:
    observed = simulator.body.observables(state.body, simulator.field)
    for rec, cells in zip(recorders, simulator.slices, strict=True):
        rec.record_observables(t, {k: v[cells] for k, v in observed.items()})
    for prof, cells in zip(profiles, simulator.slices, strict=True):
        if prof is not None:
            prof.record(t, positions_of(state.body, prof.field)[cells])


__all__ = ["BatchSimulator", "DecisionBatch", "Replicate", "simulate_batch"]

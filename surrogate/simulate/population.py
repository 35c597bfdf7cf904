"""Run a whole population to t_end and stream its summaries to an artefact directory."""

from __future__ import annotations

import gc
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from surrogate.models.capabilities import histogram_grids_of
from surrogate.simulate import speed
from surrogate.simulate.coupling import positions_of
from surrogate.simulate.loop import Simulator
from surrogate.simulate.profiles import ProfileRecorder
from surrogate.simulate.recorders import (
    DEFAULT_RECORD_CELLS,
    DURATIONS,
    FLUSH_STEPS,
    OBSERVABLES,
    DurationMode,
    GridSpec,
    RecorderSpec,
    RunRecorder,
    records_durations,
)


@dataclass
class PopulationSummary:
    """What a finished run reports (the tables themselves are on disk)."""

    n_cells: int
    n_steps: int
    dt: float
    t_end: float
    wall_time_s: float
    loop_time_s: float
    record_times: list[float] = field(default_factory=list)
    compile_time_s: float = 0.0  # warm-up (torch.compile) time, not part of loop_time_s
    means: dict[str, list[float]] = field(default_factory=dict)  # observable -> mean per record
    n_durations: int = 0
    recording: dict[str, Any] = field(default_factory=dict)  # RunRecorder.commit()'s facts
    #: inputs outside the abstraction's trained range (SupportMonitor.report; None: not learned)
    outside_training: dict[str, Any] | None = None
    #: ProfileRecorder.commit()'s facts (a run in a grid field); None for a given field
    profiles: dict[str, Any] | None = None

    @property
    def cell_steps_per_s(self) -> float:
        """Throughput of the time loop (:func:`~surrogate.simulate.speed.cell_steps_per_s`)."""
        return speed.cell_steps_per_s(self.n_cells, self.n_steps, max(self.loop_time_s, 1e-12))


def steps_between(interval: float, dt: float, what: str) -> int:
    """Whole number of steps in ``interval`` (must be a positive multiple of dt)."""
    k = round(interval / dt)
    if k < 1 or abs(k * dt - interval) > 1e-6 * max(1.0, interval):
        raise ValueError(f"{what}={interval:g} s must be a positive multiple of dt={dt:g} s")
    return k


def simulate_population(  # noqa: PLR0913  # the public entry point, called with keywords
    simulator: Simulator,
    n_cells: int,
    t_end: float,
    out_dir: str | os.PathLike,
    record_interval: float = 1.0,
    start: Sequence[float] | torch.Tensor = (2.0, 0.0),
    equilibration_time: float = 0.0,
    record_durations: bool = True,
    progress: bool = True,
    *,
    record_cells: int | None = DEFAULT_RECORD_CELLS,
    durations: DurationMode | None = None,
    histogram_spec: Mapping[str, GridSpec] | None = None,
    recorder_seed: int | None = None,
) -> PopulationSummary:
    """Simulate ``n_cells`` cells to ``t_end`` and write what
    :class:`~surrogate.simulate.recorders.RunRecorder` keeps into ``out_dir`` (atomically, only
    once the run completes): the observables at record times (histograms and moments over all
    cells, exact values of ``record_cells`` seeded random cells; None: every cell) and the completed phi segments
    (exact lattice histogram; ``durations="histogram"`` keeps the recorded cells' segments in
    ``durations.parquet``, ``"all"`` every segment, ``"none"`` nothing); in a grid field, also
    the density and concentration profiles along x at the record times
    (:class:`~surrogate.simulate.profiles.ProfileRecorder`: ``profiles.parquet``).
    ``durations`` defaults to ``"histogram"``, or ``"none"`` when ``record_durations`` is
    false. ``recorder_seed`` (default ``torch.initial_seed()``) seeds the choice of recorded
    cells.

    The state is checked for NaN/inf at every record time (:meth:`Simulator.check_state`,
    raising :class:`~surrogate.errors.NumericalError` with the time window), not every step,
    so the loop has no per-step host sync. With ``simulator.compile`` (or a compiled per-cell
    kernel, ``backend``) the step is compiled first without changing the state
    (``compile_time_s``), outside the loop timing. The loop advances one record interval per
    :meth:`Simulator.advance` call.
    """
    dt = simulator.dt
    n_steps = steps_between(t_end, dt, "t_end")
    every = steps_between(record_interval, dt, "record_interval")
    out = Path(out_dir)
    t0 = time.perf_counter()
    body, field_ = simulator.body, simulator.field
    mode = durations if durations is not None else ("histogram" if record_durations else "none")
    seed = torch.initial_seed() if recorder_seed is None else recorder_seed
    recorder: RunRecorder | None = None
    profiles: ProfileRecorder | None = None
    try:
        # created inside the try, so an interrupt right at the start drops its temporaries too
        grids = {**histogram_grids_of(body), **dict(histogram_spec or {})}
        spec = RecorderSpec(record_cells, mode, grids, seed)
        recorder = RunRecorder(out, n_cells, dt, body.observable_names,
                               simulator.model.internal.lump_names, block_steps=max(every, FLUSH_STEPS),
                               device=simulator.device, spec=spec)  # fmt: skip
        profiles = ProfileRecorder.of(out, field_, n_cells)
        steps_recorded = records_durations(mode)
        with torch.inference_mode():  # cheaper per op than no_grad
            state = simulator.initial_state(n_cells, start, equilibration_time)
            simulator.check_state(state)
            recorder.record_observables(0.0, body.observables(state.body, field_))
            if profiles is not None:
                profiles.record(0.0, positions_of(state.body, profiles.field))
            compile_time = simulator.warm_up(state)
            # the objects alive now (models, compiled graphs, caches) are set aside from the
            # cyclic GC for the loop, so its frequent young-generation passes stay short (they
            # are collectable again after the loop)
            gc.freeze()
            loop_start = time.perf_counter()
            k = 0
            with tqdm(total=n_steps, desc=f"simulate {simulator.decision.name}", unit="step",
                      disable=not progress, mininterval=1.0) as bar:  # fmt: skip
                while k < n_steps:  # one call per record interval (many steps for a kernel)
                    steps = min(every - k % every, n_steps - k)
                    ended = simulator.advance(state, steps)
                    if steps_recorded:
                        recorder.record_block(k, ended)
                    k += steps
                    bar.update(steps)
                    if k % every == 0:
                        simulator.check_state(state)
                        simulator.observe_support(state)
                        recorder.record_observables(k * dt, body.observables(state.body, field_))
                        if profiles is not None:
                            profiles.record(k * dt, positions_of(state.body, profiles.field))
            simulator.check_state(state)  # the tail after the last record time
            if simulator.device.type == "cuda":
                torch.cuda.synchronize(simulator.device)
            loop_time = time.perf_counter() - loop_start
            gc.unfreeze()
        facts = recorder.commit()
        profile_facts = profiles.commit() if profiles is not None else None
    except BaseException:
        gc.unfreeze()
        for rec in (recorder, profiles):
            if rec is not None:
                rec.abort()
        raise
    return PopulationSummary(
        n_cells=n_cells,
        n_steps=n_steps,
        dt=dt,
        t_end=t_end,
        wall_time_s=time.perf_counter() - t0,
        loop_time_s=loop_time,
        record_times=recorder.times,
        means=recorder.means,
        n_durations=facts["n_durations"],
        compile_time_s=compile_time,
        recording=facts,
        outside_training=simulator.support_report()[0],
        profiles=profile_facts,
    )


__all__ = ["DURATIONS", "OBSERVABLES", "PopulationSummary", "simulate_population", "steps_between"]

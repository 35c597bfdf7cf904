"""Runs as the checks read them: each cell's observable at the check times and the completed
phi segments, simulated in one batch (:func:`simulate_runs`) or merged from shards
(:meth:`RunResult.merge`).

The fidelity stage compares candidates with the full model through these; the stored full-model
references (:mod:`surrogate.stages.reference`) are shards of the same function's output, merged.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm.auto import tqdm

from surrogate.models.base import Model
from surrogate.simulate.batch import BatchSimulator, Replicate
from surrogate.simulate.population import steps_between

log = logging.getLogger(__name__)

#: steps per Simulator.advance call between check times
CHUNK_STEPS = 20
#: longest segment (steps) the duration histograms resolve; longer ones go to the last bin
MAX_SEGMENT_STEPS = 1 << 14


@dataclass
class RunResult:
    """What the checks need of one run.

    Attributes:
        observables: time (s) -> every cell's observable value at that time (``n``).
        mean_durations: lump name -> mean completed segment duration (s).
        segments: lump name -> completed segments.
        histograms: lump name -> completed segments by length, ``counts[k]`` of ``k`` steps
            (the last entry: :data:`MAX_SEGMENT_STEPS` or longer); empty when not recorded.
        total_steps: lump name -> the completed segments' summed length in steps (exact,
            so merged shards give the unsharded mean).
    """

    observables: dict[float, np.ndarray]
    mean_durations: dict[str, float]
    segments: dict[str, int]
    histograms: dict[str, np.ndarray] = field(default_factory=dict)
    total_steps: dict[str, int] = field(default_factory=dict)

    @classmethod
    def merge(cls, parts: Sequence[RunResult], dt: float) -> RunResult:
        """One run from shards of it (cells concatenated in shard order, segments added).

        Raises:
            ValueError: no parts, or parts without the segment totals, or with other check
                times or lumps.
        """
        if not parts:
            raise ValueError("merging needs at least one shard")
        times = list(parts[0].observables)
        lumps = list(parts[0].segments)
        for p in parts:
            if list(p.observables) != times or list(p.segments) != lumps:
                raise ValueError("shards of one run must share their times and lumps")
            if set(p.total_steps) != set(lumps) or set(p.histograms) != set(lumps):
                raise ValueError("a shard without segment totals and histograms cannot merge")
        totals = {k: sum(int(p.total_steps[k]) for p in parts) for k in lumps}
        counts = {k: sum(int(p.segments[k]) for p in parts) for k in lumps}
        return cls(
            observables={t: np.concatenate([p.observables[t] for p in parts]) for t in times},
            mean_durations={k: totals[k] / max(counts[k], 1) * dt for k in lumps},
            segments=counts,
            histograms={k: np.sum([p.histograms[k] for p in parts], axis=0) for k in lumps},
            total_steps=totals,
        )


@dataclass(frozen=True)
class RunPlan:
    """The schedule and the loop of :func:`simulate_runs`.

    Attributes:
        dt: the time step (s).
        times: the check times (s), multiples of dt in (0, t_end].
        t_end: simulated time after equilibration (s).
        equilibration_time: internal dynamics before cells move (s).
        device, compile, backend: the loop (:class:`~surrogate.simulate.Simulator`).
    """

    dt: float
    times: Sequence[float]
    t_end: float
    equilibration_time: float
    device: str | torch.device = "cpu"
    compile: bool = False
    backend: str = "auto"


def simulate_runs(
    model: Model,
    replicates: Sequence[Replicate],
    labels: Sequence[str],
    plan: RunPlan,
    *,
    progress: bool = True,
    desc: str = "runs",
    info: dict[str, object] | None = None,
) -> dict[str, RunResult]:
    """Simulate ``replicates`` as one population to ``plan.t_end``; record each cell's
    observable at ``plan.times`` and every completed phi segment.

    Args:
        model: the agent model every replicate runs.
        replicates: the runs (decision layer, field, size, seed, start), in block order.
        labels: one name per replicate, the keys of the result.
        plan: the time step, check times, duration, equilibration and loop (:class:`RunPlan`).
        progress: a progress bar over the steps.
        desc: the progress bar's label.
        info: if given, filled with the loop that ran (``loop_backend``) and, per label, the
            share of sampled cell-steps outside the trained range (``outside_training``).

    Returns:
        ``{label: RunResult}`` with segment histograms and exact totals.
    """
    dt, times = plan.dt, plan.times
    sim = BatchSimulator(model, replicates, dt, plan.device, compile=plan.compile,
                         backend=plan.backend, compile_fallback=False)  # fmt: skip
    log.info("simulating %d run(s) in one batch (%d cells, %s loop)", len(replicates),
             sum(sim.sizes), sim.backend)  # fmt: skip
    if info is not None:
        info["loop_backend"] = sim.backend
    r = len(replicates)
    width = MAX_SEGMENT_STEPS + 1
    with torch.inference_mode():  # cheaper per op than no_grad
        state = sim.initial_state(equilibration_time=float(plan.equilibration_time))
        sim.warm_up(state)
        n_steps = steps_between(float(plan.t_end), dt, "t_end")
        record = {steps_between(t, dt, "times"): t for t in times}
        dev = sim.device
        replicate_of = torch.repeat_interleave(
            torch.arange(r, device=dev), torch.tensor(sim.sizes, device=dev)
        )
        # per replicate and lump (row 2i + p): completed segments by length, and their total
        hist = torch.zeros(2 * r * width, dtype=torch.int64, device=dev)
        totals = torch.zeros(2 * r, dtype=torch.int64, device=dev)
        observed: dict[float, np.ndarray] = {}
        name = model.body.observable_names[0]
        k = 0
        with tqdm(total=n_steps, desc=desc, disable=not progress, mininterval=1.0) as bar:
            while k < n_steps:  # up to the next check time, CHUNK_STEPS steps per call
                upcoming = [s for s in record if s > k]
                steps = min(min(upcoming, default=n_steps) - k, n_steps - k, CHUNK_STEPS)
                ended = sim.advance(state, steps)  # steps x n: +-length of ended segments
                sim.observe_support(state)
                done = ended != 0
                row = (2 * replicate_of + (ended > 0).long())[done]
                length = ended.abs().long()[done]
                hist.index_add_(0, row * width + length.clamp(max=MAX_SEGMENT_STEPS),
                                torch.ones_like(length))  # fmt: skip
                totals.index_add_(0, row, length)
                k += steps
                bar.update(steps)
                if k in record:
                    sim.check_state(state)
                    observed[record[k]] = (
                        model.body.observables(state.body, sim.field)[name].double().cpu().numpy()
                    )
    if info is not None:
        info["outside_training"] = dict(zip(labels, sim.support_report(), strict=True))
    lumps = model.internal.lump_names
    hist_np = hist.reshape(2 * r, width).cpu().numpy()
    totals_np = totals.cpu().numpy()
    out = {}
    for i, (label, cells) in enumerate(zip(labels, sim.slices, strict=True)):
        counts = {lumps[p]: int(hist_np[2 * i + p].sum()) for p in (0, 1)}
        steps_sum = {lumps[p]: int(totals_np[2 * i + p]) for p in (0, 1)}
        out[label] = RunResult(
            observables={t: v[cells] for t, v in sorted(observed.items())},
            mean_durations={k: steps_sum[k] / max(counts[k], 1) * dt for k in counts},
            segments=counts,
            histograms={lumps[p]: hist_np[2 * i + p].copy() for p in (0, 1)},
            total_steps=steps_sum,
        )
    return out


def mean_observables(results: Mapping[str, RunResult]) -> dict[str, dict[str, list[float]]]:
    """Each run's mean observable per check time with its standard error (the drift)."""
    return {
        label: {f"{t:g}": [float(v.mean()), float(v.std(ddof=1) / np.sqrt(max(len(v), 1)))]
                for t, v in r.observables.items()}
        for label, r in results.items()
    }  # fmt: skip


__all__ = [
    "CHUNK_STEPS",
    "MAX_SEGMENT_STEPS",
    "RunPlan",
    "RunResult",
    "mean_observables",
    "simulate_runs",
]

"""Loop speed: one formula for every speed figure, and the side-by-side measurement.

Every speed figure of the package (the benchmark, the speed stage, reproduce's measurement, the
evaluate stage's speed-up) is a ratio of :func:`cell_steps_per_s` of two :class:`LoopTiming`\\ s
through :func:`speedup` (the same loop for both models) or :func:`best_loop_speedup` (each model
on its fastest loop): per cell-step, and only between loops timed on the same device with the
same threads and the SAME number of cells. A loop's throughput per cell-step changes several-fold
with the population's size (fixed per-step costs spread over more cells: measured 6.5x between
1,000 and 100,000 cells on one torch step), so a ratio of throughputs at different sizes says as
much about the sizes as about the models, and is refused.

:func:`measure_speed` times decision layers side by side in one process on the same population.
Runs simulated together in one batch share their steps, so a run's own loop time no longer
exists; the speed of the full model against the abstraction is measured there instead, the same
way for each: the same model, field and number of cells, the same compile setting, after a
warm-up (compile time reported separately), best of ``repeats``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from surrogate.errors import ArtefactError, SurrogateError
from surrogate.fields import Field
from surrogate.models.base import Model
from surrogate.simulate.decision import DecisionLayer
from surrogate.simulate.loop import Simulator

#: what must match for two loops to compare at all: the machine and the population's size
MACHINE = ("device", "threads", "n_cells")
#: what must match for two loop times to compare loop for loop (a difference in any one is not
#: the model's)
SETUP = (*MACHINE, "backend", "compiled")


class IncomparableSpeeds(SurrogateError, ValueError):
    """Two loops timed under different set-ups (device, threads, cells, loop or compile state)."""


def cell_steps_per_s(n_cells: int, steps: float, seconds: float) -> float:
    """Throughput of a loop that advanced ``n_cells`` cells by ``steps`` steps in ``seconds``.

    Args:
        n_cells: cells simulated (> 0).
        steps: steps of dt each cell took (> 0; the SSA benchmark passes simulated seconds).
        seconds: wall-clock seconds of those steps (finite, > 0).

    Returns:
        ``n_cells * steps / seconds``.
    """
    if not (n_cells > 0 and steps > 0):
        raise ValueError(f"a timed loop needs cells and steps, got {n_cells} x {steps}")
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"a timed loop needs a positive finite time, got {seconds!r} s")
    return n_cells * steps / seconds


@dataclass(frozen=True)
class LoopTiming:
    """One timed simulation loop: its workload, its time and the set-up it ran under.

    Attributes:
        n_cells: cells simulated.
        steps: steps of dt timed.
        seconds: wall-clock seconds of those steps (the loop: no set-up, no compilation).
        device: the device type (``cpu``, ``cuda``).
        threads: torch's intra-op threads (merged shards with different counts: "1,2").
        backend: the loop that ran (``torch``: the batched torch step; ``numba``: the model's
            per-cell kernel). ``backend=auto`` picks per model, so a model without a kernel
            (e.g. the classifier every step, or the SBML network) beside one with a kernel is
            no comparison of the models.
        compiled: whether the torch step ran through ``torch.compile`` (asked for and not
            fallen back to eager).
    """

    n_cells: int
    steps: int
    seconds: float
    device: str
    threads: int | str
    backend: str
    compiled: bool

    @property
    def cell_steps_per_s(self) -> float:
        """:func:`cell_steps_per_s` of this loop."""
        return cell_steps_per_s(self.n_cells, self.steps, self.seconds)

    def setup(self) -> dict[str, Any]:
        """What must match for this loop's time to compare with another's (:data:`SETUP`)."""
        return {key: getattr(self, key) for key in SETUP}

    def with_seconds(self, seconds: float) -> LoopTiming:
        """The same loop with another time (e.g. the wall time of the run around it)."""
        return dataclasses.replace(self, seconds=float(seconds))

    @classmethod
    def of(cls, simulator: Simulator, n_cells: int, steps: int, seconds: float) -> LoopTiming:
        """The timing of ``steps`` steps of ``n_cells`` cells by ``simulator``, on this
        process's current thread count."""
        return cls(int(n_cells), int(steps), float(seconds), simulator.device.type,
                   torch.get_num_threads(), simulator.backend, simulator.compiled)  # fmt: skip

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> LoopTiming:
        """A timing from a mapping with its fields (e.g. one :func:`measure_speed` entry)."""
        names = [f.name for f in dataclasses.fields(cls)]
        missing = [n for n in names if n not in values]
        if missing:
            raise KeyError(f"a loop timing needs {missing}")
        return cls(**{n: values[n] for n in names})

    @classmethod
    def from_manifest(cls, manifest: Mapping[str, Any], seconds: str = "loop_time_s") -> LoopTiming:
        """The loop of a simulation run from its ``manifest.json`` (``seconds``: the time to
        use, the loop's or ``wall_time_s``)."""
        needed = ("n_cells", "n_steps", seconds, "device", "torch_threads", "loop_backend")
        missing = [k for k in needed if manifest.get(k) is None]
        if missing:
            raise ArtefactError(f"a simulation manifest without {missing} has no loop timing; "
                                "re-run the simulation")  # fmt: skip
        threads = manifest["torch_threads"]  # merged shards with different counts: "1,2"
        return cls(
            n_cells=int(manifest["n_cells"]),
            steps=int(manifest["n_steps"]),
            seconds=float(manifest[seconds]),
            device=str(manifest["device"]).split(":")[0],
            threads=int(threads) if str(threads).isdigit() else str(threads),
            backend=str(manifest["loop_backend"]),
            compiled=bool(manifest.get("compiled", manifest.get("compile", False))),
        )


def differences(
    reference: LoopTiming, candidate: LoopTiming, keys: Sequence[str] = SETUP
) -> list[str]:
    """Why two loop times do not compare: one line per differing entry of ``keys`` (default
    :data:`SETUP`; empty: they compare)."""
    a, b = reference.setup(), candidate.setup()
    return [f"{key} {a[key]} vs {b[key]}" for key in keys if a[key] != b[key]]


def speedup(reference: LoopTiming, candidate: LoopTiming) -> float:
    """How many times faster ``candidate`` is than ``reference`` per cell-step.

    Args:
        reference: the loop compared against (e.g. the full model's).
        candidate: the loop compared (e.g. the abstraction's), under the same set-up.

    Returns:
        ``candidate.cell_steps_per_s / reference.cell_steps_per_s`` (over equal steps, the
        ratio of loop times).

    Raises:
        IncomparableSpeeds: the set-ups differ (:func:`differences` says how).
    """
    why = differences(reference, candidate)
    if why:
        raise IncomparableSpeeds(f"loop times under different set-ups do not compare: "
                                 f"{'; '.join(why)}")  # fmt: skip
    return candidate.cell_steps_per_s / reference.cell_steps_per_s


def best_loop_speedup(
    reference: Sequence[LoopTiming], candidate: Sequence[LoopTiming]
) -> tuple[float, LoopTiming, LoopTiming]:
    """How many times faster ``candidate`` is than ``reference``, each on its fastest loop.

    What a user asks ("how much faster is my run with the abstraction"): each model run the
    fastest way it can be, on the same machine, threads and number of cells. The loops may
    differ (e.g. the full model's torch step with a compiled SSA against the abstraction's
    per-cell kernel).

    Args:
        reference: the reference model's timed loops (e.g. the full model's), >= 1.
        candidate: the candidate's timed loops, >= 1.

    Returns:
        ``(ratio, the reference's fastest loop, the candidate's fastest loop)``.

    Raises:
        IncomparableSpeeds: the loops were not all timed on one machine set-up and size
            (:data:`MACHINE`), or one side has none.
    """
    if not reference or not candidate:
        raise IncomparableSpeeds("each model needs at least one timed loop")
    first = reference[0]
    for t in [*reference, *candidate]:
        why = differences(first, t, MACHINE)
        if why:
            raise IncomparableSpeeds(f"fastest loops compare only on one machine set-up and "
                                     f"population size: {'; '.join(why)}")  # fmt: skip
    best_ref = max(reference, key=lambda t: t.cell_steps_per_s)
    best_cand = max(candidate, key=lambda t: t.cell_steps_per_s)
    return best_cand.cell_steps_per_s / best_ref.cell_steps_per_s, best_ref, best_cand


def loop_name(timing: LoopTiming) -> str:
    """``numba kernel``, ``compiled torch step`` or ``torch step``."""
    if timing.backend == "numba":
        return "numba kernel"
    return "compiled torch step" if timing.compiled else "torch step"


def speed_summary(full: Sequence[LoopTiming], abstract: Sequence[LoopTiming]) -> dict[str, Any]:
    """The abstraction's speed-up over the full model two ways: each on its fastest loop
    (:func:`best_loop_speedup`: ``speedup``, ``fastest``), and loop for loop where both ran the
    same loop (:func:`speedup`: ``same_loop``, by :func:`loop_name`). ``speedup`` is None, with
    ``speed_not_comparable`` saying why, where the loops ran on different machines or sizes.

    Args:
        full: the full model's timed loops.
        abstract: the abstraction's timed loops.
    """
    out: dict[str, Any] = {"speedup": None, "fastest": None, "same_loop": {},
                           "speed_not_comparable": []}  # fmt: skip
    try:
        ratio, best_full, best_abstract = best_loop_speedup(full, abstract)
    except IncomparableSpeeds as exc:
        out["speed_not_comparable"] = [str(exc)]
        return out
    out["speedup"] = ratio
    out["fastest"] = {"full": loop_name(best_full), "abstract": loop_name(best_abstract)}
    for f in full:
        for a in abstract:
            if not differences(f, a):
                out["same_loop"][loop_name(f)] = speedup(f, a)
    return out


def compare(
    reference: LoopTiming | Mapping[str, Any], candidate: LoopTiming | Mapping[str, Any]
) -> tuple[float | None, list[str]]:
    """:func:`speedup` of ``candidate`` over ``reference`` where their set-ups match, else None;
    and why not (:func:`differences`; empty when they match).

    Args:
        reference: a :class:`LoopTiming`, or a mapping with its fields (a
            :func:`measure_speed` entry, a bench throughput result).
        candidate: the same for the loop compared.
    """
    a, b = (t if isinstance(t, LoopTiming) else LoopTiming.from_mapping(t)
            for t in (reference, candidate))  # fmt: skip
    why = differences(a, b)
    return (None if why else speedup(a, b)), why


@dataclass(frozen=True)
class SpeedWorkload:
    """What :func:`measure_speed` times.

    Attributes:
        n_cells: cells of the population.
        steps: steps timed.
        dt: the time step (s).
        start: where the cells start.
        repeats: timings taken (the best is kept).
        chunk_steps: steps per :meth:`Simulator.advance` call, as the simulate stage takes a
            record interval (20 steps: 1 s at dt 0.05) per call.
    """

    n_cells: int
    steps: int
    dt: float
    start: Sequence[float] = (2.0, 0.0)
    repeats: int = 2
    chunk_steps: int = 20


def measure_speed(
    model: Model,
    decisions: Mapping[str, DecisionLayer],
    field: Field,
    workload: SpeedWorkload,
    device: str | torch.device = "cpu",
    compile: bool = False,
    backend: str = "torch",
) -> dict[str, dict[str, Any]]:
    """Loop time of ``workload.steps`` steps of ``workload.n_cells`` cells for each decision
    layer (on the loop ``device``, ``compile``, ``backend`` choose, as for :class:`Simulator`).

    Returns, per name: the :class:`LoopTiming` fields (``seconds``: best of ``repeats``;
    ``backend``: the loop that ran), ``cell_steps_per_s``, ``us_per_step``, ``compile_s`` (the
    warm-up) and ``compile_error``.
    """
    n_cells, steps, dt, start = workload.n_cells, workload.steps, workload.dt, workload.start
    repeats, chunk_steps = workload.repeats, workload.chunk_steps
    out = {}
    for name, decision in decisions.items():
        sim = Simulator(model, decision, field, dt, device, compile=compile, backend=backend)
        with torch.inference_mode():  # cheaper per op than no_grad
            state = sim.initial_state(n_cells, start)
            compile_s = sim.warm_up(state)
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                done = 0
                while done < steps:
                    k = min(chunk_steps, steps - done)
                    sim.advance(state, k)
                    done += k
                if sim.device.type == "cuda":
                    torch.cuda.synchronize(sim.device)
                best = min(best, time.perf_counter() - t0)
        timing = LoopTiming.of(sim, n_cells, steps, best)
        out[name] = {
            **dataclasses.asdict(timing),
            "cell_steps_per_s": timing.cell_steps_per_s,
            "us_per_step": 1e6 * best / steps,
            "compile_s": compile_s,
            "compile_error": sim.compile_error,
        }
    return out


__all__ = [
    "MACHINE",
    "SETUP",
    "IncomparableSpeeds",
    "LoopTiming",
    "SpeedWorkload",
    "best_loop_speedup",
    "cell_steps_per_s",
    "compare",
    "differences",
    "loop_name",
    "measure_speed",
    "speed_summary",
    "speedup",
]

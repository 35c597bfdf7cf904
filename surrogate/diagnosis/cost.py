"""What a simulation costs, estimated before it runs: steps x (the loop's fixed cost per step
+ cells x the model's cost per cell-step).

The cost model every estimate shares (:func:`cost_seconds`, one :class:`Work` per simulation),
the loop's fixed cost per step measured once per process (:func:`step_seconds`) and a duration
as words (:func:`duration`). The stages' budgets (:mod:`surrogate.stages.budget`) list the works
a stage would run from its settings; the inspection and the cost probe price theirs here.

The estimate is a guard against runs of hours or years, not a forecast: it has no accuracy
guarantee (measured runs took 0.37x to 1.64x of it on the three shipped models, none bounds it
on others; docs/performance.md, "The cost estimate").
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from surrogate.kinds import decision_kind

log = logging.getLogger(__name__)


#: seconds per step whatever the population where it is not measured (:func:`step_seconds`
#: falls back to it where the simulator cannot be built; a :class:`Work` built without one):
#: the loop's dispatch, ~20 us for the numba kernel, 0.1-1 ms for the eager torch step
STEP_SECONDS = 1e-4
#: the two populations :func:`step_seconds` times (cells), the steps timed per repeat, repeats
PROBE_CELLS = (1, 16)
PROBE_STEPS = 4
PROBE_REPEATS = 3
#: a network's probe cells start from the file's counts (no burn-in: the steps' fixed cost is
#: what is timed) and refuse more SSA events than this per cell and window; a runaway network
#: then falls back to :data:`STEP_SECONDS` in milliseconds instead of timing windows of
#: millions of events (each population's 14 windows at 1e5 events: ~2 s on the compiled SSA)
PROBE_MAX_EVENTS = 10**5


@dataclass(frozen=True)
class Work:
    """One simulation a stage would run.

    Attributes:
        what: what it is, e.g. ``"the full-model run"``.
        cells: cells simulated together.
        steps: time steps of dt.
        cell_step_seconds: the model's estimated cost of one cell-step under its decision.
        settings: the settings that set its size, as they would be written on the command line.
        model: the model's name.
        decision: the decision layer it runs (``full``: the internal network, whose cost per
            cell-step is the model's; the chains cost :data:`~surrogate.models.base.
            CELL_STEP_SECONDS`).
        step_seconds: the loop's fixed cost per step, whatever the cells
            (:func:`step_seconds`, measured; :data:`STEP_SECONDS` where not given).
    """

    what: str
    cells: int
    steps: float
    cell_step_seconds: float
    settings: str
    model: str
    decision: str = "full"
    step_seconds: float = STEP_SECONDS

    @property
    def seconds(self) -> float:
        """Estimated wall time (s): steps x (fixed per step + cells x per cell-step)."""
        return cost_seconds(self.steps, self.cells, self.step_seconds, self.cell_step_seconds)

    @property
    def full(self) -> bool:
        """Whether it runs the full model (``decision=full``), not a chain."""
        return decision_kind(self.decision).full

    def describe(self) -> str:
        """One line: what, its size, the settings behind it, the costs per step and cell-step."""
        return (
            f"{self.what}: {self.steps:.3g} steps x {self.cells} cells ({self.settings}) at "
            f"~{self.step_seconds:.2g} s per step + ~{self.cell_step_seconds:.2g} s per "
            f"cell-step of model {self.model!r}"
        )


def cost_seconds(steps: float, cells: int, step_seconds: float, cell_step_seconds: float) -> float:
    """``steps x (step_seconds + cells x cell_step_seconds)``: the cost model of every estimate
    (the fixed part is the loop's, whatever the cells; the rest grows with them)."""
    return steps * (step_seconds + cells * cell_step_seconds)


_STEP_CACHE: dict[tuple[Any, ...], float] = {}


def step_seconds(
    model: Any, field: Any, dt: float, decision: str = "full", device: Any = "cpu"
) -> float:
    """The simulation loop's fixed cost per step (s), whatever the cells: measured once per
    process (cached by model, body, field, dt, decision, device and torch threads).

    Times :data:`PROBE_STEPS` steps (best of :data:`PROBE_REPEATS`, after two untimed ones)
    of the stages' own :class:`~surrogate.simulate.loop.Simulator` (``backend=auto``, as the
    stages run it) at each of :data:`PROBE_CELLS` cells; the fixed part is where the line
    through the two meets 0 cells, kept within [1/2, 1] of the smaller population's step
    (timing noise). ``decision`` (a ``decision.name``) ``full`` runs the internal model; any
    other a two-state chain at a constant psi, standing in for the abstraction (which may not
    exist yet). The random state of torch is left as it was. Where the simulator cannot be
    built or run here, :data:`STEP_SECONDS` (the run itself says why). Takes ~0.1 s for a
    network in a walker (plus its SSA's compile, once per process, which the run pays
    anyway)."""
    import torch

    full = decision_kind(decision).full
    body = getattr(model, "body", None)
    key = (type(model).__qualname__, getattr(model, "name", ""), _sources(model),
           type(body).__qualname__, type(field).__qualname__, float(dt),
           "full" if full else "chain", str(device), torch.get_num_threads())  # fmt: skip
    if key not in _STEP_CACHE:
        try:
            with torch.random.fork_rng(devices=cuda_devices(device)):
                _STEP_CACHE[key] = _measure_step(model, field, dt, full, device)
        except Exception as error:  # the run reports it; the estimate only falls back
            log.debug("the cost per step was not measured (%s): %g s assumed", error,
                      STEP_SECONDS)  # fmt: skip
            _STEP_CACHE[key] = STEP_SECONDS
    return _STEP_CACHE[key]


def _sources(model: Any) -> tuple[tuple[str, str], ...]:
    try:
        return tuple(sorted(model.sources().items()))
    except Exception:  # a model without sources: its name and class identify it
        return ()


def cuda_devices(device: Any) -> list[int]:
    import torch

    d = torch.device(device)
    return [d.index or 0] if d.type == "cuda" else []


def _measure_step(model: Any, field: Any, dt: float, full: bool, device: Any) -> float:
    """Seconds per step at the cells of :data:`PROBE_CELLS`, reduced to the fixed part, of the
    full model (``full``) or a chain. A network's cells start from the file's counts, without
    its burn-in, and refuse a window of more than :data:`PROBE_MAX_EVENTS` events per cell
    (a ``RuntimeError``: :func:`step_seconds` falls back)."""
    import time

    import torch

    from surrogate.models.capabilities import start_size_of
    from surrogate.models.network import NetworkInternalModel
    from surrogate.simulate import AbstractDecision, FullDecision
    from surrogate.simulate.loop import Simulator

    def constant(phi: Any, z: Any) -> Any:
        return torch.full((z.shape[0],), 0.5, device=z.device)

    dev = torch.device(device)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    internal = model.internal
    if isinstance(internal, NetworkInternalModel):  # bounded: no burn-in, no runaway window
        internal = internal.bounded(PROBE_MAX_EVENTS, burn_in=0.0)
    per_step = []
    for cells in PROBE_CELLS:
        layer = FullDecision(internal) if full else AbstractDecision(constant, internal)
        simulator = Simulator(model, layer, field, dt, dev, backend="auto")
        state = simulator.initial_state(cells, torch.zeros(start_size_of(model.body) or 2))
        simulator.advance(state, 2)  # untimed: first calls load kernels
        best = math.inf
        for _ in range(PROBE_REPEATS):
            sync()
            t0 = time.perf_counter()
            simulator.advance(state, PROBE_STEPS)
            sync()
            best = min(best, (time.perf_counter() - t0) / PROBE_STEPS)
        per_step.append(best)
    (a, b), (ta, tb) = PROBE_CELLS, per_step
    intercept = (b * ta - a * tb) / (b - a)
    return min(ta, max(intercept, 0.5 * ta))


def duration(seconds: float) -> str:
    """``12 s``, ``4.2 min``, ``3.1 h``, ``2.0e+03 days``."""
    if seconds < 120:
        return f"{seconds:.2g} s"
    if seconds < 7200:
        return f"{seconds / 60:.2g} min"
    if seconds < 5 * 86400:
        return f"{seconds / 3600:.2g} h"
    return f"{seconds / 86400:.2g} days"


__all__ = [
    "PROBE_CELLS",
    "PROBE_MAX_EVENTS",
    "PROBE_REPEATS",
    "PROBE_STEPS",
    "STEP_SECONDS",
    "Work",
    "cost_seconds",
    "cuda_devices",
    "duration",
    "step_seconds",
]

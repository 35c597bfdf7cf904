"""What a report needs that the learned psi does not change, and reproduce's head start on it.

Half of ``reproduce``'s work does not depend on the abstraction: the collection, the train
diagnostic's occupancy run, the runs of the full model and of the exact psi. ``reproduce``
hands it to a :class:`~surrogate.stages.background.Worker` while it trains;
``scripts/reproduce.py`` starts that worker (:func:`head_start`, given the job's final config
and threads by :func:`surrogate.cli.prepared_job`) before it imports torch, pandas and scipy
(~2.5 s): the worker validates the same config (its process's edge) and makes that work in the
order it is needed (:func:`prepare`); the train stage here waits for the collection under the
artefact's lock, then reuses it. This module imports nothing heavy at
import (the worker imports only what its jobs need).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from surrogate.stages.background import Worker, worker_threads

if TYPE_CHECKING:
    from surrogate.stages.settings import (
        EvaluateSettings,
        OccupancySettings,
        ReproduceSettings,
        SimulateSettings,
    )

log = logging.getLogger(__name__)

#: the worker takes its pipes by descriptor (and runs niced): POSIX only; elsewhere reproduce
#: runs in one process
SUPPORTED = os.name == "posix"
#: the worker's niceness: it yields to the reproduce process (which trains on all its threads:
#: the fit's result depends on their count), mildly, since that process may wait on its locks
WORKER_NICE = 10


def head_start(config: Mapping[str, Any] | None, threads: int = 1) -> Worker | None:
    """Start the worker of a reproduce job on :func:`prepare` of ``config`` (the job's final
    config, plain containers: :func:`surrogate.cli.prepared_job`) where it asks for one
    (``batch``, and ``background`` true, or auto with two or more ``threads`` for this job on
    the CPU); None otherwise, and for no config (one the job will refuse: its own validation,
    inside the job, says why)."""
    if config is None or not wants_worker(config.get("background", "auto"),
                                          config.get("batch", True), threads,
                                          config.get("device", "cpu")):  # fmt: skip
        return None
    worker = Worker(worker_threads(threads), nice=WORKER_NICE)
    worker.submit(prepare, config)
    log.info("in a background process (%d thread(s)): the collection, then what needs no "
             "abstraction (the full model's and the exact psi's runs and evaluations)",
             worker.threads)  # fmt: skip
    return worker


def wants_worker(setting: Any, batch: Any, threads: int, device: Any) -> bool:
    """The ``background`` rule, for the head start (from the config) and for reproduce (from
    torch): true, false, or auto: when the job has two or more threads (a sweep job with one
    thread per core would only share its core with a second process) and runs on the CPU (two
    processes on one GPU would share its memory); only with ``batch`` and where the worker is
    supported (POSIX). Invalid values start none (the job's validation names them)."""
    if batch is not True or not SUPPORTED:
        return False
    if setting == "auto":
        return threads >= 2 and str(device).split(":")[0] == "cpu"
    return setting is True


def needs_training(run: SimulateSettings) -> bool:
    """Whether ``run`` waits for a trained abstraction (its decision layer is the learned psi)."""
    return run.decision.train is not None


def missing_runs(runs: Sequence[SimulateSettings]) -> list[SimulateSettings]:
    """The runs of ``runs`` without a complete artefact, each once."""
    from surrogate.io import existing_artefact

    unique = {s.directory: s for s in runs}
    return [s for d, s in unique.items() if existing_artefact(d, s.identity(), s.command()) is None]


@dataclasses.dataclass(frozen=True)
class IndependentWork:
    """The report's missing work that the learned psi does not change, in the order it is
    needed: the train diagnostic's occupancy run (None: not needed or made), the runs of the
    full model and of the exact psi (one batch), then the exact psi's evaluations."""

    occupancy_run: OccupancySettings | None
    runs: list[SimulateSettings]
    exact: list[EvaluateSettings]

    def __call__(self) -> None:
        """Make it (in a worker: a job is a picklable callable)."""
        from surrogate.stages import evaluate as evaluate_stage
        from surrogate.stages.occupancy import occupancy
        from surrogate.stages.simulate import simulate_together

        if self.occupancy_run is not None:
            occupancy(self.occupancy_run)
        simulate_together(self.runs)
        for e in self.exact:
            evaluate_stage.evaluate(e)


def independent_work(settings: ReproduceSettings) -> IndependentWork | None:
    """The report's missing :class:`IndependentWork`. None when there is none, or when the runs
    are ``torch.compile``-batched (their last bits depend on the batch's shape: they stay in
    one batch, simulated after training)."""
    from surrogate.io import existing_artefact

    runs = settings.runs()
    if any(s.batch is not None for s in runs):
        return None
    todo = [_quiet(s) for s in missing_runs(runs) if not needs_training(s)]
    tr = settings.train
    occupancy_run = None
    if existing_artefact(tr.directory, tr.identity(), tr.command()) is None:
        o = tr.occupancy()
        if existing_artefact(o.directory, o.identity(), o.command()) is None:
            occupancy_run = _quiet(o)
    exact = [e for e in settings.exact.values()
             if existing_artefact(e.directory, e.identity(), e.command()) is None]  # fmt: skip
    if not todo and occupancy_run is None and not exact:
        return None
    return IndependentWork(occupancy_run, todo, exact)


def prepare(config: Mapping[str, Any]) -> None:
    """The head start's job (in a worker started before the reproduce process has imported
    torch): the collection, then :func:`independent_work` (compiling the kernel on its first
    call where it is not cached)."""
    from surrogate.stages.collect import collect
    from surrogate.stages.settings import CollectSettings, ReproduceSettings

    settings = ReproduceSettings.from_config(config)
    tr = settings.train
    if isinstance(tr.source, CollectSettings):
        collect(_quiet(tr.source))
    work = independent_work(settings)
    if work is not None:
        work()


def _quiet(settings: Any) -> Any:
    """The same settings without progress bars (a worker's would interleave with ours)."""
    return dataclasses.replace(settings, job=dataclasses.replace(settings.job, progress=False))


__all__ = [
    "WORKER_NICE",
    "IndependentWork",
    "head_start",
    "independent_work",
    "missing_runs",
    "needs_training",
    "prepare",
    "wants_worker",
]

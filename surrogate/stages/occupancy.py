"""Where an unperturbed full-model population lives: the train diagnostic's weights.

An artefact of its own (``data/occupancy/.../occupancy.parquet``: the abstraction's inputs,
``phi`` and ``phi_next`` of every ``record_every``-th step of every cell), made once per model,
training field, step, seed and ``gp.diagnostic`` settings. It does not depend on the learned
psi; the train stage reads it (or makes it) for its diagnostic. Seeded with the run's seed, so
the diagnostic's reference is the same whatever the GP recipe.
"""

from __future__ import annotations

import logging
import time

import pandas as pd
import torch

from surrogate.config import seed_everything
from surrogate.io import make_once, read_parquet, write_manifest, write_parquet
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import record_occupancy
from surrogate.stages.artefacts import OCCUPANCY
from surrogate.stages.settings import OccupancySettings

log = logging.getLogger(__name__)


def occupancy(settings: OccupancySettings) -> pd.DataFrame:
    """The occupancy rows of ``settings``: read when complete, else recorded and written (under
    the artefact's lock, so a concurrent maker is waited for, not repeated)."""
    out = settings.directory
    make_once(out, settings.identity(), settings.command(), lambda _: _record(settings),
              what="occupancy run")  # fmt: skip
    return read_parquet(out / OCCUPANCY, made_by=settings.command())


def _record(settings: OccupancySettings) -> None:
    setup, d = settings.setup, settings.options
    model = setup.model
    t0 = time.perf_counter()
    seed_everything(setup.seed)
    # the model's per-cell kernel where it has one: the unrecorded steps in one call each
    simulator = Simulator(model, FullDecision(model.internal), setup.field, setup.dt,
                          settings.job.device, backend="auto")  # fmt: skip
    table = record_occupancy(
        simulator,
        int(d["n_cells"]),
        float(d["t_end"]),
        torch.tensor(d["start"]),
        int(d["record_every"]),
        float(d["equilibration_time"]),
        clock=bool(d.get("clock", False)),
    )
    out = settings.directory
    write_parquet(out / OCCUPANCY, table)
    wall = time.perf_counter() - t0
    write_manifest(out, stage="occupancy", config=settings.identity(), seed=setup.seed,
                   settings=settings.identity(), rows=len(table), backend=simulator.backend,
                   device=str(settings.job.device), wall_time_s=wall)  # fmt: skip
    log.info("occupancy run: %d rows in %.1f s; artefacts in %s", len(table), wall, out)


__all__ = ["OCCUPANCY", "occupancy"]

"""Settings of the simulate stage: one population run (or one shard of it), with its
decision layer, and the checks made before any cell is simulated (memory, backend)."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from surrogate.config import CONF_DIR, non_negative, positive, to_dict, validate_start
from surrogate.errors import ConfigError
from surrogate.grid import is_coupled
from surrogate.io import artefact_dir
from surrogate.models.capabilities import start_size_of
from surrogate.simulate.coupling import check_coupled_run
from surrogate.simulate.recorders import DEFAULT_RECORD_CELLS
from surrogate.stages.settings.collect import CollectSettings
from surrogate.stages.settings.common import (
    SIMULATE_CMD,
    Job,
    ModelSetup,
    command_line,
    format_value,
    free_memory_bytes,
    group_overrides,
)
from surrogate.stages.settings.decision import DecisionSettings

#: bytes of device memory per simulated cell, measured at ~690 B for the E. coli abstraction
#: (1e6 cells in 689 MiB); the estimate is generous (recorders, the full model's motors)
BYTES_PER_CELL = 4096


@dataclass(frozen=True, eq=False)
class SimulateSettings:
    """The simulate stage: one population run (or one shard of it)."""

    setup: ModelSetup
    decision: DecisionSettings
    n_cells: int
    t_end: float
    record_interval: float
    start: tuple[float, ...]
    equilibration_time: float
    record_durations: bool
    compile: bool
    job: Job
    shard: dict[str, int] | None = None
    record_cells: int | None = DEFAULT_RECORD_CELLS
    #: compiled runs simulated in one batch (reproduce): the batch's id (in the identity, since
    #: kernels fused for the batch's shape round differently) and the command that makes it
    batch: str | None = None
    made_by: str | None = None
    #: the loop's backend: auto | torch | numba (see :class:`~surrogate.simulate.Simulator`)
    backend: str = "auto"

    @classmethod
    def from_config(
        cls, cfg: Mapping[str, Any], setup: ModelSetup | None = None, job: Job | None = None
    ) -> SimulateSettings:
        """Validate the run settings, the decision and a memory estimate.

        Args:
            cfg: The run's config.
            setup: The model setup, built once at the stage's entry (None: built from ``cfg``;
                evaluate's full run passes the candidate's, in its field and seed).
            job: The job, likewise.
        """
        from surrogate.simulate.population import steps_between

        setup = ModelSetup.from_config(cfg) if setup is None else setup
        n_cells = int(positive(cfg, "n_cells", integer=True))
        t_end = float(positive(cfg, "t_end"))
        interval = float(positive(cfg, "record_interval"))
        if setup.dt > interval:
            raise ConfigError(f"dt={setup.dt:g} s is larger than record_interval={interval:g} s")
        try:
            steps_between(interval, setup.dt, "record_interval")
            steps_between(t_end, setup.dt, "t_end")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        eq = float(non_negative(cfg, "equilibration_time"))
        start = validate_start(cfg, size=start_size_of(setup.model.body))
        job = Job.from_config(cfg) if job is None else job
        decision = DecisionSettings.from_config(cfg, setup, job)
        shards = (cfg.get("shard") or {}).get("count", 1)
        per_job = -(-n_cells // shards) if isinstance(shards, int) and shards >= 1 else n_cells
        check_memory(per_job, job.device)
        record_cells = cfg.get("record_cells", DEFAULT_RECORD_CELLS)
        if record_cells is not None:
            record_cells = int(positive(cfg, "record_cells", integer=True))
        backend, compile = validate_backend(cfg), bool(cfg.get("compile", False))
        check_coupled_run(setup.field, dt=setup.dt, shards=shards)
        check_field_memory(setup.field, job.device)
        return cls(setup, decision, n_cells, t_end, interval, start, eq,
                   bool(cfg.get("record_durations", True)), compile, job,
                   record_cells=record_cells, backend=backend)  # fmt: skip

    def identity(self) -> dict[str, Any]:
        """Everything that defines a population run (``compile`` and ``backend`` too: compiled
        kernels round differently, so runs with one seed differ in the last bits; the device
        type: CPU and CUDA draw different random streams)."""
        out = {**self.setup.identity(), **self.decision.identity(), "n_cells": self.n_cells,
               "t_end": self.t_end, "record_interval": self.record_interval,
               "start": list(self.start), "equilibration_time": self.equilibration_time,
               "record_durations": self.record_durations, "compile": self.compile,
               "record_cells": self.record_cells, "backend": self.backend,
               "device": self.job.device_type}  # fmt: skip
        if self.shard is not None:
            out["shard"] = self.shard
        if self.batch is not None:
            out["batch"] = self.batch
        return out

    def label(self) -> dict[str, Any]:
        """Readable part of the directory name."""
        return {"decision": self.decision.name, **self.setup.label(), "n": self.n_cells,
                "T": self.t_end, "seed": self.setup.seed}  # fmt: skip

    @functools.cached_property
    def directory(self) -> Path:
        """``data/simulate/<decision>_model=..._field=..._n=..._T=..._seed=...-<hash>``."""
        return artefact_dir(self.job.data_dir, "simulate", self.label(), self.identity())

    def overrides(self) -> list[str]:
        """Overrides that reproduce this run (shards: the parent run's)."""
        setup = self.setup
        n, seed = self.n_cells, setup.seed
        if self.shard is not None:
            n, seed = self.shard["parent_n_cells"], self.shard["parent_seed"]
        out = [*group_overrides("decision", self.decision.config, self.decision.name),
               *setup.with_seed(seed).overrides()]  # fmt: skip
        shipped = _shipped_run_settings()
        run = {"n_cells": n, "t_end": self.t_end, "record_interval": self.record_interval,
               "start": list(self.start), "equilibration_time": self.equilibration_time,
               "record_durations": self.record_durations, "compile": self.compile,
               "record_cells": self.record_cells, "backend": self.backend}  # fmt: skip
        out += [
            f"{k}={format_value(v)}"
            for k, v in run.items()
            if shipped.get(k) != v or k in ("n_cells", "t_end")
        ]
        if self.decision.train is not None:
            out += self.decision.train.gp_overrides()
            if isinstance(self.decision.train.source, CollectSettings):
                out += self.decision.train.source._overrides()
        if self.shard is not None:
            out += [f"shard.count={self.shard['count']}", f"shard.index={self.shard['index']}"]
        return out

    def command(self) -> str:
        """The command that makes this run."""
        return self.made_by or command_line(SIMULATE_CMD, self.overrides())

    def replace(self, **changes: Any) -> SimulateSettings:
        """A copy with some fields changed (``seed=`` changes the setup's seed)."""
        from dataclasses import replace

        seed = changes.pop("seed", None)
        out = replace(self, **changes)
        if seed is not None:
            out = replace(out, setup=self.setup.with_seed(seed))
        out.__dict__.pop("directory", None)
        return out


@functools.lru_cache(maxsize=1)
def _shipped_run_settings() -> dict[str, Any]:
    """The run settings of the shipped ``conf/simulate.yaml`` (what a command need not repeat)."""
    from omegaconf import OmegaConf

    data = to_dict(OmegaConf.load(CONF_DIR / "simulate.yaml"))
    return {k: v for k, v in data.items() if k != "defaults"}


def check_memory(n_cells: int, device: torch.device) -> None:
    """Refuse a population that cannot fit in memory, before allocating it (naming sharding)."""
    need = n_cells * BYTES_PER_CELL
    have = torch.cuda.mem_get_info(device)[0] if device.type == "cuda" else free_memory_bytes()
    if have is None:
        return
    if need > have:
        raise ConfigError(
            f"n_cells={n_cells} needs about {need / 2**30:.1f} GiB (~{BYTES_PER_CELL} B per "
            f"cell) but {have / 2**30:.1f} GiB are free on {device}; split the population "
            f"into shards (`{SIMULATE_CMD} -m shard.count=K shard.index='range(K)' "
            f"n_cells={n_cells}`, then scripts/merge_shards.py)"
        )


def check_field_memory(field: Any, device: torch.device) -> None:
    """Refuse a coupled field whose grid cannot fit in memory, naming ``field.shape``."""
    if not is_coupled(field):
        return
    need = field.memory_bytes()
    have = torch.cuda.mem_get_info(device)[0] if device.type == "cuda" else free_memory_bytes()
    if have is not None and need > have:
        raise ConfigError(
            f"field.shape={list(field.grid.shape)}: the grid field needs about "
            f"{need / 2**30:.1f} GiB ({len(field.species)} species) but {have / 2**30:.1f} GiB "
            f"are free on {device}; lower field.shape"
        )


def validate_backend(cfg: Mapping[str, Any]) -> str:
    """The ``backend`` setting (auto | torch | numba)."""
    from surrogate.simulate.loop import check_backend

    return check_backend(cfg.get("backend", "auto"))

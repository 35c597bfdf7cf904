"""Stored full-model references: the full model's runs for a fidelity check, made once.

An expensive internal network (``model=ecoli_phospho``: ~10,000 SSA events per cell and step)
makes the full model's runs the cost of a fidelity check at scale: hours of both cores. They do
not depend on the abstraction, so they are made once and kept:

``python scripts/reference.py [experiment=phospho]`` simulates, for every field of the fidelity
group, the full model (seed ``fidelity.sim_seed``) and its noise-floor run (seed ``sim_seed +
noise_seed_offset``), each moved per field by :func:`field_seed`, ``fidelity.n_cells`` cells
for ``fidelity.t_end`` s each, in shards of ``reference.shard_cells`` cells (shard i: seed
``SeedSequence(seed).spawn(K)[i]``, as population shards,
:func:`~surrogate.stages.shards.shard_seed`), ``reference.workers`` processes at once.

* **Resumable.** Each shard is an artefact of its own under ``data/reference_shards/`` (written
  atomically, manifest last, under a lock): a stopped run continues from its finished shards, and
  two commands started together share the work.
* **Content-addressed.** A run's directory is named after a hash of its identity
  (:meth:`ReferenceRun.identity`: the full model's identity, ``Model.full_model_identity``: its
  config and the digests of the files it is read from, less what shapes only the abstraction,
  such as a yaml model's classes and collection budget; dt, the field, size, duration, start, equilibration, seed, shard size and the format's
  version): what defines the full model's law and the sample. The device, loop and threads a
  shard ran on are recorded in its manifest, not its identity: they change the random stream,
  not the law, so a reference made on one machine serves a check on another.
* **Small.** The merged runs (every cell's observable every ``reference.record_interval`` s,
  the completed segments as a histogram over their length in steps with exact totals, and a
  manifest) are a few hundred kB each, kept under ``reference.dir`` (``references/``, committed).

``python scripts/fidelity.py fidelity.reference=stored`` (``experiment=phospho`` sets it) then
reads the full model and its noise floor from there instead of simulating them, and refuses, by
the settings that differ, a reference made for another model identity.
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import json
import logging
import math
import multiprocessing
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from surrogate.config import (
    field_config,
    non_negative,
    positive,
    seed_everything,
    to_dict,
    validate_start,
)
from surrogate.ctmc.compiled import match_torch_threads
from surrogate.diagnosis.cost import Work, step_seconds
from surrogate.errors import ArtefactError, ConfigError, MissingArtefactError
from surrogate.io import (
    MANIFEST,
    artefact_dir,
    artefact_lock,
    existing_artefact,
    make_once,
    read_manifest,
    read_parquet,
    settings_hash,
    write_manifest,
    write_parquet,
)
from surrogate.models.capabilities import start_size_of
from surrogate.simulate.batch import Replicate
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.population import steps_between
from surrogate.stages import budget
from surrogate.stages.runs import MAX_SEGMENT_STEPS, RunPlan, RunResult, simulate_runs
from surrogate.stages.settings import Job, ModelSetup, group_overrides
from surrogate.stages.settings.common import format_value
from surrogate.stages.shards import shard_seed, shard_sizes

log = logging.getLogger(__name__)

REFERENCE_CMD = "python scripts/reference.py"
#: the stored format's version: part of every reference's identity
REFERENCE_VERSION = 1
#: the two runs of a field: the full model and its noise floor (seed + noise_seed_offset)
WHICH = ("full", "full_repeat")
#: ``fidelity.streams``: ``per_field``, every run of the i-th field of ``fidelity.fields`` draws
#: from its seed + i x :data:`FIELD_SEED_STRIDE` (each field its own stream); ``shared``, every
#: field from the same seeds, the draws before 2026-12-01 (session 32: one seed's cells on two
#: fields that both start at the peak moved alike, their distances correlated 0.93 per cell, so
#: a check's two fields were nearly one draw counted twice)
STREAMS = ("per_field", "shared")
FIELD_SEED_STRIDE = 10_000_000
OBSERVABLES = "observables.parquet"
SEGMENTS = "duration_histogram.parquet"
SHARDS_DIR = "reference_shards"


def streams_of(f: Mapping[str, Any]) -> str:
    """``fidelity.streams`` of the fidelity group ``f``, checked (:data:`STREAMS`)."""
    streams = f.get("streams", "per_field")
    if streams not in STREAMS:
        raise ConfigError(f"fidelity.streams must be one of {list(STREAMS)} (per_field: each "
                          f"field its own draws; shared: every field the same seeds, as stored "
                          f"references made before 2026-12-01 were drawn), got {streams!r}")  # fmt: skip
    return str(streams)


def field_seed(seed: int, field_index: int, streams: str) -> int:
    """The seed a run of the ``field_index``-th field of ``fidelity.fields`` draws from, for a
    run whose stream is ``seed`` (the full model, its floor, a chain): ``seed`` + index x
    :data:`FIELD_SEED_STRIDE` where ``streams`` is ``per_field``, else ``seed``.

    Example:
        >>> field_seed(5000, 1, "per_field"), field_seed(5000, 1, "shared")
        (10005000, 5000)
    """
    return seed + field_index * FIELD_SEED_STRIDE if streams == "per_field" else seed


@dataclass(frozen=True, eq=False)
class ReferenceRun:
    """One stored full-model run: a field, a seed and a size, simulated in shards.

    Attributes:
        setup: the model, its config and dt (the field is ``field_name``'s).
        which: ``full`` or ``full_repeat`` (the noise floor's run).
        field_name: a shipped field (``conf/field/<name>.yaml``).
        n_cells: cells in the whole run.
        t_end: simulated time (s) after equilibration.
        record_interval: every cell's observable is kept at multiples of this (s).
        start: where every cell starts.
        equilibration_time: internal dynamics before cells move (s).
        seed: the run's seed (shard i draws from child i of ``SeedSequence(seed)``).
        shard_cells: cells per shard (the last shards may hold one fewer).
        root: where merged references are kept (``reference.dir``).
        data_dir: where the shards go (``data_dir/reference_shards``).
    """

    setup: ModelSetup
    which: str
    field_name: str
    n_cells: int
    t_end: float
    record_interval: float
    start: tuple[float, ...]
    equilibration_time: float
    seed: int
    shard_cells: int
    root: Path
    data_dir: Path

    @property
    def shard_count(self) -> int:
        """Shards of the run: ``ceil(n_cells / shard_cells)``."""
        return -(-self.n_cells // self.shard_cells)

    @property
    def record_times(self) -> tuple[float, ...]:
        """The times (s) every cell's observable is kept at."""
        k = steps_between(self.record_interval, self.setup.dt, "reference.record_interval")
        n = steps_between(self.t_end, self.setup.dt, "t_end")
        return tuple(round(s * self.setup.dt, 9) for s in range(k, n + 1, k))

    def identity(self) -> dict[str, Any]:
        """What defines the run's law and sample (not the device, loop or threads: recorded)."""
        out = {"version": REFERENCE_VERSION, "dt": self.setup.dt,
               **self.setup.model.full_model_identity(self.setup.model_config),
               "field": field_config(self.field_name),
               "n_cells": self.n_cells, "t_end": self.t_end,
               "record_interval": self.record_interval, "start": list(self.start),
               "equilibration_time": self.equilibration_time, "seed": self.seed,
               "shard_cells": self.shard_cells}  # fmt: skip
        return out

    def label(self) -> dict[str, Any]:
        """Readable part of the directory names."""
        return {"field": self.field_name, "seed": self.seed, "n": self.n_cells, "T": self.t_end}

    @functools.cached_property
    def directory(self) -> Path:
        """``reference.dir/<model>/field=..._seed=..._n=..._T=...-<hash>``."""
        return artefact_dir(self.root, self.setup.model.name, self.label(), self.identity())

    def shard_dir(self, index: int) -> Path:
        """``data_dir/reference_shards/<model>/<the run's directory name>/shard-<i>``."""
        return (self.data_dir / SHARDS_DIR / self.setup.model.name / self.directory.name
                / f"shard-{index:04d}")  # fmt: skip

    def shard_identity(self, index: int) -> dict[str, Any]:
        """The run's identity and the shard's index."""
        return {**self.identity(), "shard": index}

    def describe(self) -> str:
        """e.g. ``full model on gaussian, seed 5000, 1000 cells x 200 s``."""
        what = "noise-floor run" if self.which == "full_repeat" else "full model"
        return (f"{what} on {self.field_name}, seed {self.seed}, {self.n_cells} cells x "
                f"{self.t_end:g} s")  # fmt: skip


@dataclass(frozen=True, eq=False)
class ReferenceSettings:
    """The stored runs a fidelity config needs, and how to make them."""

    runs: tuple[ReferenceRun, ...]
    workers: int
    job: Job
    command: str
    #: the config the workers rebuild these settings from (objects are not sent across)
    config: dict[str, Any]

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> ReferenceSettings:
        """Validate the fidelity group's run settings and the reference group."""
        c = to_dict(cfg)
        f = dict(c.get("fidelity") or {})
        r = dict(c.get("reference") or {})
        setup = ModelSetup.from_config(c)
        fields = tuple(str(x) for x in f.get("fields") or [])
        if not fields:
            raise ConfigError("fidelity.fields must list at least one field")
        for name in fields:
            field_config(name)
        n_cells = int(positive(f, "n_cells", "fidelity.", integer=True))
        t_end = float(positive(f, "t_end", "fidelity."))
        interval = float(positive(r, "record_interval", "reference."))
        shard_cells = int(positive(r, "shard_cells", "reference.", integer=True))
        workers = r.get("workers")
        if workers is None:
            workers = os.cpu_count() or 1
        elif isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ConfigError(f"reference.workers must be a positive integer or null (the "
                              f"cores), got {workers!r}")  # fmt: skip
        if not r.get("dir"):
            raise ConfigError("reference.dir must name the directory the references are kept in")
        for key, value in (("fidelity.t_end", t_end), ("reference.record_interval", interval)):
            try:
                steps_between(value, setup.dt, key)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
        if steps_between(t_end, setup.dt, "t_end") % steps_between(interval, setup.dt, "r"):
            raise ConfigError(f"fidelity.t_end={t_end:g} s must be a multiple of "
                              f"reference.record_interval={interval:g} s")  # fmt: skip
        start = validate_start(f, "start", "fidelity.", start_size_of(setup.model.body))
        eq = float(non_negative(f, "equilibration_time", "fidelity."))
        seeds = {
            "sim_seed": f.get("sim_seed"),
            "noise_seed_offset": f.get("noise_seed_offset", 1000),
        }
        for key, given in seeds.items():
            if isinstance(given, bool) or not isinstance(given, int):
                raise ConfigError(f"fidelity.{key} must be an integer, got {given!r}")
        seed, offset = int(seeds["sim_seed"]), int(seeds["noise_seed_offset"])
        if offset == 0 or seed < 0 or seed + offset < 0:
            raise ConfigError(f"fidelity.sim_seed ({seed!r}) and sim_seed + noise_seed_offset "
                              f"({offset!r}) must be two different non-negative seeds")  # fmt: skip
        streams = streams_of(f)
        job = Job.from_config(c)
        root = Path(str(r["dir"]))
        runs = tuple(
            ReferenceRun(setup.with_field(field_config(name)), which, name, n_cells, t_end,
                         interval, start, eq, field_seed(s, i, streams), shard_cells, root,
                         job.data_dir)
            for i, name in enumerate(fields)
            for which, s in zip(WHICH, (seed, seed + offset), strict=True)
        )  # fmt: skip
        return cls(runs, int(workers), job, _command(c, setup), c)

    def run_for(self, field_name: str, which: str) -> ReferenceRun:
        """The stored run of ``field_name`` (``which``: ``full`` or ``full_repeat``)."""
        for run in self.runs:
            if run.field_name == field_name and run.which == which:
                return run
        raise KeyError(f"no reference run {which} on {field_name}")


def _command(c: Mapping[str, Any], setup: ModelSetup) -> str:
    """The command that makes these references: the model and every run setting, explicit."""
    f, r = c["fidelity"], c["reference"]
    parts = [REFERENCE_CMD, *group_overrides("model", setup.model_config), f"dt={setup.dt:g}"]
    for key in ("fields", "n_cells", "t_end", "start", "equilibration_time", "sim_seed",
                "noise_seed_offset"):  # fmt: skip
        parts.append(f"fidelity.{key}={format_value(f.get(key))}")
    if streams_of(f) != STREAMS[0]:
        parts.append(f"fidelity.streams={streams_of(f)}")
    parts += [f"reference.{k}={format_value(r[k])}" for k in ("shard_cells", "record_interval")]
    if str(r["dir"]) != "references":
        parts.append(f"reference.dir={r['dir']}")
    return " ".join(parts)


def validate(cfg: Mapping[str, Any]) -> ReferenceSettings:
    """All checks of a reference config and the estimated cost of what is missing."""
    settings = ReferenceSettings.from_config(cfg)
    works = []
    for run in settings.runs:
        if (run.directory / MANIFEST).exists():
            continue
        missing = sum(
            1 for i in range(run.shard_count) if not (run.shard_dir(i) / MANIFEST).exists()
        )
        if missing:
            cells = missing * run.shard_cells
            # each worker runs its shards one after the other: a loop (and its fixed cost per
            # step) per shard
            fixed = step_seconds(run.setup.model, run.setup.field, run.setup.dt, "full",
                                 settings.job.device) * -(-missing // settings.workers)  # fmt: skip
            works.append(Work(
                f"the {run.describe()} ({missing} of {run.shard_count} shards left, "
                f"{settings.workers} at once)",
                max(1, cells // settings.workers), steps_between(run.t_end, run.setup.dt, "t_end"),
                run.setup.model.cell_step_seconds(run.setup.dt, device=settings.job.device),
                "fidelity.n_cells, fidelity.t_end",
                run.setup.model.name, step_seconds=fixed))  # fmt: skip
    budget.check(cfg, works, "reference")
    return settings


# ----------------------------------------------------------------------------------------------
# making them


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Make every missing reference of a fidelity config; return the references' directory."""
    settings = validate(cfg)
    make(settings, force=force)
    return settings.runs[0].directory.parent


def make(settings: ReferenceSettings, force: bool = False) -> list[Path]:
    """Simulate the missing shards (``settings.workers`` processes), merge each run; return the
    runs' directories. A stopped call resumes from the finished shards."""
    todo = [r for r in settings.runs
            if force or existing_artefact(r.directory, r.identity(), settings.command) is None]  # fmt: skip
    tasks = [(settings.runs.index(r), i) for r in todo for i in range(r.shard_count)
             if force or existing_artefact(r.shard_dir(i), r.shard_identity(i),
                                           settings.command) is None]  # fmt: skip
    if tasks:
        _simulate_shards(settings, tasks, force)
    for r in todo:
        _merge(r, settings.command)
        log.info("reference: the %s in %s", r.describe(), r.directory)
    for r in settings.runs:
        if r not in todo:
            log.info("reference exists, reusing %s", r.directory)
    return [r.directory for r in settings.runs]


def _simulate_shards(
    settings: ReferenceSettings, tasks: list[tuple[int, int]], force: bool
) -> None:
    t0 = time.perf_counter()
    workers = min(settings.workers, len(tasks))
    threads = max(1, (os.cpu_count() or 1) // workers) if workers > 1 else torch.get_num_threads()
    log.info("reference: %d shard(s) to simulate, %d process(es) of %d thread(s); finished "
             "shards are kept, so a stopped run resumes", len(tasks), workers, threads)  # fmt: skip
    done = 0

    def finished(i: int, seconds: float) -> None:
        nonlocal done
        done += 1
        left = (time.perf_counter() - t0) / done * (len(tasks) - done)
        r = settings.runs[tasks[i][0]]
        log.info("reference: shard %d/%d done (%s, shard %d: %.0f s); ~%.0f min left", done,
                 len(tasks), r.describe(), tasks[i][1], seconds, left / 60)  # fmt: skip

    if workers == 1:
        _set_threads(threads)
        for i, (r, s) in enumerate(tasks):
            finished(i, _make_shard(settings, r, s, force))
        return
    context = multiprocessing.get_context("spawn")  # no forked torch or numba thread pools
    with cf.ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_init,
                                initargs=(threads,)) as pool:  # fmt: skip
        futures = {pool.submit(_shard_job, settings.config, r, s, force): i
                   for i, (r, s) in enumerate(tasks)}  # fmt: skip
        for future in cf.as_completed(futures):
            finished(futures[future], future.result())


def _worker_init(threads: int) -> None:
    """A worker process: its thread counts, and INFO logging of this package to stderr."""
    logging.basicConfig(level=logging.WARNING,
                        format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")  # fmt: skip
    logging.getLogger("surrogate").setLevel(logging.INFO)
    _set_threads(threads)


def _set_threads(threads: int) -> None:
    """``threads`` for torch and numba's compiled SSA."""
    torch.set_num_threads(threads)
    match_torch_threads()


@functools.lru_cache(maxsize=1)
def _settings_of(blob: str) -> ReferenceSettings:
    return ReferenceSettings.from_config(json.loads(blob))


def _shard_job(config: Mapping[str, Any], run_index: int, shard: int, force: bool) -> float:
    """A worker's task: rebuild the settings (once per process) and make one shard."""
    settings = _settings_of(json.dumps(config, sort_keys=True))
    return _make_shard(settings, run_index, shard, force)


def _make_shard(settings: ReferenceSettings, run_index: int, shard: int, force: bool) -> float:
    """Make shard ``shard`` of run ``run_index`` (reusing it when it exists); its wall time."""
    t0 = time.perf_counter()
    r = settings.runs[run_index]
    out = r.shard_dir(shard)
    make_once(out, r.shard_identity(shard), settings.command,
              lambda _: _adopt_or_simulate(r, shard, out, settings, force),
              what="reference shard", force=force)  # fmt: skip
    return time.perf_counter() - t0


def equivalent_shard(r: ReferenceRun, index: int) -> Path | None:
    """A finished shard ``index`` of another size of the same run, if one exists: shard i
    draws from child i of ``SeedSequence(seed)`` whatever the shard count, so a run of the same
    law, seed and shard size (only ``n_cells`` differs) has the very same cells there, and
    extending a stored run from 1,000 to 4,000 cells pays for the 3,000 new ones only."""
    size = shard_sizes(r.n_cells, r.shard_count)[index]
    want = settings_hash({k: v for k, v in r.shard_identity(index).items() if k != "n_cells"}, 64)
    root = r.data_dir / SHARDS_DIR / r.setup.model.name
    for d in sorted(root.glob(f"*/shard-{index:04d}")):
        if d == r.shard_dir(index) or not (d / MANIFEST).exists():
            continue
        try:
            m = read_manifest(d)
        except ArtefactError:
            continue
        theirs = m.get("settings") or {}
        if (m.get("n_cells") == size
                and settings_hash({k: v for k, v in theirs.items() if k != "n_cells"}, 64) == want):  # fmt: skip
            return d
    return None


def _adopt_or_simulate(
    r: ReferenceRun, shard: int, out: Path, settings: ReferenceSettings, force: bool
) -> None:
    """Shard ``shard`` copied from an equivalent one (:func:`equivalent_shard`), else simulated."""
    source = None if force else equivalent_shard(r, shard)
    if source is None:
        _simulate_shard(r, shard, out, settings)
        return
    out.mkdir(parents=True, exist_ok=True)
    for name in (OBSERVABLES, SEGMENTS):  # the manifest, written last, marks the shard done
        shutil.copyfile(source / name, out / name)
    kept = {k: v for k, v in read_manifest(source).items()
            if k not in ("stage", "config", "seed", "settings", "versions", "torch_threads",
                         "host")}  # fmt: skip
    log.info("reference: shard %d of the %s is shard %d of %s (same cells), copied", shard,
             r.describe(), shard, source.parent.name)  # fmt: skip
    write_manifest(out, stage="reference_shard", config=settings.config,
                   seed=shard_seed(r.seed, r.shard_count, shard),
                   settings=r.shard_identity(shard), copied_from=str(source), **kept)  # fmt: skip


def _simulate_shard(r: ReferenceRun, shard: int, out: Path, settings: ReferenceSettings) -> None:
    t0 = time.perf_counter()
    n = shard_sizes(r.n_cells, r.shard_count)[shard]
    seed = shard_seed(r.seed, r.shard_count, shard)
    model = r.setup.model
    seed_everything(seed)
    rep = Replicate(FullDecision(model.internal), r.setup.field, n, seed, r.start)
    info: dict[str, Any] = {}
    plan = RunPlan(r.setup.dt, r.record_times, r.t_end, r.equilibration_time,
                   settings.job.device, backend="auto")  # fmt: skip
    result = simulate_runs(model, [rep], ["shard"], plan=plan, progress=False,
                           desc=f"shard {shard}", info=info)["shard"]  # fmt: skip
    facts = write_result(out, result, model.body.observable_names[0])
    write_manifest(out, stage="reference_shard", config=settings.config, seed=seed,
                   settings=r.shard_identity(shard), n_cells=n, device=str(settings.job.device),
                   wall_time_s=time.perf_counter() - t0, **info, **facts)  # fmt: skip


def _merge(r: ReferenceRun, command: str) -> None:
    """Merge the run's shards into its directory (files first, manifest last, under a lock)."""
    parts, shards = [], []
    for i in range(r.shard_count):
        d = r.shard_dir(i)
        manifest = existing_artefact(d, r.shard_identity(i), command)
        if manifest is None:
            raise MissingArtefactError(f"reference shard {d} is missing; run `{command}`")
        parts.append(read_result(d, manifest, r.setup.dt))
        shards.append({k: manifest.get(k) for k in ("n_cells", "device", "loop_backend",
                                                     "torch_threads", "host", "wall_time_s")})  # fmt: skip
    result = RunResult.merge(parts, r.setup.dt)
    with artefact_lock(r.directory):
        facts = write_result(r.directory, result, r.setup.model.body.observable_names[0])
        write_manifest(r.directory, stage="reference", config={"command": command}, seed=r.seed,
                       settings=r.identity(), command=command, which=r.which,
                       n_cells=r.n_cells, record_times=list(r.record_times),
                       shard_count=r.shard_count, shards=shards,
                       cpu_seconds=sum(float(s["wall_time_s"] or 0) for s in shards),
                       **facts)  # fmt: skip


# ----------------------------------------------------------------------------------------------
# the stored format


def write_result(out: Path, result: RunResult, observable: str) -> dict[str, Any]:
    """Write a run's observables and segment histogram; the facts its manifest keeps."""
    n = len(next(iter(result.observables.values()))) if result.observables else 0
    times = sorted(result.observables)
    write_parquet(out / OBSERVABLES, pd.DataFrame({
        "cell": np.tile(np.arange(n, dtype=np.int32), len(times)),
        "t": np.repeat(np.asarray(times, dtype=np.float64), n),
        observable: np.concatenate([result.observables[t] for t in times]) if times else [],
    }))  # fmt: skip
    rows = []
    for lump, counts in result.histograms.items():
        (k,) = np.nonzero(counts)
        rows.append(pd.DataFrame({"lump": lump, "steps": k.astype(np.int32),
                                  "count": counts[k].astype(np.int64)}))  # fmt: skip
    write_parquet(out / SEGMENTS, pd.concat(rows, ignore_index=True))
    return {"observable": observable, "segments": result.segments,
            "total_steps": result.total_steps, "mean_durations": result.mean_durations}  # fmt: skip


def read_result(directory: Path, manifest: Mapping[str, Any], dt: float) -> RunResult:
    """A stored run (shard or merged) as the checks read it."""
    obs = read_parquet(directory / OBSERVABLES)
    name = str(manifest["observable"])
    observables = {float(t): g.sort_values("cell")[name].to_numpy(np.float64)
                   for t, g in obs.groupby("t", sort=True)}  # fmt: skip
    seg = read_parquet(directory / SEGMENTS)
    histograms = {}
    for lump in manifest["segments"]:
        counts = np.zeros(MAX_SEGMENT_STEPS + 1, dtype=np.int64)
        g = seg[seg["lump"] == lump]
        counts[g["steps"].to_numpy()] = g["count"].to_numpy()
        histograms[lump] = counts
    segments = {k: int(v) for k, v in manifest["segments"].items()}
    totals = {k: int(v) for k, v in manifest["total_steps"].items()}
    for lump, counts in histograms.items():
        if int(counts.sum()) != segments[lump]:
            raise ArtefactError(f"{directory}: the {lump} histogram does not add up to its "
                                "segment count; re-create it")  # fmt: skip
    return RunResult(observables, {k: totals[k] / max(segments[k], 1) * dt for k in segments},
                     segments, histograms, totals)  # fmt: skip


# ----------------------------------------------------------------------------------------------
# reading them for a check


def load(r: ReferenceRun, command: str, times: Sequence[float]) -> RunResult:
    """The stored run ``r`` at the check ``times``.

    Raises:
        MissingArtefactError: it is not stored; the message names the stored references of the
            same model and field whose identity differs (and in what), and the command.
        ArtefactError: its files disagree with its manifest, or ``times`` are not kept.
    """
    manifest = existing_artefact(r.directory, r.identity(), command)
    if manifest is None:
        raise MissingArtefactError(_missing_message(r, command))
    result = read_result(r.directory, manifest, r.setup.dt)
    kept = sorted(result.observables)
    missing = [t for t in times if not any(math.isclose(t, k, abs_tol=1e-9) for k in kept)]
    if missing:
        raise ArtefactError(f"the stored reference {r.directory} keeps the observable at "
                            f"multiples of {r.record_interval:g} s, not at {missing}: choose "
                            "fidelity.times among them")  # fmt: skip
    pick = {t: next(k for k in kept if math.isclose(t, k, abs_tol=1e-9)) for t in times}
    result.observables = {t: result.observables[k] for t, k in pick.items()}
    return result


def _missing_message(r: ReferenceRun, command: str) -> str:
    """No stored run for ``r``: what is stored for this model and how it differs."""
    want = json.loads(json.dumps(r.identity(), default=str))
    near = []
    folder = r.root / r.setup.model.name
    for d in sorted(folder.glob("*")) if folder.is_dir() else []:
        if not (d / MANIFEST).exists():
            continue
        try:
            have = read_manifest(d).get("settings", {})
        except ArtefactError:
            continue
        diffs = _differences(want, have)
        near.append((len(diffs), d, diffs))
    near.sort(key=lambda x: x[0])
    hours = r.shard_count * r.shard_cells * steps_between(r.t_end, r.setup.dt, "t_end") * \
        r.setup.model.cell_step_seconds(r.setup.dt) / 3600  # fmt: skip
    text = f"no stored full-model reference for the {r.describe()} ({r.directory} is missing)."
    if near:
        count, d, diffs = near[0]
        shown = "; ".join(diffs[:6]) + (f"; and {count - 6} more" if count > 6 else "")
        text += (
            f" The closest stored one, {d}, was made with other settings: {shown}. A "
            "reference serves only the model identity it was made with."
        )
    return (
        f"{text} Make it with `{command}` (~{hours:.2g} h of one core, estimated; "
        "resumable), or check with fidelity.reference=run (the full model simulated "
        "beside the candidates)."
    )


def _differences(want: Mapping[str, Any], have: Mapping[str, Any], prefix: str = "") -> list[str]:
    """``key: stored X, wanted Y`` for every differing leaf."""
    out = []
    for key in sorted(set(want) | set(have)):
        a, b = want.get(key), have.get(key)
        name = f"{prefix}{key}"
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += _differences(a, b, f"{name}.")
        elif settings_hash({"v": a}) != settings_hash({"v": b}):
            out.append(f"{name}: stored {b!r}, wanted {a!r}")
    return out


__all__ = [
    "FIELD_SEED_STRIDE",
    "REFERENCE_CMD",
    "STREAMS",
    "ReferenceRun",
    "ReferenceSettings",
    "field_seed",
    "load",
    "make",
    "read_result",
    "run",
    "streams_of",
    "validate",
    "write_result",
]

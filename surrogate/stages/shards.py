"""Population sharding: one large population as K independent jobs, merged into one run.

``shard.count=K shard.index=i`` makes a simulate job run shard i: ``n_cells // K`` cells (one more
for the first ``n_cells % K`` shards) with a seed of its own, drawn from
``numpy.random.SeedSequence(seed).spawn(K)[i]``, so shards are statistically independent streams
and no shard repeats the unsharded run's stream (which seeds torch with ``seed`` itself). A shard
is an ordinary simulation with those settings, so it lands in its own settings-derived directory
under ``data/simulate``. ``shard.count=1`` (the default) is the unsharded run, unchanged.

:func:`merge` (``python scripts/merge_shards.py shard.count=K``) streams the K shards' tables into
ONE run directory in exactly the unsharded format: cell ids offset to ``0..n_cells-1`` (shard 0
first), observables ordered by record time then cell, durations concatenated in shard order, and a
manifest with the unsharded keys (``n_cells`` the total, wall and loop times summed, throughput
recomputed) plus ``shards``, the shard directories.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from surrogate.config import to_dict
from surrogate.errors import ArtefactError, ConfigError, MissingArtefactError
from surrogate.io import (
    MANIFEST,
    artefact_dir,
    artefact_lock,
    existing_artefact,
    read_manifest,
    write_manifest,
)
from surrogate.simulate.population import DURATIONS, OBSERVABLES
from surrogate.simulate.recorders import DURATION_SCHEMA, StreamingParquet, observable_schema
from surrogate.stages.settings import SIMULATE_CMD, SimulateSettings
from surrogate.stages.simulate import simulate

log = logging.getLogger(__name__)

MERGE_CMD = "python scripts/merge_shards.py"
_BATCH_ROWS = 1 << 18  # rows read per batch while merging: memory stays flat in n_cells x t_end


# ----------------------------------------------------------------------------------------------
# shard settings


def shard_settings(cfg: Mapping[str, Any]) -> tuple[int, int]:
    """Validated ``(count, index)`` of a config; ``(1, 0)`` when it has no ``shard`` section."""
    shard = cfg.get("shard") or {}
    count, index = shard.get("count", 1), shard.get("index", 0)
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ConfigError(f"shard.count must be a positive integer, got {count!r}")
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < count:
        raise ConfigError(f"shard.index must be an integer in 0..{count - 1}, got {index!r}")
    n_cells = cfg.get("n_cells")
    if count > 1 and isinstance(n_cells, int) and count > n_cells:
        raise ConfigError(
            f"shard.count={count} is larger than n_cells={n_cells}: every shard needs a cell"
        )
    return count, index


def shard_sizes(n_cells: int, count: int) -> list[int]:
    """Cells per shard: ``n_cells // count``, one more for the first ``n_cells % count``."""
    base, extra = divmod(int(n_cells), int(count))
    return [base + (1 if i < extra else 0) for i in range(count)]


def shard_offsets(n_cells: int, count: int) -> list[int]:
    """Id of each shard's first cell in the merged run (shard 0 first)."""
    return [0, *itertools.accumulate(shard_sizes(n_cells, count))][:count]


def shard_seed(seed: int, count: int, index: int) -> int:
    """Seed of shard ``index`` of ``count``: child ``index`` of ``SeedSequence(seed)``, 63 bits
    (torch and numpy both take it), independent of the parent's and the siblings' streams."""
    if not 0 <= index < count:
        raise ValueError(f"shard index {index} outside 0..{count - 1}")
    child = np.random.SeedSequence(int(seed)).spawn(count)[index]
    return int(child.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def shard_run(settings: SimulateSettings, count: int, index: int) -> SimulateSettings:
    """The settings of one shard: its share of the cells and its own seed (the parent's seed and
    size are recorded in ``shard``)."""
    if count == 1:
        return settings
    if not 0 <= index < count:
        raise ConfigError(f"shard.index must be an integer in 0..{count - 1}, got {index!r}")
    n_total, seed = settings.n_cells, settings.setup.seed
    return settings.replace(
        n_cells=shard_sizes(n_total, count)[index],
        seed=shard_seed(seed, count, index),
        shard={"count": count, "index": index, "parent_seed": seed, "parent_n_cells": n_total},
    )


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """The simulate job: the whole population, or shard ``shard.index`` of ``shard.count``."""
    count, index = shard_settings(cfg)
    settings = shard_run(SimulateSettings.from_config(cfg), count, index)
    if count > 1:
        log.info("shard %d of %d: %d cells, seed %d", index, count, settings.n_cells,
                 settings.setup.seed)  # fmt: skip
    return simulate(settings, config=to_dict(cfg), force=force)


# ----------------------------------------------------------------------------------------------
# merge


def merged_identity(settings: SimulateSettings, count: int) -> dict[str, Any]:
    """What defines a merged run: the unsharded run's settings plus the shard count."""
    return {**settings.identity(), "shard_count": count}


def merged_dir(settings: SimulateSettings, count: int) -> Path:
    """``data/simulate/<decision>_..._seed=..._shards=K-<hash>``."""
    label = {**settings.label(), "shards": count}
    return artefact_dir(settings.job.data_dir, "simulate", label, merged_identity(settings, count))


def simulate_command(
    settings: SimulateSettings,
    count: int,
    indices: Sequence[int],
    overrides: Sequence[str] | None = None,
) -> str:
    """The command that makes shards ``indices``: the merge's own overrides when known (so every
    setting matches), else the main settings; a multirun for several shards."""
    if overrides is not None:
        keep = [o for o in overrides if not o.lstrip("+~").startswith("shard.")]
    else:
        keep = settings.overrides()
    multi = ["-m"] if len(indices) > 1 else []
    shard = [f"shard.count={count}", f"shard.index={','.join(str(i) for i in indices)}"]
    return " ".join([SIMULATE_CMD, *multi, *keep, *shard])


def merge(
    cfg: Mapping[str, Any], overrides: Sequence[str] | None = None, force: bool = False
) -> Path:
    """Merge the ``shard.count`` shards of ``cfg`` into one run directory; return it.

    Raises:
        ConfigError: ``shard.count`` is 1 or a simulate setting is invalid.
        MissingArtefactError: A shard has not been simulated (the message names the shards and
            the command that makes them).
        ArtefactError: The shards disagree (record times, steps, cells).
    """
    count, _ = shard_settings(cfg)
    if count == 1:
        raise ConfigError("shard.count=1: nothing to merge; set shard.count to the shards' K")
    settings = SimulateSettings.from_config(cfg)
    out = merged_dir(settings, count)
    made_by = f"{MERGE_CMD} shard.count={count}"
    identity = merged_identity(settings, count)
    if not force and existing_artefact(out, identity, made_by) is not None:
        log.info("merged run exists, reusing %s", out)
        return out
    dirs = [shard_run(settings, count, i).directory for i in range(count)]
    missing = [i for i, d in enumerate(dirs) if not (d / MANIFEST).exists()]
    if missing:
        names = ", ".join(f"shard {i} ({dirs[i]})" for i in missing)
        raise MissingArtefactError(
            f"missing {len(missing)} of {count} shards: {names}. "
            f"Run `{simulate_command(settings, count, missing, overrides)}` first."
        )
    with artefact_lock(out):  # two merges of the same run take turns
        if not force and existing_artefact(out, identity, made_by) is not None:
            return out
        _merge(settings, count, dirs, out, to_dict(cfg))
    return out


def _merge(
    settings: SimulateSettings, count: int, dirs: Sequence[Path], out: Path, config: dict[str, Any]
) -> None:
    """Write the merged tables, then (last, marking completion) the manifest into ``out``."""
    t0 = time.perf_counter()
    manifests = [read_manifest(d) for d in dirs]
    sizes = shard_sizes(settings.n_cells, count)
    _check_shards(dirs, manifests, sizes)
    offsets = shard_offsets(settings.n_cells, count)
    names = list(manifests[0].get("observables") or ["distance"])
    _merge_observables([d / OBSERVABLES for d in dirs], offsets, sizes, out / OBSERVABLES, names)
    n_durations = 0
    has_durations = [(d / DURATIONS).exists() for d in dirs]
    if any(has_durations):
        if not all(has_durations):
            lacking = [str(d) for d, h in zip(dirs, has_durations, strict=True) if not h]
            raise ArtefactError(f"shard(s) {lacking} lack {DURATIONS} but others have one")
        n_durations = _merge_durations([d / DURATIONS for d in dirs], offsets, out / DURATIONS)
    write_manifest(out, **merged_manifest(settings, count, config, manifests, dirs, n_durations),
                   merge_time_s=time.perf_counter() - t0)  # fmt: skip
    log.info("merged %d shards (%d cells) into %s", count, sum(sizes), out)


def merged_manifest(
    settings: SimulateSettings, count: int, config: dict[str, Any],
    manifests: Sequence[Mapping[str, Any]], dirs: Sequence[Path], n_durations: int,
) -> dict[str, Any]:  # fmt: skip
    """Keyword arguments of :func:`~surrogate.io.write_manifest` for the merged run: the
    unsharded run's keys, with totals over the shards."""
    n_cells = sum(int(m["n_cells"]) for m in manifests)
    n_steps = int(manifests[0]["n_steps"])
    loop = sum(float(m["loop_time_s"]) for m in manifests)
    config = {**config, "shard": {"count": count, "index": None}}
    extra = {}  # what the decision layer reported (same abstraction in every shard)
    for key in ("abstraction_dir", "lookup_max_deviation", "inputs"):
        values = [m[key] for m in manifests if key in m]
        if values:
            extra[key] = max(values) if key == "lookup_max_deviation" else values[0]
    devices = sorted({str(m.get("device")) for m in manifests})
    finals = [m.get("final_means") or {} for m in manifests]
    return {
        "stage": "simulate",
        "config": config,
        "seed": settings.setup.seed,
        "settings": merged_identity(settings, count),
        "decision": manifests[0]["decision"],
        "device": devices[0] if len(devices) == 1 else ",".join(devices),
        "wall_time_s": sum(float(m["wall_time_s"]) for m in manifests),
        "loop_time_s": loop,
        "compile_time_s": sum(float(m.get("compile_time_s", 0.0)) for m in manifests),
        "compile": bool(manifests[0].get("compile", False)),
        "compiled": all(bool(m.get("compiled", False)) for m in manifests),
        "cell_steps_per_s": n_cells * n_steps / max(loop, 1e-12),
        "n_cells": n_cells,
        "n_steps": n_steps,
        "n_durations": n_durations,
        # mean over all cells = cell-weighted mean of the shards' means
        "final_means": {
            k: sum(int(m["n_cells"]) * float(f[k]) for m, f in zip(manifests, finals, strict=True))
            / n_cells
            for k in finals[0]
        },
        "observables": manifests[0].get("observables"),
        "lump_names": manifests[0].get("lump_names"),
        **extra,
        "shard_count": count,
        "shards": [str(d) for d in dirs],
        "shard_seeds": [int(m["seed"]) for m in manifests],
    }


def _check_shards(
    dirs: Sequence[Path], manifests: Sequence[Mapping[str, Any]], sizes: Sequence[int]
) -> None:
    steps = {int(m["n_steps"]) for m in manifests}
    if len(steps) != 1:
        raise ArtefactError(f"shards disagree on the number of steps ({sorted(steps)}): {dirs}")
    for d, m, n in zip(dirs, manifests, sizes, strict=True):
        if int(m["n_cells"]) != n:
            raise ArtefactError(f"shard {d} has {m['n_cells']} cells, expected {n}")


def _time_groups(path: Path, columns: Sequence[str]) -> Iterator[tuple[float, pa.Table]]:
    """The rows of an observables table, one record time at a time (rows are grouped by time)."""
    pending: list[pa.Table] = []
    pending_t: float | None = None
    for batch in pq.ParquetFile(path).iter_batches(batch_size=_BATCH_ROWS, columns=list(columns)):
        table = pa.Table.from_batches([batch])
        t = table.column("t").to_numpy()
        cuts = [0, *(np.flatnonzero(np.diff(t)) + 1).tolist(), len(t)]
        for start, stop in itertools.pairwise(cuts):
            if stop == start:
                continue
            tv = float(t[start])
            if pending and tv != pending_t:
                yield pending_t, pa.concat_tables(pending)  # type: ignore[misc]
                pending = []
            pending_t = tv
            pending.append(table.slice(start, stop - start))
    if pending:
        yield pending_t, pa.concat_tables(pending)  # type: ignore[misc]


def _merge_observables(
    paths: Sequence[Path],
    offsets: Sequence[int],
    sizes: Sequence[int],
    out: Path,
    names: Sequence[str],
) -> None:
    """Stream the shards' observables into one table: per record time, every shard's cells."""
    for p in paths:
        if not p.exists():
            raise MissingArtefactError(f"missing artefact {p} (its shard's manifest exists)")
    schema = observable_schema(names)
    writer = StreamingParquet(out, schema)
    try:
        groups = [_time_groups(p, schema.names) for p in paths]
        for k, row in enumerate(itertools.zip_longest(*groups)):
            if any(g is None for g in row):
                short = [str(paths[i]) for i, g in enumerate(row) if g is None]
                raise ArtefactError(f"shard table(s) {short} have fewer record times than others")
            times = {t for t, _ in row}
            if len(times) != 1:
                raise ArtefactError(f"shards disagree on record time #{k}: {sorted(times)}")
            for (t, table), offset, n, path in zip(row, offsets, sizes, paths, strict=True):
                cells = table.column("cell").to_numpy()
                if len(cells) != n or cells.min() < 0 or cells.max() >= n:
                    raise ArtefactError(
                        f"{path} at t={t:g} has {len(cells)} rows with cell ids "
                        f"{cells.min()}..{cells.max()}, expected {n} cells 0..{n - 1}"
                    )
                writer.append(
                    t=table.column("t").to_numpy(),
                    cell=cells.astype(np.int64) + offset,
                    **{n: table.column(n).to_numpy().astype(np.float32) for n in names},
                )
        writer.commit()
    except BaseException:
        writer.abort()
        raise


def _merge_durations(paths: Sequence[Path], offsets: Sequence[int], out: Path) -> int:
    """Concatenate the shards' durations (shard order), offsetting cell ids; return the rows."""
    writer = StreamingParquet(out, DURATION_SCHEMA)
    try:
        for path, offset in zip(paths, offsets, strict=True):
            for batch in pq.ParquetFile(path).iter_batches(
                batch_size=_BATCH_ROWS, columns=DURATION_SCHEMA.names
            ):
                writer.append(
                    kind=batch.column("kind").to_numpy(zero_copy_only=False).astype(object),
                    duration=batch.column("duration").to_numpy(),
                    cell=batch.column("cell").to_numpy().astype(np.int64) + offset,
                    t_end=batch.column("t_end").to_numpy(),
                )
        writer.commit()
    except BaseException:
        writer.abort()
        raise
    return writer.n_rows

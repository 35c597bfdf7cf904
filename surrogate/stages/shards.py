"""Population sharding: one large population as K independent jobs, merged into one run.

``shard.count=K shard.index=i`` makes a simulate job run shard i: ``n_cells // K`` cells (one more
for the first ``n_cells % K`` shards) with a seed of its own, drawn from
``numpy.random.SeedSequence(seed).spawn(K)[i]``, so shards are statistically independent streams
and no shard repeats the unsharded run's stream (which seeds torch with ``seed`` itself). A shard
is an ordinary simulation with those settings, so it lands in its own settings-derived directory
under ``data/simulate``. ``shard.count=1`` (the default) is the unsharded run, unchanged.

:func:`merge` (``python scripts/merge_shards.py shard.count=K``) merges the K shards into ONE run
directory in exactly the unsharded format (:mod:`surrogate.simulate.recorders`), streaming, so
memory stays flat in n_cells x t_end: cell ids offset to ``0..n_cells-1`` (shard 0 first);
moments combined exactly over all cells (counts, means and variances by the pairwise formula,
extremes); histograms (observables on their common grid, durations on the lattice) added; the
recorded cells' values kept as a uniform random subsample of ``min(record_cells, n_cells)`` cells
of the merged population (seeded by the run's seed: how many cells come from each shard is drawn
as for a simple random sample of the whole population, then that many from each shard's own
uniform subsample; every cell when the shards recorded every cell, ``record_cells=null``), rows
by record time then cell; ``durations.parquet`` the shards' rows in shard order (those of the
kept cells, unless it holds every segment); and a manifest with the unsharded keys
(``n_cells`` the total, wall and loop times summed, throughput recomputed) plus ``shards``, the
shard directories. Shards written before the summaries existed (complete tables only) merge
into a run of that older format.
"""

from __future__ import annotations

import itertools
import json
import logging
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
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
    read_parquet,
    write_manifest,
)
from surrogate.simulate.recorders import (
    DURATION_HISTOGRAM,
    DURATION_HISTOGRAM_SCHEMA,
    DURATION_SCHEMA,
    DURATIONS,
    HISTOGRAM_SCHEMA,
    HISTOGRAMS,
    MOMENTS,
    MOMENTS_SCHEMA,
    OBSERVABLES,
    StreamingParquet,
    duration_histogram_rows,
    observable_schema,
    read_metadata,
    records_durations,
    with_metadata,
)
from surrogate.simulate.speed import cell_steps_per_s
from surrogate.simulate.support import merge_reports
from surrogate.stages import budget
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
    # the estimate of this job's own cells (scripts/simulate.py comes here, not to validate)
    budget.check(cfg, budget.run_work(settings), "simulate")
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
    names = list(manifests[0].get("observables") or settings.setup.model.body.observable_names)
    facts = merge_runs(dirs, sizes, out, names, seed=settings.setup.seed)
    write_manifest(out, **merged_manifest(settings, count, config, manifests, dirs,
                                          facts["n_durations"]),
                   recording=facts, merge_time_s=time.perf_counter() - t0)  # fmt: skip
    log.info("merged %d shards (%d cells) into %s", count, sum(sizes), out)


def merge_runs(
    dirs: Sequence[Path], sizes: Sequence[int], out: Path, names: Sequence[str], seed: int
) -> dict[str, Any]:
    """Merge the data files of the runs in ``dirs`` (``sizes`` cells each, in order) into
    ``out`` (see the module docstring); return the merged recording's facts (those of
    :meth:`~surrogate.simulate.recorders.RunRecorder.commit` that the files determine).

    Raises:
        MissingArtefactError: A run lacks a file.
        ArtefactError: The runs disagree (formats, record times, grids, recording settings).
    """
    offsets = [0, *itertools.accumulate(sizes)][: len(sizes)]
    summarised = [(d / MOMENTS).exists() for d in dirs]
    if any(summarised) and not all(summarised):
        raise ArtefactError(f"shards mix formats: only some have {MOMENTS}: {list(dirs)}")
    metas = [read_metadata(d / MOMENTS) for d in dirs] if all(summarised) else []
    for key in ("record_cells", "durations", "lump_names", "dt"):
        values = {json.dumps(m.get(key)) for m in metas}
        if len(values) > 1:
            raise ArtefactError(f"shards disagree on {key} ({sorted(values)}): {list(dirs)}")
    for d in dirs:
        if not (d / OBSERVABLES).exists():
            raise MissingArtefactError(
                f"missing artefact {d / OBSERVABLES} (its shard's manifest exists)"
            )
    rng = np.random.default_rng([int(seed) & (2**63 - 1), len(dirs)])
    recorded = [_recorded_cells(d / OBSERVABLES) for d in dirs]
    n_total = int(sum(sizes))
    every_cell = not metas or metas[0].get("record_cells") is None  # shards kept every cell
    target = n_total if every_cell else min(int(metas[0]["record_cells"]), n_total)
    if target >= sum(r.size for r in recorded):
        keep = recorded
    else:  # a simple random sample of the whole population, from the shards' own samples
        alloc = _allocate(sizes, target, rng)
        keep = [
            np.sort(rng.choice(r, m, replace=False)) for r, m in zip(recorded, alloc, strict=True)
        ]
    has_table = [(d / DURATIONS).exists() for d in dirs]
    if any(has_table) and not all(has_table):
        lacking = [str(d) for d, h in zip(dirs, has_table, strict=True) if not h]
        raise ArtefactError(f"shard(s) {lacking} lack {DURATIONS} but others have one")
    mode = metas[0].get("durations", "histogram") if metas else "all"
    facts: dict[str, Any] = {"n_cells": n_total, "observable_cells": int(sum(k.size for k in keep)),
                             "seed": int(seed), "shards": len(dirs), "durations": mode}  # fmt: skip
    if metas:
        facts.update(
            {k: metas[0][k] for k in ("record_cells", "dt", "lump_names") if k in metas[0]}
        )
    written: list[Path] = []
    try:
        _merge_observables([d / OBSERVABLES for d in dirs], offsets, recorded, keep,
                           out / OBSERVABLES, names)  # fmt: skip
        written.append(out / OBSERVABLES)
        if metas:
            written += _merge_summaries(dirs, out, facts)
        n_rows = 0
        if all(has_table):
            every = mode == "all"
            n_rows = _merge_durations([d / DURATIONS for d in dirs], offsets, out / DURATIONS,
                                      keep=None if every else keep)  # fmt: skip
            written.append(out / DURATIONS)
        n_durations = n_rows
        if metas and records_durations(mode):
            n_durations = _merge_duration_histograms(dirs, out, facts)
            written.append(out / DURATION_HISTOGRAM)
    except BaseException:
        for path in written:  # no half-merged set of files (the manifest is not written)
            path.unlink(missing_ok=True)
        raise
    return {**facts, "n_durations": int(n_durations), "duration_rows": int(n_rows)}


def _allocate(sizes: Sequence[int], total: int, rng: np.random.Generator) -> np.ndarray:
    """How many of a simple random sample of ``total`` cells of the merged population fall in
    each part of ``sizes`` (multivariate hypergeometric, for any population size)."""
    picked = rng.choice(int(sum(sizes)), size=total, replace=False)
    part = np.searchsorted(np.cumsum(sizes), picked, side="right")
    return np.bincount(part, minlength=len(sizes))


def _recorded_cells(path: Path) -> np.ndarray:
    """The cells of an observables table (those of its first record time), sorted."""
    for _, table in _time_groups(path, ["t", "cell"]):
        return np.sort(table.column("cell").to_numpy().astype(np.int64))
    raise ArtefactError(f"{path} has no rows")


def _merge_summaries(dirs: Sequence[Path], out: Path, facts: dict[str, Any]) -> list[Path]:
    """Combine the moments (exactly) and add the histograms of the runs into ``out``."""
    frames = [read_parquet(d / MOMENTS) for d in dirs]
    first = frames[0]
    for d, f in zip(dirs, frames, strict=True):
        same = len(f) == len(first) and all(
            np.array_equal(f[c].to_numpy(), first[c].to_numpy())
            for c in ("t", "observable", "lo", "width", "n_bins")
        )
        if not same:
            raise ArtefactError(
                f"{d / MOMENTS} differs from {dirs[0] / MOMENTS} in record times, observables or "
                "histogram grids: shards must share them"
            )
    n = np.stack([f["n"].to_numpy(np.int64) for f in frames])
    mean = np.stack([f["mean"].to_numpy(np.float64) for f in frames])
    var = np.stack([f["variance"].to_numpy(np.float64) for f in frames])
    total = n.sum(axis=0)
    merged_mean = (n * mean).sum(axis=0) / total
    # pairwise (Chan et al.) combination of the sums of squared deviations
    m2 = (np.where(n > 1, (n - 1) * var, 0.0) + n * (mean - merged_mean) ** 2).sum(axis=0)
    moments = {
        "t": first["t"].to_numpy(np.float64),
        "observable": first["observable"].to_numpy(object),
        "n": total,
        "mean": merged_mean,
        "variance": np.where(total > 1, m2 / np.maximum(total - 1, 1), np.nan),
        "min": np.min([f["min"].to_numpy(np.float64) for f in frames], axis=0),
        "max": np.max([f["max"].to_numpy(np.float64) for f in frames], axis=0),
        "lo": first["lo"].to_numpy(np.float64),
        "width": first["width"].to_numpy(np.float64),
        "n_bins": first["n_bins"].to_numpy(np.int32),
    }
    paths = []
    for name in (MOMENTS, HISTOGRAMS):
        if not all((d / name).exists() for d in dirs):
            raise MissingArtefactError(f"missing {name} in a shard of {list(dirs)}")
    writer = StreamingParquet(out / MOMENTS, with_metadata(MOMENTS_SCHEMA, facts))
    try:
        writer.append(**moments)
        paths.append(writer.commit())
    except BaseException:
        writer.abort()
        raise
    hist = StreamingParquet(out / HISTOGRAMS, HISTOGRAM_SCHEMA)
    try:
        groups = [_time_groups(d / HISTOGRAMS, HISTOGRAM_SCHEMA.names) for d in dirs]
        for k, row in enumerate(itertools.zip_longest(*groups)):
            if any(g is None for g in row) or len({t for t, _ in row}) != 1:
                raise ArtefactError(f"shards' {HISTOGRAMS} disagree on record time #{k}")
            table = pa.concat_tables([tbl for _, tbl in row]).to_pandas()
            summed = table.groupby(["observable", "bin"], sort=False)["count"].sum().reset_index()
            order = {name: i for i, name in enumerate(pd.unique(first["observable"]))}
            summed = summed.sort_values(["observable", "bin"], key=lambda c: c.map(order)
                                        if c.name == "observable" else c)  # fmt: skip
            hist.append(t=np.full(len(summed), row[0][0]),
                        observable=summed["observable"].to_numpy(object),
                        bin=summed["bin"].to_numpy(np.int32),
                        count=summed["count"].to_numpy(np.int64))  # fmt: skip
        paths.append(hist.commit())
    except BaseException:
        hist.abort()
        for path in paths:
            path.unlink(missing_ok=True)
        raise
    return paths


def _merge_duration_histograms(dirs: Sequence[Path], out: Path, facts: dict[str, Any]) -> int:
    """Add the runs' lattice histograms of durations; return the number of durations."""
    frames = [read_parquet(d / DURATION_HISTOGRAM) for d in dirs]
    table = pd.concat(frames, ignore_index=True)
    lumps = list(facts.get("lump_names") or pd.unique(table["kind"]))
    k_max = int(table["steps"].max()) if len(table) else 0
    counts = np.zeros((2, k_max + 1), dtype=np.int64)
    phi = table["kind"].map({lumps[0]: 0, lumps[1]: 1})
    if phi.isna().any():
        raise ArtefactError(f"{DURATION_HISTOGRAM} of the shards has kinds outside {lumps}")
    np.add.at(counts, (phi.to_numpy(np.int64), table["steps"].to_numpy(np.int64)),
              table["count"].to_numpy(np.int64))  # fmt: skip
    dt = float(facts["dt"])
    writer = StreamingParquet(
        out / DURATION_HISTOGRAM, with_metadata(DURATION_HISTOGRAM_SCHEMA, facts)
    )
    try:
        writer.append(**duration_histogram_rows(counts, dt, lumps))
        writer.commit()
    except BaseException:
        writer.abort()
        raise
    return int(counts.sum())


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
    threads = sorted({int(m["torch_threads"]) for m in manifests if "torch_threads" in m})
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
        "loop_backend": "/".join(sorted({str(m.get("loop_backend", "torch")) for m in manifests})),
        "cell_steps_per_s": cell_steps_per_s(n_cells, n_steps, max(loop, 1e-12)),
        # the shards' threads (a speed compares only under one count), not this process's
        "torch_threads": threads[0] if len(threads) == 1 else ",".join(map(str, threads)),
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
        "outside_training": merge_reports([m.get("outside_training") for m in manifests]),
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
    recorded: Sequence[np.ndarray],
    keep: Sequence[np.ndarray],
    out: Path,
    names: Sequence[str],
) -> None:
    """Stream the shards' observables into one table: per record time, every shard's kept
    cells (``keep``, a subset of the ``recorded`` ones: local ids), offset."""
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
            for (t, table), offset, mine, kept, path in zip(
                row, offsets, recorded, keep, paths, strict=True
            ):
                cells = table.column("cell").to_numpy()
                if len(cells) != mine.size or not np.array_equal(np.sort(cells), mine):
                    raise ArtefactError(
                        f"{path} at t={t:g} has {len(cells)} rows with cell ids "
                        f"{cells.min()}..{cells.max()}, expected the {mine.size} cells of its "
                        "first record time"
                    )
                if kept.size != mine.size:
                    table = table.filter(pa.array(np.isin(cells, kept)))
                    cells = table.column("cell").to_numpy()
                writer.append(
                    t=table.column("t").to_numpy(),
                    cell=cells.astype(np.int64) + offset,
                    **{n: table.column(n).to_numpy().astype(np.float32) for n in names},
                )
        writer.commit()
    except BaseException:
        writer.abort()
        raise


def _merge_durations(
    paths: Sequence[Path],
    offsets: Sequence[int],
    out: Path,
    keep: Sequence[np.ndarray] | None = None,
) -> int:
    """Concatenate the shards' durations (shard order), offsetting cell ids; with ``keep``
    only the rows of those cells (local ids per shard). Returns the rows written."""
    writer = StreamingParquet(out, DURATION_SCHEMA)
    try:
        for i, (path, offset) in enumerate(zip(paths, offsets, strict=True)):
            for batch in pq.ParquetFile(path).iter_batches(
                batch_size=_BATCH_ROWS, columns=DURATION_SCHEMA.names
            ):
                cells = batch.column("cell").to_numpy().astype(np.int64)
                rows = slice(None) if keep is None else np.isin(cells, keep[i])
                writer.append(
                    kind=batch.column("kind").to_numpy(zero_copy_only=False).astype(object)[rows],
                    duration=batch.column("duration").to_numpy()[rows],
                    cell=cells[rows] + offset,
                    t_end=batch.column("t_end").to_numpy()[rows],
                )
        writer.commit()
    except BaseException:
        writer.abort()
        raise
    return writer.n_rows

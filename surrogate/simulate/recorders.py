"""Streaming recorders: what a run keeps leaves the time loop in chunks, so memory stays flat in
t_end and bounded in n_cells, and disk stays bounded for any population.

Tables are streamed to temporary Parquet files (one row group per ~1e6 rows) and renamed into
place only when the run completes, so a killed run never leaves a readable partial table.

:class:`RunRecorder` writes, into a run directory:

``observables.parquet``
    ``t`` (s), ``cell``, one float32 column per observable: the exact values of a seeded random
    subsample of ``record_cells`` cells at every record time (rows by ``t`` then ``cell``); every
    cell when ``n_cells <= record_cells`` (then it is the complete table).
``observable_moments.parquet``
    one row per record time and observable, over ALL cells: ``t``, ``observable``, ``n``,
    ``mean``, ``variance`` (ddof=1, NaN for one cell), ``min``, ``max`` (float64, of the float32
    values the subsample stores) and the histogram grid ``lo``, ``width``, ``n_bins``. Its Parquet
    metadata (key ``surrogate.recording``, JSON) holds ``n_cells``, ``record_cells``,
    ``observable_cells`` and ``seed``.
``observable_histograms.parquet``
    ``t``, ``observable``, ``bin`` (int32), ``count`` (int64): the counts of ALL cells on the
    fixed grid ``[lo + bin * width, lo + (bin + 1) * width)``; ``bin = -1`` counts the values
    below ``lo`` (and NaN-free -inf), ``bin = n_bins`` those at or above ``lo + n_bins * width``
    (and +inf/NaN): no value is lost. Only non-zero counts are stored (rows by ``t``,
    ``observable``, ``bin``).
``duration_histogram.parquet``
    ``kind`` (the lump's name), ``steps`` (k), ``duration`` (k dt, s), ``count``: every completed
    phi segment of every cell, exactly (durations are whole numbers of steps); rows by phi
    (phi = 0 first) then ``steps``. Metadata: ``dt``, ``lump_names``, ``durations`` (the mode),
    ``record_cells``.
``durations.parquet``
    ``kind``, ``duration`` (s), ``cell``, ``t_end`` (s): with ``durations="all"`` every completed
    segment (the complete table); with ``durations="histogram"`` every completed segment of the
    recorded cells only (the same cells as ``observables.parquet``; all cells when
    ``n_cells <= record_cells``), an equal-probability sample for figures and per-cell analysis.

``durations="none"`` writes neither duration file.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torch import Tensor

from surrogate.io import publish

OBSERVABLES = "observables.parquet"
DURATIONS = "durations.parquet"
MOMENTS = "observable_moments.parquet"
HISTOGRAMS = "observable_histograms.parquet"
DURATION_HISTOGRAM = "duration_histogram.parquet"
#: Parquet key-value metadata key of the recording facts (JSON)
METADATA_KEY = b"surrogate.recording"

DurationMode = Literal["histogram", "all", "none"]
DURATION_MODES: tuple[str, ...] = ("histogram", "all", "none")
#: the mode that writes neither duration file: a recorder's word, not the chain's
#: ``gp.history=none`` (named here so no module compares a bare kind's name, issue 40)
NO_DURATIONS: Final = "none"


def records_durations(mode: str) -> bool:
    """Whether the ``durations`` mode ``mode`` writes the duration files (every mode but
    :data:`NO_DURATIONS`)."""
    return mode != NO_DURATIONS


#: cells whose exact values (and, with ``durations="histogram"``, durations) are kept
DEFAULT_RECORD_CELLS = 2000
#: device memory the per-step duration buffer may take (int32 x block rows x n_cells)
BUFFER_BYTES = 64 << 20
#: steps of segment ends buffered on the device between reductions (capped by BUFFER_BYTES):
#: one reduction and host sync per block, so small populations stop paying it every few steps
FLUSH_STEPS = 1024
#: bins of the fallback grid of an observable the spec does not name
FALLBACK_BINS = 10_000


@dataclass(frozen=True)
class HistogramGrid:
    """A fixed grid of ``n_bins`` bins of ``width`` from ``lo``: bin i is
    ``[lo + i * width, lo + (i + 1) * width)``."""

    lo: float
    width: float
    n_bins: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lo) and math.isfinite(self.width) and self.width > 0):
            raise ValueError(f"histogram grid needs finite lo and width > 0, got {self}")
        if self.n_bins < 1:
            raise ValueError(f"histogram grid needs at least one bin, got {self.n_bins}")

    @classmethod
    def from_range(cls, lo: float, hi: float, width: float) -> HistogramGrid:
        """The grid covering ``[lo, hi]`` in bins of ``width`` (the last bin may end past hi)."""
        if not hi > lo:
            raise ValueError(f"histogram range needs hi > lo, got [{lo}, {hi}]")
        if not width > 0:
            raise ValueError(f"histogram bin width must be > 0, got {width}")
        return cls(float(lo), float(width), max(1, math.ceil((hi - lo) / width - 1e-9)))

    @classmethod
    def around(cls, values: np.ndarray, n_bins: int = FALLBACK_BINS) -> HistogramGrid:
        """A fallback grid from the first record's values: their range widened by 10 times their
        scale (the larger of their spread, their magnitude and 1) on either side, in ``n_bins``
        bins."""
        finite = values[np.isfinite(values)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
        scale = max(hi - lo, abs(lo), abs(hi), 1.0)
        return cls.from_range(lo - 10 * scale, hi + 10 * scale, (hi - lo + 20 * scale) / n_bins)

    @property
    def hi(self) -> float:
        """The upper end of the last bin."""
        return self.lo + self.n_bins * self.width

    def edges(self) -> np.ndarray:
        """The ``n_bins + 1`` bin edges (float64)."""
        return self.lo + self.width * np.arange(self.n_bins + 1, dtype=np.float64)


GridSpec = HistogramGrid | Sequence[float] | Mapping[str, float]


def grid_from_spec(spec: GridSpec) -> HistogramGrid:
    """A grid from ``(lo, hi, width)``, ``{"lo", "hi", "width"}`` or a :class:`HistogramGrid`."""
    if isinstance(spec, HistogramGrid):
        return spec
    if isinstance(spec, Mapping):
        return HistogramGrid.from_range(float(spec["lo"]), float(spec["hi"]), float(spec["width"]))
    lo, hi, width = (float(v) for v in spec)
    return HistogramGrid.from_range(lo, hi, width)


def bin_counts(values: Tensor, grid: HistogramGrid) -> Tensor:
    """Counts of ``values`` (``(n,)``, any float dtype, any device) on ``grid``: int64
    ``(n_bins + 2,)`` = [below lo, bin 0, ..., bin n_bins - 1, at/above hi]; NaN and +inf count
    above, -inf below. Binned in float64 as ``floor((x - lo) / width)``; no host sync on CUDA
    apart from what ``bincount`` does."""
    pos = (values.to(torch.float64) - grid.lo) / grid.width
    pos = torch.nan_to_num(pos, nan=grid.n_bins, posinf=grid.n_bins, neginf=-1.0)
    idx = torch.floor(pos).clamp_(-1, grid.n_bins).to(torch.int64) + 1
    return torch.bincount(idx, minlength=grid.n_bins + 2)


def choose_cells(n_cells: int, record_cells: int | None, seed: int) -> np.ndarray:
    """The recorded cells: every cell when ``record_cells`` is None or ``n_cells <=
    record_cells``, else a uniform random subset of ``record_cells`` cells (seeded), sorted
    (int64)."""
    if record_cells is None or n_cells <= record_cells:
        return np.arange(n_cells, dtype=np.int64)
    rng = np.random.default_rng([int(seed) & (2**63 - 1), 0])
    return np.sort(rng.choice(n_cells, size=record_cells, replace=False)).astype(np.int64)


def with_metadata(schema: pa.Schema, facts: Mapping[str, Any]) -> pa.Schema:
    """``schema`` carrying ``facts`` as JSON under :data:`METADATA_KEY`."""
    return schema.with_metadata({METADATA_KEY: json.dumps(dict(facts), sort_keys=True)})


def read_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The recording facts a summary table carries (empty when it has none)."""
    meta = pq.read_schema(path).metadata or {}
    raw = meta.get(METADATA_KEY)
    return json.loads(raw) if raw else {}


class StreamingParquet:
    """Append column chunks; flush a row group when enough rows are buffered; commit atomically."""

    def __init__(
        self, path: str | os.PathLike, schema: pa.Schema, rows_per_group: int = 1 << 20
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent
        )
        os.close(fd)
        self.tmp = Path(tmp)
        self.schema = schema
        self.rows_per_group = rows_per_group
        self._writer = pq.ParquetWriter(self.tmp, schema)
        self._chunks: list[dict[str, np.ndarray]] = []
        self._buffered = 0
        self.n_rows = 0

    def append(self, **columns: np.ndarray) -> None:
        """Buffer one chunk (all columns of equal length)."""
        n = len(next(iter(columns.values())))
        if n == 0:
            return
        self._chunks.append(columns)
        self._buffered += n
        self.n_rows += n
        if self._buffered >= self.rows_per_group:
            self._flush()

    def _flush(self) -> None:
        if not self._chunks:
            return
        arrays = {
            name: np.concatenate([c[name] for c in self._chunks]) for name in self.schema.names
        }
        self._writer.write_table(pa.table(arrays, schema=self.schema))
        self._chunks.clear()
        self._buffered = 0

    def commit(self) -> Path:
        """Write what is buffered, close, and rename into place."""
        self._flush()
        self._writer.close()
        publish(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the partial file."""
        try:
            self._writer.close()
        finally:
            self.tmp.unlink(missing_ok=True)


DURATION_SCHEMA = pa.schema(
    [
        ("kind", pa.string()),
        ("duration", pa.float64()),
        ("cell", pa.int64()),
        ("t_end", pa.float64()),
    ]
)
MOMENTS_SCHEMA = pa.schema(
    [
        ("t", pa.float64()),
        ("observable", pa.string()),
        ("n", pa.int64()),
        ("mean", pa.float64()),
        ("variance", pa.float64()),
        ("min", pa.float64()),
        ("max", pa.float64()),
        ("lo", pa.float64()),
        ("width", pa.float64()),
        ("n_bins", pa.int32()),
    ]
)
HISTOGRAM_SCHEMA = pa.schema(
    [("t", pa.float64()), ("observable", pa.string()), ("bin", pa.int32()), ("count", pa.int64())]
)
DURATION_HISTOGRAM_SCHEMA = pa.schema(
    [("kind", pa.string()), ("steps", pa.int64()), ("duration", pa.float64()),
     ("count", pa.int64())]
)  # fmt: skip


def observable_schema(names: Sequence[str]) -> pa.Schema:
    """Columns ``t``, ``cell`` and one float32 column per observable."""
    return pa.schema(
        [("t", pa.float64()), ("cell", pa.int64()), *[(n, pa.float32()) for n in names]]
    )


def duration_rows(
    lengths: np.ndarray, steps: np.ndarray, cells: np.ndarray, dt: float, lumps: Sequence[str]
) -> dict[str, np.ndarray]:
    """Columns of :data:`DURATION_SCHEMA` for segment ends: ``lengths`` (signed steps, +k a phi = 1
    segment), the loop ``steps`` at which they ended and their ``cells``."""
    off, on = lumps
    return {
        "kind": np.where(lengths > 0, on, off).astype(object),
        "duration": np.abs(lengths).astype(np.float64) * dt,
        "cell": cells.astype(np.int64),
        "t_end": (steps.astype(np.float64) + 1) * dt,
    }


def duration_histogram_rows(
    counts: np.ndarray, dt: float, lumps: Sequence[str]
) -> dict[str, np.ndarray]:
    """Columns of :data:`DURATION_HISTOGRAM_SCHEMA` from ``counts`` ``(2, K)`` (phi, steps):
    the non-zero entries, phi = 0 first, then by steps."""
    phi, steps = np.nonzero(counts)
    return {
        "kind": np.asarray(lumps, dtype=object)[phi],
        "steps": steps.astype(np.int64),
        "duration": steps.astype(np.float64) * dt,
        "count": counts[phi, steps].astype(np.int64),
    }


@dataclass(frozen=True)
class RecorderSpec:
    """What a :class:`RunRecorder` keeps beyond the observables' histograms and moments.

    Attributes:
        record_cells: cells whose exact values are kept; None keeps every cell (and says so in
            the metadata, so that shards of any sizes merge into a run that keeps every cell).
        durations: ``"histogram"`` (lattice histogram + the recorded cells' segments),
            ``"all"`` (lattice histogram + every segment) or ``"none"``.
        histogram_spec: observable -> grid (``(lo, hi, width)``, a mapping with those keys or a
            :class:`HistogramGrid`; the simulators pass the body's declared
            ``histogram_grids`` under the caller's); observables it does not name get a grid
            around the first record's values (:meth:`HistogramGrid.around`, with a warning
            unless every cell's value is kept).
        seed: seeds the choice of recorded cells.
    """

    record_cells: int | None = DEFAULT_RECORD_CELLS
    durations: DurationMode = "histogram"
    histogram_spec: Mapping[str, GridSpec] | None = None
    seed: int = 0


class RunRecorder:
    """Everything a population run keeps: observables at record times, phi segment durations.

    Per record time and observable, over all cells: a histogram on a fixed grid (device-side
    counts), moments (n, mean, variance, min, max), and the exact values of the recorded cells
    (a seeded random subsample of ``record_cells``; all cells when ``n_cells <= record_cells``).
    Per step, the ended segment lengths go into a device buffer of ``block_rows`` steps
    (``block_steps`` capped so the buffer stays within :data:`BUFFER_BYTES`); a full block is
    reduced on the device into the exact lattice histogram of durations (count per number of
    steps and lump) and, depending on ``durations``, the segments of the recorded cells or of
    all cells are streamed to ``durations.parquet``. One host sync per block and per record
    time, none per step. The files are described in the module docstring.

    Memory: the buffer (<= 64 MiB), one float64 copy of an observable at record times
    (8 n_cells bytes), the grids (8 (n_bins + 2) bytes per observable) and the duration
    histogram (16 (n_steps + 1) bytes): flat in t_end apart from the last, bounded in n_cells.

    Args:
        out_dir: the run directory.
        n_cells: cells of the population.
        dt: the time step (s); durations are whole numbers of steps.
        observable_names: the body's observables, in order.
        lump_names: names of phi = 0 and phi = 1 (e.g. ``("tumble", "run")``).
        block_steps: steps per buffer block at most (e.g. the steps between record times).
        device: where the simulation's tensors live.
        spec: the recorded cells, the durations kept, the histogram grids and the seed
            (:class:`RecorderSpec`).
    """

    @torch.inference_mode()
    def __init__(
        self,
        out_dir: str | os.PathLike,
        n_cells: int,
        dt: float,
        observable_names: Sequence[str],
        lump_names: Sequence[str],
        block_steps: int,
        device: torch.device | str,
        spec: RecorderSpec = RecorderSpec(),
    ) -> None:
        record_cells, durations, seed = spec.record_cells, spec.durations, spec.seed
        if durations not in DURATION_MODES:
            raise ValueError(f"durations must be one of {DURATION_MODES}, got {durations!r}")
        if n_cells < 1 or (record_cells is not None and record_cells < 1):
            raise ValueError(f"need n_cells >= 1 and record_cells >= 1, got {n_cells}, "
                             f"{record_cells}")  # fmt: skip
        self.out = Path(out_dir)
        self.n_cells, self.dt = int(n_cells), float(dt)
        self.names = tuple(observable_names)
        self.lumps = (str(lump_names[0]), str(lump_names[1]))
        self.device = torch.device(device)
        self.mode = durations
        self.record_cells = None if record_cells is None else int(record_cells)
        self.seed = int(seed)
        grids = dict(spec.histogram_spec or {})
        self.grids: dict[str, HistogramGrid | None] = {
            n: grid_from_spec(grids[n]) if n in grids else None for n in self.names
        }
        self.cells = choose_cells(self.n_cells, self.record_cells, self.seed)
        self._all_cells = self.cells.size == self.n_cells
        self._cells_dev = (
            None if self._all_cells else torch.as_tensor(self.cells, device=self.device)
        )
        self.times: list[float] = []
        self.means: dict[str, list[float]] = {n: [] for n in self.names}
        self._durations_on = records_durations(durations)
        self.block_rows = max(1, min(int(block_steps), BUFFER_BYTES // (4 * self.n_cells)))
        self._buffer = (
            torch.zeros(self.block_rows, self.n_cells, dtype=torch.int32, device=self.device)
            if self._durations_on
            else None
        )
        self._block_start, self._filled = 0, 0
        # lattice histogram of signed lengths: index half + v for v in -half..half
        self._half = 0
        self._lattice = torch.zeros(1, dtype=torch.int64, device=self.device)
        self._tables: dict[str, StreamingParquet] = {}
        try:  # opened now, so a run killed at any point leaves only temporaries
            self._tables[OBSERVABLES] = StreamingParquet(
                self.out / OBSERVABLES, observable_schema(self.names)
            )
            self._tables[HISTOGRAMS] = StreamingParquet(self.out / HISTOGRAMS, HISTOGRAM_SCHEMA)
            self._moments: list[dict[str, Any]] = []
            if self._durations_on:
                self._tables[DURATIONS] = StreamingParquet(self.out / DURATIONS, DURATION_SCHEMA)
        except BaseException:
            self.abort()
            raise

    # ------------------------------------------------------------------------------------
    @torch.inference_mode()  # the loop's tensors are inference tensors
    def record_observables(self, t: float, observables: Mapping[str, Tensor]) -> None:
        """Record the observables (each ``(n_cells,)``) at time ``t``: histograms and moments
        over all cells, exact values of the recorded cells (one device->host copy each)."""
        values: dict[str, np.ndarray] = {}
        for name in self.names:
            x = observables[name].detach().to(torch.float32)
            x64 = x.to(torch.float64)
            grid = self.grids[name]
            if grid is None:
                grid = HistogramGrid.around(x64.cpu().numpy())
                self.grids[name] = grid
                if not self._all_cells:
                    warnings.warn(
                        f"no histogram grid given for observable {name!r}; using "
                        f"[{grid.lo:.4g}, {grid.hi:.4g}) in {grid.n_bins} bins around its first "
                        "values (pass histogram_spec)",
                        RuntimeWarning,
                        stacklevel=2,
                    )
            counts = bin_counts(x64, grid)
            n = x64.numel()
            var = x64.var() if n > 1 else torch.full((), float("nan"), dtype=torch.float64)
            stats = torch.stack([x64.mean(), var, x64.min(), x64.max()]).cpu().numpy()
            counts_np = counts.cpu().numpy()
            nz = np.flatnonzero(counts_np)
            self._tables[HISTOGRAMS].append(
                t=np.full(nz.size, float(t)),
                observable=np.full(nz.size, name, dtype=object),
                bin=(nz - 1).astype(np.int32),
                count=counts_np[nz].astype(np.int64),
            )
            self._moments.append(
                {"t": float(t), "observable": name, "n": n, "mean": stats[0],
                 "variance": stats[1], "min": stats[2], "max": stats[3], "lo": grid.lo,
                 "width": grid.width, "n_bins": grid.n_bins}
            )  # fmt: skip
            sub = x if self._cells_dev is None else x[self._cells_dev]
            values[name] = sub.cpu().numpy()
            self.means[name].append(float(stats[0]))
        self._tables[OBSERVABLES].append(
            t=np.full(self.cells.size, float(t)), cell=self.cells, **values
        )
        self.times.append(float(t))

    @torch.inference_mode()  # the loop's tensors are inference tensors
    def record_step(self, step: int, ended_length: Tensor) -> None:
        """``ended_length`` (``(n_cells,)`` int32) of loop step ``step``: +k a phi = 1 segment of
        k steps ended, -k a phi = 0 one, 0 nothing. Buffered on the device (no host sync)."""
        if self._buffer is None:
            return
        if self._filled == 0:
            self._block_start = step
        self._buffer[self._filled] = ended_length
        self._filled += 1
        if self._filled == self.block_rows:
            self.flush()

    @torch.inference_mode()  # the loop's tensors are inference tensors
    def record_block(self, first_step: int, block: Tensor) -> None:
        """:meth:`record_step` for ``k`` consecutive loop steps at once (``block``: ``k x
        n_cells`` int32, rows from step ``first_step`` on): one copy per buffer block."""
        if self._buffer is None:
            return
        i, k = 0, int(block.shape[0])
        while i < k:
            if self._filled == 0:
                self._block_start = first_step + i
            take = min(k - i, self.block_rows - self._filled)
            self._buffer[self._filled : self._filled + take] = block[i : i + take]
            self._filled += take
            i += take
            if self._filled == self.block_rows:
                self.flush()

    @torch.inference_mode()  # the loop's tensors are inference tensors
    def flush(self) -> None:
        """Reduce the buffered block: lattice histogram, and the segments kept in the table."""
        if self._buffer is None or self._filled == 0:
            return
        block = self._buffer[: self._filled]
        # a segment ending at loop step s lasts at most s + 1 steps
        self._grow_lattice(self._block_start + self._filled)
        every_cell = self._cells_dev is None or self.mode == "all"
        kept = block if every_cell else block[:, self._cells_dev]
        rows, cols = torch.nonzero(kept, as_tuple=True)  # the block's one host sync
        lengths = kept[rows, cols]
        ended = lengths if every_cell else block[block != 0]
        if ended.numel():
            self._lattice += torch.bincount(
                ended.to(torch.int64) + self._half, minlength=self._lattice.numel()
            )
        if lengths.numel():
            cells = cols.cpu().numpy()
            if not every_cell:
                cells = self.cells[cells]
            self._tables[DURATIONS].append(
                **duration_rows(lengths.cpu().numpy(), self._block_start + rows.cpu().numpy(),
                                cells, self.dt, self.lumps)
            )  # fmt: skip
        self._filled = 0

    def _grow_lattice(self, max_length: int) -> None:
        if max_length <= self._half:
            return
        half = max(max_length, 2 * self._half)
        grown = torch.zeros(2 * half + 1, dtype=torch.int64, device=self.device)
        grown[half - self._half : half + self._half + 1] = self._lattice
        self._lattice, self._half = grown, half

    @torch.inference_mode()  # the loop's tensors are inference tensors
    def duration_counts(self) -> np.ndarray:
        """The lattice histogram so far: int64 ``(2, K)``, ``[phi, k]`` = completed segments of
        phi lasting k steps (one host copy)."""
        self.flush()
        lattice = self._lattice.cpu().numpy()
        h = self._half
        counts = np.zeros((2, h + 1), dtype=np.int64)
        counts[1] = lattice[h:]
        counts[0] = lattice[h::-1]
        counts[:, 0] = 0
        return counts

    # ------------------------------------------------------------------------------------
    def facts(self) -> dict[str, Any]:
        """What the summary tables' metadata record about this recording."""
        return {"n_cells": self.n_cells, "record_cells": self.record_cells,
                "observable_cells": int(self.cells.size), "seed": self.seed, "dt": self.dt,
                "lump_names": list(self.lumps), "durations": self.mode}  # fmt: skip

    @torch.inference_mode()  # the loop's tensors are inference tensors
    def commit(self) -> dict[str, Any]:
        """Flush, write the summary tables and rename every file into place. Returns facts for
        the manifest: ``n_cells``, ``record_cells``, ``observable_cells``, ``seed``, ``dt``,
        ``lump_names``, ``durations`` (the mode), ``n_records``, ``final_means`` (per observable,
        at the last record time, over all cells), ``n_durations`` (all completed segments),
        ``duration_rows`` (rows of ``durations.parquet``), ``histogram_grids`` (observable ->
        ``[lo, hi, width]``), ``files`` and ``bytes`` (their total size)."""
        try:
            facts = self.facts()
            moments = StreamingParquet(self.out / MOMENTS, with_metadata(MOMENTS_SCHEMA, facts))
            self._tables[MOMENTS] = moments
            if self._moments:
                moments.append(**{c: np.asarray([m[c] for m in self._moments],
                                                dtype=object if c == "observable" else None)
                                  for c in MOMENTS_SCHEMA.names})  # fmt: skip
            n_durations, duration_rows_ = 0, 0
            if self._durations_on:
                counts = self.duration_counts()
                n_durations = int(counts.sum())
                duration_rows_ = self._tables[DURATIONS].n_rows
                hist = StreamingParquet(
                    self.out / DURATION_HISTOGRAM, with_metadata(DURATION_HISTOGRAM_SCHEMA, facts)
                )
                self._tables[DURATION_HISTOGRAM] = hist
                hist.append(**duration_histogram_rows(counts, self.dt, self.lumps))
            paths = [table.commit() for table in list(self._tables.values())]
        except BaseException:
            self.abort()
            raise
        self._tables.clear()
        return {
            **facts,
            "n_records": len(self.times),
            "final_means": {n: v[-1] for n, v in self.means.items() if v},
            "n_durations": n_durations,
            "duration_rows": duration_rows_,
            "histogram_grids": {
                n: [g.lo, g.hi, g.width] for n, g in self.grids.items() if g is not None
            },
            "files": sorted(p.name for p in paths),
            "bytes": int(sum(p.stat().st_size for p in paths)),
        }

    def abort(self) -> None:
        """Drop every temporary file (the committed ones stay: a later manifest decides)."""
        for table in self._tables.values():
            if table.tmp.exists():
                table.abort()
        self._tables.clear()

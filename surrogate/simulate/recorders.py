"""Streaming recorders: summaries leave the time loop in chunks, so memory stays flat in t_end.

Tables are streamed to a temporary Parquet file (one row group per ~1e6 rows) and renamed into
place only when the run completes, so a killed run never leaves a readable partial table.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torch import Tensor

from surrogate.io import publish


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


def observable_schema(names: Sequence[str]) -> pa.Schema:
    """Columns ``t``, ``cell`` and one float32 column per observable."""
    return pa.schema(
        [("t", pa.float64()), ("cell", pa.int64()), *[(n, pa.float32()) for n in names]]
    )


class ObservableRecorder:
    """Each cell's observables (e.g. distance from the peak) at record times ->
    ``observables.parquet`` (columns ``t``, ``cell``, one per observable)."""

    def __init__(self, path: str | os.PathLike, n_cells: int, names: Sequence[str]) -> None:
        self.names = tuple(names)
        self.table = StreamingParquet(path, observable_schema(self.names))
        self.cells = np.arange(n_cells, dtype=np.int64)
        self.times: list[float] = []
        self.mean: dict[str, list[float]] = {n: [] for n in self.names}

    def record(self, t: float, observables: Mapping[str, Tensor]) -> None:
        """Record the observables (each ``(n,)``) at time t (one device->host copy each)."""
        values = {n: observables[n].detach().to("cpu", torch.float32).numpy() for n in self.names}
        self.table.append(t=np.full(self.cells.shape[0], t), cell=self.cells, **values)
        self.times.append(t)
        for n, v in values.items():
            self.mean[n].append(float(v.mean()))


class DurationRecorder:
    """Completed phi segments (e.g. runs and tumbles) -> ``durations.parquet`` (``kind`` = the
    lump's name, ``duration`` in s, ``cell``, ``t_end``).

    Segment ends are buffered on the device for a block of steps and moved to the host in one
    transfer per block, so the loop does not synchronise every step.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        n_cells: int,
        dt: float,
        block_steps: int,
        device: torch.device,
        lump_names: tuple[str, str] = ("tumble", "run"),
    ) -> None:
        self.table = StreamingParquet(path, DURATION_SCHEMA)
        self.dt = dt
        self.lump_names = lump_names
        self.block_steps = max(1, block_steps)
        # steps of the segment that ended at this step (0 = nothing ended); sign = phi
        self._buffer = torch.zeros(self.block_steps, n_cells, dtype=torch.int32, device=device)
        self._block_start = 0
        self._filled = 0

    def record(self, step: int, ended_length: Tensor) -> None:
        """``ended_length`` (n,) int32: +k a phi=1 segment of k steps ended, -k phi=0, 0 none."""
        if self._filled == 0:
            self._block_start = step
        self._buffer[self._filled] = ended_length
        self._filled += 1
        if self._filled == self.block_steps:
            self.flush()

    def flush(self) -> None:
        """Move the buffered block to the host table."""
        if self._filled == 0:
            return
        block = self._buffer[: self._filled]
        rows, cells = torch.nonzero(block, as_tuple=True)
        values = block[rows, cells].cpu().numpy()
        rows_np, cells_np = rows.cpu().numpy(), cells.cpu().numpy()
        t_end = (self._block_start + rows_np + 1) * self.dt
        off, on = self.lump_names
        self.table.append(
            kind=np.where(values > 0, on, off).astype(object),
            duration=np.abs(values).astype(np.float64) * self.dt,
            cell=cells_np.astype(np.int64),
            t_end=t_end.astype(np.float64),
        )
        self._filled = 0

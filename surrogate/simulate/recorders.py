"""Streaming recorders: summaries leave the time loop in chunks, so memory stays flat in t_end.

Tables are streamed to a temporary Parquet file (one row group per ~1e6 rows) and renamed into
place only when the run completes, so a killed run never leaves a readable partial table.
"""

from __future__ import annotations

import os
import tempfile
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


DISTANCE_SCHEMA = pa.schema([("t", pa.float64()), ("cell", pa.int64()), ("distance", pa.float32())])
DURATION_SCHEMA = pa.schema(
    [
        ("kind", pa.string()),
        ("duration", pa.float64()),
        ("cell", pa.int64()),
        ("t_end", pa.float64()),
    ]
)


class DistanceRecorder:
    """Each cell's distance from the field's peak at record times -> ``distances.parquet``."""

    def __init__(self, path: str | os.PathLike, n_cells: int) -> None:
        self.table = StreamingParquet(path, DISTANCE_SCHEMA)
        self.cells = np.arange(n_cells, dtype=np.int64)
        self.times: list[float] = []
        self.mean: list[float] = []

    def record(self, t: float, distance: Tensor) -> None:
        """Record the distances (n,) at time t (one device->host copy per record time)."""
        d = distance.detach().to("cpu", torch.float32).numpy()
        self.table.append(t=np.full(d.shape[0], t), cell=self.cells, distance=d)
        self.times.append(t)
        self.mean.append(float(d.mean()))


class DurationRecorder:
    """Completed run and tumble durations -> ``durations.parquet``.

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
    ) -> None:
        self.table = StreamingParquet(path, DURATION_SCHEMA)
        self.dt = dt
        self.block_steps = max(1, block_steps)
        # steps of the segment that ended at this step (0 = nothing ended); sign = kind
        self._buffer = torch.zeros(self.block_steps, n_cells, dtype=torch.int32, device=device)
        self._block_start = 0
        self._filled = 0

    def record(self, step: int, ended_length: Tensor) -> None:
        """``ended_length`` (n,) int32: +k a run of k steps ended, -k a tumble, 0 nothing."""
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
        self.table.append(
            kind=np.where(values > 0, "run", "tumble").astype(object),
            duration=np.abs(values).astype(np.float64) * self.dt,
            cell=cells_np.astype(np.int64),
            t_end=t_end.astype(np.float64),
        )
        self._filled = 0

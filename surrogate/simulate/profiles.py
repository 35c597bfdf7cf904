"""Profiles along a channel's long axis (x) over time: what a run in a coupled grid field keeps
of its population and its field (issue 39), with memory bounded whatever the number of cells.

At every record time :class:`ProfileRecorder` keeps, on the grid field's own x cells,

* the **density**: how many of the run's cells have their x in each grid column (a histogram
  of the cells' x positions, whatever their y; computed on the device with one ``bincount``,
  so it costs one float64 copy of the positions, 8 n bytes, and keeps ``n_x + 2`` counts), and
* the **concentration** of every species averaged over y per grid column (mM: the mean over a
  column's cells, which all have the same volume, is the column's amount over its volume).

So what a run keeps is ``(n_x + 2) x (1 + S)`` numbers per record time: bins x record times,
the same for 100 cells as for 1e6.

``profiles.parquet`` (rows by ``t`` then ``bin``)
    ``t`` (s), ``bin`` (int32), ``x`` (the column's centre, mm), ``count`` (int64), then one
    float64 column ``c_<species>`` (mM) per species. Bins ``0 .. n_x - 1`` are the grid's
    columns ``[x_lo + bin h_x, x_lo + (bin + 1) h_x)``; bin ``-1`` counts the cells beyond the
    lower x end, bin ``n_x`` those at or beyond the upper one (bodies know no walls, so cells
    swim past a no-flux end; a periodic x axis wraps positions first, so those two stay 0).
    Those two rows have ``x`` and the concentrations NaN (no grid there): no cell is lost.
    Its Parquet metadata (key ``surrogate.recording``, JSON) holds the grid and the run:
    ``n_cells``, ``x_lo``, ``x_hi``, ``n_x``, ``h_x``, ``boundary_x``, ``species``, ``read``,
    ``cross_section`` (the channel's cross-section, ``(y_hi - y_lo) depth``, mm^2).

:func:`read_profiles` loads it as arrays (:class:`Profiles`);
:mod:`surrogate.evaluate.band` computes band position and speed from them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torch import Tensor

from surrogate.errors import ArtefactError
from surrogate.fields import Field
from surrogate.grid import GridField
from surrogate.simulate.recorders import (
    HistogramGrid,
    StreamingParquet,
    bin_counts,
    read_metadata,
    with_metadata,
)

__all__ = [
    "PROFILES",
    "ProfileRecorder",
    "Profiles",
    "profile_schema",
    "read_profiles",
    "species_column",
]

PROFILES = "profiles.parquet"


def species_column(name: str) -> str:
    """The column of species ``name``'s concentration in :data:`PROFILES`."""
    return f"c_{name}"


def profile_schema(species: Sequence[str]) -> pa.Schema:
    """Columns ``t``, ``bin``, ``x``, ``count`` and one float64 ``c_<species>`` per species."""
    return pa.schema(
        [("t", pa.float64()), ("bin", pa.int32()), ("x", pa.float64()), ("count", pa.int64()),
         *[(species_column(s), pa.float64()) for s in species]]
    )  # fmt: skip


class ProfileRecorder:
    """Density and concentration profiles along x of one run in a grid field (module docstring).

    Args:
        out_dir: the run directory (:data:`PROFILES` is written there, atomically, by
            :meth:`commit`).
        field: the run's grid field (its grid gives the bins; its state is read at each record).
        n_cells: the run's cells (for the metadata; each record counts the cells it is given).
    """

    def __init__(self, out_dir: str | os.PathLike, field: GridField, n_cells: int) -> None:
        grid = field.grid
        self.field = field
        self.n_cells = int(n_cells)
        self.n_x = grid.shape[0]
        h_x = grid.spacing[0]
        self.bins = HistogramGrid(grid.lower[0], h_x, self.n_x)
        self.periodic = grid.boundary[0] == "periodic"
        self.species = list(field.species_names)
        centres = grid.lower[0] + (np.arange(self.n_x, dtype=np.float64) + 0.5) * h_x
        self._x = np.concatenate([[np.nan], centres, [np.nan]])
        self._bin = np.arange(-1, self.n_x + 1, dtype=np.int32)
        self._nan = np.full(1, np.nan)
        self.times: list[float] = []
        self.facts: dict[str, Any] = {
            "n_cells": self.n_cells, "x_lo": grid.lower[0], "x_hi": grid.upper[0],
            "n_x": self.n_x, "h_x": h_x, "boundary_x": grid.boundary[0],
            "species": self.species, "read": field.read,
            "cross_section": (grid.upper[1] - grid.lower[1]) * grid.depth,
        }  # fmt: skip
        self._table = StreamingParquet(
            Path(out_dir) / PROFILES, with_metadata(profile_schema(self.species), self.facts)
        )

    @torch.inference_mode()  # the loop's tensors are inference tensors
    def record(self, t: float, position: Tensor) -> None:
        """Record the profiles at time ``t``: the field's state now and the cells' positions.

        Args:
            t: the record time (s).
            position: ``(n, 2)`` the run's cells' positions (mm), any float dtype and device.
        """
        x = position[:, 0].to(torch.float64)
        if self.periodic:
            x = self.bins.lo + torch.remainder(x - self.bins.lo, self.n_x * self.bins.width)
        counts = bin_counts(x, self.bins).cpu().numpy()
        # (S, n_x): a column's cells have one volume, so their mean is the column's mean
        mean = self.field.state.concentration.mean(-1).cpu().numpy()
        rows = self.n_x + 2
        columns = {
            species_column(s): np.concatenate([self._nan, mean[k], self._nan])
            for k, s in enumerate(self.species)
        }
        self._table.append(t=np.full(rows, float(t)), bin=self._bin, x=self._x,
                           count=counts.astype(np.int64), **columns)  # fmt: skip
        self.times.append(float(t))

    def commit(self) -> dict[str, Any]:
        """Write the table into place; facts for the manifest (the metadata's, ``n_records``,
        ``file`` and ``bytes``)."""
        path = self._table.commit()
        return {**self.facts, "n_records": len(self.times), "file": path.name,
                "bytes": int(path.stat().st_size)}  # fmt: skip

    def abort(self) -> None:
        """Drop the temporary file."""
        if self._table.tmp.exists():
            self._table.abort()

    @classmethod
    def of(cls, out_dir: str | os.PathLike, field: Field, n_cells: int) -> ProfileRecorder | None:
        """A recorder for a run in ``field`` when it is a grid field, else None (a given field
        has no profiles to keep)."""
        return cls(out_dir, field, n_cells) if isinstance(field, GridField) else None


@dataclass(frozen=True)
class Profiles:
    """A run's profiles as arrays (:func:`read_profiles`).

    Attributes:
        t: ``(T,)`` record times (s).
        edges: ``(n_x + 1,)`` the grid columns' edges along x (mm).
        counts: ``(T, n_x)`` int64, cells per column.
        below: ``(T,)`` int64, cells beyond the lower x end.
        above: ``(T,)`` int64, cells at or beyond the upper x end.
        concentration: species -> ``(T, n_x)`` float64, mM averaged over y.
        read: the species the cells read.
        n_cells: the run's cells.
        cross_section: the channel's cross-section (mm^2).
        boundary_x: the x axis's boundary condition.
    """

    t: np.ndarray
    edges: np.ndarray
    counts: np.ndarray
    below: np.ndarray
    above: np.ndarray
    concentration: Mapping[str, np.ndarray]
    read: str
    n_cells: int
    cross_section: float = math.nan
    boundary_x: str = "no_flux"

    @property
    def centres(self) -> np.ndarray:
        """``(n_x,)`` the columns' centres (mm)."""
        return 0.5 * (self.edges[1:] + self.edges[:-1])

    @property
    def width(self) -> float:
        """The columns' width h_x (mm)."""
        return float(self.edges[1] - self.edges[0])

    @property
    def density(self) -> np.ndarray:
        """``(T, n_x)`` the fraction of the run's cells per mm along x (``counts / (n_cells
        h_x)``): populations of different sizes on one scale."""
        return self.counts / (self.n_cells * self.width)

    def read_concentration(self) -> np.ndarray:
        """``(T, n_x)`` the read species' concentration (mM)."""
        return self.concentration[self.read]


def read_profiles(path: str | os.PathLike) -> Profiles:
    """The profiles of a run directory (or of a :data:`PROFILES` file).

    Raises:
        ArtefactError: no profiles there (the run was not in a grid field), or a table whose
            rows are not whole records.
    """
    path = Path(path)
    if path.is_dir():
        path = path / PROFILES
    if not path.exists():
        raise ArtefactError(f"no {PROFILES} at {path.parent}: only a run in a coupled grid "
                            f"field (e.g. field=channel_consumed) records profiles")  # fmt: skip
    facts = read_metadata(path)
    table = pq.read_table(path)
    n_x = int(facts["n_x"])
    rows = n_x + 2
    if table.num_rows % rows:
        raise ArtefactError(f"{path}: {table.num_rows} rows are not whole records of {rows}")
    n_t = table.num_rows // rows

    def grid_of(name: str) -> np.ndarray:
        return table.column(name).to_numpy().reshape(n_t, rows)

    counts = grid_of("count").astype(np.int64)
    edges = float(facts["x_lo"]) + float(facts["h_x"]) * np.arange(n_x + 1, dtype=np.float64)
    edges[-1] = float(facts["x_hi"])
    return Profiles(
        t=grid_of("t")[:, 0].astype(np.float64),
        edges=edges,
        counts=counts[:, 1:-1],
        below=counts[:, 0],
        above=counts[:, -1],
        concentration={
            s: grid_of(species_column(s))[:, 1:-1].astype(np.float64) for s in facts["species"]
        },
        read=str(facts["read"]),
        n_cells=int(facts["n_cells"]),
        cross_section=float(facts.get("cross_section", math.nan)),
        boundary_x=str(facts.get("boundary_x", "no_flux")),
    )

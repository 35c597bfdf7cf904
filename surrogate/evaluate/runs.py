"""A simulation run's artefacts as read for the comparisons (:class:`SimulationRun`,
:func:`load_run`): observables at record times (the recorded cells' values, or the moments and
histograms over all cells) and the property's segment durations (the lattice histogram, or the
table), with the small views the figures and reports read (:func:`observable_at`,
:func:`default_times`, :func:`mean_std_over_time`)."""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from surrogate.errors import ArtefactError
from surrogate.evaluate.ks import BinnedSample, Distribution, ExactSample
from surrogate.io import read_json, read_parquet
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
    read_metadata,
)

MADE_BY = "python scripts/simulate.py ..."


#: most values :meth:`SimulationRun.durations_of` expands a lattice histogram into
EXPAND_LIMIT = 20_000_000


# Relative tolerance when a run has a single record time (no interval to take half of).
_SINGLE_RECORD_RTOL = 1e-9


RUN_SOURCES: tuple[str, ...] = ("auto", "tables", "summaries")


@dataclass
class SimulationRun:
    """The artefacts of one simulation run directory.

    A run written by :class:`~surrogate.simulate.recorders.RunRecorder` has summaries over all
    cells (moments, histograms, the lattice histogram of durations) beside its tables; an older
    run has the complete tables only. Statistics use the most exact source a run has: the
    recorded cells' values when they are all cells, else the histograms; durations from the
    lattice histogram (exact), else the table.

    Attributes:
        observables: Long table ``t``, ``cell`` and one column per observable (e.g.
            ``distance``, mm from the field's peak): every cell, or the recorded subsample.
        durations: ``kind`` (the lump's name, e.g. "run"/"tumble"), ``duration`` (s), ``cell``,
            ``t_end``: every completed segment, or the recorded cells' (see
            ``recording["durations"]``); empty when the run kept none.
        manifest: The run's ``manifest.json`` (``wall_time_s``, ``seed``, ``config``, ...).
        path: The run directory.
        moments: ``observable_moments.parquet`` (``t``, ``observable``, ``n``, ``mean``,
            ``variance``, ``min``, ``max``, ``lo``, ``width``, ``n_bins``), or None.
        histograms: ``observable_histograms.parquet`` (``t``, ``observable``, ``bin``,
            ``count``), or None.
        duration_counts: ``duration_histogram.parquet`` (``kind``, ``steps``, ``duration``,
            ``count``), or None.
        recording: The recording facts of the summaries' metadata (``n_cells``,
            ``record_cells``, ``observable_cells``, ``durations``, ...), or empty.
        source: ``"auto"`` (the most exact source), ``"tables"`` (the tables only, as an older
            run; they must be complete) or ``"summaries"`` (histograms even where every cell's
            value is known).
    """

    observables: pd.DataFrame
    durations: pd.DataFrame
    manifest: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None
    moments: pd.DataFrame | None = None
    histograms: pd.DataFrame | None = None
    duration_counts: pd.DataFrame | None = None
    recording: dict[str, Any] = field(default_factory=dict)
    source: str = "auto"

    @property
    def observable_names(self) -> list[str]:
        """The observables recorded (the moments' order, else every column but ``t``, ``cell``)."""
        if self.moments is not None:
            return [str(n) for n in pd.unique(self.moments["observable"])]
        return [c for c in self.observables.columns if c not in ("t", "cell")]

    @property
    def lump_names(self) -> tuple[str, str]:
        """Names of phi = 0 and phi = 1 (the duration kinds), as the run recorded its model's.

        Raises:
            ArtefactError: The run records none (written before runs named their lumps).
        """
        names = self.manifest.get("lump_names") or self.recording.get("lump_names")
        if not names:
            raise ArtefactError(f"{self.path or 'the run'} does not name its lumps (the manifest's "
                                f"lump_names: phi = 0 and 1's names, recorded since runs name "
                                f"their model's); re-run `{MADE_BY}`")  # fmt: skip
        return (str(names[0]), str(names[1]))

    @property
    def record_times(self) -> np.ndarray:
        """The sorted distinct record times (s)."""
        table = self.moments if self.moments is not None else self.observables
        return np.unique(table["t"].to_numpy(dtype=np.float64))

    @property
    def t_end(self) -> float:
        """The last record time (s)."""
        return float(self.record_times[-1])

    @property
    def label(self) -> str:
        """A short name for messages: the directory name, or "run" when built in memory."""
        return self.path.name if self.path is not None else "run"

    def record_time(self, t: float) -> float:
        """The record time closest to ``t``.

        Raises:
            ValueError: No record lies within half a record interval of ``t``; the message
                names ``t`` and the recorded range.
        """
        times = self.record_times
        i = int(np.argmin(np.abs(times - t)))
        nearest = float(times[i])
        # Half the (median) record interval: a regular grid puts every t in range within it.
        tol = 0.5 * float(np.median(np.diff(times))) if times.size > 1 else _SINGLE_RECORD_RTOL
        if abs(nearest - t) > tol * (1 + 1e-9):
            raise ValueError(
                f"no record near t={t:g} s in {self.label}: records span "
                f"{times[0]:g}..{times[-1]:g} s ({times.size} record times); pass times within "
                f"that range"
            )
        return nearest

    def _moment(self, name: str, t: float) -> pd.Series:
        assert self.moments is not None
        m = self.moments
        rows = m[(m["observable"] == name) & (m["t"] == t)]
        if rows.empty:
            raise ArtefactError(f"{self.label} has no moments of {name!r} at t={t:g} s")
        return rows.iloc[0]

    def recorded_values(self, name: str, t: float) -> np.ndarray:
        """The recorded cells' values of observable ``name`` at record time ``t`` (float64)."""
        if name not in self.observables.columns:
            raise ValueError(f"{self.label} has no observable {name!r} (has "
                             f"{self.observable_names})")  # fmt: skip
        values = self.observables.loc[self.observables["t"] == t, name]
        return values.to_numpy(dtype=np.float64)

    def complete_at(self, name: str, t: float) -> bool:
        """Whether the recorded values at record time ``t`` are every cell's."""
        if self.moments is None:
            return True
        return int(self._moment(name, t)["n"]) == int((self.observables["t"] == t).sum())

    def observable_distribution(self, name: str, t: float) -> Distribution:
        """Observable ``name`` over all cells at the record time closest to ``t``: the exact
        values when every cell's is recorded (and ``source`` is not "summaries"), else the
        histogram over all cells."""
        t = self.record_time(t)
        if self.source != "summaries" and self.complete_at(name, t):
            return ExactSample(self.recorded_values(name, t))
        if self.histograms is None or self.moments is None:
            raise ArtefactError(
                f"{self.label} recorded {name!r} for only some cells and has no histograms; "
                f"re-run `{MADE_BY}`"
            )
        m = self._moment(name, t)
        n_bins = int(m["n_bins"])
        counts = np.zeros(n_bins + 2, dtype=np.int64)
        rows = self._histogram_rows.get((name, t))
        if rows is not None:
            h = self.histograms
            counts[h["bin"].to_numpy()[rows] + 1] = h["count"].to_numpy()[rows]
        edges = float(m["lo"]) + float(m["width"]) * np.arange(n_bins + 1, dtype=np.float64)
        if int(counts.sum()) != int(m["n"]):
            raise ArtefactError(
                f"{self.label}: histogram of {name!r} at t={t:g} s counts {counts.sum()} values "
                f"but its moments say {int(m['n'])}"
            )
        return BinnedSample(edges, counts, float(m["min"]), float(m["max"]))

    @functools.cached_property
    def _histogram_rows(self) -> dict[tuple[str, float], np.ndarray]:
        if self.histograms is None or self.histograms.empty:
            return {}
        groups = self.histograms.groupby(["observable", "t"], sort=False).indices
        return {(str(k[0]), float(k[1])): v for k, v in groups.items()}

    def duration_distribution(self, kind: str) -> ExactSample:
        """Every completed segment duration of ``kind`` (a lump name): the lattice histogram's
        counts when the run has one (and ``source`` is not "tables"), else the table's column
        (in the table's order)."""
        if kind not in self.lump_names:
            raise ValueError(f"duration kind must be one of {self.lump_names}, got {kind!r}")
        if self.duration_counts is not None:
            d = self.duration_counts
            mask = d["kind"].astype(str) == kind
            return ExactSample.from_counts(d.loc[mask, "duration"], d.loc[mask, "count"])
        mask = self.durations["kind"].astype(str) == kind
        return ExactSample(self.durations.loc[mask, "duration"].to_numpy(dtype=np.float64))

    def durations_of(self, kind: str) -> np.ndarray:
        """All completed segment durations of ``kind`` (a lump name, e.g. "run"), expanded from
        the lattice histogram when the run has one (at most :data:`EXPAND_LIMIT` values; use
        :meth:`duration_distribution` or :meth:`mean_duration` for more)."""
        dist = self.duration_distribution(kind)
        if dist.counts is not None and dist.n > EXPAND_LIMIT:
            raise ValueError(
                f"{self.label} has {dist.n} {kind} durations, more than {EXPAND_LIMIT} to expand; "
                f"use duration_distribution({kind!r}) (values and counts) instead"
            )
        return dist.expand()

    def mean_duration(self, kind: str) -> float | None:
        """The mean completed segment duration of ``kind`` (s), None when there is none."""
        dist = self.duration_distribution(kind)
        return dist.mean() if dist.n else None

    def mean_duration_se(self, kind: str) -> float | None:
        """The standard error (s) of :meth:`mean_duration`, each cell one cluster: a cell's
        segments share its parameters (E. coli: cv 0.1 per cell) and its history, so they
        are not independent draws (at 100 cells the cluster-robust error is ~1.5 % of the
        mean, two full runs' means ~6 % apart). From the recorded cells' segments ``i``
        (``S_i`` their total duration, ``N_i`` their count, ``m`` their mean):
        ``sqrt(sum_i (S_i - m N_i)^2) / sum_i N_i``, times ``sqrt(recorded / n_cells)`` when
        only some of the run's cells are recorded. None with fewer than two recorded cells."""
        d = self.durations
        if d.empty or "cell" not in d:
            return None
        recorded = int(d["cell"].nunique())
        cells = d.loc[d["kind"].astype(str) == kind].groupby("cell")["duration"]
        sums = cells.sum().to_numpy(np.float64)
        counts = cells.count().to_numpy(np.float64)
        if recorded < 2 or counts.sum() == 0:
            return None
        mean = sums.sum() / counts.sum()
        se = math.sqrt(float(((sums - mean * counts) ** 2).sum())) / counts.sum()
        n_cells = int(self.manifest.get("n_cells") or recorded)
        return se * math.sqrt(min(1.0, recorded / n_cells))


def load_run(directory: str | os.PathLike, source: str = "auto") -> SimulationRun:
    """Read a run directory: ``observables.parquet``, ``manifest.json``, and the summaries when
    it has them (``observable_moments.parquet``, ``observable_histograms.parquet``,
    ``duration_histogram.parquet``; :mod:`surrogate.simulate.recorders`) or else
    ``durations.parquet`` (which is read whenever present).

    Args:
        directory: The run directory.
        source: See :class:`SimulationRun`; ``"tables"`` reads a new run as an old one and
            refuses it unless its tables are complete (every cell and every duration).

    Raises:
        MissingArtefactError: A file is missing (the message says which command makes it).
        ArtefactError: A file is corrupt or lacks the expected columns.
        ValueError: ``source="tables"`` on a run whose tables are a subsample, or
            ``"summaries"`` on a run without summaries.
    """
    if source not in RUN_SOURCES:
        raise ValueError(f"source must be one of {RUN_SOURCES}, got {source!r}")
    path = Path(directory)
    observables = read_parquet(path / OBSERVABLES, made_by=MADE_BY)
    _require_columns(observables, ("t", "cell"), path / OBSERVABLES)
    moments = _optional(path / MOMENTS, MOMENTS_SCHEMA.names)
    histograms = _optional(path / HISTOGRAMS, HISTOGRAM_SCHEMA.names)
    duration_counts = _optional(path / DURATION_HISTOGRAM, DURATION_HISTOGRAM_SCHEMA.names)
    if duration_counts is None or (path / DURATIONS).exists():
        durations = read_parquet(path / DURATIONS, made_by=MADE_BY)
        _require_columns(durations, ("kind", "duration"), path / DURATIONS)
    else:
        durations = pd.DataFrame({n: pd.Series(dtype=t.to_pandas_dtype()) for n, t in
                                  zip(DURATION_SCHEMA.names, DURATION_SCHEMA.types, strict=True)})  # fmt: skip
    manifest = read_json(path / "manifest.json", made_by=MADE_BY)
    if observables.empty or observables.shape[1] < 3:
        raise ArtefactError(f"{path / OBSERVABLES} has no observations; re-run `{MADE_BY}`")
    recording: dict[str, Any] = {}
    for name in (MOMENTS, DURATION_HISTOGRAM):
        if (path / name).exists():
            recording.update(read_metadata(path / name))
    if source == "tables" and moments is not None:
        # the recorded cells' durations are all durations when the recorded cells are all cells
        if int(recording.get("observable_cells", 0)) < int(recording.get("n_cells", 0)):
            raise ValueError(
                f"{path} recorded {recording.get('observable_cells')} of "
                f"{recording.get('n_cells')} cells: its tables are a subsample; use "
                f"source='auto'"
            )
        moments = histograms = duration_counts = None
    if source == "summaries" and (moments is None or histograms is None):
        raise ValueError(f"{path} has no summaries ({MOMENTS}, {HISTOGRAMS}); use source='auto'")
    return SimulationRun(observables=observables, durations=durations, manifest=manifest,
                         path=path, moments=moments, histograms=histograms,
                         duration_counts=duration_counts, recording=recording, source=source)  # fmt: skip


def _optional(path: Path, columns: Sequence[str]) -> pd.DataFrame | None:
    if not path.exists():
        return None
    table = read_parquet(path, made_by=MADE_BY)
    _require_columns(table, columns, path)
    return table


def _require_columns(df: pd.DataFrame, columns: Sequence[str], where: Path) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ArtefactError(
            f"{where} lacks column(s) {missing} (has {list(df.columns)}); re-create it with "
            f"`{MADE_BY}`"
        )


def observable_at(run: SimulationRun, name: str, t: float) -> np.ndarray:
    """The recorded cells' values of observable ``name`` at the record time closest to ``t``
    (every cell's, unless the run recorded a subsample; see
    :meth:`SimulationRun.observable_distribution` for all cells).

    Raises:
        ValueError: No record lies within half a record interval of ``t``; the message names
            ``t`` and the recorded range.
    """
    return run.recorded_values(name, run.record_time(t))


def distances_at(run: SimulationRun, t: float) -> np.ndarray:
    """The cells' distances from the peak at the record time closest to ``t`` (E. coli)."""
    return observable_at(run, "distance", t)


def default_times(run: SimulationRun, n: int = 4) -> tuple[float, ...]:
    """``n`` evenly spaced times ending at ``t_end``: the paper's 125/250/375/500 s for 500 s.

    Useful for scaled-down runs, whose ``t_end`` is below the paper's 500 s.
    """
    return tuple(run.t_end * (k + 1) / n for k in range(n))


def mean_std_over_time(run: SimulationRun, name: str | None = None) -> pd.DataFrame:
    """Per record time: the mean, sample standard deviation (ddof=1) and count of observable
    ``name`` (default: the first one), over all cells (from the moments when the run has them).

    Columns ``t``, ``mean``, ``std``, ``n``; ``std`` is NaN where only one cell is recorded.
    """
    name = name or run.observable_names[0]
    if run.moments is not None:
        m = run.moments[run.moments["observable"] == name].sort_values("t")
        if m.empty:
            raise ValueError(f"{run.label} has no observable {name!r} (has "
                             f"{run.observable_names})")  # fmt: skip
        return pd.DataFrame(
            {
                "t": m["t"].to_numpy(np.float64),
                "mean": m["mean"].to_numpy(np.float64),
                "std": np.sqrt(m["variance"].to_numpy(np.float64)),
                "n": m["n"].to_numpy(np.int64).astype(int),
            }
        )
    d = run.observables.assign(**{name: run.observables[name].astype(np.float64)})
    out = d.groupby("t", sort=True)[name].agg(["mean", "std", "count"]).reset_index()
    return out.rename(columns={"count": "n"}).astype({"t": float, "n": int})


__all__ = [
    "EXPAND_LIMIT",
    "RUN_SOURCES",
    "SimulationRun",
    "default_times",
    "distances_at",
    "load_run",
    "mean_std_over_time",
    "observable_at",
]

"""Two-sample comparisons of full and abstracted simulation runs (the paper's Table 1).

The paper compares the two models with the two-sample Kolmogorov-Smirnov (KS) statistic on

* the body's observables at a few record times (for E. coli the cells' distance from the
  field's peak; one value per cell, so 100 values per model for a 100-cell population), and
* the durations of the property's segments (the lumps the run names; E. coli: run and
  tumble) pooled over the whole trajectory (~60,000 values per model), of which a random 1,000
  are drawn from each model before the test, because with tens of thousands of values any
  approximation error, however small, gives a vanishing p-value.

Besides the KS statistic and its p-value we report the 1-Wasserstein distance (in the data's
units, so it says *how far* apart the distributions are, not only whether they differ) and the
asymptotic 5 % critical value of the KS statistic for the sample sizes used.

A KS distance alone does not say whether the abstraction is good: two full-model runs with
different seeds also differ. ``noise_floor_table`` measures that run-to-run difference and
``combine_with_noise_floor`` judges the abstraction against it.
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from scipy import stats

from surrogate.errors import ArtefactError, NumericalError
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

#: c(alpha) of the asymptotic two-sample KS critical value at alpha = 0.05,
#: sqrt(-ln(alpha / 2) / 2) = 1.358.
KS_C_ALPHA_05 = 1.358

#: The paper's record times for the distance distributions (s).
PAPER_TIMES: tuple[float, ...] = (125.0, 250.0, 375.0, 500.0)

#: Durations subsample size used by the paper.
PAPER_SUBSAMPLE = 1000

MADE_BY = "python scripts/simulate.py ..."

COLUMNS: tuple[str, ...] = (
    "quantity",
    "ks",
    "ks_pvalue",
    "wasserstein",
    "n_reference",
    "n_candidate",
    "ks_critical_05",
    "ks_full",
    "ks_pvalue_full",
)

#: sample size up to which ``ks_2samp`` computes the exact p-value (its ``method="auto"``)
_SCIPY_EXACT_N = 10_000


#: most values :meth:`SimulationRun.durations_of` expands a lattice histogram into
EXPAND_LIMIT = 20_000_000


# Relative tolerance when a run has a single record time (no interval to take half of).
_SINGLE_RECORD_RTOL = 1e-9


# ----------------------------------------------------------------------------------------------
# two-sample statistics


def ks_critical_value(n_a: int, n_b: int, c_alpha: float = KS_C_ALPHA_05) -> float:
    """Asymptotic two-sample KS critical value ``c(alpha) * sqrt((n_a + n_b) / (n_a * n_b))``."""
    if n_a <= 0 or n_b <= 0:
        raise ValueError(f"KS critical value needs positive sample sizes, got {n_a} and {n_b}")
    return c_alpha * math.sqrt((n_a + n_b) / (n_a * n_b))


def ks_c_alpha(alpha: float) -> float:
    """c(alpha) of :func:`ks_critical_value`: ``sqrt(-ln(alpha / 2) / 2)``, the leading term of
    Kolmogorov's limit law (``scipy.stats.kstwobign.isf(alpha)`` within 3e-6 relative for
    alpha <= 0.05, 2e-5 at 0.1): 1.358 at 0.05, 1.628 at 0.01."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    return math.sqrt(-math.log(alpha / 2.0) / 2.0)


def noise_threshold(
    floor: ArrayLike, critical: ArrayLike, factor: float = 1.0, cap: float = math.inf
) -> np.ndarray:
    """The rule a candidate's distance from the full model is judged by, everywhere: it is
    within the noise when it is at most ``min(max(factor x floor, critical), cap)``.

    ``floor`` is the same distance between two full runs with different seeds (what sampling
    alone gives), ``critical`` the smallest distance the test can tell from none (the KS
    critical value at the sample sizes; a resolution for a position), so a floor that happens
    to be tiny does not make the rule stricter than the test can see. A NaN floor (no second
    full run) leaves ``critical`` alone.

    Args:
        floor: the full-vs-full distances, any shape.
        critical: the critical values, broadcast against ``floor``.
        factor: how far above the floor a candidate may be (the fidelity stage's ``ks_factor``).
        cap: an absolute upper limit (the fidelity stage's ``ks_max``).

    Returns:
        The thresholds, ``floor`` and ``critical`` broadcast.
    """
    scaled = float(factor) * np.asarray(floor, dtype=np.float64)
    return np.minimum(np.fmax(scaled, np.asarray(critical, dtype=np.float64)), float(cap))


def compare_samples(
    a: ArrayLike,
    b: ArrayLike,
    subsample: int | None = None,
    rng: np.random.Generator | None = None,
    *,
    name: str = "sample",
) -> dict[str, float | int]:
    """Compare two 1-D samples with the two-sample KS test and the Wasserstein distance.

    Args:
        a: First sample (any shape; flattened).
        b: Second sample.
        subsample: If given, draw ``min(subsample, n)`` values WITHOUT replacement from each
            sample before comparing (the paper draws 1,000 run/tumble durations).
        rng: Generator for the subsample; a fresh ``default_rng(0)`` when omitted, so the
            result is reproducible either way.
        name: What the samples are, used in error messages.

    Returns:
        ``ks``, ``ks_pvalue`` (``scipy.stats.ks_2samp``), ``wasserstein``
        (``scipy.stats.wasserstein_distance``), ``n_a``, ``n_b`` (sizes actually used) and
        ``ks_critical_05`` (asymptotic critical value of ``ks`` at alpha = 0.05 for those sizes).

    Raises:
        ValueError: A sample is empty or ``subsample`` is not positive.
        NumericalError: A sample contains NaN or infinite values.
    """
    x = _as_sample(a, f"{name} (first sample)")
    y = _as_sample(b, f"{name} (second sample)")
    if subsample is not None:
        if subsample <= 0:
            raise ValueError(f"subsample for {name} must be positive, got {subsample}")
        rng = np.random.default_rng(0) if rng is None else rng
        x = _subsample(x, subsample, rng)
        y = _subsample(y, subsample, rng)
    result = stats.ks_2samp(x, y)
    return {
        "ks": float(result.statistic),
        "ks_pvalue": float(result.pvalue),
        "wasserstein": float(stats.wasserstein_distance(x, y)),
        "n_a": int(x.size),
        "n_b": int(y.size),
        "ks_critical_05": ks_critical_value(x.size, y.size),
    }


def _as_sample(values: ArrayLike, what: str) -> np.ndarray:
    # float64: distances are stored as float32 and scipy's statistics should not run in float32
    arr = np.asarray(values, dtype=np.float64).ravel()
    if arr.size == 0:
        raise ValueError(f"{what} is empty: nothing to compare")
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise NumericalError(f"{what} has {bad} NaN or infinite value(s) out of {arr.size}")
    return arr


def _subsample(arr: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    if arr.size <= size:
        return arr
    return rng.choice(arr, size=size, replace=False)


# ----------------------------------------------------------------------------------------------
# empirical distributions: every value, or counts on a grid


@dataclass(frozen=True, eq=False)
class ExactSample:
    """Every value of a sample: ``values`` ``(k,)`` with multiplicities ``counts`` ``(k,)`` int64
    (a lattice histogram: distinct values, sorted), or ``counts=None`` (a raw sample: each value
    once, in the order recorded, e.g. a table's column)."""

    values: np.ndarray
    counts: np.ndarray | None = None

    @classmethod
    def from_counts(cls, values: ArrayLike, counts: ArrayLike) -> ExactSample:
        """Distinct ``values`` with their ``counts`` (sorted; zero counts dropped)."""
        v, c = np.asarray(values, dtype=np.float64), np.asarray(counts, dtype=np.int64)
        order = np.argsort(v, kind="stable")
        v, c = v[order], c[order]
        keep = c > 0
        return cls(v[keep], c[keep])

    @property
    def n(self) -> int:
        """Sample size."""
        return int(self.values.size if self.counts is None else self.counts.sum())

    @functools.cached_property
    def _sorted(self) -> tuple[np.ndarray, np.ndarray]:
        if self.counts is not None:
            return self.values, np.concatenate([[0], np.cumsum(self.counts)])
        v = np.sort(np.asarray(self.values, dtype=np.float64))
        return v, np.arange(v.size + 1, dtype=np.int64)

    def below(self, x: ArrayLike) -> np.ndarray:
        """How many values are ``< x`` (int64, the shape of ``x``)."""
        v, cum = self._sorted
        return cum[np.searchsorted(v, np.asarray(x, dtype=np.float64), side="left")]

    def at_most(self, x: ArrayLike) -> np.ndarray:
        """How many values are ``<= x``."""
        v, cum = self._sorted
        return cum[np.searchsorted(v, np.asarray(x, dtype=np.float64), side="right")]

    def expand(self) -> np.ndarray:
        """Every value (float64): the raw order, or sorted for a lattice histogram."""
        values = np.asarray(self.values, dtype=np.float64)
        return values if self.counts is None else np.repeat(values, self.counts)

    def draw(self, size: int, rng: np.random.Generator) -> np.ndarray:
        """``size`` values drawn without replacement: positions ``rng.choice(n, size,
        replace=False)`` in the raw order (so a raw sample gives exactly
        ``rng.choice(values, size, replace=False)``) or in sorted order (a lattice histogram);
        every value, without touching ``rng``, when ``n <= size``."""
        if self.n <= size:
            return self.expand()
        positions = rng.choice(self.n, size=size, replace=False)
        if self.counts is None:
            return np.asarray(self.values, dtype=np.float64)[positions]
        v, cum = self._sorted
        return v[np.searchsorted(cum, positions, side="right") - 1]

    def mean(self) -> float:
        """The sample mean."""
        if self.counts is None:
            return float(np.mean(np.asarray(self.values, dtype=np.float64)))
        return float(np.dot(self.values, self.counts) / self.counts.sum())


@dataclass(frozen=True, eq=False)
class BinnedSample:
    """A sample known by its counts on a grid: ``edges`` ``(n_bins + 1,)``, ``counts``
    ``(n_bins + 2,)`` int64 = [values below ``edges[0]``, bin 0, ..., bin n_bins - 1, values at or
    above ``edges[-1]``] (bin i is ``[edges[i], edges[i + 1])``), and the sample's extremes
    ``vmin``/``vmax`` (which bound the two outer bins)."""

    edges: np.ndarray
    counts: np.ndarray
    vmin: float
    vmax: float

    @property
    def n(self) -> int:
        """Sample size (outer bins included)."""
        return int(self.counts.sum())

    def below_edges(self) -> np.ndarray:
        """How many values are ``< edges[i]``, for every edge (int64 ``(n_bins + 1,)``)."""
        return np.cumsum(self.counts)[:-1]

    def below(self, points: ArrayLike) -> np.ndarray:
        """How many values are ``< x`` for each of ``points``: exact at the grid's edges
        (matched to 1e-9 relative); elsewhere the count below the edge under the point, a lower
        bound."""
        x = np.asarray(points, dtype=np.float64)
        e = self.edges
        idx = np.clip(np.searchsorted(e, x), 0, e.size - 1)
        near = np.abs(e[idx] - x) <= 1e-9 * max(1.0, float(np.abs(e).max()))
        idx = np.where(near | (x >= e[idx]), idx, np.clip(idx - 1, 0, e.size - 1))
        below = self.below_edges()[idx]
        below = np.where(x < e[0] - 1e-9 * max(1.0, abs(float(e[0]))), 0, below)
        return np.where(x > e[-1] + 1e-9 * max(1.0, abs(float(e[-1]))), self.n, below)

    def points(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Representative points for the Wasserstein distance: the centre of every non-empty
        bin (the outer bins' between the extreme and the grid) with its count, and how far the
        sample's values lie from them on average (the representation's W1 error bound)."""
        e = self.edges
        lo_out = min(self.vmin, e[0])
        hi_out = max(self.vmax, e[-1])
        left = np.concatenate([[lo_out], e])
        right = np.concatenate([e, [hi_out]])
        keep = self.counts > 0
        centre = 0.5 * (left + right)[keep]
        weight = self.counts[keep].astype(np.float64)
        error = float(np.dot(weight, 0.5 * (right - left)[keep]) / weight.sum())
        return centre, weight, error


Distribution = ExactSample | BinnedSample


def ks_pvalue_asymptotic(d: float, n_a: int, n_b: int) -> float:
    """The two-sided KS p-value of ``scipy.stats.ks_2samp``'s asymptotic method:
    ``kstwo.sf(d, round(n_a n_b / (n_a + n_b)))`` (what scipy uses above 10,000 values)."""
    m, n = sorted([float(n_a), float(n_b)], reverse=True)
    en = m * n / (m + n)
    return float(np.clip(stats.kstwo.sf(d, np.round(en)), 0.0, 1.0))


def compare_distributions(
    a: Distribution,
    b: Distribution,
    subsample: int | None = None,
    rng: np.random.Generator | None = None,
    *,
    name: str = "sample",
) -> dict[str, float | int]:
    """:func:`compare_samples` for exact samples and binned summaries alike.

    * Both raw samples: exactly :func:`compare_samples`.
    * Exact samples with counts (lattice histograms): the same KS statistic, computed from the
      counts (``ks_2samp``'s own value: identical ECDFs); its p-value as ``ks_2samp`` gives it
      (the exact method on the expanded values up to 10,000 values per sample, else
      :func:`ks_pvalue_asymptotic`); Wasserstein from the weighted values.
    * ``subsample``: ``min(subsample, n)`` values drawn from each (``a`` first) with
      :meth:`ExactSample.draw`, then compared as raw samples (exact samples only).
    * Either binned: the ECDFs are compared where both are known exactly, at the grid's edges
      (both grids' common edges). ``ks`` is the largest difference there, the KS distance of
      the two samples with every value moved down to its bin's lower edge, a lower bound of the
      exact KS; ``ks_error`` bounds its shortfall: in each interval between known points the
      ECDFs move by at most that interval's mass, so exact KS <= max over intervals of
      ``max(F(right) - G(left), G(right) - F(left))``. Wasserstein from bin centres (the outer
      bins' between the extremes and the grid), ``wasserstein_error`` = the mean distance of
      the values from their centres (half a bin width inside the grid), summed over the binned
      samples, bounds ``|wasserstein - exact|``. The p-value is :func:`ks_pvalue_asymptotic`.

    Returns:
        :func:`compare_samples`' keys plus ``ks_error`` and ``wasserstein_error`` (0 when both
        are exact).
    """
    for dist, which in ((a, "first"), (b, "second")):
        if dist.n == 0:
            raise ValueError(f"{name} ({which} sample) is empty: nothing to compare")
    exact = {"ks_error": 0.0, "wasserstein_error": 0.0}
    if subsample is not None:
        if subsample <= 0:
            raise ValueError(f"subsample for {name} must be positive, got {subsample}")
        if not (isinstance(a, ExactSample) and isinstance(b, ExactSample)):
            raise ValueError(f"{name}: a binned summary cannot be subsampled value by value")
        rng = np.random.default_rng(0) if rng is None else rng
        x, y = a.draw(subsample, rng), b.draw(subsample, rng)
        return {**compare_samples(x, y, name=name), **exact}
    if isinstance(a, ExactSample) and isinstance(b, ExactSample):
        if a.counts is None and b.counts is None:
            return {**compare_samples(a.values, b.values, name=name), **exact}
        if max(a.n, b.n) <= _SCIPY_EXACT_N:
            return {**compare_samples(a.expand(), b.expand(), name=name), **exact}
        return {**_compare_weighted(a, b, name), **exact}
    return _compare_binned(a, b, name)


def _compare_weighted(a: ExactSample, b: ExactSample, name: str) -> dict[str, float | int]:
    ua, ub = (
        _as_sample(d.values, f"{name} ({w} sample)") for d, w in ((a, "first"), (b, "second"))
    )
    wa = np.ones(ua.size) if a.counts is None else a.counts.astype(np.float64)
    wb = np.ones(ub.size) if b.counts is None else b.counts.astype(np.float64)
    grid = np.union1d(ua, ub)
    diff = a.at_most(grid) / a.n - b.at_most(grid) / b.n  # ks_2samp's ECDFs at every value
    d = float(max(np.clip(-diff.min(), 0, 1), diff.max()))
    return {
        "ks": d,
        "ks_pvalue": ks_pvalue_asymptotic(d, a.n, b.n),
        "wasserstein": float(stats.wasserstein_distance(ua, ub, wa, wb)),
        "n_a": a.n,
        "n_b": b.n,
        "ks_critical_05": ks_critical_value(a.n, b.n),
    }


def _known_points(a: Distribution, b: Distribution) -> np.ndarray:
    """The points where both ECDFs are known: a binned sample's edges (both grids' common
    edges, matched to 1e-9 relative)."""
    grids = [d.edges for d in (a, b) if isinstance(d, BinnedSample)]
    edges = grids[0]
    if len(grids) == 2 and not np.array_equal(grids[0], grids[1]):
        other = grids[1]
        j = np.clip(np.searchsorted(other, edges), 1, other.size - 1)
        nearest = np.minimum(np.abs(other[j] - edges), np.abs(other[j - 1] - edges))
        tol = 1e-9 * max(1.0, float(np.abs(edges).max()), float(np.abs(other).max()))
        edges = edges[nearest <= tol]
    return edges


def _compare_binned(a: Distribution, b: Distribution, name: str) -> dict[str, float | int]:
    points = _known_points(a, b)
    f = np.concatenate([[0.0], a.below(points) / a.n, [1.0]])
    g = np.concatenate([[0.0], b.below(points) / b.n, [1.0]])
    ks = float(np.abs(f - g).max())
    upper = float(max((f[1:] - g[:-1]).max(), (g[1:] - f[:-1]).max()))
    pos, wts, errs = [], [], []
    for d, which in ((a, "first"), (b, "second")):
        if isinstance(d, ExactSample):
            pos.append(_as_sample(d.values, f"{name} ({which} sample)"))
            wts.append(None if d.counts is None else d.counts.astype(np.float64))
            errs.append(0.0)
        else:
            if not (math.isfinite(d.vmin) and math.isfinite(d.vmax)):
                raise NumericalError(f"{name} ({which} sample) has NaN or infinite values")
            centre, weight, error = d.points()
            pos.append(centre)
            wts.append(weight)
            errs.append(error)
    return {
        "ks": ks,
        "ks_pvalue": ks_pvalue_asymptotic(ks, a.n, b.n),
        "wasserstein": float(stats.wasserstein_distance(pos[0], pos[1], wts[0], wts[1])),
        "n_a": a.n,
        "n_b": b.n,
        "ks_critical_05": ks_critical_value(a.n, b.n),
        "ks_error": max(upper - ks, 0.0),
        "wasserstein_error": float(sum(errs)),
    }


# ----------------------------------------------------------------------------------------------
# simulation runs

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


def observable_quantity(name: str, t: float) -> str:
    """The ``quantity`` label of an observable's row at time ``t``, e.g. ``distance_t125``."""
    return f"{name}_t{t:g}"


#: extra columns of ``comparison_table(..., errors=True)``
ERROR_COLUMNS: tuple[str, ...] = ("ks_binning_error", "wasserstein_binning_error")


def comparison_table(
    reference: SimulationRun,
    candidate: SimulationRun,
    times: Sequence[float] = PAPER_TIMES,
    subsample: int | None = PAPER_SUBSAMPLE,
    seed: int = 0,
    errors: bool = False,
) -> pd.DataFrame:
    """One row per quantity comparing ``candidate`` against ``reference`` (the paper's Table 1).

    Rows: ``<observable>_t<t>`` for each observable and each of ``times`` (all cells, no
    subsampling: every cell's value when the runs recorded them all, else the histograms, see
    :func:`compare_distributions`), then one per lump, phi = 1 first (``run``, ``tumble``:
    ``subsample`` durations drawn without replacement from each run, from a generator seeded
    with ``seed``, reference then candidate; from a lattice histogram the draw is of positions
    in sorted order, from a table of positions in the table's order). Columns: see
    ``COLUMNS``; ``n_reference``/``n_candidate`` are the sizes actually compared, and the
    duration rows also carry the full-sample ``ks_full``/``ks_pvalue_full`` (NaN on
    observable rows), exact from the lattice histograms. ``errors=True`` appends
    :data:`ERROR_COLUMNS`: bounds on ``|ks - exact KS|`` and ``|wasserstein - exact|`` of
    histogram-based rows (0 where every value is known).

    The caller chooses ``times``: runs shorter than the paper's 500 s need times within their
    record range (``default_times`` gives the paper's quarters of ``t_end``); a time outside it
    raises ``ValueError``.

    Between two full-model runs with different seeds the same table is the noise floor; see
    ``noise_floor_table``.
    """
    rng = np.random.default_rng(seed)
    rows: list[dict[str, Any]] = []
    for name in reference.observable_names:
        for t in times:
            quantity = observable_quantity(name, t)
            res = compare_distributions(
                reference.observable_distribution(name, t),
                candidate.observable_distribution(name, t),
                name=quantity,
            )
            rows.append(_row(quantity, res, full=None))
    for kind in reversed(reference.lump_names):
        ref = _durations(reference, kind, "reference")
        cand = _durations(candidate, kind, "candidate")
        full = compare_distributions(ref, cand, name=f"{kind} durations")
        sub = compare_distributions(
            ref, cand, subsample=subsample, rng=rng, name=f"{kind} durations"
        )
        rows.append(_row(kind, sub, full=full))
    columns = [*COLUMNS, *ERROR_COLUMNS] if errors else list(COLUMNS)
    return pd.DataFrame(rows, columns=columns)


def _durations(run: SimulationRun, kind: str, role: str) -> ExactSample:
    values = run.duration_distribution(kind)
    if values.n == 0:
        raise ValueError(
            f"{kind} durations of the {role} run {run.label} are empty: no completed {kind} "
            f"segment was recorded (run longer or with more cells)"
        )
    return values


def _row(quantity: str, res: dict[str, Any], full: dict[str, Any] | None) -> dict[str, Any]:
    return {
        "quantity": quantity,
        "ks": res["ks"],
        "ks_pvalue": res["ks_pvalue"],
        "wasserstein": res["wasserstein"],
        "n_reference": res["n_a"],
        "n_candidate": res["n_b"],
        "ks_critical_05": res["ks_critical_05"],
        "ks_full": np.nan if full is None else full["ks"],
        "ks_pvalue_full": np.nan if full is None else full["ks_pvalue"],
        "ks_binning_error": res.get("ks_error", 0.0),
        "wasserstein_binning_error": res.get("wasserstein_error", 0.0),
    }


def noise_floor_table(
    full_a: SimulationRun,
    full_b: SimulationRun,
    times: Sequence[float] = PAPER_TIMES,
    subsample: int | None = PAPER_SUBSAMPLE,
    seed: int = 0,
    errors: bool = False,
) -> pd.DataFrame:
    """``comparison_table`` between two FULL-model runs that differ only in their seed.

    Its KS distances are what sampling noise alone produces at these sample sizes, i.e. the
    best an abstraction can be expected to do. Warns when both manifests name the same seed,
    since identical runs give a floor of zero.
    """
    seed_a, seed_b = full_a.manifest.get("seed"), full_b.manifest.get("seed")
    if seed_a is not None and seed_a == seed_b:
        warnings.warn(
            f"noise floor from two runs with the same seed {seed_a} ({full_a.label}, "
            f"{full_b.label}): the floor will be ~0; use runs with different seeds",
            stacklevel=2,
        )
    return comparison_table(full_a, full_b, times=times, subsample=subsample, seed=seed,
                            errors=errors)  # fmt: skip


def combine_with_noise_floor(table: pd.DataFrame, floor_table: pd.DataFrame) -> pd.DataFrame:
    """Add ``ks_noise_floor``, ``wasserstein_noise_floor`` and ``within_noise`` to ``table``.

    Rows are matched on ``quantity``. Rule: a quantity is ``within_noise`` when its KS distance
    is no larger than ``max(noise-floor KS, ks_critical_05)``, i.e. the abstraction differs from
    the full model by no more than a second full run does, or by no more than a 5 % KS test
    can detect at these sample sizes. A quantity missing from ``floor_table`` gets NaN floors
    and is judged against ``ks_critical_05`` alone.
    """
    floor = floor_table.loc[:, ["quantity", "ks", "wasserstein"]].rename(
        columns={"ks": "ks_noise_floor", "wasserstein": "wasserstein_noise_floor"}
    )
    out = table.drop(
        columns=["ks_noise_floor", "wasserstein_noise_floor", "within_noise"], errors="ignore"
    ).merge(floor, on="quantity", how="left", validate="one_to_one")
    # a NaN floor falls back to the critical value
    threshold = noise_threshold(out["ks_noise_floor"].to_numpy(float),
                                out["ks_critical_05"].to_numpy(float))  # fmt: skip
    out["within_noise"] = out["ks"].to_numpy(float) <= threshold
    return out


def family_failures(
    tables: Mapping[str, pd.DataFrame], alpha: float = 0.05
) -> tuple[dict[str, list[str]], int]:
    """Per table (e.g. per field), the quantities outside sampling noise at a family-wise level
    ``alpha`` over every comparison of ``tables`` (Bonferroni): a KS distance above both its
    noise floor and the KS critical value at ``alpha / m``, ``m`` the comparisons counted. A
    report of 18 tests each at 5 % marks ~1 by chance; this counts a difference only where the
    whole report's chance of one false mark is ``alpha``. Tables without ``within_noise``
    (no noise floor) count no failure. Returns the failures and ``m``.

    Args:
        tables: ``combine_with_noise_floor`` tables (columns ``quantity``, ``ks``,
            ``n_reference``, ``n_candidate``, ``ks_noise_floor``).
        alpha: the family-wise level.
    """
    judged = {k: t for k, t in tables.items() if "within_noise" in t}
    m = sum(len(t) for t in judged.values())
    out: dict[str, list[str]] = {k: [] for k in tables}
    if m == 0:
        return out, 0
    c_alpha = ks_c_alpha(alpha / m)
    for name, t in judged.items():
        critical = [ks_critical_value(int(a), int(b), c_alpha)
                    for a, b in zip(t["n_reference"], t["n_candidate"], strict=True)]  # fmt: skip
        threshold = noise_threshold(t["ks_noise_floor"].to_numpy(float), np.asarray(critical))
        out[name] = t.loc[t["ks"].to_numpy(float) > threshold, "quantity"].tolist()
    return out, m


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

"""Two-sample statistics: the Kolmogorov-Smirnov (KS) statistic, its p-value and critical value,
the 1-Wasserstein distance, and the rule a distance is judged by (:func:`noise_threshold`), on
plain samples (:func:`compare_samples`) or on empirical distributions known exactly
(:class:`ExactSample`) or as counts on a grid (:class:`BinnedSample`,
:func:`compare_distributions`)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from surrogate.errors import NumericalError

#: c(alpha) of the asymptotic two-sample KS critical value at alpha = 0.05,
#: sqrt(-ln(alpha / 2) / 2) = 1.358.
KS_C_ALPHA_05 = 1.358
#: sample size up to which ``ks_2samp`` computes the exact p-value (its ``method="auto"``)
_SCIPY_EXACT_N = 10_000


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
    from scipy import stats  # ~1.7 s to import: only where used

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
    from scipy import stats  # ~1.7 s to import: only where used

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
    from scipy import stats  # ~1.7 s to import: only where used

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
    from scipy import stats  # ~1.7 s to import: only where used

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


__all__ = [
    "KS_C_ALPHA_05",
    "BinnedSample",
    "Distribution",
    "ExactSample",
    "compare_distributions",
    "compare_samples",
    "ks_c_alpha",
    "ks_critical_value",
    "ks_pvalue_asymptotic",
    "noise_threshold",
]

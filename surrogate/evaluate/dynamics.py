"""Time-series statistics of simulated cells: settling, relaxation and memory of phi.

Each function takes independent cells (rows) observed at common times, so every standard
error is taken across cells (a cell's own samples are autocorrelated; the cells are not):

* :func:`settling_from_cells` / :func:`settling_time`: when a mean curve reaches its plateau;
* :func:`autocorrelation` / :func:`relaxation_from_series`: the decay time of phi's
  autocorrelation at stationarity;
* :func:`switch_hazards`: the hazard of leaving phi against the time since phi last changed,
  and a chi-square test of its constancy (a two-state Markov chain over phi has a constant
  hazard; a hidden slow variable makes it depend on the age);
* :func:`oscillation_from_acf` / :func:`segment_durations`: whether phi oscillates (a negative
  lobe of its autocorrelation, which no reversible network and no memoryless lump can give),
  its period, and how regular the durations of its segments are.

Used by the inspection (:mod:`surrogate.diagnosis`); the definitions are in the docstrings, the
tests (tests/diagnosis/) check them against closed forms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "Hazard",
    "Oscillation",
    "Relaxation",
    "Settling",
    "autocorrelation",
    "bonferroni_z",
    "oscillation_from_acf",
    "relaxation_from_series",
    "segment_durations",
    "settling_from_cells",
    "settling_time",
    "switch_hazards",
]


def bonferroni_z(k: int, alpha: float = 0.05) -> float:
    """The two-sided normal quantile that ``k`` tests share at family-wise level ``alpha``:
    ``Phi^-1(1 - alpha / (2 k))`` (k = 64: 3.4)."""
    from scipy import stats  # ~1.7 s to import: only where used

    return float(stats.norm.isf(alpha / (2 * max(int(k), 1))))


# ----------------------------------------------------------------------------------------------
# settling


@dataclass(frozen=True)
class Settling:
    """When a mean curve reaches its plateau.

    Attributes:
        time: the settling time (s): the first sample time after the last sample whose mean
            lies outside the band around the final value (0: never outside; inf: outside at
            the last sample, so not settled within the record).
        final: the final value (the plateau: the mean over the samples of the second half).
        final_se: its standard error (across cells; 0 for an exact curve).
        settled: whether ``time`` lies within the first half of the record (the second half,
            which defines the final value, is then all within the band) and the cells' mean
            change from the quarter before it to the second half is within the tolerance or
            the noise of that paired change: a drift slow against the record is not taken for
            a plateau. Over cells that all start from one state, not settled either where that
            start lies beyond the tolerance from the final value but within the noise band:
            the record has too few cells to see the curve leave its start.
    """

    time: float
    final: float
    final_se: float
    settled: bool


def settling_time(
    times: ArrayLike,
    mean: ArrayLike,
    se: ArrayLike,
    final: float,
    final_se: float = 0.0,
    rel_tol: float = 0.05,
    alpha: float = 0.05,
) -> float:
    """The settling time of a mean curve (s): the first of ``times`` after the last one at which
    ``|mean - final|`` exceeds the band ``max(rel_tol |final|, z sqrt(se^2 + final_se^2))``,
    ``z`` the Bonferroni quantile over the ``K`` samples at level ``alpha`` (so that a curve
    already at its plateau leaves the band anywhere with probability <= alpha).

    Args:
        times: ``(K,)`` increasing sample times (s), the first usually 0 (the initial state).
        mean: ``(K,)`` the curve.
        se: ``(K,)`` its standard errors (0 for an exact curve).
        final: the plateau value.
        final_se: its standard error.
        rel_tol: the relative tolerance.
        alpha: the family-wise level of the noise band.

    Returns:
        0 when the curve never leaves the band, inf when it is outside at the last sample.

    Example:
        >>> t = np.linspace(0, 10, 101)
        >>> round(settling_time(t, 1 - np.exp(-t), np.zeros(101), 1.0), 1)  # ln 20 = 3.0
        3.0
    """
    t = np.asarray(times, dtype=float)
    m, s = np.asarray(mean, dtype=float), np.asarray(se, dtype=float)
    z = bonferroni_z(t.size, alpha)
    band = np.maximum(rel_tol * abs(final), z * np.sqrt(s**2 + final_se**2))
    # round-off of an exact curve must not count as a departure from a plateau at 0
    band = np.maximum(band, 1e-9 * max(1.0, abs(final)))
    outside = np.flatnonzero(np.abs(m - final) > band)
    if outside.size == 0:
        return 0.0
    last = int(outside[-1])
    return math.inf if last == t.size - 1 else float(t[last + 1])


def settling_from_cells(
    times: ArrayLike, values: ArrayLike, rel_tol: float = 0.05, alpha: float = 0.05
) -> Settling:
    """The settling of the mean over independent cells (:func:`settling_time`): the final
    value is the mean over cells of each cell's average over the samples after half the record
    (its standard error across cells), each sample's standard error ``sqrt(var / N)`` with its
    variance across cells, at least the mean variance of the second half's samples; settled
    as :class:`Settling` says (the paired change compared at the samples' Bonferroni
    quantile).

    Args:
        times: ``(K,)`` increasing sample times (s); the plateau is ``times > times[-1] / 2``.
        values: ``N x K`` each cell's value at each sample.
        rel_tol, alpha: as :func:`settling_time`.
    """
    t = np.asarray(times, dtype=float)
    v = np.asarray(values, dtype=float)
    n = v.shape[0]
    late = t > t[-1] / 2
    if not late.any():
        late[-1] = True
    per_cell = v[:, late].mean(1)
    final = float(per_cell.mean())
    final_se = float(per_cell.std(ddof=1) / math.sqrt(n)) if n > 1 else 0.0
    # a sample's variance is at least the plateau's (a rare 0/1 value's sample is often all 0,
    # its own variance then 0: that is no evidence of a departure)
    var = v.var(0, ddof=1) if n > 1 else np.zeros(t.size)
    se = np.sqrt(np.maximum(var, var[late].mean()) / n)
    z = bonferroni_z(t.size, alpha)
    time = settling_time(t, v.mean(0), se, final, final_se, rel_tol, alpha)
    settled = time <= t[-1] / 2
    start = v[:, 0]
    if settled and n > 1 and float(np.ptp(start)) == 0.0:
        # every cell starts from one known state: if its distance from the plateau exceeds the
        # tolerance yet lies within the noise band, the record cannot see the start depart
        # from the plateau, so "settled at once" would be an artefact of too few cells (an
        # oscillator's cells, spread over its cycle, make the plateau's variance huge)
        departure = abs(float(start[0]) - final)
        band = z * math.sqrt(float(se[0]) ** 2 + final_se**2)
        if rel_tol * abs(final) < departure <= band:
            settled = False
    before = (t > t[-1] / 4) & ~late
    if settled and before.any() and n > 1:
        # each cell's change between the two spans: what persists in a cell (a slow hidden
        # level) cancels, so a slow drift shows against the fast noise alone
        change = per_cell - v[:, before].mean(1)
        band = max(rel_tol * abs(final), z * float(change.std(ddof=1)) / math.sqrt(n), 1e-9)
        settled = abs(float(change.mean())) <= band
    return Settling(time, final, final_se, settled)


# ----------------------------------------------------------------------------------------------
# relaxation


def autocorrelation(
    series: ArrayLike, max_lag: int, groups: int = 20
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phi's autocorrelation at lags ``0..max_lag`` pooled over cells, with jackknife errors.

    ``rho(l) = c(l) / c(0)``, ``c(l) = sum_cells sum_k (x_k - p)(x_{k+l} - p) / (N (W - l))``
    with ``p`` the mean over every cell and window (the cells share one stationary law). The
    standard error is the delete-a-group jackknife over ``groups`` groups of cells.

    Args:
        series: ``N x W`` each cell's value (phi as 0/1) at ``W`` consecutive windows.
        max_lag: the largest lag ``L`` (windows), below ``W``.
        groups: jackknife groups (at most ``N``).

    Returns:
        ``rho`` ``(L + 1,)``, ``se`` ``(L + 1,)`` and the leave-one-group-out estimates
        ``G x (L + 1)`` (NaN everywhere when the series does not vary).
    """
    x = np.asarray(series, dtype=float)
    n, w = x.shape
    lag = int(min(max_lag, w - 1))
    x = x - x.mean()
    spectrum = np.fft.rfft(x, n=2 * w, axis=1)
    per_cell = np.fft.irfft(spectrum * spectrum.conj(), n=2 * w, axis=1)[:, : lag + 1]
    g = int(min(max(groups, 2), n))
    sums = np.stack([part.sum(0) for part in np.array_split(per_cell, g)])  # (G, L + 1)
    norm = w - np.arange(lag + 1)

    def rho(total: np.ndarray) -> np.ndarray:
        cov = total / norm
        with np.errstate(invalid="ignore", divide="ignore"):
            return cov / cov[..., :1]

    full = rho(sums.sum(0))
    leave_out = rho(sums.sum(0)[None, :] - sums)
    se = np.sqrt((g - 1) / g * ((leave_out - leave_out.mean(0)) ** 2).sum(0))
    return full, se, leave_out


@dataclass(frozen=True)
class Relaxation:
    """The decay time of phi's autocorrelation at stationarity.

    Attributes:
        tau: the time (s) of the fit ``rho(l) ~ A exp(-l dt / tau)`` over the lags ``1..``
            up to the first whose autocorrelation is not above both ``floor`` and ``z`` standard
            errors; NaN where phi does not vary or already the first lag fails (see ``bound``).
        tau_se: its jackknife standard error (over groups of cells).
        amplitude: the fit's ``A`` (1 for one exponential; below 1 where faster modes decay
            within the first lag).
        lags: the lags the fit used.
        bound: ``""``; ``"below"`` (the first lag is below the floor: tau is shorter than a
            window); ``"noise"`` (the first lag is above the floor but within the noise: more
            cells are needed); ``"above"`` (still above at the last lag measured: a slower
            component, e.g. a slowly drifting hidden count, makes tau longer than the record
            can measure).
        rho, rho_se: the autocorrelation and its standard errors at lags ``0..L``.
    """

    tau: float
    tau_se: float
    amplitude: float
    lags: int
    bound: str
    rho: np.ndarray
    rho_se: np.ndarray


def _fit_tau(rho: np.ndarray, dt: float) -> tuple[float, float]:
    """``(tau, A)`` of ``log rho(l) = log A - l dt / tau`` by least squares over lags
    ``1..len(rho)`` (one lag: A = 1)."""
    if np.any(~(rho > 0)):
        return math.nan, math.nan
    lags = np.arange(1, rho.size + 1) * dt
    if rho.size == 1:
        slope, intercept = math.log(rho[0]) / lags[0], 0.0
    else:
        slope, intercept = (float(v) for v in np.polyfit(lags, np.log(rho), 1))
    return (math.inf if slope >= 0 else -1.0 / slope), math.exp(intercept)


def relaxation_from_series(
    series: ArrayLike,
    dt: float,
    max_lag: int | None = None,
    floor: float = 0.05,
    z: float = 2.0,
    groups: int = 20,
) -> Relaxation:
    """The decay time of the autocorrelation of ``series`` (see :class:`Relaxation`).

    Args:
        series: ``N x W`` phi (0/1) of independent cells at consecutive windows of ``dt``,
            at stationarity.
        dt: the window (s).
        max_lag: the largest lag (windows; default ``W // 4``).
        floor: the autocorrelation below which a lag is not fitted (noise and the fast modes'
            tail matter there).
        z: a lag is fitted only while ``rho > z se``.
        groups: jackknife groups of cells.

    Example:
        >>> rng = np.random.default_rng(0)  # a telegraph at rate 1 each way, dt 0.1: tau = 0.5
        >>> flips = rng.random((200, 2000)) < 1 - np.exp(-0.2)  # changes of state, half flips
        >>> x = (np.cumsum(flips & (rng.random((200, 2000)) < 0.5), 1) % 2).astype(float)
        >>> 0.4 < relaxation_from_series(x, 0.1).tau < 0.6
        True
    """
    x = np.asarray(series)
    lag = int(max_lag if max_lag is not None else max(1, x.shape[1] // 4))
    rho, se, leave_out = autocorrelation(x, lag, groups)
    if not np.isfinite(rho[0]):
        return Relaxation(math.nan, math.nan, math.nan, 0, "", rho, se)
    above = rho[1:] > np.maximum(floor, z * se[1:])
    stop = int(np.argmin(above)) if not above.all() else above.size
    if stop == 0:
        bound = "below" if rho[1] <= floor else "noise"
        return Relaxation(math.nan, math.nan, math.nan, 0, bound, rho, se)
    tau, amplitude = _fit_tau(rho[1 : stop + 1], dt)
    replicates = np.array([_fit_tau(r[1 : stop + 1], dt)[0] for r in leave_out])
    replicates = replicates[np.isfinite(replicates)]
    g = replicates.size
    tau_se = (math.sqrt((g - 1) / g * ((replicates - replicates.mean()) ** 2).sum())
              if g > 1 else math.nan)  # fmt: skip
    bound = "above" if stop == above.size else ""
    return Relaxation(tau, tau_se, amplitude, stop, bound, rho, se)


# ----------------------------------------------------------------------------------------------
# memory


@dataclass(frozen=True)
class Hazard:
    """The hazard of leaving phi = ``origin`` against the time since phi last changed.

    Rows are windows at whose start a cell is in ``origin`` with a known age ``a`` (windows
    since phi last changed: 0 when it changed in the window just ended, as collect's
    ``phi_age``; a cell's windows before its first observed change are left out, their age
    unknown); a row switches when phi differs at the window's end.

    Attributes:
        origin: 0 or 1.
        edges: ``(B,)`` the first age (windows) of each bin; the last bin is open-ended. Bins
            double in width (0, 1, 2-3, 4-7, ...) and are merged until each expects at least a
            few switches and stays under constancy.
        rows, switches: ``(B,)`` counts per bin.
        hazard, se: ``(B,)`` switches / rows and its binomial standard error.
        pooled: the hazard over every row.
        chi2, df, p_value: Pearson's test that the hazard is the same in every bin.
        effect: the largest ``|hazard_b - pooled| / pooled`` over the bins that depart from the
            pooled hazard by more than 3 standard errors (0 where none does).
        flat_from: the first age (windows) from which on the bins are consistent with one
            hazard (the test at ``alpha`` over those bins alone).
    """

    origin: int
    edges: np.ndarray
    rows: np.ndarray
    switches: np.ndarray
    hazard: np.ndarray
    se: np.ndarray
    pooled: float
    chi2: float
    df: int
    p_value: float
    effect: float
    flat_from: int


def _constancy(rows: np.ndarray, switches: np.ndarray) -> tuple[float, int, float]:
    """Pearson's chi-square that the bins share one hazard: (statistic, df, p-value)."""
    from scipy import stats  # ~1.7 s to import: only where used

    h = switches.sum() / rows.sum()
    if rows.size < 2 or not 0 < h < 1:
        return 0.0, 0, 1.0
    chi2 = float(((switches - rows * h) ** 2 / (rows * h * (1 - h))).sum())
    df = rows.size - 1
    return chi2, df, float(stats.chi2.sf(chi2, df))


def switch_hazards(
    series: ArrayLike, alpha: float = 0.001, min_expected: float = 5.0
) -> list[Hazard | None]:
    """The hazard of leaving each lump against the time since phi last changed (see
    :class:`Hazard`), for origin 0 and 1 (None where no row has a known age).

    Args:
        series: ``N x W`` phi (0/1) of independent cells at consecutive windows, at
            stationarity and fixed inputs.
        alpha: the level of the test that finds ``flat_from``.
        min_expected: a bin is merged with the next until it expects at least this many
            switches and this many stays (the chi-square's approximation).

    Example:
        >>> rng = np.random.default_rng(1)  # memoryless: switch with probability 0.1
        >>> x = np.cumsum(rng.random((100, 3000)) < 0.1, 1) % 2
        >>> [round(h.pooled, 2) for h in switch_hazards(x)], switch_hazards(x)[0].p_value > 1e-3
        ([0.1, 0.1], True)
    """
    x = np.asarray(series).astype(np.int8)
    w = x.shape[1]
    k = np.arange(w)
    change = np.zeros_like(x, dtype=bool)
    change[:, 1:] = x[:, 1:] != x[:, :-1]
    last = np.maximum.accumulate(np.where(change, k, -1), axis=1)
    age = k - last  # windows since the last change (meaningless where last < 0)
    known = (last >= 0)[:, :-1]
    switched = change[:, 1:]
    origin, age = x[:, :-1], age[:, :-1]
    out: list[Hazard | None] = []
    for v in (0, 1):
        rows_mask = known & (origin == v)
        if not rows_mask.any():
            out.append(None)
            continue
        a, s = age[rows_mask], switched[rows_mask]
        # ages 0, 1, 2-3, 4-7, ... -> bins 0, 1, 2, 3 (the bit length of the age), so that
        # bin b starts at age 0 (b = 0) or 2^(b-1), as the edges below say
        fine = np.frexp(a.astype(np.float64))[1]
        nb = int(fine.max()) + 1
        rows = np.bincount(fine, minlength=nb).astype(float)
        hits = np.bincount(fine, weights=s, minlength=nb)
        pooled = hits.sum() / rows.sum()
        starts, r_merged, s_merged = [], [], []
        r_acc = s_acc = 0.0
        first = 0
        for b in range(nb):
            r_acc, s_acc = r_acc + rows[b], s_acc + hits[b]
            if min(r_acc * pooled, r_acc * (1 - pooled)) >= min_expected:
                starts.append(0 if first == 0 else 2 ** (first - 1))
                r_merged.append(r_acc)
                s_merged.append(s_acc)
                r_acc = s_acc = 0.0
                first = b + 1
        if r_acc > 0:  # the remainder joins the last bin
            if r_merged:
                r_merged[-1] += r_acc
                s_merged[-1] += s_acc
            else:
                starts, r_merged, s_merged = [0], [r_acc], [s_acc]
        edges = np.array(starts, dtype=int)
        rows_b, hits_b = np.array(r_merged), np.array(s_merged)
        hazard = hits_b / rows_b
        se = np.sqrt(hazard * (1 - hazard) / rows_b)
        chi2, df, p = _constancy(rows_b, hits_b)
        null_se = np.sqrt(pooled * (1 - pooled) / rows_b)
        departs = np.abs(hazard - pooled) > 3 * null_se
        effect = float((np.abs(hazard - pooled)[departs] / pooled).max()) if departs.any() \
            and pooled > 0 else 0.0  # fmt: skip
        flat = next(j for j in range(edges.size)
                    if _constancy(rows_b[j:], hits_b[j:])[2] >= alpha)  # fmt: skip
        out.append(Hazard(v, edges, rows_b, hits_b, hazard, se, float(pooled), chi2, df, p,
                          effect, int(edges[flat])))  # fmt: skip
    return out


# ----------------------------------------------------------------------------------------------
# oscillation

#: the depth of phi's negative autocorrelation lobe from which phi oscillates. The
#: autocorrelation of any observable of a reversible Markov process (detailed balance: every
#: one-species birth-death count, a telegraph gene, the two-state chain itself) is a mixture of
#: decaying exponentials with nonnegative weights, ``sum_k w_k exp(-lambda_k t)``: never
#: negative. A negative lobe needs a probability current circulating through the network's
#: states, a phase. Its depth measures how regular the cycle is: phi alternating with
#: gamma-distributed durations of shape 2 (coefficient of variation 0.71, half an exponential's
#: variance: a hazard rising clearly with the time since the last change) dips to -0.074 at
#: occupancy 0.5 and -0.059 at occupancy 0.8 (200 cells x 4,000 windows simulated); shape 1.5
#: (CV 0.82) to -0.02, shape 1 (exponential) to 0. Measured: Tyson's oscillator -0.26 (period
#: 3.5 s, segment CVs 0.27 and 0.45), the toggle switch -0.013 +- 0.006 (within noise)
OSCILLATION_DEPTH = 0.05


@dataclass(frozen=True)
class Oscillation:
    """Whether phi oscillates, from its autocorrelation at stationarity.

    Attributes:
        detected: the deepest autocorrelation ``rho_min`` is below ``-depth_threshold`` and
            below ``-z`` of its standard errors (``z`` the Bonferroni quantile over the lags).
        depth: ``-rho_min`` (positive where there is a negative lobe).
        depth_se: its standard error (0 for an exact autocorrelation).
        trough_s: the lag of ``rho_min`` (s): about half a period.
        period_s: the lag of the highest autocorrelation after the trough, within three times
            the trough's lag, where it is positive beyond ``z`` standard errors (the next
            crest: one period); else twice the trough's lag. NaN where not detected.
        crest: the autocorrelation at ``period_s`` (NaN where the crest is not significant).
        coherence_s: the decay time of the oscillation's envelope, ``-period / ln(crest)``:
            over it the cells forget their phase (NaN without a crest).
        z: the standard errors a lag's autocorrelation must clear.
        depth_threshold: the depth that counts (:data:`OSCILLATION_DEPTH`).
        bound: the trough is at the last lag measured (the autocorrelation still falling
            there): the depth and the period are lower bounds, the record too short for the
            cycle.
    """

    detected: bool
    depth: float
    depth_se: float
    trough_s: float
    period_s: float
    crest: float
    coherence_s: float
    z: float
    depth_threshold: float
    bound: bool = False


def oscillation_from_acf(
    rho: ArrayLike,
    se: ArrayLike | None,
    dt: float,
    depth: float = OSCILLATION_DEPTH,
    alpha: float = 0.05,
) -> Oscillation:
    """Whether phi oscillates (see :class:`Oscillation` and :data:`OSCILLATION_DEPTH`).

    Args:
        rho: phi's autocorrelation at lags ``0..L`` windows (:func:`autocorrelation`, or exact).
        se: its standard errors (None or zeros: exact).
        dt: the window (s).
        depth: the depth of the negative lobe that counts.
        alpha: the family-wise level over the lags of the significance of the lobe and crest.

    Example:
        >>> t = np.arange(400) * 0.05  # a damped cosine of period 4 s, coherent over 10 s
        >>> o = oscillation_from_acf(np.cos(2 * np.pi * t / 4) * np.exp(-t / 10), None, 0.05)
        >>> o.detected, round(o.period_s, 1), round(o.coherence_s)  # the crest: 3.95 s, 0.67
        (True, 4.0, 10)
    """
    r = np.asarray(rho, dtype=float)
    s = np.zeros_like(r) if se is None else np.nan_to_num(np.asarray(se, dtype=float))
    lags = r.size - 1
    z = bonferroni_z(max(lags, 1), alpha)
    nan = math.nan
    if lags < 2 or not np.isfinite(r[1:]).all():
        return Oscillation(False, nan, nan, nan, nan, nan, nan, z, depth)
    trough = 1 + int(np.argmin(r[1:]))
    low, low_se = float(r[trough]), float(s[trough])
    detected = low < -depth and low < -z * low_se
    period, crest, coherence = nan, nan, nan
    if detected:
        end = min(lags, 3 * trough)
        if end > trough:
            top = trough + 1 + int(np.argmax(r[trough + 1 : end + 1]))
            if r[top] > 0 and r[top] > z * s[top]:
                period, crest = top * dt, float(r[top])
                coherence = -period / math.log(crest) if crest < 1 else math.inf
        if not math.isfinite(period):
            period = 2 * trough * dt
    return Oscillation(bool(detected), -low, low_se, trough * dt, period, crest, coherence, z,
                       depth, trough == lags)  # fmt: skip


def segment_durations(series: ArrayLike) -> list[np.ndarray]:
    """The durations (windows) of phi's complete segments, per lump: the runs of equal phi
    between two observed changes (a cell's first and last runs, cut by the record, left out).

    Example:
        >>> [d.tolist() for d in segment_durations([[0, 1, 1, 0, 0, 0, 1, 1]])]
        [[3], [2]]
    """
    x = np.asarray(series).astype(np.int8)
    out: list[list[np.ndarray]] = [[], []]
    for row in x:
        changes = np.flatnonzero(row[1:] != row[:-1]) + 1
        if changes.size < 2:
            continue
        lengths = np.diff(changes)
        values = row[changes[:-1]]
        for v in (0, 1):
            out[v].append(lengths[values == v])
    return [np.concatenate(p) if p else np.zeros(0, dtype=int) for p in out]

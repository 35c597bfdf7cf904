"""Band fidelity: two runs' profiles along a channel compared, and a candidate's distance from
the full model judged against two full runs' (issue 39, item 4).

Two runs in one grid field (:mod:`surrogate.simulate.profiles`) are compared at every record
time they share:

* **ks**: the two-sample KS distance between the two populations' x positions, from their
  counts per grid column (:func:`binned_ks`). Each run's counts are divided by its own total, so
  runs of different sizes compare (20,000 full cells against 100,000 abstract ones). It is the
  KS statistic at the grid's resolution: the largest difference of the two empirical CDFs at
  the columns' edges, where both are known exactly. The unbinned statistic is the same supremum
  over every x, so this is a lower bound of it (the difference inside a column can only be
  larger).
* **ks_critical**: the asymptotic two-sample critical value at ``alpha`` for the two sizes,
  ``c(alpha) sqrt((n + m) / (n m))`` with ``c(alpha) = sqrt(-ln(alpha / 2) / 2)`` (1.358 at
  5 %; :func:`~surrogate.evaluate.ks.ks_c_alpha`). It is the unbinned test's; binning
  only lowers the statistic, so it stays a valid level-alpha bar.
* **front**: each run's depletion front (:func:`~surrogate.evaluate.band.front_position`) and
  their difference (mm).
* **c_l1**, **c_linf**: the read species' y-averaged concentration profiles' difference,
  ``sum |c_a - c_b| h_x`` (mM mm) and ``max |c_a - c_b|`` (mM).

Per pair of runs (:func:`summarise_pair`): the largest KS over the record times, the front's
RMS difference over the times both have one, the largest concentration difference, and the
fronts' least-squares speeds (:func:`~surrogate.evaluate.band.band_speed`, fitted over those
common times) with their difference and its combined standard error ``sqrt(se_a^2 + se_b^2)``.

**The rule** (:func:`judge`), the one every evaluation uses
(:func:`~surrogate.evaluate.ks.noise_threshold`: ``max(factor x floor, critical)``),
applied to the candidate-vs-full figure with the full-vs-full one as the floor:

* the largest KS over the record times, against ``max(factor x the floor's largest KS, the
  critical value)`` (maxima on both sides, so the candidate and the floor pay the same price for
  the many record times looked at);
* the fronts' RMS difference, against ``max(factor x the floor's, half a column)`` (the front is
  read off the grid's columns: a position known to half a column, as
  :func:`~surrogate.evaluate.band.slope_resolution` takes it);
* the speed difference, against ``max(factor x the floor's, z x its combined standard error)``
  (``z`` the two-sided normal quantile at ``alpha``, 1.96 at 5 %).

Without a floor (no second full run) each falls back to its critical value alone.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from surrogate.evaluate.band import band_speed, front_position
from surrogate.evaluate.ks import ks_c_alpha, ks_critical_value, noise_threshold
from surrogate.simulate.profiles import Profiles

__all__ = [
    "CHECKS",
    "band_fidelity",
    "band_markdown",
    "binned_cdf",
    "binned_ks",
    "compare_profiles",
    "judge",
    "plot_band_fidelity",
    "position_bins",
    "speed_difference",
    "summarise_pair",
]

#: the checks of :func:`judge`: the pair summary's value, its critical value's key, what it is
CHECKS: tuple[tuple[str, str, str], ...] = (
    ("max_ks", "ks_critical", "largest KS of the cells' x over the record times"),
    ("front_rms", "front_resolution", "RMS difference of the depletion front (mm)"),
    ("speed_diff", "speed_critical", "difference of the front's speed (mm/s)"),
)


def position_bins(profiles: Profiles) -> np.ndarray:
    """``(T, n_x + 2)`` int64 cells per bin along x at each record time: beyond the lower end,
    the grid's columns in order, at or beyond the upper end (every cell counted once)."""
    return np.concatenate([profiles.below[:, None], profiles.counts, profiles.above[:, None]],
                          axis=1)  # fmt: skip


def binned_cdf(bins: np.ndarray) -> np.ndarray:
    """The empirical CDF at the bins' inner edges, from counts.

    Args:
        bins: ``(..., B)`` counts per bin, the outer two the overflow bins
            (:func:`position_bins`); every row with at least one cell.

    Returns:
        ``(..., B - 1)`` the fraction of cells below each edge between two bins (for a
        run's profiles: below ``edges[0] .. edges[n_x]``).
    """
    counts = np.asarray(bins, dtype=np.float64)
    total = counts.sum(axis=-1, keepdims=True)
    if np.any(total <= 0):
        raise ValueError("a record without cells has no distribution of positions")
    return np.cumsum(counts, axis=-1)[..., :-1] / total


def binned_ks(bins_a: np.ndarray, bins_b: np.ndarray) -> np.ndarray:
    """The two-sample KS distance from counts on the same bins (module docstring): the sup of
    the two CDFs' difference over the bins' edges, each run's counts over its own total.

    It is the KS statistic at the bins' resolution, a lower bound of the statistic of the
    unbinned positions (equal to ``scipy.stats.ks_2samp`` on values moved to their bin's
    lower edge).

    Args:
        bins_a: ``(..., B)`` the first run's counts per bin (any total).
        bins_b: ``(..., B)`` the second's, on the same bins.

    Returns:
        ``(...)`` the distance in [0, 1].
    """
    a, b = np.asarray(bins_a), np.asarray(bins_b)
    if a.shape[-1] != b.shape[-1]:
        raise ValueError(f"bins differ: {a.shape[-1]} against {b.shape[-1]}")
    return np.abs(binned_cdf(a) - binned_cdf(b)).max(axis=-1)


def _common_times(a: Profiles, b: Profiles) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``a.t`` and ``b.t`` of the record times both have (to 1e-9 s x scale)."""
    tol = 1e-9 * max(1.0, float(np.abs(a.t).max(initial=0.0)), float(np.abs(b.t).max(initial=0.0)))
    j = np.clip(np.searchsorted(b.t, a.t), 0, max(b.t.size - 1, 0))
    j_lo = np.clip(j - 1, 0, None)
    nearest = np.where(np.abs(b.t[j_lo] - a.t) < np.abs(b.t[j] - a.t), j_lo, j)
    keep = np.abs(b.t[nearest] - a.t) <= tol
    return np.flatnonzero(keep), nearest[keep]


def _check_same_grid(a: Profiles, b: Profiles) -> None:
    """Refuse two runs on different grids (their bins and profiles would not line up)."""
    if a.edges.shape != b.edges.shape or not np.allclose(a.edges, b.edges, rtol=0, atol=1e-9):
        raise ValueError(
            f"the runs' grids differ along x ({a.edges.size - 1} columns over "
            f"[{a.edges[0]:g}, {a.edges[-1]:g}] mm against {b.edges.size - 1} over "
            f"[{b.edges[0]:g}, {b.edges[-1]:g}] mm): compare runs in one field.shape and domain"
        )
    if a.read != b.read:
        raise ValueError(f"the runs read different species: {a.read!r} and {b.read!r}")


def compare_profiles(
    reference: Profiles, other: Profiles, alpha: float = 0.05, direction: int = 1
) -> pd.DataFrame:
    """Two runs' profiles at every record time they share (module docstring).

    Args:
        reference: the full model's profiles (``T_a`` records on ``n_x`` columns).
        other: the run compared with it (``T_b`` records on the same columns; any number of
            cells).
        alpha: the level of the KS critical value.
        direction: the band's direction for the front (+1: towards larger x).

    Returns:
        One row per common record time: ``t``, ``ks``, ``ks_critical``, ``n_reference``,
        ``n_other``, ``front_reference``, ``front_other``, ``front_diff`` (other minus
        reference, mm; NaN where either has no front), ``c_l1`` (mM mm), ``c_linf`` (mM).

    Raises:
        ValueError: the runs are on different grids, or share no record time.
    """
    _check_same_grid(reference, other)
    i, j = _common_times(reference, other)
    if not i.size:
        raise ValueError("the runs share no record time: record both with one record_interval")
    bins_a, bins_b = position_bins(reference)[i], position_bins(other)[j]
    n_a, n_b = bins_a.sum(axis=1), bins_b.sum(axis=1)
    c_alpha = ks_c_alpha(alpha)
    critical = [ks_critical_value(int(p), int(q), c_alpha) for p, q in zip(n_a, n_b, strict=True)]
    # each run's front relative to its own first record (the initial profile, the same field)
    fronts = [front_position(p.centres, p.read_concentration(), direction=direction)[k]
              for p, k in ((reference, i), (other, j))]  # fmt: skip
    gap = np.abs(reference.read_concentration()[i] - other.read_concentration()[j])
    return pd.DataFrame({
        "t": reference.t[i],
        "ks": binned_ks(bins_a, bins_b),
        "ks_critical": critical,
        "n_reference": n_a,
        "n_other": n_b,
        "front_reference": fronts[0],
        "front_other": fronts[1],
        "front_diff": fronts[1] - fronts[0],
        "c_l1": gap.sum(axis=1) * reference.width,
        "c_linf": gap.max(axis=1),
    })  # fmt: skip


def speed_difference(table: pd.DataFrame, t_min: float | None = None) -> dict[str, float]:
    """The two runs' front speeds, fitted over the record times where both have a front (from
    ``t_min``), and their difference.

    Args:
        table: :func:`compare_profiles`' rows.
        t_min: fit from this time on (s).

    Returns:
        ``speed_reference``, ``speed_other`` (mm/s), ``speed_diff`` (other minus reference),
        ``speed_se`` (``sqrt(se_a^2 + se_b^2)``), ``speed_n`` (records fitted); NaN where
        fewer than three records have both fronts.
    """
    both = table.loc[table["front_diff"].notna()]
    t = both["t"].to_numpy()
    fits = [band_speed(t, both[c].to_numpy(), t_min=t_min)
            for c in ("front_reference", "front_other")]  # fmt: skip
    return {
        "speed_reference": fits[0].speed,
        "speed_other": fits[1].speed,
        "speed_diff": fits[1].speed - fits[0].speed,
        "speed_se": math.hypot(fits[0].stderr, fits[1].stderr),
        "speed_n": float(fits[0].n),
    }


def summarise_pair(
    table: pd.DataFrame, column_width: float, alpha: float = 0.05, t_min: float | None = None
) -> dict[str, float]:
    """One pair's figures over its record times (module docstring).

    Args:
        table: :func:`compare_profiles`' rows.
        column_width: the grid's column width h_x (mm): half of it is the front's resolution.
        alpha: the level of the speed's critical value (``z`` at ``alpha``, two-sided).
        t_min: fit the speeds from this time on (s).

    Returns:
        ``max_ks``, ``t_max_ks``, ``ks_critical`` (its largest over the records),
        ``front_rms`` (mm, NaN without a common front), ``front_n``, ``front_resolution``,
        ``c_l1_max``, ``c_linf_max``, :func:`speed_difference`'s keys, ``speed_critical``
        (``z`` x ``speed_se``).
    """
    from scipy import stats  # ~1.7 s to import: only where used

    k = int(np.argmax(table["ks"].to_numpy()))
    diff = table["front_diff"].dropna().to_numpy()
    speeds = speed_difference(table, t_min)
    z = float(stats.norm.isf(alpha / 2.0))
    return {
        "max_ks": float(table["ks"].iloc[k]),
        "t_max_ks": float(table["t"].iloc[k]),
        "ks_critical": float(table["ks_critical"].max()),
        "front_rms": float(np.sqrt(np.mean(diff**2))) if diff.size else math.nan,
        "front_n": float(diff.size),
        "front_resolution": 0.5 * float(column_width),
        "c_l1_max": float(table["c_l1"].max()),
        "c_linf_max": float(table["c_linf"].max()),
        **speeds,
        "speed_critical": z * speeds["speed_se"],
    }


def judge(
    candidate: Mapping[str, float], floor: Mapping[str, float] | None, factor: float = 1.5
) -> list[dict[str, Any]]:
    """The rule (module docstring) on a candidate's pair summary against the floor's.

    Args:
        candidate: :func:`summarise_pair` of the candidate against the full run.
        floor: the same of the second full run against the full run (None: no floor).
        factor: how far above the floor a candidate may be (the fidelity stage's 1.5).

    Returns:
        One dict per check of :data:`CHECKS`: ``check``, ``what``, ``value`` (its magnitude),
        ``floor`` (NaN without one), ``critical``, ``threshold``, ``passed`` (False where the
        value is NaN: no front, or no speed, to judge).
    """
    out = []
    for key, critical_key, what in CHECKS:
        value = abs(float(candidate[key]))
        base = abs(float(floor[key])) if floor is not None else math.nan
        critical = float(candidate[critical_key])
        threshold = float(noise_threshold(base, critical, factor))
        out.append({"check": key, "what": what, "value": value, "floor": base,
                    "critical": critical, "threshold": threshold,
                    "passed": bool(value <= threshold)})  # fmt: skip
    return out


def plot_band_fidelity(
    runs: Mapping[str, Profiles],
    tables: Mapping[str, pd.DataFrame],
    floor: str | None,
    thresholds: Mapping[str, float],
    direction: int = 1,
) -> Figure:
    """The band of every run and the candidates' KS against the floor.

    Left: each run's depletion front against time. Right: the KS distance of each run's cells'
    x from the full model's against time (the floor dashed), each candidate's critical value
    and its threshold on the largest KS (the rule compares maxima).

    Args:
        runs: label -> profiles, the full model's first.
        tables: label -> :func:`compare_profiles` against the full model (every run but it).
        floor: the label of the second full run among ``tables`` (None: none).
        thresholds: label -> the threshold its largest KS is judged by.
        direction: the band's direction for the front (+1: towards larger x).
    """
    fig = Figure(figsize=(10.0, 3.8), layout="constrained")
    ax_front, ax_ks = fig.subplots(1, 2)
    candidates = [label for label in tables if label != floor]
    # one colour per run in both panels: the full runs black (the floor dashed), candidates C0..
    colour = {label: f"C{k}" for k, label in enumerate(candidates)}
    for label, p in runs.items():
        x = front_position(p.centres, p.read_concentration(), direction=direction)
        ax_front.plot(p.t, x, ls="--" if label == floor else "-", color=colour.get(label, "k"),
                      label=f"{label} (n={p.n_cells})")  # fmt: skip
    ax_front.set_xlabel("t (s)")
    ax_front.set_ylabel("depletion front (mm)")
    ax_front.legend(fontsize=7)
    if floor is not None and floor in tables:
        ax_ks.plot(tables[floor]["t"], tables[floor]["ks"], ls="--", color="k",
                   label=f"{floor} (noise floor)")  # fmt: skip
    for label in candidates:
        table = tables[label]
        ax_ks.plot(table["t"], table["ks"], color=colour[label], label=label)
        # the candidate's own critical value (it depends on the pair's sizes) and threshold
        ax_ks.plot(table["t"], table["ks_critical"], color=colour[label], lw=0.8, ls="-.",
                   label=f"{label}: KS critical value")  # fmt: skip
        if label in thresholds:
            ax_ks.axhline(thresholds[label], color=colour[label], lw=0.8, ls=":",
                          label=f"{label}: threshold on the largest")  # fmt: skip
    ax_ks.set_xlabel("t (s)")
    ax_ks.set_ylabel("KS of the cells' x vs the full model")
    ax_ks.legend(fontsize=7)
    return fig


def _json_float(value: float) -> float | None:
    """NaN and infinities as None (strict JSON)."""
    return float(value) if math.isfinite(value) else None


def band_fidelity(
    full: Profiles,
    others: Mapping[str, Profiles],
    floor: str | None,
    factor: float = 1.5,
    alpha: float = 0.05,
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Every run against the full model's band and every candidate judged (module docstring).

    Args:
        full: the full model's profiles.
        others: label -> profiles of the runs compared with it (candidates, and the second full
            run under the label ``floor``).
        floor: the second full run's label in ``others`` (None: no floor; each check then
            against its critical value alone).
        factor: how far above the floor a candidate may be.
        alpha: the level of the critical values.

    Returns:
        The per-record-time table (:func:`compare_profiles`' columns with ``run`` first) and
        the summary: ``factor``, ``alpha``, ``floor``, ``pairs`` (label -> :func:`summarise_pair`),
        ``checks`` (candidate label -> :func:`judge`), ``passed`` (every candidate's every
        check); NaN as None.
    """
    if floor is not None and floor not in others:
        raise ValueError(f"the floor {floor!r} is none of the runs {list(others)}")
    tables = {label: compare_profiles(full, p, alpha) for label, p in others.items()}
    pairs = {label: summarise_pair(t, full.width, alpha) for label, t in tables.items()}
    base = pairs[floor] if floor is not None else None
    checks = {label: judge(s, base, factor) for label, s in pairs.items() if label != floor}
    table = pd.concat([t.assign(run=label) for label, t in tables.items()], ignore_index=True)
    table = table[["run", *[c for c in table.columns if c != "run"]]]
    summary = {
        "factor": float(factor),
        "alpha": float(alpha),
        "floor": floor,
        "pairs": {label: {k: _json_float(v) for k, v in s.items()} for label, s in pairs.items()},
        "checks": {label: [{k: _json_float(v) if isinstance(v, float) else v for k, v in c.items()}
                           for c in cs] for label, cs in checks.items()},
        "passed": all(c["passed"] for cs in checks.values() for c in cs),
    }  # fmt: skip
    return table, summary


def band_markdown(summary: Mapping[str, Any]) -> str:
    """The checks of :func:`band_fidelity`'s summary as a Markdown table: one row per candidate
    and check (its value, the floor's, the critical value, the threshold, pass or fail)."""
    from surrogate.evaluate.report import format_markdown_table

    rows = [
        {"run": label, "check": c["what"], "value": c["value"], "noise floor": c["floor"],
         "critical": c["critical"], "threshold": c["threshold"], "passed": c["passed"]}
        for label, cs in summary["checks"].items() for c in cs
    ]  # fmt: skip
    return format_markdown_table(pd.DataFrame(rows), floatfmt=".4g")

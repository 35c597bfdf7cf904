"""Two-sample comparisons of full and abstracted simulation runs (the paper's Table 1).

The paper compares the two models with the two-sample Kolmogorov-Smirnov (KS) statistic on

* the body's observables at a few record times (for E. coli the cells' distance from the
  field's peak; one value per cell, so 100 values per model for a 100-cell population), and
* the durations of the property's segments (run and tumble) pooled over the whole trajectory
  (~60,000 values per model), of which a random 1,000 are drawn from each model before the
  test, because with tens of thousands of values any approximation error, however small, gives
  a vanishing p-value.

Besides the KS statistic and its p-value we report the 1-Wasserstein distance (in the data's
units, so it says *how far* apart the distributions are, not only whether they differ) and the
asymptotic 5 % critical value of the KS statistic for the sample sizes used.

A KS distance alone does not say whether the abstraction is good: two full-model runs with
different seeds also differ. ``noise_floor_table`` measures that run-to-run difference and
``combine_with_noise_floor`` judges the abstraction against it.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from scipy import stats

from surrogate.errors import ArtefactError, NumericalError
from surrogate.io import read_json, read_parquet

#: c(alpha) of the asymptotic two-sample KS critical value at alpha = 0.05,
#: sqrt(-ln(alpha / 2) / 2) = 1.358.
KS_C_ALPHA_05 = 1.358

#: The paper's record times for the distance distributions (s).
PAPER_TIMES: tuple[float, ...] = (125.0, 250.0, 375.0, 500.0)

#: Durations subsample size used by the paper.
PAPER_SUBSAMPLE = 1000

MADE_BY = "python scripts/simulate.py ..."

OBSERVABLES = "observables.parquet"
DURATIONS = "durations.parquet"
DEFAULT_LUMPS: tuple[str, str] = ("tumble", "run")

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

# Relative tolerance when a run has a single record time (no interval to take half of).
_SINGLE_RECORD_RTOL = 1e-9


# ----------------------------------------------------------------------------------------------
# two-sample statistics


def ks_critical_value(n_a: int, n_b: int, c_alpha: float = KS_C_ALPHA_05) -> float:
    """Asymptotic two-sample KS critical value ``c(alpha) * sqrt((n_a + n_b) / (n_a * n_b))``."""
    if n_a <= 0 or n_b <= 0:
        raise ValueError(f"KS critical value needs positive sample sizes, got {n_a} and {n_b}")
    return c_alpha * math.sqrt((n_a + n_b) / (n_a * n_b))


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
# simulation runs


@dataclass
class SimulationRun:
    """The artefacts of one simulation run directory.

    Attributes:
        observables: Long table ``t``, ``cell`` and one column per observable (e.g.
            ``distance``, mm from the field's peak).
        durations: ``kind`` (the lump's name, e.g. "run"/"tumble"), ``duration`` (s), ``cell``,
            ``t_end``.
        manifest: The run's ``manifest.json`` (``wall_time_s``, ``seed``, ``config``, ...).
        path: The run directory.
    """

    observables: pd.DataFrame
    durations: pd.DataFrame
    manifest: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def observable_names(self) -> list[str]:
        """The observables recorded (every column but ``t`` and ``cell``)."""
        return [c for c in self.observables.columns if c not in ("t", "cell")]

    @property
    def lump_names(self) -> tuple[str, str]:
        """Names of phi = 0 and phi = 1 (the duration kinds)."""
        names = self.manifest.get("lump_names") or DEFAULT_LUMPS
        return (str(names[0]), str(names[1]))

    @property
    def record_times(self) -> np.ndarray:
        """The sorted distinct record times (s)."""
        return np.unique(self.observables["t"].to_numpy(dtype=np.float64))

    @property
    def t_end(self) -> float:
        """The last record time (s)."""
        return float(self.record_times[-1])

    @property
    def label(self) -> str:
        """A short name for messages: the directory name, or "run" when built in memory."""
        return self.path.name if self.path is not None else "run"

    def durations_of(self, kind: str) -> np.ndarray:
        """All completed segment durations of ``kind`` (a lump name, e.g. "run")."""
        if kind not in self.lump_names:
            raise ValueError(f"duration kind must be one of {self.lump_names}, got {kind!r}")
        mask = self.durations["kind"].astype(str) == kind
        return self.durations.loc[mask, "duration"].to_numpy(dtype=np.float64)


def load_run(directory: str | os.PathLike) -> SimulationRun:
    """Read ``observables.parquet``, ``durations.parquet`` and ``manifest.json`` of a run.

    Raises:
        MissingArtefactError: A file is missing (the message says which command makes it).
        ArtefactError: A file is corrupt or lacks the expected columns.
    """
    path = Path(directory)
    observables = read_parquet(path / OBSERVABLES, made_by=MADE_BY)
    durations = read_parquet(path / DURATIONS, made_by=MADE_BY)
    manifest = read_json(path / "manifest.json", made_by=MADE_BY)
    _require_columns(observables, ("t", "cell"), path / OBSERVABLES)
    _require_columns(durations, ("kind", "duration"), path / DURATIONS)
    if observables.empty or observables.shape[1] < 3:
        raise ArtefactError(f"{path / OBSERVABLES} has no observations; re-run `{MADE_BY}`")
    return SimulationRun(observables=observables, durations=durations, manifest=manifest,
                         path=path)  # fmt: skip


def _require_columns(df: pd.DataFrame, columns: Sequence[str], where: Path) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ArtefactError(
            f"{where} lacks column(s) {missing} (has {list(df.columns)}); re-create it with "
            f"`{MADE_BY}`"
        )


def observable_at(run: SimulationRun, name: str, t: float) -> np.ndarray:
    """The cells' values of observable ``name`` at the record time closest to ``t``.

    Raises:
        ValueError: No record lies within half a record interval of ``t``; the message names
            ``t`` and the recorded range.
    """
    times = run.record_times
    i = int(np.argmin(np.abs(times - t)))
    nearest = float(times[i])
    # Half the (median) record interval: a regular grid puts every t in range within it.
    tol = 0.5 * float(np.median(np.diff(times))) if times.size > 1 else _SINGLE_RECORD_RTOL
    if abs(nearest - t) > tol * (1 + 1e-9):
        raise ValueError(
            f"no record near t={t:g} s in {run.label}: records span "
            f"{times[0]:g}..{times[-1]:g} s ({times.size} record times); pass times within "
            f"that range"
        )
    values = run.observables.loc[run.observables["t"] == nearest, name]
    return values.to_numpy(dtype=np.float64)


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


def comparison_table(
    reference: SimulationRun,
    candidate: SimulationRun,
    times: Sequence[float] = PAPER_TIMES,
    subsample: int | None = PAPER_SUBSAMPLE,
    seed: int = 0,
) -> pd.DataFrame:
    """One row per quantity comparing ``candidate`` against ``reference`` (the paper's Table 1).

    Rows: ``<observable>_t<t>`` for each observable and each of ``times`` (all cells, no
    subsampling), then one per lump, phi = 1 first (``run``, ``tumble``: ``subsample``
    durations drawn without replacement from each run, from a generator seeded with ``seed``). Columns: see ``COLUMNS``; ``n_reference``/``n_candidate``
    are the sizes actually compared, and the duration rows also carry the full-sample
    ``ks_full``/``ks_pvalue_full`` (NaN on distance rows).

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
            res = compare_samples(
                observable_at(reference, name, t),
                observable_at(candidate, name, t),
                name=quantity,
            )
            rows.append(_row(quantity, res, full=None))
    for kind in reversed(reference.lump_names):
        ref = _durations(reference, kind, "reference")
        cand = _durations(candidate, kind, "candidate")
        full = compare_samples(ref, cand, name=f"{kind} durations")
        sub = compare_samples(ref, cand, subsample=subsample, rng=rng, name=f"{kind} durations")
        rows.append(_row(kind, sub, full=full))
    return pd.DataFrame(rows, columns=list(COLUMNS))


def _durations(run: SimulationRun, kind: str, role: str) -> np.ndarray:
    values = run.durations_of(kind)
    if values.size == 0:
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
    }


def noise_floor_table(
    full_a: SimulationRun,
    full_b: SimulationRun,
    times: Sequence[float] = PAPER_TIMES,
    subsample: int | None = PAPER_SUBSAMPLE,
    seed: int = 0,
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
    return comparison_table(full_a, full_b, times=times, subsample=subsample, seed=seed)


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
    # fmax ignores a NaN floor, falling back to the critical value
    threshold = np.fmax(
        out["ks_noise_floor"].to_numpy(float), out["ks_critical_05"].to_numpy(float)
    )
    out["within_noise"] = out["ks"].to_numpy(float) <= threshold
    return out


def speedup(
    reference: SimulationRun, candidate: SimulationRun, per_cell_step: bool = False
) -> float:
    """Reference wall time / candidate wall time (``manifest["wall_time_s"]``).

    With ``per_cell_step`` the ratio of throughputs ``cell_steps_per_s`` (candidate / reference)
    instead, which stays fair when the two runs simulated different numbers of cell-steps.
    """
    if per_cell_step:
        ref = _positive(reference, "cell_steps_per_s")
        cand = _positive(candidate, "cell_steps_per_s")
        return cand / ref
    return _positive(reference, "wall_time_s") / _positive(candidate, "wall_time_s")


def _positive(run: SimulationRun, key: str) -> float:
    value = run.manifest.get(key)
    if value is None:
        raise ArtefactError(f"manifest of {run.label} has no {key!r}; re-run `{MADE_BY}`")
    value = float(value)
    if not value > 0 or not math.isfinite(value):
        raise ArtefactError(f"manifest of {run.label} has {key}={value}; expected positive")
    return value


def mean_std_over_time(run: SimulationRun, name: str | None = None) -> pd.DataFrame:
    """Per record time: the mean, sample standard deviation (ddof=1) and count of observable
    ``name`` (default: the first one).

    Columns ``t``, ``mean``, ``std``, ``n``; ``std`` is NaN where only one cell is recorded.
    """
    name = name or run.observable_names[0]
    d = run.observables.assign(**{name: run.observables[name].astype(np.float64)})
    out = d.groupby("t", sort=True)[name].agg(["mean", "std", "count"]).reset_index()
    return out.rename(columns={"count": "n"}).astype({"t": float, "n": int})

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

The samples and the KS statistic live in :mod:`surrogate.evaluate.ks`, the runs in
:mod:`surrogate.evaluate.runs`; the names callers outside this package import from here stay
importable from here.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from surrogate.evaluate.ks import (
    KS_C_ALPHA_05,
    ExactSample,
    compare_distributions,
    compare_samples,
    ks_c_alpha,
    ks_critical_value,
    noise_threshold,
)
from surrogate.evaluate.runs import SimulationRun, load_run, mean_std_over_time

#: The paper's record times for the distance distributions (s).
PAPER_TIMES: tuple[float, ...] = (125.0, 250.0, 375.0, 500.0)

#: Durations subsample size used by the paper.
PAPER_SUBSAMPLE = 1000

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


#: the tables' names, and (from :mod:`~surrogate.evaluate.ks` and
#: :mod:`~surrogate.evaluate.runs`) the names the stages and kinds import from here
__all__ = [
    "COLUMNS",
    "ERROR_COLUMNS",
    "KS_C_ALPHA_05",
    "PAPER_SUBSAMPLE",
    "PAPER_TIMES",
    "ExactSample",
    "SimulationRun",
    "combine_with_noise_floor",
    "compare_distributions",
    "compare_samples",
    "comparison_table",
    "family_failures",
    "ks_critical_value",
    "load_run",
    "mean_std_over_time",
    "noise_floor_table",
    "noise_threshold",
    "observable_quantity",
]

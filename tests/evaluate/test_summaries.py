"""Evaluation from run summaries (histograms, moments, lattice histograms of durations) against
today's evaluation from the complete tables."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from matplotlib.figure import Figure
from scipy import stats

from surrogate.evaluate import runs as run_module
from surrogate.evaluate.figures import (
    plot_duration_histograms,
    plot_observable_histograms,
    plot_observable_over_time,
)
from surrogate.evaluate.ks import (
    BinnedSample,
    ExactSample,
    compare_distributions,
    compare_samples,
    ks_pvalue_asymptotic,
)
from surrogate.evaluate.runs import load_run, mean_std_over_time
from surrogate.evaluate.statistics import (
    COLUMNS,
    ERROR_COLUMNS,
    comparison_table,
    noise_floor_table,
)
from surrogate.fields import GaussianField
from surrogate.io import write_json
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import FullDecision, Simulator, simulate_population
from surrogate.simulate.recorders import HistogramGrid, bin_counts

DT = 0.05


def binned(values: np.ndarray, grid: HistogramGrid) -> BinnedSample:
    """``values`` summarised as the recorder does (float32 values, binned in float64)."""
    x = torch.as_tensor(values, dtype=torch.float32)
    counts = bin_counts(x, grid).numpy()
    x64 = x.double().numpy()
    return BinnedSample(grid.edges(), counts, float(x64.min()), float(x64.max()))


def as_recorded(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, dtype=np.float32).astype(np.float64)


# ----------------------------------------------------------------------------------------------
# exact samples with counts: the lattice histogram of durations


@pytest.mark.parametrize("n", [300, 30_000])  # scipy's exact p-value, and its asymptotic one
def test_counts_give_ks_2samp_exactly(n: int) -> None:
    rng = np.random.default_rng(1)
    a = rng.geometric(0.2, n) * DT  # durations: whole numbers of steps, many ties
    b = rng.geometric(0.21, n + 17) * DT
    ua, ca = np.unique(a, return_counts=True)
    ub, cb = np.unique(b, return_counts=True)
    got = compare_distributions(ExactSample.from_counts(ua, ca), ExactSample.from_counts(ub, cb))
    want = stats.ks_2samp(a, b)
    assert got["ks"] == want.statistic  # bit for bit: the same ECDFs
    assert got["ks_pvalue"] == want.pvalue
    assert got["wasserstein"] == pytest.approx(stats.wasserstein_distance(a, b), rel=1e-12)
    assert (got["n_a"], got["n_b"], got["ks_error"]) == (n, n + 17, 0.0)


def test_draws_from_counts_are_without_replacement_and_reproducible() -> None:
    values, counts = np.array([0.05, 0.1, 0.15, 1.0]), np.array([5, 1, 3000, 2])
    dist = ExactSample.from_counts(values[::-1], counts[::-1])  # any order in: sorted inside
    np.testing.assert_array_equal(dist.values, values)
    one = dist.draw(1000, np.random.default_rng(3))
    again = dist.draw(1000, np.random.default_rng(3))
    np.testing.assert_array_equal(one, again)
    # the same positions in the sorted expansion: a draw without replacement
    positions = np.random.default_rng(3).choice(dist.n, 1000, replace=False)
    np.testing.assert_array_equal(one, dist.expand()[positions])
    drawn = dict(zip(*np.unique(one, return_counts=True), strict=True))
    assert all(drawn.get(v, 0) <= c for v, c in zip(values, counts, strict=True))
    # a raw sample draws exactly what compare_samples draws (rng.choice on the values)
    raw = np.random.default_rng(0).exponential(size=5000)
    np.testing.assert_array_equal(
        ExactSample(raw).draw(1000, np.random.default_rng(9)),
        np.random.default_rng(9).choice(raw, 1000, replace=False),
    )
    # all values, and no random number used, when the sample is no larger than the draw
    rng = np.random.default_rng(5)
    np.testing.assert_array_equal(ExactSample.from_counts([1.0], [7]).draw(10, rng), [1.0] * 7)
    assert rng.random() == np.random.default_rng(5).random()


# ----------------------------------------------------------------------------------------------
# binned observables: a lower bound of the exact KS, and a stated error


@pytest.mark.parametrize("case", range(12))
def test_binned_ks_and_wasserstein_bracket_the_exact_values(case: int) -> None:
    rng = np.random.default_rng(case)
    n_a, n_b = rng.integers(50, 3000, 2)
    loc = rng.uniform(0.5, 3.0)
    spread = [0.003, 0.05, 0.8][case % 3]  # narrower than, near and far wider than a bin
    a = as_recorded(np.abs(loc + spread * rng.standard_normal(n_a)))
    b = as_recorded(np.abs(loc + 0.3 * spread + spread * rng.standard_gamma(2.0, n_b) / 2))
    if case % 4 == 0:
        b[:5] = [-1.0, 30.0, 25.0, 20.0, 0.0]  # outside the grid, at its ends
    grid = HistogramGrid.from_range(0.0, 20.0, 0.002 * (1 + case % 2))
    exact = compare_samples(a, b)
    for pair in ((binned(a, grid), binned(b, grid)), (ExactSample(a), binned(b, grid))):
        got = compare_distributions(*pair)
        assert got["ks"] <= exact["ks"] + 1e-12
        assert exact["ks"] <= got["ks"] + got["ks_error"] + 1e-12
        assert abs(got["wasserstein"] - exact["wasserstein"]) <= got["wasserstein_error"] + 1e-12
        assert (got["n_a"], got["n_b"]) == (n_a, n_b)
        assert got["ks_pvalue"] == ks_pvalue_asymptotic(got["ks"], n_a, n_b)
    # the error bound is what the grid allows: at most the largest bin mass (of either sample,
    # outer bins included) on either side of an interval, so a wide spread makes it small
    ba, bb = binned(a, grid), binned(b, grid)
    got = compare_distributions(ba, bb)
    biggest = max((ba.counts / ba.n).max(), (bb.counts / bb.n).max())
    assert got["ks_error"] <= 2 * biggest + 1e-12
    inside = 1 - (ba.counts[[0, -1]].sum() / ba.n + bb.counts[[0, -1]].sum() / bb.n)
    if inside == 1:
        assert got["wasserstein_error"] == pytest.approx(grid.width, rel=1e-9)


def test_grids_that_share_edges_compare_on_the_common_ones() -> None:
    rng = np.random.default_rng(4)
    a, b = as_recorded(rng.uniform(1, 3, 4000)), as_recorded(rng.uniform(1.1, 3, 4000))
    fine, coarse = HistogramGrid(0.0, 0.001, 20_000), HistogramGrid(0.0, 0.004, 5_000)
    mixed = compare_distributions(binned(a, fine), binned(b, coarse))
    same = compare_distributions(binned(a, coarse), binned(b, coarse))
    assert mixed["ks"] == pytest.approx(same["ks"], abs=1e-12)
    exact = compare_samples(a, b)["ks"]
    assert mixed["ks"] <= exact <= mixed["ks"] + mixed["ks_error"]


def test_binned_samples_cannot_be_subsampled() -> None:
    g = HistogramGrid(0.0, 1.0, 4)
    with pytest.raises(ValueError, match="cannot be subsampled"):
        compare_distributions(binned(np.ones(3), g), binned(np.ones(3), g), subsample=2)
    with pytest.raises(ValueError, match="first sample"):
        compare_distributions(ExactSample(np.array([])), binned(np.ones(3), g))


# ----------------------------------------------------------------------------------------------
# real runs small enough to have both: summaries vs complete tables


def simulate(out: Path, seed: int, n: int, t_end: float, **kw) -> Path:
    """A full-model E. coli run (gaussian field) with a manifest as the simulate stage's."""
    torch.manual_seed(seed)
    model = EcoliModel()
    sim = Simulator(model, FullDecision(model.internal), GaussianField(), DT)
    summary = simulate_population(sim, n, t_end, out, progress=False, **kw)
    write_json(out / "manifest.json", {"seed": seed, "lump_names": ["tumble", "run"],
                                       "n_cells": n, **summary.recording})  # fmt: skip
    return out


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    """Two full-model runs (noise-floor pair) of 3,000 cells for 40 s, complete tables kept."""
    root = tmp_path_factory.mktemp("runs")
    kw = {"n": 3000, "t_end": 40.0, "record_cells": 3000, "durations": "all"}
    return simulate(root / "a", 1, **kw), simulate(root / "b", 2, **kw)


TIMES = (10.0, 20.0, 30.0, 40.0)


def test_summaries_agree_with_the_complete_tables(pair: tuple[Path, Path]) -> None:
    tables = [load_run(p, source="tables") for p in pair]
    summaries = [load_run(p, source="summaries") for p in pair]
    auto = [load_run(p) for p in pair]
    assert tables[0].moments is None and summaries[0].moments is not None
    old = comparison_table(*tables, times=TIMES, errors=True)
    new = comparison_table(*summaries, times=TIMES, errors=True)
    assert list(new.columns) == [*COLUMNS, *ERROR_COLUMNS]
    assert list(new["quantity"]) == [f"distance_t{t:g}" for t in TIMES] + ["run", "tumble"]
    o, s = old.set_index("quantity"), new.set_index("quantity")
    for q in s.index[:4]:  # distances: binned vs every value
        assert s.loc[q, "ks"] <= o.loc[q, "ks"] <= s.loc[q, "ks"] + s.loc[q, "ks_binning_error"]
        assert abs(s.loc[q, "ks"] - o.loc[q, "ks"]) <= 0.005  # the target, met on these runs
        w_err = s.loc[q, "wasserstein_binning_error"]
        assert w_err == pytest.approx(0.002)  # a 0.002 mm grid, nothing outside it
        assert abs(s.loc[q, "wasserstein"] - o.loc[q, "wasserstein"]) <= w_err
        assert (s.loc[q, "n_reference"], s.loc[q, "n_candidate"]) == (3000, 3000)
        # p-values: the asymptotic p of the binned KS, between those of its bounds, and within
        # what the KS difference allows of the exact p-value (ks_2samp's exact method at n=3000)
        p_hi = ks_pvalue_asymptotic(s.loc[q, "ks"], 3000, 3000)
        p_lo = ks_pvalue_asymptotic(s.loc[q, "ks"] + s.loc[q, "ks_binning_error"], 3000, 3000)
        assert s.loc[q, "ks_pvalue"] == p_hi and p_lo <= o.loc[q, "ks_pvalue"] + 0.01
        assert o.loc[q, "ks_pvalue"] <= p_hi + 0.01
    for q in ("run", "tumble"):  # durations: the full sample exactly, from the lattice
        assert s.loc[q, "ks_full"] == o.loc[q, "ks_full"]
        assert s.loc[q, "ks_pvalue_full"] == o.loc[q, "ks_pvalue_full"]
        assert s.loc[q, "n_reference"] == o.loc[q, "n_reference"] == 1000
        assert s.loc[q, "ks_binning_error"] == 0.0
    # auto: every cell's value (exact), durations from the lattice
    a = comparison_table(*auto, times=TIMES).set_index("quantity")
    pd.testing.assert_frame_equal(a.iloc[:4], o.iloc[:4, : len(COLUMNS) - 1])
    pd.testing.assert_frame_equal(a.iloc[4:], s.iloc[4:, : len(COLUMNS) - 1])
    # the noise floor is computed the same way
    floor = noise_floor_table(*summaries, times=TIMES)
    pd.testing.assert_frame_equal(floor, new[list(COLUMNS)])


def test_duration_subsamples_from_counts_and_tables_are_the_same_statistic(
    pair: tuple[Path, Path],
) -> None:
    """The 1,000-duration KS is a random variable: drawn from the lattice (sorted positions) or
    from the table (table order) it has the same law. Over 150 seeds the two means agree within
    4.5 standard errors of their difference (the draws are independent given the runs)."""
    runs = {src: [load_run(p, source=src) for p in pair] for src in ("tables", "summaries")}
    ks = {src: [] for src in runs}
    for src, (ra, rb) in runs.items():
        da, db = ra.duration_distribution("run"), rb.duration_distribution("run")
        for seed in range(150):
            rng = np.random.default_rng(seed)
            ks[src].append(compare_distributions(da, db, subsample=1000, rng=rng)["ks"])
    x, y = np.array(ks["tables"]), np.array(ks["summaries"])
    assert not np.array_equal(x, y)
    se = math.sqrt(x.var(ddof=1) / x.size + y.var(ddof=1) / y.size)
    assert abs(x.mean() - y.mean()) < 4.5 * se


def test_a_subsampled_run_is_evaluated_over_all_cells(tmp_path: Path, pair) -> None:
    """The same simulation (same seed) recorded with 150 of 3,000 cells: its statistics are
    those of all cells (moments exact, histograms identical), only its tables are smaller."""
    sub = simulate(tmp_path / "sub", 1, n=3000, t_end=40.0, record_cells=150)
    run, full = load_run(sub), load_run(pair[0])
    assert run.recording["observable_cells"] == 150 and run.observables["cell"].nunique() == 150
    assert run.observables.groupby("t").size().eq(150).all()
    assert isinstance(run.observable_distribution("distance", 20.0), BinnedSample)
    assert isinstance(full.observable_distribution("distance", 20.0), ExactSample)
    ms, exact = mean_std_over_time(run), mean_std_over_time(load_run(pair[0], source="tables"))
    np.testing.assert_array_equal(ms["t"], exact["t"])
    np.testing.assert_array_equal(ms["n"], exact["n"])
    np.testing.assert_allclose(ms["mean"], exact["mean"], rtol=1e-12)
    np.testing.assert_allclose(ms["std"], exact["std"], rtol=1e-9)
    other = load_run(pair[1], source="summaries")
    pd.testing.assert_frame_equal(
        comparison_table(run, other, times=TIMES),
        comparison_table(load_run(pair[0], source="summaries"), other, times=TIMES),
    )
    # its durations: every duration in the lattice, the 150 cells' rows in the table
    assert run.mean_duration("run") == pytest.approx(float(full.durations_of("run").mean()))
    assert len(run.durations) < len(full.durations) / 10
    assert set(run.durations["cell"]) <= set(run.observables["cell"])
    with pytest.raises(ValueError, match="recorded 150 of 3000 cells"):
        load_run(sub, source="tables")


def test_figures_from_summaries(pair: tuple[Path, Path], tmp_path: Path) -> None:
    runs = [load_run(p, source="summaries") for p in pair]
    fig = plot_observable_histograms(*runs, times=TIMES)
    assert isinstance(fig, Figure) and len(fig.axes) == 4
    table = comparison_table(*runs, times=TIMES).set_index("quantity")
    for ax, t in zip(fig.axes, TIMES, strict=True):
        assert ax.get_title() == f"t = {t:g} s (KS {table.loc[f'distance_t{t:g}', 'ks']:.3f})"
        for stairs in ax.patches:  # densities on whole groups of grid bins: they integrate to 1
            values, edges = stairs.get_data().values, stairs.get_data().edges
            assert np.sum(values * np.diff(edges)) == pytest.approx(1.0, abs=1e-9)
            np.testing.assert_allclose(edges / 0.002, np.round(edges / 0.002), atol=1e-6)
    lines = plot_observable_over_time(*runs).axes[0].get_lines()
    np.testing.assert_allclose(lines[0].get_ydata(), mean_std_over_time(runs[0])["mean"])
    # durations: the lattice gives the figure the values give
    fig = plot_duration_histograms(*runs)
    assert [ax.get_title() for ax in fig.axes] == ["run durations", "tumble durations"]
    ax = fig.axes[0]
    data = ax.patches[0].get_data()
    values = runs[0].durations_of("run")
    counts, _ = np.histogram(values, bins=data.edges)
    np.testing.assert_allclose(data.values, counts / (values.size * np.diff(data.edges)))
    assert ax.get_legend().get_texts()[0].get_text() == f"full (n={values.size})"


def test_load_run_sources_and_expansion_limit(pair: tuple[Path, Path], monkeypatch) -> None:
    with pytest.raises(ValueError, match="source must be one of"):
        load_run(pair[0], source="best")
    run = load_run(pair[0])
    assert run.lump_names == ("tumble", "run") and run.observable_names == ["distance"]
    assert run.record_times[-1] == 40.0 and run.recording["durations"] == "all"
    n_runs = run.duration_distribution("run").n
    assert run.durations_of("run").size == n_runs
    assert run.mean_duration("run") == pytest.approx(run.durations_of("run").mean(), rel=1e-12)
    monkeypatch.setattr(run_module, "EXPAND_LIMIT", n_runs - 1)
    with pytest.raises(ValueError, match="duration_distribution"):
        run.durations_of("run")
    old = load_run(pair[0], source="tables")
    assert old.durations_of("tumble").size == run.duration_distribution("tumble").n

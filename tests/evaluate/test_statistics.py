"""Tests of surrogate.evaluate.statistics."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from surrogate.errors import ArtefactError, MissingArtefactError, NumericalError
from surrogate.evaluate.ks import compare_samples, ks_critical_value
from surrogate.evaluate.runs import (
    SimulationRun,
    default_times,
    distances_at,
    load_run,
    mean_std_over_time,
    observable_at,
)
from surrogate.evaluate.statistics import (
    COLUMNS,
    combine_with_noise_floor,
    comparison_table,
    noise_floor_table,
    observable_quantity,
)
from surrogate.io import write_json, write_parquet

TIMES = (5.0, 10.0, 15.0, 20.0)


def write_synthetic_run(
    directory: Path,
    seed: int,
    n_cells: int = 50,
    t_end: float = 20.0,
    dt: float = 1.0,
    shift: float = 0.0,
    n_durations: int = 3000,
    wall_time_s: float = 10.0,
    extra_observable: bool = False,
    lump_names: tuple[str, str] | None = ("tumble", "run"),
) -> Path:
    """Write observables.parquet, durations.parquet and manifest.json like a simulation run.

    ``extra_observable`` adds a second observable ``speed`` (after ``distance``);
    ``lump_names`` renames the duration kinds (tumble, run) and records them in the manifest
    (None: a run that records none, as runs did before they named their lumps).
    """
    rng = np.random.default_rng(seed)
    times = np.arange(0.0, t_end + dt / 2, dt)
    t = np.repeat(times, n_cells)
    cell = np.tile(np.arange(n_cells, dtype=np.int64), times.size)
    # cells drift towards the peak, with spread; distances must stay non-negative
    distance = np.abs(2.0 - 0.05 * t + shift + 0.3 * rng.standard_normal(t.size))
    observables = pd.DataFrame(
        {"t": t.astype(np.float64), "cell": cell, "distance": distance.astype(np.float32)}
    )
    if extra_observable:
        observables["speed"] = (0.02 + shift * 0.01 * t + 0.005 * rng.random(t.size)).astype(
            np.float32
        )
    kinds = np.array(["run"] * n_durations + ["tumble"] * (n_durations // 2))
    scale = np.where(kinds == "run", 0.5 * (1 + shift), 0.2)
    manifest_extra = {}
    if lump_names is not None:
        kinds = np.where(kinds == "run", lump_names[1], lump_names[0])
        manifest_extra["lump_names"] = list(lump_names)
    durations = pd.DataFrame(
        {
            "kind": kinds,
            "duration": rng.exponential(scale),
            "cell": rng.integers(0, n_cells, kinds.size).astype(np.int64),
            "t_end": rng.uniform(0, t_end, kinds.size),
        }
    )
    write_parquet(directory / "observables.parquet", observables)
    write_parquet(directory / "durations.parquet", durations)
    write_json(
        directory / "manifest.json",
        {
            "wall_time_s": wall_time_s,
            "seed": seed,
            "config": {"n_cells": n_cells, "t_end": t_end},
            "cell_steps_per_s": n_cells * t_end / 0.05 / wall_time_s,
            **manifest_extra,
        },
    )
    return directory


@pytest.fixture
def runs(tmp_path: Path) -> tuple[SimulationRun, SimulationRun]:
    """A reference run and a slightly shifted candidate run, loaded from disk."""
    ref = load_run(write_synthetic_run(tmp_path / "ref", seed=1, wall_time_s=80.0))
    cand = load_run(write_synthetic_run(tmp_path / "cand", seed=2, shift=0.2, wall_time_s=10.0))
    return ref, cand


# ----------------------------------------------------------------------------------------------
# compare_samples


def test_compare_samples_hand_checkable() -> None:
    assert compare_samples([1, 2, 3], [1, 2, 3])["ks"] == 0.0
    assert compare_samples([0, 0], [1, 1])["ks"] == 1.0
    assert compare_samples([0.0], [1.0])["wasserstein"] == 1.0
    res = compare_samples([1, 2, 3], [4, 5])
    assert (res["n_a"], res["n_b"]) == (3, 2)
    assert res["ks_critical_05"] == pytest.approx(1.358 * math.sqrt(5 / 6))


def test_compare_samples_matches_scipy() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=200), rng.gamma(2.0, size=150)
    res = compare_samples(a, b)
    ks = stats.ks_2samp(a, b)
    assert res["ks"] == ks.statistic
    assert res["ks_pvalue"] == ks.pvalue
    assert res["wasserstein"] == stats.wasserstein_distance(a, b)
    assert (res["n_a"], res["n_b"]) == (200, 150)


def test_subsample_without_replacement_and_reproducible() -> None:
    a = np.arange(5000, dtype=float)  # distinct values: a duplicate would reveal replacement
    b = np.arange(3000, dtype=float) + 0.5
    r1 = compare_samples(a, b, subsample=1000, rng=np.random.default_rng(7))
    r2 = compare_samples(a, b, subsample=1000, rng=np.random.default_rng(7))
    r3 = compare_samples(a, b, subsample=1000, rng=np.random.default_rng(8))
    assert r1 == r2
    assert r1 != r3
    assert (r1["n_a"], r1["n_b"]) == (1000, 1000)
    assert r1["ks_critical_05"] == pytest.approx(ks_critical_value(1000, 1000))

    # the same draws by hand: choice without replacement, first from a then from b
    rng = np.random.default_rng(7)
    sa = rng.choice(a, 1000, replace=False)
    sb = rng.choice(b, 1000, replace=False)
    assert np.unique(sa).size == 1000
    assert r1["ks"] == stats.ks_2samp(sa, sb).statistic


def test_subsample_larger_than_sample_uses_all() -> None:
    res = compare_samples(np.arange(10.0), np.arange(20.0), subsample=1000)
    assert (res["n_a"], res["n_b"]) == (10, 20)


def test_ks_against_critical_value() -> None:
    rng = np.random.default_rng(0)
    same = compare_samples(rng.normal(size=1000), rng.normal(size=1000))
    shifted = compare_samples(rng.normal(size=1000), rng.normal(0.5, 1.0, size=1000))
    assert same["ks"] < same["ks_critical_05"]
    assert shifted["ks"] > shifted["ks_critical_05"]


def test_compare_samples_errors_name_quantity() -> None:
    with pytest.raises(ValueError, match="tumble durations"):
        compare_samples([], [1.0], name="tumble durations")
    with pytest.raises(NumericalError, match="distances"):
        compare_samples([1.0, np.nan], [1.0], name="distances")
    with pytest.raises(ValueError, match="subsample"):
        compare_samples([1.0], [1.0], subsample=0)


# ----------------------------------------------------------------------------------------------
# runs


def test_load_run_missing_names_command(tmp_path: Path) -> None:
    with pytest.raises(MissingArtefactError, match=r"scripts/simulate\.py"):
        load_run(tmp_path)


def test_load_run_rejects_missing_columns(tmp_path: Path) -> None:
    write_synthetic_run(tmp_path, seed=0)
    # no observable column at all
    write_parquet(tmp_path / "observables.parquet", pd.DataFrame({"t": [0.0], "cell": [0]}))
    with pytest.raises(ArtefactError, match=r"observables\.parquet has no observations"):
        load_run(tmp_path)
    # no time column
    write_parquet(tmp_path / "observables.parquet", pd.DataFrame({"cell": [0], "distance": [1.0]}))
    with pytest.raises(ArtefactError, match=r"observables\.parquet lacks column\(s\) \['t'\]"):
        load_run(tmp_path)
    write_synthetic_run(tmp_path, seed=0)
    write_parquet(tmp_path / "durations.parquet", pd.DataFrame({"duration": [1.0]}))
    with pytest.raises(ArtefactError, match=r"durations\.parquet lacks column\(s\) \['kind'\]"):
        load_run(tmp_path)


def test_load_run_reads_the_old_file_name_no_more(tmp_path: Path) -> None:
    write_synthetic_run(tmp_path, seed=0)
    (tmp_path / "observables.parquet").rename(tmp_path / "distances.parquet")
    with pytest.raises(MissingArtefactError, match=r"observables\.parquet"):
        load_run(tmp_path)


def test_run_observables_and_lumps(tmp_path: Path) -> None:
    run = load_run(write_synthetic_run(tmp_path / "a", seed=0, extra_observable=True))
    assert run.observable_names == ["distance", "speed"]
    assert run.lump_names == ("tumble", "run")  # as the manifest records them
    assert run.durations_of("run").size == 3000 and run.durations_of("tumble").size == 1500
    with pytest.raises(ValueError, match="duration kind"):
        run.durations_of("swim")
    other = load_run(
        write_synthetic_run(tmp_path / "b", seed=0, n_durations=40, lump_names=("off", "on"))
    )
    assert other.lump_names == ("off", "on")
    assert other.durations_of("on").size == 40 and other.durations_of("off").size == 20
    with pytest.raises(ValueError, match="duration kind"):
        other.durations_of("run")
    # no lump names are assumed (the engine knows no run and tumble): a run must record them
    unnamed = load_run(write_synthetic_run(tmp_path / "c", seed=0, n_durations=40, lump_names=None))
    with pytest.raises(ArtefactError, match="does not name its lumps"):
        unnamed.lump_names


def test_observable_at(tmp_path: Path) -> None:
    run = load_run(write_synthetic_run(tmp_path, seed=0, extra_observable=True))
    for name in ("distance", "speed"):
        expected = run.observables.loc[run.observables["t"] == 7.0, name].to_numpy(np.float64)
        got = observable_at(run, name, 7.2)
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, expected)
    assert not np.array_equal(observable_at(run, "speed", 7.0), observable_at(run, "distance", 7.0))
    np.testing.assert_array_equal(distances_at(run, 7.0), observable_at(run, "distance", 7.0))
    assert observable_quantity("speed", 125.0) == "speed_t125"
    assert observable_quantity("distance", 2.5) == "distance_t2.5"


def test_distances_at_nearest_and_out_of_range(runs: tuple[SimulationRun, SimulationRun]) -> None:
    ref, _ = runs
    obs = ref.observables
    expected = obs.loc[obs["t"] == 10.0, "distance"].to_numpy(np.float64)
    np.testing.assert_array_equal(distances_at(ref, 10.0), expected)
    np.testing.assert_array_equal(distances_at(ref, 10.4), expected)  # within half of dt=1
    assert distances_at(ref, 10.0).dtype == np.float64
    with pytest.raises(ValueError, match=r"t=125.*0\.\.20"):
        distances_at(ref, 125.0)
    with pytest.raises(ValueError, match=r"t=20\.6"):
        distances_at(ref, 20.6)


def test_default_times(runs: tuple[SimulationRun, SimulationRun]) -> None:
    assert default_times(runs[0]) == TIMES


def test_comparison_table_rows_columns_and_values(
    runs: tuple[SimulationRun, SimulationRun],
) -> None:
    ref, cand = runs
    table = comparison_table(ref, cand, times=TIMES, subsample=1000, seed=0)
    assert list(table.columns) == list(COLUMNS)
    assert list(table["quantity"]) == [
        "distance_t5",
        "distance_t10",
        "distance_t15",
        "distance_t20",
        "run",
        "tumble",
    ]
    by_q = table.set_index("quantity")

    a = ref.observables.loc[ref.observables["t"] == 15.0, "distance"].to_numpy(np.float64)
    b = cand.observables.loc[cand.observables["t"] == 15.0, "distance"].to_numpy(np.float64)
    row = by_q.loc["distance_t15"]
    assert row["ks"] == stats.ks_2samp(a, b).statistic
    assert row["ks_pvalue"] == stats.ks_2samp(a, b).pvalue
    assert row["wasserstein"] == stats.wasserstein_distance(a, b)
    assert (row["n_reference"], row["n_candidate"]) == (50, 50)
    assert np.isnan(row["ks_full"]) and np.isnan(row["ks_pvalue_full"])

    # durations: full sample and the documented subsample draw order (run ref, run cand, ...)
    rng = np.random.default_rng(0)
    run_ref, run_cand = ref.durations_of("run"), cand.durations_of("run")
    sub_ref = rng.choice(run_ref, 1000, replace=False)
    sub_cand = rng.choice(run_cand, 1000, replace=False)
    row = by_q.loc["run"]
    assert row["ks"] == stats.ks_2samp(sub_ref, sub_cand).statistic
    assert row["wasserstein"] == stats.wasserstein_distance(sub_ref, sub_cand)
    assert row["ks_full"] == stats.ks_2samp(run_ref, run_cand).statistic
    assert row["ks_pvalue_full"] == stats.ks_2samp(run_ref, run_cand).pvalue
    assert (row["n_reference"], row["n_candidate"]) == (1000, 1000)
    assert by_q.loc["tumble", "n_reference"] == 1000  # 1500 tumbles subsampled to 1000

    # reproducible with the seed, different with another
    again = comparison_table(ref, cand, times=TIMES, subsample=1000, seed=0)
    pd.testing.assert_frame_equal(table, again)
    other = comparison_table(ref, cand, times=TIMES, subsample=1000, seed=1)
    assert other.set_index("quantity").loc["run", "ks"] != row["ks"]


def test_comparison_table_out_of_range_time(runs: tuple[SimulationRun, SimulationRun]) -> None:
    with pytest.raises(ValueError, match="t=125"):
        comparison_table(*runs)  # the paper's 125..500 s are outside these 20 s runs


def test_comparison_table_empty_durations(runs: tuple[SimulationRun, SimulationRun]) -> None:
    ref, cand = runs
    no_tumbles = SimulationRun(
        observables=cand.observables,
        durations=cand.durations[cand.durations["kind"] == "run"],
        manifest=cand.manifest,
    )
    with pytest.raises(ValueError, match="tumble durations of the candidate"):
        comparison_table(ref, no_tumbles, times=TIMES)


def test_noise_floor_and_combination(tmp_path: Path) -> None:
    full_a = load_run(write_synthetic_run(tmp_path / "a", seed=1))
    full_b = load_run(write_synthetic_run(tmp_path / "b", seed=2))
    abstract = load_run(write_synthetic_run(tmp_path / "c", seed=3, shift=0.5))
    floor = noise_floor_table(full_a, full_b, times=TIMES)
    pd.testing.assert_frame_equal(floor, comparison_table(full_a, full_b, times=TIMES))

    table = comparison_table(full_a, abstract, times=TIMES)
    combined = combine_with_noise_floor(table, floor)
    assert list(combined["quantity"]) == list(table["quantity"])
    np.testing.assert_array_equal(combined["ks_noise_floor"], floor["ks"])
    np.testing.assert_array_equal(combined["wasserstein_noise_floor"], floor["wasserstein"])
    threshold = np.maximum(floor["ks"], table["ks_critical_05"])
    np.testing.assert_array_equal(combined["within_noise"], table["ks"] <= threshold)
    # the shifted model is clearly outside noise for distances and runs (tumbles are unshifted)
    by_q = combined.set_index("quantity")
    assert not by_q.loc["distance_t10", "within_noise"]
    assert not by_q.loc["run", "within_noise"]
    assert by_q.loc["tumble", "within_noise"]

    # a quantity missing from the floor is judged against the critical value alone
    partial = combine_with_noise_floor(table, floor[floor["quantity"] != "tumble"])
    row = partial.set_index("quantity").loc["tumble"]
    assert np.isnan(row["ks_noise_floor"])
    assert row["within_noise"] == (row["ks"] <= row["ks_critical_05"])


def test_noise_floor_warns_on_same_seed(tmp_path: Path) -> None:
    a = load_run(write_synthetic_run(tmp_path / "a", seed=1))
    b = load_run(write_synthetic_run(tmp_path / "b", seed=1))
    with pytest.warns(UserWarning, match="same seed"):
        floor = noise_floor_table(a, b, times=TIMES)
    # identical runs: zero on all-cell distances and full duration samples (the two duration
    # subsamples are independent draws, so those differ)
    assert (floor["ks"].iloc[:4] == 0).all()
    assert (floor["ks_full"].iloc[4:] == 0).all()


def test_mean_std_over_time(runs: tuple[SimulationRun, SimulationRun]) -> None:
    ref, _ = runs
    ms = mean_std_over_time(ref)
    assert list(ms.columns) == ["t", "mean", "std", "n"]
    assert ms["t"].tolist() == [float(t) for t in range(21)]
    assert (ms["n"] == 50).all()
    at5 = ref.observables.loc[ref.observables["t"] == 5.0, "distance"].to_numpy(np.float64)
    row = ms.set_index("t").loc[5.0]
    assert row["mean"] == pytest.approx(at5.mean())
    assert row["std"] == pytest.approx(at5.std(ddof=1))
    pd.testing.assert_frame_equal(mean_std_over_time(ref, "distance"), ms)


def test_mean_std_over_time_of_a_named_observable(tmp_path: Path) -> None:
    run = load_run(write_synthetic_run(tmp_path, seed=0, n_cells=3, extra_observable=True))
    ms = mean_std_over_time(run, "speed")
    at5 = run.observables.loc[run.observables["t"] == 5.0, "speed"].to_numpy(np.float64)
    row = ms.set_index("t").loc[5.0]
    assert row["n"] == 3
    assert row["mean"] == pytest.approx(at5.mean(), rel=1e-12)
    assert row["std"] == pytest.approx(at5.std(ddof=1), rel=1e-12)
    assert row["mean"] != pytest.approx(mean_std_over_time(run).set_index("t").loc[5.0, "mean"])
    one = SimulationRun(run.observables[run.observables["cell"] == 0], run.durations)
    assert mean_std_over_time(one, "speed")["std"].isna().all()  # one cell: no spread


def test_comparison_table_is_generic_over_observables_and_lumps(tmp_path: Path) -> None:
    kw = {"extra_observable": True, "lump_names": ("off", "on"), "n_durations": 400}
    ref = load_run(write_synthetic_run(tmp_path / "ref", seed=1, **kw))
    cand = load_run(write_synthetic_run(tmp_path / "cand", seed=2, shift=0.3, **kw))
    table = comparison_table(ref, cand, times=(5.0, 20.0), subsample=100, seed=0)
    # every observable at every time, then the lumps with phi = 1 first
    assert list(table["quantity"]) == [
        "distance_t5", "distance_t20", "speed_t5", "speed_t20", "on", "off",
    ]  # fmt: skip
    by_q = table.set_index("quantity")
    a, b = observable_at(ref, "speed", 20.0), observable_at(cand, "speed", 20.0)
    assert by_q.loc["speed_t20", "ks"] == stats.ks_2samp(a, b).statistic
    assert by_q.loc["speed_t20", "wasserstein"] == stats.wasserstein_distance(a, b)
    assert np.isnan(by_q.loc["speed_t20", "ks_full"])
    on_ref, on_cand = ref.durations_of("on"), cand.durations_of("on")
    assert by_q.loc["on", "ks_full"] == stats.ks_2samp(on_ref, on_cand).statistic
    # the subsample draws: phi = 1 (on) first, reference then candidate
    rng = np.random.default_rng(0)
    sub_ref = rng.choice(on_ref, 100, replace=False)
    sub_cand = rng.choice(on_cand, 100, replace=False)
    assert by_q.loc["on", "ks"] == stats.ks_2samp(sub_ref, sub_cand).statistic
    assert (by_q.loc["off", "n_reference"], by_q.loc["off", "n_candidate"]) == (100, 100)


# ---------------------------------------------------------------------------------------------
# the standard error of a mean segment duration, cells as clusters


def _population(rng: np.random.Generator, n_cells: int, cv: float, t_end: float = 200.0):
    """Each cell's segments: exponential durations with a mean of its own (log-normal across
    cells with coefficient of variation ``cv``), back to back until ``t_end``."""
    durations, cells = [], []
    scale = rng.lognormal(np.log(0.5), cv, n_cells) if cv else np.full(n_cells, 0.5)
    for cell, mean in enumerate(scale):  # the same draws as a frame per cell, one frame made
        d = rng.exponential(mean, int(2 * t_end / mean))
        d = d[np.cumsum(d) < t_end]
        durations.append(d)
        cells.append(np.full(len(d), cell))
    return pd.DataFrame({"kind": "run", "duration": np.concatenate(durations),
                         "cell": np.concatenate(cells)})  # fmt: skip


def _se(durations: pd.DataFrame, n_cells: int) -> float | None:
    run = SimpleNamespace(durations=durations, manifest={"n_cells": n_cells})
    return SimulationRun.mean_duration_se(run, "run")  # type: ignore[arg-type]


def test_the_mean_durations_error_is_calibrated_when_cells_differ() -> None:
    """Over 300 populations of 100 cells whose mean durations differ by 30 %, the spread of the
    mean duration is what the error says (the naive error of iid segments is ~3x too small);
    the chi-square bound on a standard deviation from 300 draws is +-8 % at 3 sigma."""
    rng = np.random.default_rng(0)
    means, errors, naive = [], [], []
    for _ in range(300):
        d = _population(rng, 100, cv=0.3)
        means.append(d["duration"].mean())
        errors.append(_se(d, 100))
        naive.append(d["duration"].std() / np.sqrt(len(d)))
    spread = float(np.std(means, ddof=1))
    assert abs(float(np.sqrt(np.mean(np.square(errors)))) / spread - 1) < 0.12
    assert float(np.mean(naive)) < 0.6 * spread


def test_the_error_of_alike_cells_is_the_iid_one_and_a_subsample_scales_it() -> None:
    rng = np.random.default_rng(1)
    d = _population(rng, 400, cv=0.0)
    naive = d["duration"].std() / np.sqrt(len(d))
    assert abs(_se(d, 400) / naive - 1) < 0.1  # segments of alike cells: ~iid
    assert _se(d, 1600) == pytest.approx(_se(d, 400) / 2)  # 400 of 1,600 cells recorded
    assert _se(d.iloc[:0], 400) is None


def test_family_failures_count_a_difference_at_the_reports_level() -> None:
    """Bonferroni over every comparison of the tables: with 18 tests at n = 20,000 each, a KS
    of 0.016 (above the per-test critical 0.0136) is not counted, 0.019 (above 1.81 x 0.01)
    is; a floor above the critical value still sets the bar; a table without floors counts
    nothing and adds no comparison."""
    from surrogate.evaluate.ks import ks_c_alpha, ks_critical_value
    from surrogate.evaluate.statistics import family_failures

    def table(ks, floors):
        n = len(ks)
        return pd.DataFrame({"quantity": [f"q{i}" for i in range(n)], "ks": ks,
                             "n_reference": [20_000] * n, "n_candidate": [20_000] * n,
                             "ks_noise_floor": floors, "within_noise": [True] * n})  # fmt: skip

    per_test = ks_critical_value(20_000, 20_000)
    family = ks_critical_value(20_000, 20_000, ks_c_alpha(0.05 / 18))
    assert per_test < 0.016 < family < 0.019
    tables = {
        "a": table([0.016] + [0.005] * 5, [0.009] * 6),
        "b": table([0.019] + [0.005] * 5, [0.009] * 6),
        "c": table([0.020] + [0.005] * 5, [0.025] + [0.009] * 5),
        "no floor": pd.DataFrame({"quantity": ["x"], "ks": [0.5]}),
    }
    failures, m = family_failures(tables)
    assert m == 18
    assert failures == {"a": [], "b": ["q0"], "c": [], "no floor": []}

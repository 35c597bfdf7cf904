"""RunRecorder: histograms, moments and a seeded cell subsample of the observables; the exact
lattice histogram of durations; small runs keep exactly the complete tables they always had."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.fields import GaussianField
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision, Simulator, simulate_population
from surrogate.simulate import recorders as rec
from surrogate.simulate.recorders import (
    DURATION_HISTOGRAM,
    DURATIONS,
    HISTOGRAMS,
    MOMENTS,
    OBSERVABLES,
    HistogramGrid,
    RecorderSpec,
    RunRecorder,
    bin_counts,
    choose_cells,
    grid_from_spec,
    read_metadata,
)

DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]
LUMPS = ("tumble", "run")
DT = 0.05


def segment_ends(n_cells: int, n_steps: int, seed: int, rate: float = 0.15) -> np.ndarray:
    """Synthetic ``ended_length`` per step ``(n_steps, n_cells)`` int32: a few segment ends per
    step, of both signs, some longer than a block (the lattice must grow)."""
    rng = np.random.default_rng(seed)
    ends = rng.random((n_steps, n_cells)) < rate
    lengths = rng.geometric(0.3, size=(n_steps, n_cells)) * rng.choice([-1, 1], (n_steps, n_cells))
    lengths[rng.random((n_steps, n_cells)) < 0.01] *= 7  # a few long segments
    out = np.where(ends, lengths, 0)
    # a segment ending at step s lasts at most s + 1 steps (it began inside the loop)
    limit = np.arange(1, n_steps + 1)[:, None]
    return np.clip(out, -limit, limit).astype(np.int32)


def reference_rows(ends: np.ndarray, cells: np.ndarray | None = None) -> pd.DataFrame:
    """Today's durations table for ``ends``: every segment end in (step, cell) order, as the
    old DurationRecorder wrote it; ``cells`` keeps only those cells."""
    steps, cell = np.nonzero(ends)
    v = ends[steps, cell]
    table = pd.DataFrame(
        {
            "kind": np.where(v > 0, "run", "tumble").astype(object),
            "duration": np.abs(v).astype(np.float64) * DT,
            "cell": cell.astype(np.int64),
            "t_end": (steps + 1).astype(np.float64) * DT,
        }
    )
    if cells is not None:
        table = table[np.isin(table["cell"], cells)].reset_index(drop=True)
    return table


def observables_at(n_cells: int, k: int) -> dict[str, torch.Tensor]:
    """Deterministic observables at record k: distances spread over [0, 4) mm plus a few outside
    the default grid, and a second observable without a grid of its own."""
    g = torch.Generator().manual_seed(k)
    distance = 4.0 * torch.rand(n_cells, generator=g)
    distance[:3] = torch.tensor([-0.5, 25.0, 20.0])  # below lo, above hi, exactly hi
    speed = 0.02 + 0.001 * torch.randn(n_cells, generator=g)
    return {"distance": distance, "speed": speed}


#: the E. coli body's declared grid of its observable (mm)
DISTANCE_GRID = (0.0, 20.0, 0.002)


def record(
    out: Path,
    ends: np.ndarray,
    n_cells: int,
    every: int,
    device: str = "cpu",
    **kw,
) -> tuple[RunRecorder, dict, list[dict[str, torch.Tensor]]]:
    """Drive a recorder like simulate_population: observables at 0 and every ``every`` steps."""
    # the grids a body declares (histogram_grids) come in through histogram_spec
    kw = {"histogram_spec": {"distance": DISTANCE_GRID, "speed": (0.0, 0.04, 1e-4)}, **kw}
    r = RunRecorder(out, n_cells, DT, ("distance", "speed"), LUMPS, block_steps=every,
                    device=device, spec=RecorderSpec(**kw))  # fmt: skip
    seen = [observables_at(n_cells, 0)]
    r.record_observables(0.0, {k: v.to(device) for k, v in seen[0].items()})
    for s in range(ends.shape[0]):
        r.record_step(s, torch.as_tensor(ends[s], device=device))
        if (s + 1) % every == 0:
            seen.append(observables_at(n_cells, len(seen)))
            r.record_observables((s + 1) * DT, {k: v.to(device) for k, v in seen[-1].items()})
    return r, r.commit(), seen


# ----------------------------------------------------------------------------------------------
# grids


def test_grid_from_spec_and_bin_counts() -> None:
    grid = grid_from_spec((0.0, 20.0, 0.002))
    assert (grid.lo, grid.width, grid.n_bins) == (0.0, 0.002, 10_000)
    assert grid.hi == pytest.approx(20.0) and grid.edges()[[0, -1]].tolist() == [0.0, 20.0]
    assert grid_from_spec({"lo": -1, "hi": 1, "width": 0.3}).n_bins == 7  # last bin ends past hi
    assert grid_from_spec(grid) is grid
    for bad in ((1.0, 0.0, 0.1), (0.0, 1.0, 0.0), (0.0, 1.0, -1.0)):
        with pytest.raises(ValueError):
            grid_from_spec(bad)
    g = HistogramGrid(0.0, 0.5, 4)  # [0, 2) in 4 bins
    x = torch.tensor([-1e-9, 0.0, 0.49, 0.5, 1.999, 2.0, 7.0, -math.inf, math.inf, math.nan])
    # [below, b0, b1, b2, b3, above]; an edge value belongs to the bin it opens; NaN/+inf above
    assert bin_counts(x, g).tolist() == [2, 2, 1, 0, 1, 4]
    assert bin_counts(x.double(), g).sum().item() == x.numel()  # no value is lost


def test_fallback_grid_covers_the_first_values_and_warns_only_when_subsampled(tmp_path) -> None:
    values = np.array([2.0, 2.0, 2.0])
    grid = HistogramGrid.around(values)
    assert grid.lo < 2.0 < grid.hi and grid.hi - grid.lo == pytest.approx(
        40.0
    )  # 10 x scale 2 each side
    assert grid.n_bins == rec.FALLBACK_BINS
    ends = np.zeros((4, 30), np.int32)
    with pytest.warns(RuntimeWarning, match="no histogram grid given for observable 'speed'"):
        record(tmp_path / "a", ends, 30, 2, record_cells=10, histogram_spec={})
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every cell recorded: the grid is a detail, no warning
        _, facts, _ = record(
            tmp_path / "b", ends, 30, 2, histogram_spec={"distance": DISTANCE_GRID}
        )
    assert facts["histogram_grids"]["distance"] == [0.0, pytest.approx(20.0), 0.002]
    assert facts["histogram_grids"]["speed"] != [0.0, pytest.approx(0.04), 1e-4]  # from the data


def test_cell_subsample_is_seeded_uniform_and_complete_for_small_runs() -> None:
    np.testing.assert_array_equal(choose_cells(50, 50, 3), np.arange(50))
    np.testing.assert_array_equal(choose_cells(50, 80, 3), np.arange(50))
    a, b = choose_cells(50, 10, 3), choose_cells(50, 10, 3)
    np.testing.assert_array_equal(a, b)
    assert a.size == np.unique(a).size == 10 and np.all(np.diff(a) > 0)
    assert not np.array_equal(a, choose_cells(50, 10, 4))
    # every cell is recorded with probability 10/50: over 4,000 seeds each count is
    # Binomial(4000, 0.2) (mean 800, sd 25.3); 4.5 sd leaves ~3e-4 for the max of 50 cells
    hits = np.bincount(np.concatenate([choose_cells(50, 10, s) for s in range(4000)]), minlength=50)
    assert np.abs(hits - 800).max() < 4.5 * math.sqrt(4000 * 0.2 * 0.8)


# ----------------------------------------------------------------------------------------------
# small runs: the complete tables, as before


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", ["histogram", "all"])
def test_small_run_keeps_the_complete_tables(tmp_path, device: str, mode: str) -> None:
    n, steps, every = 40, 57, 10  # 57 steps: the last block is partial
    ends = segment_ends(n, steps, seed=1)
    _, facts, seen = record(tmp_path, ends, n, every, device, durations=mode)
    durations = pd.read_parquet(tmp_path / DURATIONS)
    pd.testing.assert_frame_equal(durations, reference_rows(ends))
    obs = pd.read_parquet(tmp_path / OBSERVABLES)
    assert list(obs.columns) == ["t", "cell", "distance", "speed"]
    assert obs["cell"].tolist() == list(range(n)) * len(seen)
    assert obs["t"].tolist() == [t for k in range(len(seen)) for t in [k * every * DT] * n]
    for k, values in enumerate(seen):
        rows = obs.iloc[k * n : (k + 1) * n]
        np.testing.assert_array_equal(rows["distance"], values["distance"].numpy())
    assert facts["n_durations"] == facts["duration_rows"] == len(durations)
    assert facts["observable_cells"] == facts["n_cells"] == n and facts["n_records"] == len(seen)
    assert set(facts["files"]) == {OBSERVABLES, DURATIONS, MOMENTS, HISTOGRAMS, DURATION_HISTOGRAM}
    assert facts["bytes"] == sum((tmp_path / f).stat().st_size for f in facts["files"])
    assert facts["final_means"]["distance"] == pytest.approx(
        float(seen[-1]["distance"].double().mean()), rel=1e-12
    )


def test_lattice_histogram_is_exact_whatever_the_block_size(tmp_path, monkeypatch) -> None:
    n, steps = 64, 120
    ends = segment_ends(n, steps, seed=2)
    expected = reference_rows(ends).groupby(["kind", "duration"]).size()
    results = []
    for name, buffer_bytes in (("big", 1 << 20), ("tiny", 4 * n * 3)):  # 30 or 3 rows per block
        monkeypatch.setattr(rec, "BUFFER_BYTES", buffer_bytes)
        r, facts, _ = record(tmp_path / name, ends, n, 30, durations="none")
        assert r.block_rows == (30 if name == "big" else 3)
        assert facts["files"] == sorted([OBSERVABLES, MOMENTS, HISTOGRAMS])
        r, facts, _ = record(tmp_path / name, ends, n, 30)
        hist = pd.read_parquet(tmp_path / name / DURATION_HISTOGRAM)
        assert (hist["duration"] == hist["steps"] * DT).all()
        got = hist.set_index(["kind", "duration"])["count"]
        assert got.sort_index().tolist() == expected.sort_index().tolist()
        assert got.index.sort_values().equals(expected.index.sort_values())
        assert facts["n_durations"] == int(np.count_nonzero(ends)) == hist["count"].sum()
        # rows: phi = 0 (tumble) first, then by steps; long segments grew the lattice
        assert hist["kind"].tolist() == sorted(hist["kind"], key=LUMPS.index)
        assert hist["steps"].max() == np.abs(ends).max() > 30
        results.append(hist)
    pd.testing.assert_frame_equal(*results)
    meta = read_metadata(tmp_path / "big" / DURATION_HISTOGRAM)
    assert (meta["dt"], meta["lump_names"], meta["durations"]) == (DT, list(LUMPS), "histogram")


# ----------------------------------------------------------------------------------------------
# large runs: summaries over all cells, exact values of a subsample


@pytest.mark.parametrize("device", DEVICES)
def test_summaries_cover_every_cell_and_the_subsample_is_exact(tmp_path, device: str) -> None:
    n, record_cells, steps, every = 3000, 100, 40, 10
    ends = segment_ends(n, steps, seed=3)
    r, facts, seen = record(tmp_path, ends, n, every, device, record_cells=record_cells, seed=7)
    cells = choose_cells(n, record_cells, 7)
    np.testing.assert_array_equal(r.cells, cells)
    obs = pd.read_parquet(tmp_path / OBSERVABLES)
    moments = pd.read_parquet(tmp_path / MOMENTS)
    hist = pd.read_parquet(tmp_path / HISTOGRAMS)
    assert len(obs) == record_cells * len(seen) and len(moments) == 2 * len(seen)
    edges = {"distance": (0.0, 0.002, 10_000), "speed": (0.0, 1e-4, 400)}
    for k, values in enumerate(seen):
        t = k * every * DT
        rows = obs[obs["t"] == t]
        np.testing.assert_array_equal(rows["cell"], cells)
        for name, x in values.items():
            x64 = x.numpy().astype(np.float64)
            np.testing.assert_array_equal(rows[name], x.numpy()[cells])
            m = moments[(moments["t"] == t) & (moments["observable"] == name)].iloc[0]
            assert m["n"] == n
            assert m["mean"] == pytest.approx(x64.mean(), rel=1e-12)
            assert m["variance"] == pytest.approx(x64.var(ddof=1), rel=1e-10)
            assert (m["min"], m["max"]) == (x64.min(), x64.max())
            lo, width, n_bins = edges[name]
            assert (m["lo"], m["width"], m["n_bins"]) == (lo, width, n_bins)
            # reference counts: floor((x - lo) / width) clipped to [-1, n_bins]
            idx = np.clip(np.floor((x64 - lo) / width), -1, n_bins).astype(int)
            want = pd.Series(idx).value_counts().sort_index()
            h = hist[(hist["t"] == t) & (hist["observable"] == name)]
            assert h["bin"].tolist() == want.index.tolist()  # only non-zero bins, in order
            assert h["count"].tolist() == want.tolist()
            assert h["count"].sum() == n
        h = hist[(hist["t"] == t) & (hist["observable"] == "distance")].set_index("bin")["count"]
        assert h.loc[-1] == 1 and h.loc[10_000] == 2  # -0.5 below; 25 and 20 (= hi) above
    # durations.parquet: every segment of the recorded cells; the histogram: of every cell
    durations = pd.read_parquet(tmp_path / DURATIONS)
    pd.testing.assert_frame_equal(durations, reference_rows(ends, cells))
    assert facts["duration_rows"] == len(durations) < facts["n_durations"]
    assert facts["n_durations"] == np.count_nonzero(ends)
    meta = read_metadata(tmp_path / MOMENTS)
    assert meta == {**meta, "n_cells": n, "record_cells": record_cells,
                    "observable_cells": record_cells, "seed": 7}  # fmt: skip


def test_durations_all_keeps_every_segment_of_a_subsampled_run(tmp_path) -> None:
    n = 500
    ends = segment_ends(n, 25, seed=4)
    _, facts, _ = record(tmp_path, ends, n, 5, record_cells=20, durations="all")
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / DURATIONS), reference_rows(ends))
    assert facts["duration_rows"] == facts["n_durations"] and facts["observable_cells"] == 20


def test_memory_is_flat_in_t_end_and_bounded_in_n_cells(tmp_path, monkeypatch) -> None:
    """The device buffer is capped by BUFFER_BYTES whatever the cells; what grows with the run
    is the duration lattice only (16 bytes per step of the longest segment)."""
    assert RunRecorder(tmp_path / "x", 10**6, DT, ["distance"], LUMPS, 64, "cpu").block_rows == 16
    monkeypatch.setattr(rec, "BUFFER_BYTES", 4 * 200 * 8)
    n = 200
    r = RunRecorder(tmp_path / "y", n, DT, ["distance"], LUMPS, 50, "cpu")
    assert r.block_rows == 8
    sizes = []
    for s in range(400):
        length = 5 if s % 3 == 0 else 0  # segments of 5 steps only
        r.record_step(s, torch.full((n,), length, dtype=torch.int32))
        if s in (99, 399):
            sizes.append((r._buffer.numel(), r._lattice.numel(), r._tables[DURATIONS]._buffered))
    r.abort()
    # the lattice grows with the steps seen (a segment may last that long), by doubling: it is
    # sized by the loop's length, not by the durations recorded
    assert sizes[0][0] == sizes[1][0] == 8 * n
    assert sizes[1][1] <= 2 * 2 * 400 + 1
    assert all(b <= (1 << 20) for *_, b in sizes)


def test_abort_drops_every_temporary(tmp_path) -> None:
    r = RunRecorder(tmp_path, 10, DT, ["distance"], LUMPS, 4, "cpu")
    temporaries = list(tmp_path.glob(".*.tmp"))
    assert len(temporaries) == 3  # observables, histograms, durations: open from the start
    r.record_observables(0.0, {"distance": torch.ones(10)})
    r.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="durations must be one of"):
        RunRecorder(tmp_path, 10, DT, ["distance"], LUMPS, 4, "cpu", RecorderSpec(durations="some"))


# ----------------------------------------------------------------------------------------------
# through simulate_population


def test_simulate_population_writes_bounded_summaries(tmp_path) -> None:
    """The recorded files grow with record_cells, not with n_cells; the recorder draws no random
    numbers from the simulation (the same seed gives the same cells whatever is recorded)."""
    model = EcoliModel()

    def run(n: int, out: Path, **kw):
        torch.manual_seed(11)
        table = torch.linspace(0.2, 0.8, 64).repeat(2, 1)  # a smooth, moderate psi
        from surrogate.gp import PsiLookupTable

        psi = PsiLookupTable(table, [(-3.25, 10.0)], ("dG",))
        decision = AbstractDecision(psi, model.internal, model.featurizer(["dG"]))
        sim = Simulator(model, decision, GaussianField(), DT)
        return simulate_population(sim, n, 2.0, out, record_interval=0.5, progress=False, **kw)

    small = run(1200, tmp_path / "a", record_cells=60, recorder_seed=5)
    large = run(4800, tmp_path / "b", record_cells=60, recorder_seed=5)
    for s in (small, large):
        assert s.recording["observable_cells"] == 60 and s.recording["n_records"] == 5
    assert large.n_durations > 3 * small.n_durations
    rows = [len(pd.read_parquet(tmp_path / d / OBSERVABLES)) for d in "ab"]
    assert rows == [60 * 5, 60 * 5]
    dur_rows = [s.recording["duration_rows"] for s in (small, large)]
    assert max(dur_rows) < 2 * min(dur_rows)  # the 60 recorded cells' segments, not n's
    # the same simulation recorded differently: identical moments and histograms
    full = run(1200, tmp_path / "c", record_cells=1200, durations="all")
    for name in (MOMENTS, HISTOGRAMS, DURATION_HISTOGRAM):
        pd.testing.assert_frame_equal(
            pd.read_parquet(tmp_path / "a" / name), pd.read_parquet(tmp_path / "c" / name)
        )
    assert full.recording["duration_rows"] == full.n_durations == small.n_durations
    assert small.means == full.means and small.record_times == [0.0, 0.5, 1.0, 1.5, 2.0]

"""Population sharding: shard settings and seeds, K shards merged into one ordinary run."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import torch
from omegaconf import OmegaConf

from surrogate.errors import ArtefactError, ConfigError, MissingArtefactError
from surrogate.evaluate.statistics import comparison_table, load_run
from surrogate.fields import GaussianField
from surrogate.io import read_manifest
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import FullDecision, Simulator, simulate_population
from surrogate.simulate.recorders import (
    DURATION_HISTOGRAM,
    DURATIONS,
    HISTOGRAMS,
    MOMENTS,
    OBSERVABLES,
    read_metadata,
)
from surrogate.stages import shards
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.settings import SimulateSettings

ROOT = Path(__file__).resolve().parents[2]
# Small and quick: 10 cells for 2 s, records every 0.5 s.
SMALL = ["n_cells=10", "t_end=2.0", "record_interval=0.5", "equilibration_time=0.5"]


def test_shard_sizes_offsets_and_seeds() -> None:
    assert shards.shard_sizes(10, 3) == [4, 3, 3]
    assert shards.shard_sizes(9, 3) == [3, 3, 3]
    assert shards.shard_offsets(10, 3) == [0, 4, 7]
    seeds = [shards.shard_seed(0, 3, i) for i in range(3)]
    assert len(set(seeds)) == 3 and 0 not in seeds
    assert seeds == [shards.shard_seed(0, 3, i) for i in range(3)]  # deterministic
    assert all(0 <= s < 2**63 for s in seeds)
    assert shards.shard_seed(1, 3, 0) not in seeds  # the parent seed matters


def test_default_is_unsharded_with_unchanged_directory(compose_cfg) -> None:
    cfg = compose_cfg("simulate", SMALL)
    assert (cfg.shard.count, cfg.shard.index) == (1, 0)
    without = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    del without["shard"]
    settings = SimulateSettings.from_config(cfg)
    assert (
        settings.directory
        == SimulateSettings.from_config(without).directory
        == shards.shard_run(settings, 1, 0).directory
    )


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (["shard.count=3", "shard.index=3"], "shard.index"),
        (["shard.count=0"], "shard.count"),
        (["shard.count=11"], "larger than n_cells"),
    ],
)
def test_invalid_shard_settings(compose_cfg, overrides: list[str], match: str) -> None:
    cfg = compose_cfg("simulate", [*SMALL, *overrides])
    with pytest.raises(ConfigError, match=match):
        shards.run(cfg)


def test_merge_needs_shards(compose_cfg) -> None:
    with pytest.raises(ConfigError, match="nothing to merge"):
        shards.merge(compose_cfg("simulate", SMALL))


def test_merge_names_the_missing_shard_and_its_command(compose_cfg) -> None:
    for i in (0, 2):
        shards.run(compose_cfg("simulate", [*SMALL, "shard.count=3", f"shard.index={i}"]))
    cfg = compose_cfg("simulate", [*SMALL, "shard.count=3"])
    with pytest.raises(MissingArtefactError) as err:
        shards.merge(cfg, overrides=["n_cells=10", "t_end=2.0", "shard.count=3"])
    message = str(err.value)
    assert "missing 1 of 3 shards: shard 1 (" in message
    assert "python scripts/simulate.py n_cells=10 t_end=2.0 shard.count=3 shard.index=1" in message
    # without the merge's own overrides, the command is built from the settings
    with pytest.raises(MissingArtefactError) as err:
        shards.merge(cfg)
    command = re.search(r"Run `(python scripts/simulate.py .*?)` first", str(err.value))
    assert command is not None and "n_cells=10" in command.group(1)
    assert "shard.count=3 shard.index=1" in command.group(1)


def test_three_shards_merge_into_an_ordinary_run(compose_cfg) -> None:
    base = compose_cfg("simulate", SMALL)
    unsharded = load_run(simulate_stage.run(base))
    shard_dirs = [
        shards.run(compose_cfg("simulate", [*SMALL, "shard.count=3", f"shard.index={i}"]))
        for i in range(3)
    ]
    assert len({*shard_dirs, unsharded.path}) == 4  # every shard has its own directory
    cfg = compose_cfg("simulate", [*SMALL, "shard.count=3"])
    out = shards.merge(cfg)
    settings = SimulateSettings.from_config(cfg)
    assert out == shards.merged_dir(settings, 3) and out.parent == unsharded.path.parent
    assert out not in (*shard_dirs, unsharded.path)

    merged = load_run(out)
    d = merged.observables
    np.testing.assert_array_equal(merged.record_times, unsharded.record_times)
    for _, rows in d.groupby("t"):
        assert sorted(rows["cell"]) == list(range(10))  # n_cells rows, unique contiguous ids
    # same format as an unsharded run: columns, dtypes (pandas and Parquet), row order by (t, cell)
    for name in ("observables", "durations"):
        a, b = getattr(merged, name), getattr(unsharded, name)
        assert list(a.columns) == list(b.columns) and a.dtypes.equals(b.dtypes)
        pa_schema = pq.read_schema(out / f"{name}.parquet")
        assert pa_schema.equals(pq.read_schema(unsharded.path / f"{name}.parquet"))
    assert d[["t", "cell"]].equals(d.sort_values(["t", "cell"])[["t", "cell"]])

    # each shard's cells are its rows, offset; durations are the shards' concatenated
    parts = [load_run(p) for p in shard_dirs]
    for part, offset in zip(parts, shards.shard_offsets(10, 3), strict=True):
        n = part.manifest["n_cells"]
        mine = d[(d["cell"] >= offset) & (d["cell"] < offset + n)].reset_index(drop=True)
        np.testing.assert_array_equal(mine["distance"], part.observables["distance"])
        np.testing.assert_array_equal(mine["cell"] - offset, part.observables["cell"])
    durations = merged.durations
    assert len(durations) == sum(len(p.durations) for p in parts) > 0
    offsets = np.repeat(shards.shard_offsets(10, 3), [len(p.durations) for p in parts])
    expected_cells = np.concatenate([p.durations["cell"] for p in parts]) + offsets
    np.testing.assert_array_equal(durations["cell"], expected_cells)

    # summaries over all cells: moments of the merged cells, histograms and lattice added
    for t, rows in d.groupby("t"):
        mo = merged.moments[merged.moments["t"] == t].iloc[0]
        x = rows["distance"].to_numpy(np.float64)
        assert mo["n"] == 10 and mo["mean"] == pytest.approx(x.mean(), rel=1e-12)
        assert mo["variance"] == pytest.approx(x.var(ddof=1), rel=1e-9)
        assert (mo["min"], mo["max"]) == (x.min(), x.max())
    for name, keys in ((HISTOGRAMS, ["t", "observable", "bin"]),
                       (DURATION_HISTOGRAM, ["kind", "steps", "duration"])):  # fmt: skip
        summed = (pd.concat([pd.read_parquet(p / name) for p in shard_dirs])
                  .groupby(keys, sort=False)["count"].sum())  # fmt: skip
        got = pd.read_parquet(out / name).set_index(keys)["count"]
        pd.testing.assert_series_equal(got.sort_index(), summed.sort_index())
        assert pq.read_schema(out / name).equals(pq.read_schema(unsharded.path / name))
    lattice = durations.assign(steps=np.rint(durations["duration"] / 0.05).astype(np.int64))
    assert merged.duration_counts["count"].sum() == len(lattice)
    assert read_metadata(out / MOMENTS)["n_cells"] == 10

    m, u = merged.manifest, unsharded.manifest
    assert set(u) <= set(m)
    assert m["n_cells"] == 10 and m["n_steps"] == u["n_steps"] and m["seed"] == 0
    assert m["n_durations"] == len(durations)
    assert m["wall_time_s"] == pytest.approx(sum(p.manifest["wall_time_s"] for p in parts))
    loop = sum(p.manifest["loop_time_s"] for p in parts)
    assert m["loop_time_s"] == pytest.approx(loop)
    assert m["cell_steps_per_s"] == pytest.approx(10 * m["n_steps"] / loop)
    assert m["final_means"]["distance"] == pytest.approx(
        float(d.loc[d["t"] == d["t"].max(), "distance"].mean()), rel=1e-5
    )
    assert m["shards"] == [str(p) for p in shard_dirs] and m["shard_count"] == 3
    # evaluate reads it like any run
    table = comparison_table(unsharded, merged, times=(1.0, 2.0), subsample=50, seed=0)
    assert table["ks"].notna().all()

    stamp = (out / "manifest.json").stat().st_mtime_ns
    assert shards.merge(cfg) == out  # reused, not rewritten
    assert (out / "manifest.json").stat().st_mtime_ns == stamp
    assert read_manifest(out)["shards"] == m["shards"]


def test_shards_recording_every_cell_merge_into_a_run_of_every_cell(compose_cfg) -> None:
    """``record_cells=null`` on shards of unequal sizes (4, 3, 3 cells): the merged run keeps
    all 10 cells and every segment (each shard recorded its own share, not one shard's count)."""
    every = [*SMALL, "record_cells=null"]
    shard_dirs = [
        shards.run(compose_cfg("simulate", [*every, "shard.count=3", f"shard.index={i}"]))
        for i in range(3)
    ]
    merged = load_run(shards.merge(compose_cfg("simulate", [*every, "shard.count=3"])))
    for _, rows in merged.observables.groupby("t"):
        assert sorted(rows["cell"]) == list(range(10))
    parts = [load_run(p) for p in shard_dirs]
    assert len(merged.durations) == sum(len(p.durations) for p in parts) > 0
    assert merged.duration_counts["count"].sum() == len(merged.durations)
    meta = read_metadata(merged.path / MOMENTS)
    assert meta["record_cells"] is None and meta["observable_cells"] == 10


def _shard(out: Path, seed: int, n: int, **kw) -> Path:
    """A full-model shard of ``n`` cells for 2 s (records every 0.5 s), as the stage writes it."""
    torch.manual_seed(seed)
    model = EcoliModel()
    sim = Simulator(model, FullDecision(model.internal), GaussianField(), 0.05)
    simulate_population(sim, n, 2.0, out, record_interval=0.5, progress=False,
                        recorder_seed=seed, **kw)  # fmt: skip
    return out


SIZES = [40, 30, 30]


@pytest.fixture(scope="module")
def subsampled(tmp_path_factory) -> dict[str, Path]:
    """Three shards recording 20 of their cells, the same shards recording every cell, and the
    merges of both."""
    root = tmp_path_factory.mktemp("shards")
    out: dict[str, Path] = {}
    for name, record_cells in (("sub", 20), ("all", 100)):
        dirs = [_shard(root / f"{name}{i}", 10 + i, n, record_cells=record_cells)
                for i, n in enumerate(SIZES)]  # fmt: skip
        out[name] = root / f"{name}_merged"
        facts = shards.merge_runs(dirs, SIZES, out[name], ["distance"], seed=3)
        assert facts["n_cells"] == 100 and facts["shards"] == 3
        out[f"{name}_dirs"] = dirs  # type: ignore[assignment]
    return out


def test_merged_subsample_is_a_subsample_of_the_merged_population(subsampled) -> None:
    sub = pd.read_parquet(subsampled["sub"] / OBSERVABLES)
    every = pd.read_parquet(subsampled["all"] / OBSERVABLES)
    # 20 of the 100 cells (not 3 x 20), the same cells at every record time, in (t, cell) order
    cells = sub.groupby("t")["cell"].apply(tuple)
    assert cells.nunique() == 1 and len(cells.iloc[0]) == 20 == len(set(cells.iloc[0]))
    assert sub[["t", "cell"]].equals(sub.sort_values(["t", "cell"])[["t", "cell"]])
    # exact values of those cells: the same simulation recorded in full says so
    joined = sub.merge(every, on=["t", "cell"], suffixes=("", "_all"), validate="one_to_one")
    assert len(joined) == len(sub)
    np.testing.assert_array_equal(joined["distance"], joined["distance_all"])
    # each kept cell came from its shard's own subsample
    for d, offset, n in zip(subsampled["sub_dirs"], [0, 40, 70], SIZES, strict=True):
        mine = set(pd.read_parquet(d / OBSERVABLES)["cell"] + offset)
        kept = {c for c in cells.iloc[0] if offset <= c < offset + n}
        assert kept <= mine
    # summaries: over all 100 cells whatever was recorded
    for name in (MOMENTS, HISTOGRAMS, DURATION_HISTOGRAM):
        pd.testing.assert_frame_equal(
            pd.read_parquet(subsampled["sub"] / name), pd.read_parquet(subsampled["all"] / name)
        )
    for t, rows in every.groupby("t"):  # the moments' pairwise combination is exact
        mo = pd.read_parquet(subsampled["sub"] / MOMENTS).set_index("t").loc[t]
        x = rows["distance"].to_numpy(np.float64)
        assert mo["n"] == 100 and mo["mean"] == pytest.approx(x.mean(), rel=1e-12)
        assert mo["variance"] == pytest.approx(x.var(ddof=1), rel=1e-9)
    # durations.parquet: the kept cells' rows (histogram mode), all rows from full recordings
    d_sub = pd.read_parquet(subsampled["sub"] / DURATIONS)
    d_all = pd.read_parquet(subsampled["all"] / DURATIONS)
    expected = d_all[d_all["cell"].isin(cells.iloc[0])].reset_index(drop=True)
    pd.testing.assert_frame_equal(d_sub, expected)
    assert pd.read_parquet(subsampled["all"] / DURATION_HISTOGRAM)["count"].sum() == len(d_all)
    meta = read_metadata(subsampled["sub"] / MOMENTS)
    assert (meta["n_cells"], meta["observable_cells"], meta["record_cells"]) == (100, 20, 20)


def test_merge_allocation_is_that_of_a_simple_random_sample() -> None:
    """Cells drawn per shard: multivariate hypergeometric. Over 3,000 seeds the mean draw from
    each shard is within 4.5 standard errors of total x size / N."""
    sizes, total = [400, 300, 300, 7], 50
    draws = np.array(
        [shards._allocate(sizes, total, np.random.default_rng(s)) for s in range(3000)]
    )
    assert (draws.sum(axis=1) == total).all() and (draws <= np.array(sizes)).all()
    n = sum(sizes)
    for k, size in enumerate(sizes):
        p = size / n
        sd = math.sqrt(total * p * (1 - p) * (n - total) / (n - 1))
        assert abs(draws[:, k].mean() - total * p) < 4.5 * sd / math.sqrt(len(draws))


def test_merge_refuses_mixed_formats_and_keeps_every_duration_of_full_tables(
    subsampled, tmp_path: Path
) -> None:
    dirs = [_shard(tmp_path / f"s{i}", 20 + i, n, record_cells=20, durations="all")
            for i, n in enumerate(SIZES)]  # fmt: skip
    facts = shards.merge_runs(dirs, SIZES, tmp_path / "m", ["distance"], seed=0)
    merged = pd.read_parquet(tmp_path / "m" / DURATIONS)
    assert len(merged) == sum(len(pd.read_parquet(d / DURATIONS)) for d in dirs)
    assert facts["n_durations"] == len(merged) == facts["duration_rows"]
    assert pd.read_parquet(tmp_path / "m" / OBSERVABLES)["cell"].nunique() == 20
    (dirs[1] / MOMENTS).unlink()  # a shard of the older format among new ones
    with pytest.raises(ArtefactError, match="mix formats"):
        shards.merge_runs(dirs, SIZES, tmp_path / "m2", ["distance"], seed=0)
    assert not (tmp_path / "m2").exists() or not any((tmp_path / "m2").iterdir())


def test_shard_of_an_abstract_run_keeps_decision_settings(compose_cfg) -> None:
    cfg = compose_cfg("simulate", [*SMALL, "decision=abstract", "shard.count=2", "shard.index=1"])
    settings = SimulateSettings.from_config(cfg)
    c = shards.shard_run(settings, 2, 1)
    assert c.decision is settings.decision and c.n_cells == 5
    assert c.setup.seed == shards.shard_seed(0, 2, 1)
    assert c.identity()["abstraction"] == settings.identity()["abstraction"]
    assert shards.shard_run(settings, 2, 0).setup.seed != c.setup.seed
    assert c.directory != settings.directory


@pytest.mark.slow
def test_sharded_multirun_and_merge_scripts(tmp_path: Path) -> None:
    """End to end: merge_shards.py names the missing shards' command; that command (a joblib
    multirun) makes them; merge_shards.py then writes one run that evaluate can load."""
    common = [*SMALL, f"data_dir={tmp_path / 'data'}", "threads=1"]

    def script(name: str, *args: str) -> subprocess.CompletedProcess[str]:
        env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
        return subprocess.run([sys.executable, str(ROOT / "scripts" / name), *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=300, env=env)  # fmt: skip

    first = script("merge_shards.py", *common, "shard.count=3")
    assert first.returncode == 2, first.stderr
    assert "Traceback" not in first.stderr
    command = re.search(r"Run `python scripts/simulate.py (.*?)` first", first.stderr)
    assert command is not None, first.stderr
    args = command.group(1).split()
    assert "-m" in args and "shard.index=0,1,2" in args
    made = script("simulate.py", *args, "hydra/launcher=joblib", f"hydra.sweep.dir={tmp_path}/sw")
    assert made.returncode == 0, made.stderr
    merged = script("merge_shards.py", *common, "shard.count=3")
    assert merged.returncode == 0, merged.stderr
    run = load_run(next((tmp_path / "data" / "simulate").glob("*_shards=3-*")))
    assert run.manifest["n_cells"] == 10 and len(run.manifest["shards"]) == 3

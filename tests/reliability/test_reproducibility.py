"""Same settings and seed: identical artefact contents; another seed: different ones.

Bit-for-bit on one machine (CPU, one torch thread as the suite runs): every table is compared
with ``check_exact=True``, every prediction with ``torch.equal``.
"""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch

from surrogate.io import read_manifest, write_manifest
from surrogate.stages import collect, train
from surrogate.stages import evaluate as evaluate_stage
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.collect import TRANSITIONS

from .conftest import SIM, compose_in

REPO = Path(__file__).resolve().parents[2]


def _same(a: pd.DataFrame, b: pd.DataFrame) -> None:
    pd.testing.assert_frame_equal(a, b, check_exact=True)


def _differ(a: pd.DataFrame, b: pd.DataFrame) -> None:
    with pytest.raises(AssertionError):
        _same(a, b)


@pytest.fixture(scope="module")
def second_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shared collect + train again (seed 0) in a fresh data_dir: an independent rerun."""
    data = tmp_path_factory.mktemp("rerun") / "data"
    cfg = compose_in(data, "train")
    collect.run(cfg)
    train.run(cfg)
    train.run(compose_in(data, "train", ["gp=svgp"]))
    return data


@pytest.fixture(scope="module")
def other_seed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    data = tmp_path_factory.mktemp("seed1") / "data"
    cfg = compose_in(data, "train", ["seed=1"])
    collect.run(cfg)
    train.run(cfg)
    train.run(compose_in(data, "train", ["seed=1", "gp=svgp"]))
    return data


def test_collect_same_seed_identical_other_seed_different(
    trained_data, second_run, other_seed
) -> None:
    def table(data: Path, seed: int) -> pd.DataFrame:
        return pd.read_parquet(
            collect.run(compose_in(data, "collect", [f"seed={seed}"])) / TRANSITIONS
        )

    _same(table(trained_data, 0), table(second_run, 0))
    _differ(table(trained_data, 0), table(other_seed, 1))


def test_train_same_seed_identical_other_seed_different(
    trained_data, second_run, other_seed
) -> None:
    dirs = {
        name: train.run(compose_in(data, "train", [f"seed={seed}"]))
        for name, data, seed in (("a", trained_data, 0), ("b", second_run, 0), ("c", other_seed, 1))
    }
    grids = {k: pd.read_csv(d / train.GRID) for k, d in dirs.items()}
    _same(grids["a"], grids["b"])
    _differ(grids["a"], grids["c"])
    # the reloaded classifiers agree bit for bit on new inputs too
    gen = torch.Generator().manual_seed(123)
    phi = torch.randint(0, 2, (500,), generator=gen)
    dg = -1.0 + 3.0 * torch.rand(500, 1, generator=gen)
    p = {k: train.load_abstraction(d)(phi, dg) for k, d in dirs.items()}
    assert torch.equal(p["a"], p["b"])
    assert not torch.equal(p["a"], p["c"])
    metrics = {k: read_manifest(d)["brier"] for k, d in dirs.items()}
    assert metrics["a"] == metrics["b"]


@pytest.mark.parametrize(
    "decision",
    [
        [],
        ["decision=abstract", "decision.mode=lookup"],
        [
            "decision=abstract",
            "decision.mode=classifier",
            "gp=svgp",
        ],  # two-state: K lumps is a table
    ],
    ids=["full", "abstract-lookup", "abstract-classifier"],
)
def test_simulate_same_seed_identical_other_seed_different(
    trained_data, second_run, other_seed, decision: list[str]
) -> None:
    def tables(data: Path, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
        cfg = compose_in(data, "simulate", [*decision, f"seed={seed}"])
        out = simulate_stage.run(cfg, force=True)
        return pd.read_parquet(out / "observables.parquet"), pd.read_parquet(
            out / "durations.parquet"
        )

    a, b, c = tables(trained_data, 0), tables(second_run, 0), tables(other_seed, 1)
    assert len(a[0]) == 20 * 3 and len(a[1]) > 0  # records at t = 0, 1, 2 s; some durations
    for x, y in zip(a, b, strict=True):
        _same(x, y)
    _differ(a[0], c[0])


def test_same_process_rerun_is_identical(tiny) -> None:
    """Seeding at the start of each stage: earlier draws in the same process do not leak in."""
    cfg = tiny("simulate", ["seed=5"])
    first = pd.read_parquet(simulate_stage.run(cfg) / "observables.parquet")
    torch.rand(1000)  # disturb the global stream
    again = pd.read_parquet(simulate_stage.run(cfg, force=True) / "observables.parquet")
    _same(first, again)


def test_every_manifest_records_the_seed(tiny, copy_data) -> None:
    assert inspect.signature(write_manifest).parameters["seed"].default is inspect.Parameter.empty
    cfg = tiny("evaluate", ["seed=0", "evaluate.run_missing=true"])
    out = evaluate_stage.run(cfg)
    manifests = {
        "collect": read_manifest(collect.run(tiny("collect"))),
        "train": read_manifest(train.run(tiny("train"))),
        "evaluate": read_manifest(out),
    }
    for name, path in read_manifest(out)["runs"].items():
        manifests[f"simulate {name}"] = read_manifest(path)
    for name, manifest in manifests.items():
        assert "seed" in manifest, name
    assert {k: m["seed"] for k, m in manifests.items()} == {
        "collect": 0,
        "train": 0,
        "evaluate": 0,
        "simulate full": 0,
        "simulate candidate": 0,
        "simulate full_repeat": 1000,
    }


def test_parallel_jobs_draw_independent_streams(tmp_path: Path) -> None:
    """A joblib multirun over seeds: each job equals the serial run of its seed (nothing depends on
    the worker or the job number), and different seeds give different populations."""
    data = tmp_path / "data"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    cmd = [
        sys.executable,
        "scripts/simulate.py",
        "-m",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        f"data_dir={data}",
        "progress=false",
        *SIM,
        "seed=0,1",
    ]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    parallel = {}
    for seed in (0, 1):
        cfg = compose_in(data, "simulate", [f"seed={seed}"])
        out = simulate_stage.run(cfg)  # reuses the job's artefact
        assert read_manifest(out)["seed"] == seed
        parallel[seed] = pd.read_parquet(out / "observables.parquet")
        serial = compose_in(tmp_path / "serial", "simulate", [f"seed={seed}"])
        _same(parallel[seed], pd.read_parquet(simulate_stage.run(serial) / "observables.parquet"))
    _differ(parallel[0], parallel[1])

"""The stages chained on tiny settings: collect -> train -> simulate (full, abstract) -> evaluate."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate import collect, train
from surrogate.errors import MissingArtefactError
from surrogate.evaluate import stage as evaluate_stage
from surrogate.evaluate.statistics import load_run
from surrogate.io import load_tensors
from surrogate.paths import simulate_dir
from surrogate.simulate import stage as simulate_stage

TINY = [
    "collect.n_per_state=400",
    "collect.n_cells=100",
    "gp.n_inducing=16",
    "gp.epochs=8",
    "gp.batch_size=200",
    "n_cells=40",
    "t_end=20.0",
    "equilibration_time=1.0",
    "gp.grid_size=[12,10]",
]


@pytest.fixture
def trained(compose_cfg):
    """A tiny collect + train, shared settings for the tests below."""
    cfg = compose_cfg(
        "train", [o for o in TINY if o.split("=")[0].split(".")[0] in ("collect", "gp")]
    )
    collect_dir = collect.run(cfg)
    train_dir = train.run(cfg)
    return cfg, collect_dir, train_dir


def test_collect_writes_columns_counts_and_manifest(trained) -> None:
    cfg, collect_dir, _ = trained
    table = pd.read_parquet(collect_dir / "transitions.parquet")
    assert {"m", "L", "phi", "phi_next", "cell", "t"} <= set(table.columns)
    assert (table["phi"] == 0).sum() == 400 and (table["phi"] == 1).sum() == 400
    assert set(table["phi_next"].unique()) <= {0, 1}
    assert np.isfinite(table[["m", "L"]].to_numpy()).all()
    manifest = json.loads((collect_dir / "manifest.json").read_text())
    assert manifest["counts_per_origin"] == {"tumble": 400, "run": 400}
    assert manifest["seed"] == cfg.seed and manifest["config"]["dt"] == cfg.dt
    assert sum(manifest["counts"].values()) == 800
    assert manifest["wall_time_s"] > 0 and "torch" in manifest["versions"]
    assert (collect_dir / "coverage.png").stat().st_size > 0


def test_train_writes_artefacts_and_round_trips(trained) -> None:
    cfg, _, train_dir = trained
    for name in (
        "psi.pt",
        "train_metrics.json",
        "psi_grid.csv",
        "psi_surfaces.png",
        "manifest.json",
    ):
        assert (train_dir / name).exists(), name
    grid = pd.read_csv(train_dir / "psi_grid.csv")
    assert list(grid.columns) == ["phi", "m", "L", "p"] and len(grid) == 2 * 12 * 10
    assert grid["p"].between(0, 1).all()
    load_tensors(train_dir / "psi.pt")  # loads with weights_only=True
    psi = train.load_abstraction(train_dir)
    # the saved grid is reproduced exactly by the reloaded model
    p = psi(
        torch.tensor(grid["phi"].to_numpy()),
        torch.tensor(grid["m"].to_numpy()),
        torch.tensor(grid["L"].to_numpy()),
    )
    np.testing.assert_allclose(p.numpy(), grid["p"].to_numpy(), rtol=0, atol=1e-6)
    # the same abstraction is found from the config alone
    psi2 = train.load_abstraction(cfg)
    assert torch.equal(
        psi2(torch.tensor([1, 0]), torch.tensor([2.0, 2.5]), torch.tensor([0.01, 0.05])),
        psi(torch.tensor([1, 0]), torch.tensor([2.0, 2.5]), torch.tensor([0.01, 0.05])),
    )
    metrics = json.loads((train_dir / "train_metrics.json").read_text())
    for name in ("psi_tumble", "psi_run"):
        v = metrics[name]["validation"]
        assert {"brier", "brier_baseline", "mean_log_predictive", "accuracy", "calibration"} <= set(
            v
        )


def test_train_without_collect_names_the_command(compose_cfg) -> None:
    cfg = compose_cfg("train", ["field=linear"])
    with pytest.raises(MissingArtefactError, match="python scripts/collect.py field=linear"):
        train.run(cfg)


@pytest.mark.parametrize("mode", ["lookup", "classifier"])
def test_full_vs_abstract_end_to_end(trained, compose_cfg, mode: str) -> None:
    overrides = [*TINY, "decision=abstract", f"decision.mode={mode}", "decision.lookup_size=[32,32]",
                 "evaluate.times=null", "evaluate.subsample=200", "evaluate.run_missing=true"]  # fmt: skip
    cfg = compose_cfg("evaluate", overrides)
    out = evaluate_stage.run(cfg)
    table = pd.read_csv(out / "comparison.csv")
    assert table["quantity"].tolist() == [
        "distance_t5",
        "distance_t10",
        "distance_t15",
        "distance_t20",
        "run",
        "tumble",
    ]
    assert table["ks"].between(0, 1).all() and table["ks_noise_floor"].notna().all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["speedup_loop"] > 0
    for name in (
        "distance_histograms.png",
        "distance_over_time.png",
        "durations.png",
        "comparison.md",
    ):
        assert (out / name).exists()
    # the abstract run is a complete simulation artefact in the same format as the full run
    run_cfg = evaluate_stage.run_config(cfg, "abstract")
    abstract = load_run(simulate_dir(run_cfg))
    assert abstract.distances["cell"].nunique() == 40
    assert abstract.manifest["decision"] == "abstract"


def test_simulate_abstract_without_training_names_the_command(compose_cfg) -> None:
    cfg = compose_cfg("simulate", ["decision=abstract", "n_cells=4", "t_end=1.0"])
    with pytest.raises(MissingArtefactError, match="python scripts/train.py"):
        simulate_stage.run(cfg)

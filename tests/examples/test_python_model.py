"""A second model through every stage, with no edit to the package: the seams hold.

The template for a Python model (examples/python_model/gene_switch.py, a gene switch in a walker)
is selected only by ``model._target_``; collect, train (also from an external CSV table), simulate
(full, learned, exact) and evaluate run on it unchanged, and its exact lumped psi drives a chain
that matches its full model.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from examples.python_model.gene_switch import GeneSwitchModel
from surrogate.config import CONF_DIR
from surrogate.errors import ArtefactError
from surrogate.fields import ConstantField
from surrogate.simulate import ExactDecision, FullDecision, Simulator, simulate_population
from surrogate.stages import collect, evaluate, simulate, train
from surrogate.stages.settings import EvaluateSettings

TOY = {
    "_target_": "examples.python_model.gene_switch.GeneSwitchModel",
    "perturbation": {"radius": 3.0},
}
SMALL = [
    "collect.n_per_state=1500",
    "collect.n_cells=200",
    "gp.n_inducing=20",
    "gp.epochs=10",
    "gp.batch_size=500",
    "gp.diagnostic.n_cells=200",
    "gp.diagnostic.t_end=10.0",
    "n_cells=200",
    "t_end=20.0",
    "equilibration_time=2.0",
    "start=[1.0,0.0]",
    "evaluate.subsample=500",
    "evaluate.run_missing=true",
]


def toy_config(data_dir, overrides=()):
    """The evaluate config (a superset of the others' settings) with the toy model."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="evaluate",
            overrides=[f"data_dir={data_dir}", "progress=false", *SMALL, *overrides],
        )
    cfg.model = OmegaConf.create(TOY)
    return cfg


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    data = tmp_path_factory.mktemp("toy") / "data"
    cfg = toy_config(data)
    collect_dir = collect.run(cfg)
    train_dir = train.run(cfg)
    evaluation = evaluate.run(cfg)
    return cfg, collect_dir, train_dir, evaluation


def test_collect_records_the_declared_inputs(pipeline) -> None:
    _, collect_dir, _, _ = pipeline
    table = pd.read_parquet(collect_dir / "transitions.parquet")
    assert {"s", "phi", "phi_next", "cell", "t", "since_jump"} <= set(table.columns)
    assert not {"m", "L", "dG"} & set(table.columns)  # nothing of E. coli
    assert (table["phi"] == 0).sum() == 1500 and (table["phi"] == 1).sum() == 1500
    manifest = pd.read_json(collect_dir / "manifest.json", typ="series")
    assert manifest["counts_per_origin"] == {"off": 1500, "on": 1500}


def test_train_learns_over_the_declared_input(pipeline) -> None:
    _, _, train_dir, _ = pipeline
    psi = train.load_abstraction(train_dir)
    assert psi.input_names == ("s",) and psi.lump_names == ("off", "on")
    metrics = train.read_metrics(train_dir)
    assert metrics["diagnostic"]["reference"] == "exact"
    for phi in ("phi0", "phi1"):  # scored against the toy's own exact psi where cells live
        d = metrics["diagnostic"][phi]
        assert 0 < d["mean_switching_reference"] < 1 and math.isfinite(d["rel_bias"])
        assert d["n"] > 0


def test_simulate_and_evaluate_the_toy(pipeline) -> None:
    cfg, _, _, evaluation = pipeline
    table = pd.read_csv(evaluation / "comparison.csv")
    assert table["quantity"].tolist() == [
        "distance_t5", "distance_t10", "distance_t15", "distance_t20", "on", "off",
    ]  # fmt: skip
    assert table["ks"].between(0, 1).all() and table["ks_noise_floor"].notna().all()
    settings = EvaluateSettings.from_config(cfg)
    runs = [settings.full.directory, settings.candidate.directory]
    kinds = {k for d in runs for k in pd.read_parquet(d / "durations.parquet")["kind"].unique()}
    assert kinds == {"on", "off"}
    # the exact decision runs on the toy too
    exact = simulate.run(toy_config(cfg.data_dir, ["decision=exact", "decision.mode=direct"]))
    assert pd.read_parquet(exact / "observables.parquet")["cell"].nunique() == 200


def test_train_from_an_external_table(pipeline, tmp_path) -> None:
    """Any table with the declared input columns, phi and phi_next trains an abstraction (e.g.
    tracked cells of an experiment), and a missing column is named."""
    _, collect_dir, _, _ = pipeline
    table = pd.read_parquet(collect_dir / "transitions.parquet")[["s", "phi", "phi_next"]]
    path = tmp_path / "tracked.csv"
    table.to_csv(path, index=False)
    cfg = toy_config(tmp_path / "data", [f"+transitions={path}"])
    out = train.run(cfg)
    assert train.load_abstraction(out).input_names == ("s",)
    assert "table=tracked" in out.name
    table.drop(columns="phi_next").to_csv(path, index=False)
    with pytest.raises(ArtefactError, match=r"lacks column\(s\) \['phi_next'\]"):
        train.run(toy_config(tmp_path / "data", [f"+transitions={path}"]))


def test_exact_psi_chain_follows_the_toy_full_model(tmp_path) -> None:
    """At a fixed inducer level the chain driven by the exact lumped psi gives the full model's
    mean ON and OFF durations, within 4.5 combined standard errors."""
    model = GeneSwitchModel()
    means = {}
    for name, decision in (("full", FullDecision(model.internal)),
                           ("exact", ExactDecision(model.internal, 0.05))):  # fmt: skip
        torch.manual_seed(12)
        sim = Simulator(model, decision, ConstantField(0.05), dt=0.05)
        simulate_population(sim, 300, 20.0, tmp_path / name, start=(0.0, 0.0),
                            equilibration_time=2.0, progress=False)  # fmt: skip
        d = pd.read_parquet(tmp_path / name / "durations.parquet")
        means[name] = {k: d[d.kind == k].duration.to_numpy() for k in ("on", "off")}
    for kind in ("on", "off"):
        a, b = means["full"][kind], means["exact"][kind]
        se = math.sqrt(a.var() / len(a) + b.var() / len(b))
        assert min(len(a), len(b)) > 1000
        assert abs(a.mean() - b.mean()) < 4.5 * se, (kind, a.mean(), b.mean(), se)
    assert np.isfinite(se)

"""The narrow plug-in contract: optional capabilities are detected in one way
(:mod:`surrogate.models.capabilities`), and a model that writes only the required protocol
(examples/python_model/minimal.py) runs through collect, train and simulate on the engine's
defaults."""

from __future__ import annotations

from typing import Any

import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from examples.python_model.gene_switch import GeneSwitchModel
from examples.python_model.minimal import TelegraphInternal, TelegraphModel
from surrogate.config import CONF_DIR, build_model, group_config, validate_start
from surrogate.errors import ConfigError
from surrogate.models import Randoms
from surrogate.models.capabilities import (
    concat_states_of,
    exact_age_psi_of,
    exact_psi_of,
    expected_phi_next_of,
    feature_names_of,
    features_of,
    has_exact_psi,
    histogram_grids_of,
    is_fusable,
    randoms_of,
    signal_bounds_of,
    start_size_of,
)
from surrogate.stages import collect, simulate, train
from surrogate.stages.settings import SimulateSettings
from surrogate.testing import BodyContract, InternalModelContract

MINIMAL = {"_target_": "examples.python_model.minimal.TelegraphModel"}
SMALL = [
    "collect.n_per_state=1500",
    "collect.n_cells=200",
    "gp.n_inducing=20",
    "gp.epochs=10",
    "gp.batch_size=500",
    "gp.diagnostic.n_cells=200",
    "gp.diagnostic.t_end=10.0",
    "n_cells=200",
    "t_end=10.0",
    "equilibration_time=2.0",
    "start=[1.0,0.0]",
]


def config(data_dir, overrides=(), model=MINIMAL):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="evaluate",
            overrides=[f"data_dir={data_dir}", "progress=false", *SMALL, *overrides],
        )
    cfg.model = OmegaConf.create(model)
    return cfg


def test_the_minimal_model_is_detected_as_lacking_every_option() -> None:
    internal = TelegraphModel().internal
    assert exact_psi_of(internal) is None and not has_exact_psi(internal)
    assert exact_age_psi_of(internal) is None and signal_bounds_of(internal) is None
    assert expected_phi_next_of(internal) is None and feature_names_of(internal) == ()
    assert not is_fusable(internal) and randoms_of(internal) == Randoms()
    # the engine's defaults: states joined tensor by tensor, inputs selected by name
    a, b = (torch.zeros(2),), (torch.ones(3),)
    assert torch.equal(concat_states_of(internal)([a, b])[0], torch.tensor([0, 0, 1, 1, 1.0]))
    x = torch.tensor([[0.5], [0.25]])
    assert torch.equal(features_of(internal, x, ["s"]), x)
    assert TelegraphModel().cell_step_seconds(0.05) > 0  # the base estimate


def test_declared_capabilities_are_detected() -> None:
    """A method (E. coli's motors), a property returning a callable or None (the network
    adapter), and a declared body grid."""
    ecoli = build_model(group_config("model", "ecoli"))
    motors = ecoli.internal
    assert exact_psi_of(motors) == motors.exact_psi and has_exact_psi(motors)
    assert exact_age_psi_of(motors) is not None and set(signal_bounds_of(motors)) == {"dG"}
    assert is_fusable(motors) and randoms_of(motors) == motors.randoms
    assert histogram_grids_of(ecoli.body) == {"distance": (0.0, 20.0, 0.002)}
    switch = GeneSwitchModel().internal  # 25 states: the exact psi exists
    assert has_exact_psi(switch) and signal_bounds_of(switch) is None
    phospho = build_model(group_config("model", "ecoli_phospho"))
    assert not has_exact_psi(phospho.internal)  # too large a state space: a property's None
    assert signal_bounds_of(phospho.internal) == {"activity": (0.0, 1.0)}
    assert histogram_grids_of(TelegraphModel().body) == {"distance": (0.0, 20.0, 0.002)}
    assert histogram_grids_of(object()) == {}


def test_a_start_position_has_the_size_the_body_declares() -> None:
    assert start_size_of(TelegraphModel().body) == 2 and start_size_of(object()) is None
    assert validate_start({"start": [1, 2, 3]}, size=None) == (1.0, 2.0, 3.0)
    with pytest.raises(ConfigError, match=r"start must be two coordinates \[x, y\] in mm"):
        validate_start({"start": [1.0]}, size=2)
    with pytest.raises(ConfigError, match="start must be 3 coordinates"):
        validate_start({"start": [1.0, 2.0]}, size=3)
    with pytest.raises(ConfigError, match="start must be a non-empty list"):
        validate_start({"start": []}, size=None)


def test_features_of_names_an_unknown_input() -> None:
    with pytest.raises(ValueError, match=r"unknown inputs \['dG'\]"):
        features_of(TelegraphInternal(1.0, 1.0), torch.zeros(2, 1), ["dG"])


def test_the_minimal_model_runs_through_collect_train_and_simulate(tmp_path) -> None:
    cfg = config(tmp_path / "data")
    table = pd.read_parquet(collect.run(cfg) / "transitions.parquet")
    assert {"s", "phi", "phi_next"} <= set(table.columns)
    assert (table["phi"] == 0).sum() == 1500 and (table["phi"] == 1).sum() == 1500
    train_dir = train.run(cfg)
    assert train.load_abstraction(train_dir).lump_names == ("off", "on")
    assert train.read_metrics(train_dir)["diagnostic"]["reference"] != "exact"
    for decision in ("decision=full", "decision=abstract"):
        run = simulate.run(config(cfg.data_dir, [decision]))
        observed = pd.read_parquet(run / "observables.parquet")
        assert observed["cell"].nunique() == 200 and observed["distance"].notna().all()
        kinds = set(pd.read_parquet(run / "durations.parquet")["kind"].unique())
        assert kinds == {"on", "off"}
    with pytest.raises(ConfigError, match="has no exact lumped psi"):
        SimulateSettings.from_config(config(cfg.data_dir, ["decision=exact"]))


class TestTelegraphContract(InternalModelContract):
    """The minimal model held to the internal-model contract, as a user's model is."""

    def make_internal(self) -> Any:
        return TelegraphModel().internal

    def make_inputs(self, n: int) -> torch.Tensor:
        return torch.linspace(0.0, 0.1, n)[:, None]


class TestGeneSwitchContract(TestTelegraphContract):
    def make_internal(self) -> Any:
        return GeneSwitchModel().internal

    def make_inputs(self, n: int) -> torch.Tensor:
        # no inducer at all: ON has no stationary mass, its exact psi row is 0/0
        return torch.linspace(0.001, 0.1, n)[:, None]


class TestWalkerContract(BodyContract):
    """The examples' walker held to the body contract."""

    def make_body(self) -> Any:
        return TelegraphModel().body

    def perturbation_options(self) -> dict[str, Any]:
        return dict(TelegraphModel().perturbation_options)

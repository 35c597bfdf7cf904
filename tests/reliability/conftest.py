"""Tiny stage settings and a shared collect + train for the reliability tests.

Every stage runs on sizes that take well under a second or two on one core; artefacts live in
temporary ``data_dir``s. Tests that corrupt or tamper with artefacts copy the shared ones first.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from omegaconf import DictConfig

from surrogate.stages import collect, train
from tests.conftest import composer

# collect: 200 transitions per origin state from 50 cells
COLLECT = ["collect.n_per_state=200", "collect.n_cells=50", "collect.equilibration_time=1.0"]
# train: 10 inducing points, 2 epochs, a 10-node psi grid, a small diagnostic run
GP = ["gp.epochs=2", "gp.n_inducing=10", "gp.batch_size=100", "gp.grid_size=[10]",
      "gp.diagnostic.n_cells=50", "gp.diagnostic.t_end=5.0"]  # fmt: skip
# simulate: 20 cells for 2 s
SIM = ["n_cells=20", "t_end=2.0", "equilibration_time=1.0"]
ABSTRACT = ["decision=abstract", "decision.lookup_size=[16]"]
EVALUATE = ["evaluate.times=[1.0,2.0]", "evaluate.subsample=50"]

# fidelity: one training seed, 20 cells for 2 s on one field
FIDELITY = ["fidelity.train_seeds=[0]", "fidelity.fields=[gaussian]", "fidelity.n_cells=20",
            "fidelity.t_end=2.0", "fidelity.equilibration_time=1.0"]  # fmt: skip

STAGE_OVERRIDES = {
    "collect": COLLECT,
    "train": COLLECT + GP,
    "simulate": COLLECT + GP + SIM,
    "evaluate": COLLECT + GP + SIM + ["decision.lookup_size=[16]", *EVALUATE],
    "reproduce": COLLECT + GP + SIM + ["decision.lookup_size=[16]", *EVALUATE],
    "fidelity": COLLECT + GP + FIDELITY,
}

Compose = Callable[..., DictConfig]


def compose_in(data_dir: Path, name: str, overrides: list[str] | None = None) -> DictConfig:
    """Compose primary config ``name`` with the tiny settings of its stage, then ``overrides``."""
    return composer(data_dir)(name, [*STAGE_OVERRIDES[name], *(overrides or [])])


@pytest.fixture
def tiny(tmp_path: Path) -> Compose:
    """``tiny(name, overrides)``: a tiny config of stage ``name`` with ``data_dir`` in tmp_path."""
    return lambda name, overrides=None: compose_in(tmp_path / "data", name, overrides)


@pytest.fixture(scope="session")
def trained_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ``data_dir`` holding one tiny collect + train (seed 0, gaussian field). Read-only:
    copy it (``copy_data``) before changing anything in it."""
    data = tmp_path_factory.mktemp("shared") / "data"
    cfg = compose_in(data, "train")
    collect.run(cfg)
    train.run(cfg)  # the default chain (K lumps for E. coli)
    train.run(compose_in(data, "train", ["gp=svgp"]))  # and the two-state chain
    return data


@pytest.fixture
def copy_data(trained_data: Path, tmp_path: Path) -> Path:
    """A private copy of the shared collect + train at ``tmp_path / "data"`` (for ``tiny``)."""
    target = tmp_path / "data"
    shutil.copytree(trained_data, target)
    return target


# directories of a config's artefacts, from the stages' typed settings
def collect_dir(cfg: DictConfig) -> Path:
    """The collect artefact directory of ``cfg``."""
    from surrogate.stages.settings import CollectSettings

    return CollectSettings.from_config(cfg).directory


def train_dir(cfg: DictConfig) -> Path:
    """The train artefact directory of ``cfg``."""
    from surrogate.stages.settings import TrainSettings

    return TrainSettings.from_config(cfg).directory


def fit_dir(cfg: DictConfig) -> Path:
    """The fit directory of ``cfg`` (the classifiers simulations load)."""
    from surrogate.stages.settings import TrainSettings

    return TrainSettings.from_config(cfg).fit_directory


def simulate_dir(cfg: DictConfig) -> Path:
    """The simulation artefact directory of ``cfg``."""
    from surrogate.stages.settings import SimulateSettings

    return SimulateSettings.from_config(cfg).directory

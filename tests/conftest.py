"""Shared fixtures: Hydra composition of the shipped configs."""

from __future__ import annotations

import copy
import os
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from surrogate.config import CONF_DIR

# One intra-op thread: the suite's tensors are small, and two threads stall badly whenever another
# process holds a core (measured: 55x slower GP training under load).
torch.set_num_threads(1)

# gp=auto resolves by the rule in the suite (its stages' tests run tiny configs in seconds); the
# measured choice, the default elsewhere, is tested where it is named (tests/stages/test_choice.py).
# Subprocesses the tests start inherit it.
os.environ["SURROGATE_GP_CHOICE"] = "rule"


#: configs composed so far, by name and overrides (Hydra's compose takes ~0.25 s, most of it
#: parsing the same yaml files again; ~700 composes made it ~11 % of the suite)
_COMPOSED: dict[tuple[str, tuple[str, ...]], DictConfig] = {}


def composer(data_dir: Path) -> Callable[..., DictConfig]:
    """``compose(name, overrides)``: a primary config with overrides, artefacts in ``data_dir``
    (unless the overrides name one). Each call returns a config of its own: a copy of the one
    composed for the same name and overrides, its ``data_dir`` set, since the data directory
    changes nothing else of a composition."""

    def _compose(name: str, overrides: list[str] | None = None) -> DictConfig:
        key = (name, tuple(overrides or ()))
        if key not in _COMPOSED:
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                _COMPOSED[key] = compose(config_name=name, overrides=["progress=false", *key[1]])
        cfg = copy.deepcopy(_COMPOSED[key])
        if not any(o.lstrip("+~").startswith("data_dir=") for o in key[1]):
            cfg.data_dir = str(data_dir)
        return cfg

    return _compose


@pytest.fixture
def compose_cfg(tmp_path) -> Callable[..., DictConfig]:
    """Compose a primary config with overrides; artefacts go to a temporary data_dir."""
    return composer(tmp_path / "data")

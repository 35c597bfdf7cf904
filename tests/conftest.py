"""Shared fixtures: Hydra composition of the shipped configs."""

from __future__ import annotations

import os
from collections.abc import Callable

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


@pytest.fixture
def compose_cfg(tmp_path) -> Callable[..., DictConfig]:
    """Compose a primary config with overrides; artefacts go to a temporary data_dir."""

    def _compose(name: str, overrides: list[str] | None = None) -> DictConfig:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(
                config_name=name,
                overrides=[f"data_dir={tmp_path / 'data'}", "progress=false", *(overrides or [])],
            )

    return _compose

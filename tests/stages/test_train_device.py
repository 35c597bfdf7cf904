"""``decision.train_device``: a learned run on one device with the fit another device made
(e.g. a CPU fit on CUDA), and the device in the commands that remake a device's artefacts."""

from __future__ import annotations

import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.stages.settings import SimulateSettings
from surrogate.stages.settings.common import Job


def test_the_run_finds_the_fit_of_the_train_device(compose_cfg) -> None:
    """train_device=cpu on a CPU run is the same run (the key only locates the fit: the fit's
    own identity carries its device); the fit is identified as a CPU fit."""
    plain = SimulateSettings.from_config(compose_cfg("simulate", ["decision=abstract"]))
    given = SimulateSettings.from_config(
        compose_cfg("simulate", ["decision=abstract", "decision.train_device=cpu"])
    )
    assert given.identity() == plain.identity()
    assert given.decision.train is not None and plain.decision.train is not None
    assert given.decision.train.fit_directory == plain.decision.train.fit_directory
    assert given.decision.train.fit_identity()["device"] == "cpu"


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal without CUDA")
@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("cuda", r"decision.train_device: device='cuda' was asked for but CUDA is not available"),
        ("gpu", r"decision.train_device: device='gpu' is not a torch device"),
        ("7", r"decision.train_device must be null .* got 7"),
        ("[cpu]", r"decision.train_device must be null \(the run's device\), cpu or cuda"),
    ],
)
def test_a_bad_train_device_is_refused_by_name(compose_cfg, value, message) -> None:
    with pytest.raises(ConfigError, match=message):
        SimulateSettings.from_config(
            compose_cfg("simulate", ["decision=abstract", f"decision.train_device={value}"])
        )


def test_a_commands_device_is_named_where_it_is_not_the_cpu(tmp_path) -> None:
    assert Job(tmp_path, torch.device("cpu"), False).device_overrides() == []
    assert Job(tmp_path, torch.device("cuda", 1), False).device_overrides() == ["device=cuda"]

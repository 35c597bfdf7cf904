"""Settings are built once, at a stage's entry, and passed down as objects: the model setup
(model, field, dt, seed) is built from the raw config once per entry, nested settings (a
run's abstraction, a collection's sequential design, evaluate's full runs) take it."""

from __future__ import annotations

import pytest

from surrogate.stages.settings import (
    CollectSettings,
    EvaluateSettings,
    ModelSetup,
    SimulateSettings,
    TrainSettings,
)

DESIGN = ["collect.design.target_error=0.05"]


@pytest.fixture
def setups(monkeypatch) -> list[object]:
    """The setups ``ModelSetup.from_config`` builds, one entry per call."""
    built: list[object] = []
    original = ModelSetup.from_config.__func__  # type: ignore[attr-defined]

    def counted(cls, cfg):
        built.append(setup := original(cls, cfg))
        return setup

    monkeypatch.setattr(ModelSetup, "from_config", classmethod(counted))
    return built


def test_collect_builds_its_setup_once(compose_cfg, setups) -> None:
    settings = CollectSettings.from_config(
        compose_cfg("train", DESIGN), fits=TrainSettings.design_fits
    )
    assert len(setups) == 1
    # the design's fits read the same setup and job
    assert settings.design is not None
    assert settings.design.setup is settings.setup and settings.design.job is settings.job


def test_train_builds_its_setup_once(compose_cfg, setups) -> None:
    settings = TrainSettings.from_config(compose_cfg("train", DESIGN))
    assert len(setups) == 1 and settings.setup is setups[0]


@pytest.mark.parametrize(
    "overrides",
    [
        ["decision=abstract", *DESIGN],
        ["decision=abstract", "decision.train_field=linear", "decision.train_device=cpu"],
        ["decision=exact"],
    ],
)
def test_simulate_builds_its_setup_once(compose_cfg, setups, overrides) -> None:
    settings = SimulateSettings.from_config(compose_cfg("simulate", overrides))
    assert len(setups) == 1
    train = settings.decision.train
    if train is not None:  # the abstraction's fit: the run's model in the training field
        assert train.setup.model is settings.setup.model
        assert train.setup.field_name == settings.decision.train_field


def test_evaluate_builds_its_setup_once(compose_cfg, setups) -> None:
    cfg = compose_cfg("evaluate", ["evaluate.full_n_cells=50", "evaluate.full_seed=3"])
    settings = EvaluateSettings.from_config(cfg)
    assert len(setups) == 1
    assert settings.full.setup.model is settings.candidate.setup.model
    assert settings.full.setup.seed == 3 and settings.full.n_cells == 50


def test_a_design_without_its_fits_builder_is_refused_by_name(compose_cfg) -> None:
    """collect's settings import no train settings (no circle, no import-order hook): a caller
    that builds a design without passing the fits' builder is told which one to pass."""
    with pytest.raises(TypeError, match="fits=TrainSettings.design_fits"):
        CollectSettings.from_config(compose_cfg("train", DESIGN))
    assert CollectSettings.from_config(compose_cfg("train")).design is None

"""Every config group composes and instantiates (Hydra compose API)."""

from __future__ import annotations

import pytest

from surrogate.config import CONF_DIR, build_field, build_params, validate_common
from surrogate.fields import Field
from surrogate.models.ecoli import EcoliParameters

PRIMARY = ["collect", "train", "simulate"]
FIELDS = sorted(p.stem for p in (CONF_DIR / "field").glob("*.yaml"))
DECISIONS = sorted(p.stem for p in (CONF_DIR / "decision").glob("*.yaml"))
GPS = sorted(p.stem for p in (CONF_DIR / "gp").glob("*.yaml"))
EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))


def test_the_groups_exist() -> None:
    assert {"gaussian", "linear", "dynamic", "zero"} <= set(FIELDS)
    assert {"full", "abstract"} <= set(DECISIONS)
    assert "paper" in EXPERIMENTS


@pytest.mark.parametrize("name", PRIMARY)
def test_primary_configs_compose_and_validate(compose_cfg, name: str) -> None:
    cfg = compose_cfg(name)
    validate_common(cfg)
    assert isinstance(build_params(cfg.model), EcoliParameters)


@pytest.mark.parametrize("field", FIELDS)
def test_every_field_instantiates(compose_cfg, field: str) -> None:
    cfg = compose_cfg("simulate", [f"field={field}"])
    f = build_field(cfg.field)
    assert isinstance(f, Field)


@pytest.mark.parametrize("decision", DECISIONS)
def test_every_decision_composes(compose_cfg, decision: str) -> None:
    cfg = compose_cfg("simulate", [f"decision={decision}"])
    assert cfg.decision.name == decision


@pytest.mark.parametrize("gp", GPS)
def test_every_gp_config_builds_settings(compose_cfg, gp: str) -> None:
    from surrogate.train import gp_settings

    cfg = compose_cfg("train", [f"gp={gp}"])
    assert gp_settings(cfg).n_inducing == cfg.gp.n_inducing


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes(compose_cfg, experiment: str) -> None:
    cfg = compose_cfg("simulate", [f"experiment={experiment}"])
    validate_common(cfg)


def test_overrides_reach_the_model(compose_cfg) -> None:
    cfg = compose_cfg("simulate", ["model.n_motors=10", "model.tau=20", "dt=0.02"])
    p = build_params(cfg.model)
    assert (p.n_motors, p.tau, cfg.dt) == (10, 20.0, 0.02)

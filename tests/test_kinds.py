"""The kinds of an abstraction as objects (issue 40, :mod:`surrogate.kinds`): the config's
strings looked up once, and the identities each kind gives its artefacts pinned as they were
when the kinds were strings (they are hashed into directory names: a change here would lose
every stored fit or run of that kind)."""

from __future__ import annotations

import pytest

from surrogate.errors import ConfigError
from surrogate.kinds import (
    SWITCH_CLOCK,
    TWO_STATE,
    KLumps,
    chain_kind,
    decision_identity,
    decision_kind,
    mode_kind,
)
from surrogate.stages.settings import SimulateSettings, TrainSettings


def test_the_config_strings_name_one_kind_each() -> None:
    assert chain_kind() is TWO_STATE and chain_kind("phi", "none", "learned") is TWO_STATE
    assert chain_kind("phi", "age") is SWITCH_CLOCK
    assert chain_kind("classes") == KLumps("learned")
    relaxing = chain_kind("classes", "none", "relaxation")
    assert relaxing.relaxation and relaxing.classes and not relaxing.clock
    assert SWITCH_CLOCK.clock and not (SWITCH_CLOCK.classes or SWITCH_CLOCK.relaxation)
    # the strings the settings still expose come back from the kind
    for kind in (TWO_STATE, SWITCH_CLOCK, relaxing):
        assert chain_kind(kind.lumps, kind.history, kind.class_moves) == kind
    for bad in (("classes", "age"), ("phi", "none", "relaxation"), ("motors",), ("phi", "clock")):
        with pytest.raises(ValueError, match="no chain kind"):
            chain_kind(*bad)


def test_the_decision_kinds_and_modes() -> None:
    full, abstract, exact = (decision_kind(n) for n in ("full", "abstract", "exact"))
    assert full.full and not full.modes
    assert abstract.learned and not abstract.full and abstract.mode("lookup").table
    assert not abstract.mode("classifier").table and not exact.mode("direct").table
    with pytest.raises(ConfigError, match=r"decision.mode must be one of \['lookup', 'direct'\]"):
        exact.mode("classifier")
    with pytest.raises(ConfigError, match="decision.name must be one of"):
        decision_kind(None)
    assert mode_kind("lookup").table and not mode_kind("direct").table
    with pytest.raises(ValueError, match="unknown decision mode"):
        mode_kind("table")


#: the fit identities' gp parts as they were before kinds were objects (the shipped recipes)
SHARED = {"ard": True, "batch_size": 1000, "epochs": 1000, "inputs": "signal",
          "kernel": "matern52", "labels": "auto", "learn_inducing": True, "lr": 0.05,
          "natural_gradient": False, "natural_lr": 0.1, "validation_fraction": 0.2}  # fmt: skip
GP_IDENTITIES = {
    "svgp": {**SHARED, "bins": 500, "n_inducing": 200},
    # epochs 200 -> 600 (2026-11-29): its fits at 200 differed by ~5 % in Tyson's L2 means
    "clock": {**SHARED, "bins": 200, "clock_bins": 20, "epochs": 600, "history": "age",
              "max_age": 5.0, "n_inducing": 200, "natural_gradient": True},
    # Adam's 1,000 steps -> Newton's 200 (2026-11-30): the same law at 1e5 cells, a quarter of
    # the time (conf/gp/classes.yaml)
    "classes": {**SHARED, "bins": 100, "class_law_version": 2, "epochs": 200,
                "lumps": "classes", "max_label_weight": 1000.0,
                "min_events": {"expected": 1.0, "outcome": 50}, "n_inducing": 32,
                "optimizer": "newton"},
}  # fmt: skip


@pytest.mark.parametrize("recipe", sorted(GP_IDENTITIES))
def test_each_kind_keeps_the_fit_identity_it_had(compose_cfg, recipe: str) -> None:
    settings = TrainSettings.from_config(compose_cfg("train", [f"gp={recipe}"]))
    assert settings.fit_identity()["gp"] == GP_IDENTITIES[recipe]
    assert ("lumps=classes" in settings.fit_directory.name) == (recipe == "classes")


@pytest.mark.parametrize(
    ("overrides", "decision"),
    [
        (["decision=exact"], {"history": "none", "lookup_size": None, "max_age": 5.0,
                              "mode": "lookup", "name": "exact"}),
        (["decision=exact", "decision.lumps=classes"],
         {"history": "none", "lookup_size": None, "lumps": "classes", "max_age": 5.0,
          "mode": "lookup", "name": "exact"}),
        (["decision=exact", "decision.history=age"],
         {"history": "age", "lookup_size": None, "max_age": 5.0, "mode": "lookup",
          "name": "exact"}),
        (["decision=abstract", "decision.initial=stationary"],
         {"lookup_size": None, "mode": "lookup", "name": "abstract", "train_field": "gaussian"}),
        # an abstract run's lumps is not read, and enters as given where it is not phi
        (["decision=abstract", "+decision.lumps=classes"],
         {"lookup_size": None, "lumps": "classes", "mode": "lookup", "name": "abstract",
          "train_field": "gaussian"}),
        (["decision=abstract", "+decision.lumps=phi"],
         {"lookup_size": None, "mode": "lookup", "name": "abstract", "train_field": "gaussian"}),
        (["decision=full"], {"name": "full"}),
    ],
)  # fmt: skip
def test_each_decision_keeps_the_run_identity_it_had(compose_cfg, overrides, decision) -> None:
    settings = SimulateSettings.from_config(compose_cfg("simulate", overrides))
    identity = settings.decision.identity()
    assert identity["decision"] == decision
    assert identity.get("initial") == ("stationary" if "decision.initial=stationary" in overrides
                                       else None)  # fmt: skip
    assert decision_identity(decision) == decision  # the rule is idempotent


def test_the_settings_strings_come_from_their_kind(compose_cfg) -> None:
    """The settings still give the strings (reports and advice read them), from the kind."""
    clock = TrainSettings.from_config(compose_cfg("train", ["gp=clock"]))
    assert clock.kind is SWITCH_CLOCK
    assert (clock.lumps, clock.history, clock.class_moves) == ("phi", "age", "learned")
    exact = SimulateSettings.from_config(
        compose_cfg("simulate", ["decision=exact", "decision.lumps=classes"])
    ).decision
    assert exact.chain == KLumps() and (exact.lumps, exact.history) == ("classes", "none")
    full = SimulateSettings.from_config(compose_cfg("simulate", ["decision=full"])).decision
    assert full.chain is None and (full.lumps, full.history) == ("phi", "none")

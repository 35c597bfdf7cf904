"""The inspector's pilot (issue 52): the kind is the measured choice made small, not a rule; its
overrides pass the stages' checks; it respects the inspector's budget and says where it cannot
run."""

from __future__ import annotations

import warnings

from surrogate.config import to_dict
from surrogate.diagnosis.remedies import candidate_overrides
from surrogate.kinds.scoring import candidate_cap
from surrogate.sbml.errors import SbmlWarning
from surrogate.stages import inspection
from surrogate.stages.advice_check import check_advice
from surrogate.stages.pilot import cap_name, pilot_advice, run_pilot

TOGGLE = ["model=sbml", "model.spec=examples/toggle_switch/model.yaml"]
#: small fits (the user's gp keys go into every candidate): the test times the machinery; one
#: process (the choice's own: tests/stages/test_choice.py)
SMALL = [*TOGGLE, "gp.n_inducing=16", "gp.epochs=15", "gp.choice.kinds=[two-state,clock]",
         "gp.choice.max_ages=[2.0]", "gp.choice.extend=0", "collect.n_cells=500",
         "gp.choice.workers=1"]  # fmt: skip
PILOT = {"enabled": True, "n_per_state": 2000, "n_cells": 20, "t_end": 10.0}


def test_the_pilot_chooses_by_measurement_and_its_advice_runs(compose_cfg) -> None:
    """On the toggle switch (tiny fits, ~20 s): the pilot fits the candidates plus the
    hazard's cap (1 s here, not among gp.choice.max_ages=[2]), scores them on a held-out run
    and the recommendation is its chosen kind with the table; the overrides printed pass the
    stages' checks; a second call reuses the record."""
    config = to_dict(compose_cfg("inspect", SMALL))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        pilot = run_pilot(config, PILOT, 40.0, 1.0, 1e-6)
        kinds = [r["kind"] for r in pilot["table"]]
        # with the clocks the choice adds: one on a log axis at twice the best clock's cap
        # where a clock wins, one at the held-out memory horizon past twice the largest cap
        # (2 s; the toggle's segments reach ~5 s) and the doublings from the largest
        assert pilot["ran"] and {"two-state", "clock max_age=2", cap_name(1.0)} <= set(kinds)
        assert all(k.startswith("clock log max_age=") or (candidate_cap(k) or 0.0) > 4.0
                   for k in set(kinds) - {"two-state", "clock max_age=2", cap_name(1.0)})  # fmt: skip
        assert pilot["cap_added"] and pilot["max_ages"] == [2.0, 1.0]
        assert pilot["chosen"] in kinds and pilot["n_per_state"] == 2000
        for row in pilot["table"]:
            assert {
                "log_likelihood_per_window",
                "diff_from_best",
                "diff_se",
                "holds_durations",
                "u_leads_ks",
                "u_leads_ks_critical_05",
                "u_leads_mean_rel_diff",
            } <= set(row)
        assert "log-lik / window" in pilot["text"] and pilot["chosen"] in pilot["text"]
        # each row names what trains it outright, as scored: a log clock's knee and bins too
        for row in pilot["table"]:
            named = candidate_overrides(row["kind"], row)
            assert check_advice(config, named) is None, (row["kind"], named)
            if row["kind"].startswith("clock log "):
                assert any(o.startswith("gp.clock_knee=") for o in named)
                assert any(o.startswith("gp.clock_bins=") for o in named)
        advice = pilot_advice(config, pilot)
        assert advice["kind"] == pilot["chosen"]
        from_cap = (cap_name(1.0), "clock log max_age=2")  # the log clock made from it
        added = ["gp.choice.max_ages=[2,1]"] if pilot["chosen"] in from_cap else []
        assert advice["overrides"] == ["gp.choice.by=measure", *added]  # the suite sets rule
        assert inspection.check_printed(config, advice, {}, {}, True) == []
        assert "refused" not in advice and "named_refused" not in advice
        again = run_pilot(config, PILOT, 40.0, 1.0, 1e-6)
    assert again["directory"] == pilot["directory"] and again["estimate_s"] == 0.0


def test_the_pilot_respects_the_budget_and_says_where_it_cannot_run(compose_cfg) -> None:
    """Priced before any work: over inspect.max_seconds it is halved to fit, and skipped with
    the estimate where even the smallest pilot does not; skipped, saying why, where disabled or
    the transitions are an external table."""
    config = to_dict(compose_cfg("inspect", TOGGLE))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        skipped = run_pilot(config, PILOT, 1e-9, None, 1e-6)
    assert not skipped["ran"] and "inspect.max_seconds=1e-09" in skipped["note"]
    assert "raise it" in skipped["note"] and skipped["estimate_s"] > 1e-9
    off = run_pilot(config, {**PILOT, "enabled": False}, 40.0, None, 1e-6)
    assert not off["ran"] and "inspect.pilot.enabled=false" in off["note"]
    table = run_pilot({**config, "transitions": "rows.parquet"}, PILOT, 40.0, None, 1e-6)
    assert not table["ran"] and "external table" in table["note"]
    assert pilot_advice(config, off)["kind"] is None


def test_the_pilot_trains_nothing_ahead(compose_cfg) -> None:
    """The pilot only scores (no chain is trained after its choice): K lumps, trained ahead
    with its recipe in a full-size choice, is not trained ahead in the pilot's."""
    from surrogate.stages.pilot import _plan, pilot_config

    config = to_dict(compose_cfg("inspect", ["gp.choice.by=measure"]))
    cfg, _, _ = pilot_config(config, 2000, 20, 5.0, None)
    assert cfg["gp"]["choice"]["ahead"] is False and cfg["gp"]["choice"]["by"] == "measure"
    plan = _plan(cfg)[1]
    assert plan is not None and "classes" in plan.finals and plan.ahead() is None
    # nor does it fit K lumps whose bins relax: their stationary sample is a full-model run
    # the pilot does not price; a user's list of that family alone is kept
    assert "relaxation" not in cfg["gp"]["choice"]["kinds"]
    assert "two-state" in cfg["gp"]["choice"]["kinds"]
    alone = to_dict(compose_cfg("inspect", ["gp.choice.by=measure",
                                            "gp.choice.kinds=[relaxation]"]))  # fmt: skip
    assert pilot_config(alone, 2000, 20, 5.0, None)[0]["gp"]["choice"]["kinds"] == ["relaxation"]


def test_the_pilot_scores_as_the_choice_it_stands_for(compose_cfg) -> None:
    """The pilot fits its candidates with the choice's own scoring optimiser (L-BFGS by
    default, Newton where the user asks ``gp.choice.optimizer=newton``): what it recommends is
    the measurement the next command makes."""
    from surrogate.stages.pilot import _plan, pilot_config

    for optimizer in ("lbfgs", "newton"):
        config = to_dict(compose_cfg("inspect", ["gp.choice.by=measure",
                                                 f"gp.choice.optimizer={optimizer}"]))  # fmt: skip
        cfg, _, _ = pilot_config(config, 2000, 20, 5.0, None)
        plan = _plan(cfg)[1]
        assert plan is not None
        assert {g["optimizer"] for g in plan.groups.values()} == {optimizer}, optimizer

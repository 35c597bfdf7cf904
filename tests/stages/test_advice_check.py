"""Advice that runs: every setting the verdict and the inspector print passes the stages'
own checks (issue 52), and a class that cannot exist is refused before collection."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from surrogate.config import to_dict
from surrogate.diagnosis import recommendation, settling
from surrogate.diagnosis.advice import Verdict, VerdictInputs, verdict
from surrogate.diagnosis.fixed import EXACT_METHOD, FixedInputs
from surrogate.diagnosis.jumps import blackout_advice
from surrogate.diagnosis.options import InspectOptions
from surrogate.diagnosis.remedies import (
    Check,
    MeasuredChoice,
    classes_override,
    coarser_classes,
)
from surrogate.errors import ConfigError
from surrogate.kinds import chain_kind
from surrogate.models import sbml_agent
from surrogate.models.count_classes import CountClasses
from surrogate.models.sbml_agent import SbmlAgentModel
from surrogate.stages import advice_check, inspection
from surrogate.stages.advice import applied, tried_remedies
from surrogate.stages.advice_check import apply_overrides, check_advice
from surrogate.stages.settings.inspection import InspectSettings, inspect_defaults


def verdict_of(
    check: Check | None = None, tried: dict[str, str] | None = None, **measured: Any
) -> Verdict:
    """The verdict of the measurements given by keyword."""
    return verdict(VerdictInputs(**measured), check, tried)


SPEC = "examples/gene_switch/model.yaml"  # D >= 2 is on; 25 states
UNBIASED = {"rel_bias": 0.0, "rel_bias_se": 0.01, "settling_z": 0.0}
SHARED = {"species": "P", "edges": [2, 4]}  # P runs 0-8 in both lumps
CLASSES = CountClasses("P", ((2.0, 4.0), (2.0, 4.0)), ("off", "on"))  # SHARED, built
#: what collect advises where its rows lag a jump in the first 2 s (at 0.1 jumps per s)
BLACKOUT = blackout_advice({"settled_after_s": 20.0, "lagging": [("off", 0.0, 2.0, 1.2)]}, 1.0,
                           0.1)  # fmt: skip


@pytest.fixture
def config(compose_cfg) -> dict[str, Any]:
    return to_dict(compose_cfg("reproduce", ["model=sbml", f"model.spec={SPEC}"]))


def memo_check(seen: dict, cfg, name: str):
    """The verdict's ``check`` for ``cfg``: :func:`check_advice`, each override list checked
    once per case ``name`` (``seen`` holds the answers across cases)."""

    def check(overrides, what):
        key = (name, *overrides)
        if key not in seen:
            seen[key] = check_advice(cfg, overrides)
        return seen[key]

    return check


def test_overrides_apply_as_hydra_applies_them(config) -> None:
    cfg = apply_overrides(config, ["gp=clock", "gp.max_age=4", "++model.burn_in=7"])
    assert cfg["gp"]["max_age"] == 4 and cfg["model"]["burn_in"] == 7
    with pytest.raises(ConfigError, match=r"not in the config .*\+model.classes"):
        apply_overrides(config, ["model.classes=auto"])  # Hydra's struct mode refuses it


def test_a_class_that_cannot_exist_is_refused_before_collection(config) -> None:
    """Shared edges of the lump's own count (D >= 2): `off|D>=3` and `on|D<1` hold no cell,
    so their fit would fail after a whole collection; the model refuses them, naming them."""
    reason = check_advice(config, ["gp=classes", "++model.classes={species: D, edges: [1, 3]}"])
    assert reason is not None and "'off|D>=3', 'on|D<1'" in reason and "cannot occur" in reason
    own_side = "classes: {species: D, edges: {'off': [1], 'on': [3]}}"
    assert check_advice(config, ["gp=classes"], own_side) is None
    # per-lump bins are what relaxation refuses, and its message no longer points to the trap
    refused = check_advice(config, ["gp=classes", "gp.class_moves=relaxation"], own_side)
    assert refused is not None and "not the lump's own threshold count" in refused


def _measurements(branch: str) -> dict[str, Any]:
    """Synthetic measurements that drive the verdict down one branch."""
    diag = {"phi0": dict(UNBIASED), "phi1": dict(UNBIASED)}
    clean = {"share_outside": 0.0, "inputs": {}}
    sparse = {**clean, "share_sparse": 0.2, "sparse_where": {"L": [0.0, 0.1]},
              "sparse_where_share": 0.2}  # fmt: skip
    out: dict[str, Any] = {"diagnostic": diag, "failures": {"gaussian": ["off"]},
                           "outside": {"gaussian": clean}}  # fmt: skip
    if branch == "biased":
        diag["phi0"] = {**UNBIASED, "rel_bias": 0.2, "rel_bias_se": 0.02}
    elif branch == "sparse":
        out["outside"] = {"gaussian": sparse}
    elif branch == "sparse_classes":
        out["outside"] = {"gaussian": {**sparse, "classes": True, "sparse_class": "on|P>=4"}}
    elif branch == "noisy":  # a reference too noisy to judge: the cells that make it judge
        diag["phi0"] = {**UNBIASED, "rel_bias": -0.07, "rel_bias_se": 0.046}
    elif branch == "settling":  # the diagnostic's halves apart: a later start of its record
        diag["phi0"] = {**UNBIASED, "settling_z": -6.0}
    elif branch == "drift":
        out["class_shares"] = {"t": 100.0, "total_variation": 0.1, "p_value": 1e-6,
                               "drift": True}  # fmt: skip
    elif branch == "within":  # every comparison within noise: trusted, caveats only
        out["failures"] = {"gaussian": []}
    return out


def test_every_remedy_the_verdict_prints_passes_the_settings_checks(config) -> None:
    """Every branch of the verdict, for every chain it reads (two-state, clock, classes
    learned and relaxing): each remedy it prints with settings is accepted by the stages'
    checks on the run's config. Without the check, `++model.classes=auto` was printed as
    `model.classes=auto` (refused by Hydra) and `gp=classes` offered to a model with none."""
    chains = {"phi": ([], "phi", "none", "learned"),
              "clock": (["gp=clock"], "phi", "age", "learned"),
              "classes": (["gp=classes"], "classes", "none", "learned"),
              "relaxing": (["gp=classes", "gp.class_moves=relaxation"], "classes", "none",
                           "relaxation")}  # fmt: skip
    printed, dropped = 0, 0
    seen: dict[tuple[str, ...], str | None] = {}  # a model build per distinct advice only
    for (name, (groups, *kind)), branch in itertools.product(
        chains.items(),
        ("memory", "biased", "sparse", "sparse_classes", "drift", "noisy", "settling"),
    ):
        base = apply_overrides(config, groups)
        base["model"]["classes"] = SHARED

        check = memo_check(seen, base, name)

        v = verdict_of(lump_names=("off", "on"), outside_warning=0.01, tolerance=0.03,
                    kind=chain_kind(*kind), network=True, n_per_state=1000, max_age=2.0,
                    check=check, count_classes=CLASSES, blackout=BLACKOUT, diagnostic_cells=1000,
                    diagnostic_span=(10.0, 100.0), burn_in=5.0,
                    **_measurements(branch))  # fmt: skip
        assert not v.trust
        if branch == "settling":  # a later record, or a burn-in ending where the drift did
            assert [r.overrides for _, r in v.remedies][:2] == [
                ("gp.diagnostic.equilibration_time=60",), ("++model.burn_in=65",)]  # fmt: skip
        if branch == "noisy":
            assert next(r.overrides for _, r in v.remedies) == ("gp.diagnostic.n_cells=3600",)
        if branch == "biased":  # the collection's lag first: more of the same rows keep it
            assert [r.kind for _, r in v.remedies][:2] == ["blackout", "more_rows"], name
        for _, remedy in v.remedies:
            printed += bool(remedy.overrides)
            assert check(remedy.overrides, "") is None, (name, branch, remedy)
            assert all(
                f"`{o}`" in remedy.text or o.lstrip("+") in remedy.text for o in remedy.overrides
            ), remedy  # the strings checked are printed
        dropped += len(v.dropped)
        coarser = [r for _, r in v.remedies if r.kind == "coarser_classes"]
        if branch == "sparse_classes":  # the edges with on|P>=4 merged into on|2<=P<4
            assert [r.overrides for r in coarser] == [("++model.classes={species: P, edges: [2]}",)]
    assert printed >= 10


def test_nan_or_missing_measurements_are_not_measured_never_trust() -> None:
    """Issue 54 item 7: a NaN bias (a reference that never left a lump), an absent
    diagnostic or an absent outside-training report made the verdict trust the run."""
    args: dict[str, Any] = {"lump_names": ("off", "on"), "failures": {"gaussian": []},
                            "outside_warning": 0.01, "tolerance": 0.03, "network": True,
                            "kind": chain_kind("phi", "none", "learned"), "n_per_state": 100}  # fmt: skip
    inside = {"gaussian": {"share_outside": 0.0, "inputs": {}}}
    full = {"phi0": UNBIASED, "phi1": UNBIASED}
    assert verdict_of(diagnostic=full, outside=inside, **args).trust
    cases = {
        "bias leaving on": ({"phi0": UNBIASED, "phi1": {**UNBIASED, "rel_bias": float("nan")}},
                            inside),
        "diagnostic (none": (None, inside),
        "diagnostic leaving off": ({"phi1": UNBIASED}, inside),
        "field gaussian": (full, {"gaussian": None}),
    }  # fmt: skip
    for what, (diagnostic, outside) in cases.items():
        v = verdict_of(diagnostic=diagnostic, outside=outside, **args)
        assert not v.trust, what
        assert v.causes[0][0] == "Not measured" and what in v.causes[0][1], what
        assert "Do not trust it yet" in v.markdown()


def test_a_remedy_applied_without_a_gain_is_not_advised_again() -> None:
    """The clock doubled its cap and the run got worse: the next verdict does not double
    it again; more rows at 20x (the advice was 4x) count as applied."""
    before = {"gp": {"max_age": 2.0}, "collect": {"n_per_state": 1000}}
    record = {"config": before, "outcome": 3, "tried": {},
              "remedies": [{"cause": "m", "kind": "longer_clock", "overrides": ["gp.max_age=4"]},
                           {"cause": "m", "kind": "more_rows",
                            "overrides": ["collect.n_per_state=4000"]}]}  # fmt: skip
    after = {"gp": {"max_age": 4.0}, "collect": {"n_per_state": 20000}}
    assert applied(before, after, ["collect.n_per_state=4000"])
    assert not applied(before, before, ["gp.max_age=4"])
    tried = tried_remedies(record, after, 5)
    assert set(tried) == {"longer_clock", "more_rows"} and "from 3 to 5" in tried["longer_clock"]
    assert tried_remedies(record, after, 1) == {}  # it helped: advised as usual
    # its cause gone (another found instead), a remedy had its gain whatever the outcome;
    # one set aside before is advised again once its cause has gone
    assert tried_remedies(record, after, 5, causes={"Not settled"}) == {}
    assert set(tried_remedies(record, after, 5, causes={"m"})) == {"longer_clock", "more_rows"}
    aside = {**record, "tried": {"more_rows": "tried before"}}
    assert tried_remedies(aside, after, 5, causes=set()) == {}
    args: dict[str, Any] = {"diagnostic": {"phi0": UNBIASED, "phi1": UNBIASED},
                            "lump_names": ("off", "on"), "failures": {"g": ["off"]},
                            "outside": {"g": {"share_outside": 0.0, "inputs": {}}},
                            "outside_warning": 0.01, "tolerance": 0.03, "network": True,
                            "kind": chain_kind("phi", "age", "learned"), "n_per_state": 20000,
                            "max_age": 4.0}  # fmt: skip
    assert "gp.max_age=8" in verdict_of(**args).causes[0][2]
    step = verdict_of(**args, tried=tried).causes[0][2]
    assert "`gp.max_age=8`" not in step and "collect.n_per_state=80000`" not in step
    assert "tried: `gp.max_age=4` ran" in step and "gp=classes" in step


def _choice_row(kind: str, complexity: int, gap: float, tied: bool = False) -> dict[str, Any]:
    return {"kind": kind, "complexity": complexity, "log_likelihood_per_window": -0.345 + gap,
            "diff_from_best": gap, "diff_se": 2e-5, "tied_with_best": tied,
            "holds_durations": True}  # fmt: skip


def _measured(chosen: str, rows: list[dict[str, Any]], **changes: Any) -> MeasuredChoice:
    """A fake measured choice's record (its table) and gp.choice settings."""
    base = {"kinds": ("two-state", "clock", "classes", "phases"), "max_ages": (1.0, 2.0, 5.0),
            "n_cells": 1000, "tie_se": 1.0, "classes": False}  # fmt: skip
    return MeasuredChoice(chosen, tuple(rows), **{**base, **changes})


def test_every_remedy_under_a_measured_choice_passes_the_settings_checks(
    compose_cfg, chooser
) -> None:  # fmt: skip
    """gp=auto measured the chain: the memory remedies widen the choice (a longer cap, the
    families left out, K lumps over classes: auto for a network without classes), ask for more
    held-out cells on a tie, and name the runner-up outright (a chosen spread off adds no
    screen: measured over four draws it did not help CERENA's network, session 38); class
    shares drifting name relaxation with K lumps outright (`gp.class_moves` alone is no key of gp=auto's group:
    refused); a trusted run whose choice held no candidate's durations gets the same remedies
    in its caveat. Each printed override passes the stages' checks on a measured config."""
    measured = to_dict(compose_cfg("reproduce", ["model=sbml", f"model.spec={SPEC}",
                                                 "gp.choice.by=measure"]))  # fmt: skip
    declared = copy.deepcopy(measured)
    declared["model"]["classes"] = SHARED
    rows = [_choice_row("two-state", 0, -4e-4), _choice_row("clock max_age=2", 1, -3e-5, True),
            _choice_row("clock max_age=5", 1, 0.0, True), _choice_row("phases", 3, -8e-5)]  # fmt: skip
    classes_rows = [_choice_row("two-state", 0, -4e-4), _choice_row("clock max_age=2", 1, -3e-5),
                    _choice_row("classes", 2, 0.0)]  # fmt: skip
    tie = [_choice_row("two-state", 0, -1e-5, True), _choice_row("clock max_age=2", 1, 0.0, True),
           *rows[2:]]  # fmt: skip
    none_held = [{**r, "holds_durations": False, "off_mean_rel_diff": 0.01 * (i + 3)}
                 for i, r in enumerate(rows)]  # fmt: skip
    spread = {
        "two-state": (-0.49, 0.008),
        "clock max_age=2": (0.081, 0.013),
        "phases": (0.013, 0.012),
    }
    spread_rows = [{**_choice_row(k, c, gap), "spread_rel_diff": spread[k][0],
                    "spread_rel_se": spread[k][1]}
                   for k, c, gap in (("two-state", 0, -4e-4), ("clock max_age=2", 1, 0.0),
                                     ("phases", 3, -8e-5))]  # fmt: skip
    cases = {  # config, chain (lumps, history, moves), choice, branch, the remedies expected
        "clock at the largest cap": (
            measured, ("phi", "age", "learned"),
            _measured("clock max_age=5", rows, kinds=("two-state", "clock"), thinned=True),
            "memory", ["wider_caps", "wider_kinds", "more_cells", "more_rows", "runner_up"]),
        "two-state": (
            measured, ("phi", "none", "learned"), _measured("two-state", tie), "memory",
            ["wider_kinds", "more_cells", "more_rows", "runner_up"]),
        "classes chosen": (
            declared, ("classes", "none", "learned"),
            _measured("classes", classes_rows, classes=True, kinds=("two-state", "classes")),
            "memory", ["other_classes", "wider_kinds", "more_rows"]),
        "classes drift": (
            declared, ("classes", "none", "learned"),
            _measured("classes", classes_rows, classes=True), "drift",
            ["relaxation", "more_rows"]),
        "the chosen spread off": (
            measured, ("phi", "age", "learned"), _measured("clock max_age=2", spread_rows),
            "memory", ["wider_kinds", "more_rows", "runner_up"]),
        "none held, trusted": (
            measured, ("phi", "age", "learned"),
            _measured("clock max_age=5", none_held, duration_tolerance=0.03), "within",
            ["wider_caps", "wider_kinds", "more_cells", "more_rows", "runner_up"]),
    }  # fmt: skip
    seen: dict[tuple[str, ...], str | None] = {}
    for name, (cfg, kind, choice, branch, expected) in cases.items():
        check = memo_check(seen, cfg, name)

        v = verdict_of(lump_names=("off", "on"), outside_warning=0.01, tolerance=0.03,
                       kind=chain_kind(*kind), network=True, n_per_state=1000, check=check,
                       choice=choice, **_measurements(branch))  # fmt: skip
        assert not v.dropped, (name, v.dropped)
        assert v.trust == (branch == "within"), name
        assert [r.kind for _, r in v.remedies] == expected, name
        for _, remedy in v.remedies:
            assert check(remedy.overrides, "") is None, (name, remedy)
            assert all(f"`{o}`" in remedy.text or o in remedy.text for o in remedy.overrides)
            # no kind named around the choice but as the explicit alternatives
            if remedy.kind not in ("runner_up", "relaxation"):
                assert not any(o.startswith(("gp=", "gp.max_age")) for o in remedy.overrides)
    printed = {o for key in seen for o in key[1:]}
    assert {"gp.choice.max_ages=[1,2,5,10]", "gp.choice.kinds=[two-state,clock,classes,phases]",
            "++model.classes=auto", "collect.keep_switches=true", "gp.choice.n_cells=4000",
            "gp=phases", "gp=classes"} <= printed  # fmt: skip
    # the remedies the named chain prints instead are not the choice's: gp.max_age alone,
    # accepted by the checks under gp=auto, would set every clock candidate's cap alike
    assert check_advice(measured, ["gp.class_moves=relaxation"]) is not None


def test_a_choice_remedy_applied_without_a_gain_is_not_advised_again(compose_cfg) -> None:
    """The anti-loop rule for the choice's remedies: a longer cap among the candidates that
    made the next run worse is not advised again (its cap doubled again neither), and the
    runner-up tried outright without a gain is not named again when gp=auto measures again."""
    before = to_dict(compose_cfg("reproduce", ["gp.choice.by=measure"]))
    wider, runner = ["gp.choice.max_ages=[1,2,5,10]"], ["gp=phases"]
    record = {"config": before, "outcome": 3, "tried": {},
              "remedies": [{"cause": "m", "kind": "wider_caps", "overrides": wider},
                           {"cause": "m", "kind": "runner_up", "overrides": runner}]}  # fmt: skip
    after = apply_overrides(before, wider)
    assert applied(before, after, wider) and not applied(before, after, runner)
    tried = tried_remedies(record, after, 5)
    assert set(tried) == {"wider_caps"} and "from 3 to 5" in tried["wider_caps"]
    assert tried_remedies(record, after, 2) == {}  # it helped: advised as usual
    rows = [_choice_row("two-state", 0, -4e-4), _choice_row("clock max_age=10", 1, 0.0),
            _choice_row("phases", 3, -8e-5)]  # fmt: skip
    args: dict[str, Any] = {"diagnostic": {"phi0": UNBIASED, "phi1": UNBIASED},
                            "lump_names": ("off", "on"), "failures": {"g": ["off"]},
                            "outside": {"g": {"share_outside": 0.0, "inputs": {}}},
                            "outside_warning": 0.01, "tolerance": 0.03, "network": False,
                            "kind": chain_kind("phi", "age", "learned"), "n_per_state": 1000,
                            "choice": _measured("clock max_age=10", rows,
                                                max_ages=(1.0, 2.0, 5.0, 10.0))}  # fmt: skip
    assert "gp.choice.max_ages=[1,2,5,10,20]" in verdict_of(**args).causes[0][2]
    step = verdict_of(**args, tried=tried).causes[0][2]
    assert "`gp.choice.max_ages=[1,2,5,10,20]`" not in step
    assert "tried: `gp.choice.max_ages=[1,2,5,10]` ran" in step and "`gp=phases`" in step
    # the runner-up run outright and worse: the next measured run does not name it again
    outright = tried_remedies({**record, "tried": tried}, apply_overrides(before, runner), 6)
    assert set(outright) == {"wider_caps", "runner_up"}
    again = verdict_of(**args, tried=outright)
    assert "runner_up" not in [r.kind for _, r in again.remedies]
    assert "not advised: gp=phases (tried" in again.causes[0][2]


def test_the_report_reads_the_measured_choice_that_made_its_chain(tmp_path) -> None:
    """reproduce's plumbing, on a choice train made (tiny: two candidates, 20 held-out cells):
    the verdict's choice is the record's chosen and table with the gp.choice settings it was
    made with; none where the rule chose the chain."""
    from surrogate.stages import train as train_stage
    from surrogate.stages.reproduce import measured_choice
    from tests.reliability.conftest import compose_in

    measure = ["gp.choice.by=measure", "gp.choice.kinds=[two-state,clock]",
               "gp.choice.max_ages=[1]", "gp.choice.n_cells=20", "gp.choice.t_end=5",
               "gp.choice.equilibration_time=1", "gp.choice.workers=1"]  # fmt: skip
    cfg = compose_in(tmp_path, "train", measure)
    train_stage.run(cfg)
    settled = train_stage.validate(cfg)
    record = json.loads((settled.measured_choice() / "choice.json").read_text())
    choice = measured_choice(settled)
    assert choice is not None and choice.chosen == record["chosen"]
    assert [r["kind"] for r in choice.scores] == ["two-state", "clock max_age=1"]
    assert (choice.kinds, choice.max_ages, choice.n_cells, choice.tie_se) == (
        ("two-state", "clock"), (1.0,), 20, 1.0)  # fmt: skip
    assert choice.classes is True  # E. coli declares classes (phi x CCW motors)
    assert choice.duration_tolerance == 0.03  # the screen the caveat "none held" reads
    assert choice.thinned  # one window in several, switches not kept: the classes' remedy reads it
    v = verdict_of(diagnostic={"phi0": UNBIASED, "phi1": UNBIASED}, lump_names=("off", "on"),
                   failures={"g": ["off"]}, outside={"g": {"share_outside": 0.0, "inputs": {}}},
                   outside_warning=0.01, tolerance=0.03, kind=settled.kind, network=False,
                   n_per_state=100, choice=choice)  # fmt: skip
    assert "`gp.choice.kinds=[two-state,clock,classes,phases]`" in v.causes[0][2]
    rule = train_stage.validate(compose_in(tmp_path, "train", ["gp.choice.by=rule"]))
    assert measured_choice(rule) is None


def test_collection_advice_names_the_run_it_needs_and_it_runs(config) -> None:
    """collect.max_time too short: the advice gives the max_time, or the cells, that fit the
    rows (the report printed 'too short' with no value to set)."""
    collection = {"recommended_n_per_state": 5000, "max_time": 200.0,
                  "seconds_needed": [900.0, 450.0], "max_time_needed": 900.0,
                  "n_cells_needed": 460}  # fmt: skip
    sets = recommendation.collection_overrides(collection)
    assert sets == [
        ["collect.n_per_state=5000", "collect.max_time=900"],
        ["collect.n_per_state=5000", "collect.n_cells=460"],
    ]
    advice = {"kind": "clock max_age=4", "overrides": ["gp.choice.max_ages=[1,2,5,4]"],
              "named": ["gp=clock", "gp.max_age=4"]}  # fmt: skip
    burn = {"applies": True, "enough": False, "needed_s": 30.0}
    assert inspection.check_printed(config, advice, burn, collection, True) == []
    assert collection["advised"] == sets and "refused" not in advice
    # every window recorded (collect.record_every=1) where it saves simulation: offered
    # first, with the longer run it needs in its turn
    dense = {
        **collection,
        "dense": {
            "record_every": 1,
            "cost_s": 60.0,
            "max_time": 200.0,
            "seconds_needed": [300.0, 150.0],
            "max_time_needed": 300.0,
        },
    }
    assert recommendation.collection_overrides(dense) == [
        ["collect.n_per_state=5000", "collect.record_every=1", "collect.max_time=300"],
        *sets,
    ]
    assert inspection.check_printed(config, {}, {}, dense, True) == []
    assert dense["advised"][0] == ["collect.n_per_state=5000", "collect.record_every=1",
                                   "collect.max_time=300"]  # fmt: skip
    # a cap below one window (dt = 0.05 s) is refused by gp.choice's own check
    bad = {"kind": "clock max_age=0.01", "named": [],
           "overrides": ["gp.choice.by=measure", "gp.choice.max_ages=[1,0.01]"]}  # fmt: skip
    (refusal,) = inspection.check_printed(config, bad, {}, {}, True)
    assert "below one window" in bad["refused"] and refusal.startswith("the pilot's choice")


# ----------------------------------------------------------------------------------------------
# the inspector's recommendations: every branch of recommend() and what the report prints


@pytest.fixture
def chooser(monkeypatch) -> list[bool]:
    """``classes: auto`` without its seeded run (10-20 s each): per-lump bins of D, the lump's
    own count, as the real chooser gives the gene switch, or bins of P both lumps share where
    asked (``shared``). Returns the ``shared`` of each call."""
    calls: list[bool] = []

    def choose(internal, kinetic, dt, *, binning, **_):
        shared = binning.shared
        calls.append(shared)
        classes = CountClasses("P", ((2.0, 4.0), (2.0, 4.0)), internal.lump_names) if shared \
            else CountClasses("D", ((1.0,), (3.0,)), internal.lump_names)  # fmt: skip
        return classes, {"candidates": [], "significant": True}

    monkeypatch.setattr(sbml_agent, "choose_count_classes", choose)
    return calls


@pytest.fixture
def checks(monkeypatch) -> dict[tuple, str | None]:
    """check_advice memoised (1-3 s each): the same overrides on the same config once."""
    seen: dict[tuple, str | None] = {}
    real = advice_check.check_advice

    def check(config, overrides, model_yaml=""):
        key = (repr(sorted(config["model"].items())), tuple(overrides), model_yaml)
        if key not in seen:
            seen[key] = real(config, overrides, model_yaml)
        return seen[key]

    monkeypatch.setattr(advice_check, "check_advice", check)
    return seen


def _switch_yaml(tmp_path, **keys: Any) -> str:
    """The gene switch's yaml (D >= 2 is on) without its signal_bounds, with ``keys``."""
    spec = yaml.safe_load(Path(SPEC).read_text())
    spec.pop("signal_bounds")
    spec["network"] = str(Path(SPEC).resolve().parent / spec["network"])
    path = tmp_path / f"switch_{len(list(tmp_path.glob('switch_*')))}.yaml"
    path.write_text(yaml.safe_dump({**spec, **keys}))
    return str(path)


def _hazard(flat_from_s: float = 1.5) -> dict[str, Any]:
    return {"hazard": [0.02, 0.05], "pooled": 0.04, "effect": 0.3, "p_value": 1e-6, "df": 4,
            "flat_from_s": flat_from_s}  # fmt: skip


def _fixed(**changes: Any) -> FixedInputs:
    """Synthetic measurements at one grid point (exact, settled, with memory); D's law over
    0-4 (the lump D >= 2 on about half the time)."""
    base = FixedInputs(
        method=EXACT_METHOD, occupancy=np.array([0.5]), occupancy_se=np.zeros(1),
        settled=np.array([True]), settle_phi=np.array([2.0]), settle_network=np.array([3.0]),
        species_settle={}, curves={}, horizon=60.0,
        relaxation={"tau_s": 1.0, "se": 0.1, "method": "exact"},
        hazards=[_hazard(), _hazard()], memory=True, switch=np.array([0.05, 0.08]), events=2.0,
        species_law={"D": (np.arange(5.0), np.array([0.2, 0.3, 0.25, 0.15, 0.1]))},
    )  # fmt: skip
    return dataclasses.replace(base, **changes)


def _pilot(chosen: str, cap: float | None, ages: list[float], named: list[str]) -> dict[str, Any]:
    """A pilot's outcome as :func:`~surrogate.stages.pilot.run_pilot` returns it."""
    return {"ran": True, "chosen": chosen, "reason": "measured", "named": named, "cap": cap,
            "cap_added": cap is not None and cap not in ages[:-1], "max_ages": ages}  # fmt: skip


def test_every_recommendation_the_inspector_prints_passes_the_settings_checks(
    tmp_path, compose_cfg, chooser, checks, monkeypatch
) -> None:  # fmt: skip
    """Issue 52: the pilot's recommendation (keep gp=auto, with gp=auto where another group is
    named, gp.choice.by=measure where the rule is set, the hazard's cap added to
    gp.choice.max_ages where the pilot chose it; the chosen kind named outright), the signal
    bounds, the burn-in, the collection (rows alone, a longer run or more cells, rows no memory
    holds) and the balanced threshold, each through check_printed: what it keeps passes the
    stages' checks, and what it refuses is marked, never printed as advice."""
    from surrogate.stages.pilot import pilot_advice

    spec = _switch_yaml(tmp_path)
    config = to_dict(compose_cfg("reproduce", ["model=sbml", f"model.spec={spec}"]))
    named = to_dict(compose_cfg("reproduce", ["model=sbml", f"model.spec={spec}", "gp=svgp"]))
    model = sbml_agent.SbmlAgentModel(spec)
    o = InspectOptions.from_mapping(inspect_defaults())
    ranges = {"inducer": (0.0, 0.1)}
    cases = {
        "not run": (config, {"ran": False, "note": "skipped (inspect.pilot.enabled=false)"}),
        "two-state": (
            config,
            _pilot("two-state", 1.6, [1.0, 2.0, 5.0, 1.6], ["gp=svgp", "gp.optimizer=lbfgs"]),
        ),
        "a shipped cap": (
            config,
            _pilot("clock max_age=2", 2.0, [1.0, 2.0, 5.0], ["gp=clock", "gp.max_age=2"]),
        ),
        "the hazard's cap": (
            config,
            _pilot("clock max_age=1.6", 1.6, [1.0, 2.0, 5.0, 1.6], ["gp=clock", "gp.max_age=1.6"]),
        ),
        "from gp=svgp": (
            named,
            _pilot("clock max_age=0.8", 0.8, [1.0, 2.0, 5.0, 0.8], ["gp=clock", "gp.max_age=0.8"]),
        ),
        "phases": (config, _pilot("phases", None, [1.0, 2.0, 5.0], ["gp=phases"])),
    }
    printed: dict[str, list[str]] = {}
    for name, (cfg, pilot) in cases.items():
        advice = pilot_advice(cfg, pilot)
        bounds = recommendation.signal_bounds_advice(model.internal, _fixed(), ranges)
        if bounds:
            advice["signal_bounds"] = bounds
        assert inspection.check_printed(cfg, advice, {}, {}, True) == [], name
        assert "refused" not in advice and "named_refused" not in advice, name
        printed[name] = advice["overrides"]
        if advice["kind"] is not None:
            assert advice.get("signal_bounds") == "signal_bounds: {inducer: [0.0, 0.1]}", name
            for overrides in (advice["overrides"], advice["named"]):
                assert advice_check.check_advice(cfg, overrides) is None, (name, overrides)
    rule = ["gp.choice.by=measure"]  # the test suite sets the rule (tests/conftest.py)
    assert printed == {
        "not run": [], "two-state": rule, "a shipped cap": rule,
        "the hazard's cap": [*rule, "gp.choice.max_ages=[1,2,5,1.6]"],
        "from gp=svgp": ["gp=auto", *rule, "gp.choice.max_ages=[1,2,5,0.8]"],
        "phases": rule}  # fmt: skip
    # the burn-in of a network too large to enumerate (max_states: 0)
    big = _switch_yaml(tmp_path, max_states=0)
    big_config = to_dict(compose_cfg("reproduce", ["model=sbml", f"model.spec={big}"]))
    network = sbml_agent.SbmlAgentModel(big).internal
    burn = settling.burn_in_advice(network, _fixed(settle_network=np.array([40.0])),
                                   o.burn_in_factor, o.settle_tolerance)  # fmt: skip
    assert burn["applies"] and burn["enough"] is False and burn["needed_s"] == 120.0
    assert inspection.check_printed(big_config, {}, burn, {}, True) == []
    assert "refused" not in burn
    # the verdict's longer burn-in has a value for it, none for an enumerable network's
    from surrogate.stages.reproduce import advisable_burn_in

    assert advisable_burn_in(big_config, network) == network.burn_in > 0
    assert advisable_burn_in(config, model.internal) is None  # enumerable: drawn exactly
    assert advisable_burn_in({"model": {"name": "x"}}, network) is None  # no yaml to key
    # the balanced threshold where the lump is rare
    rare = _fixed(occupancy=np.array([0.02]))
    balanced = recommendation.balanced_threshold(model.internal, rare)
    assert balanced is not None and balanced["lump"] == "D >= 2"
    assert inspection.check_printed(config, {}, {}, {}, True, balanced) == []
    # the collection: the rows alone; a run too short; rows no memory holds (refused); the
    # memory a table may take pinned at 24 GiB (this box's size), not the free memory of the
    # moment (the run too short needs ~17 GiB: refused on a box with 16.0 GiB free)
    from surrogate.stages.settings import common

    monkeypatch.setattr(common, "free_memory_bytes", lambda: 24 * 2**30)
    icfg = compose_cfg(
        "inspect", ["model=sbml", f"model.spec={spec}", "collect.keep_switches=auto"]
    )
    settings = InspectSettings.from_config(icfg)
    options = InspectOptions.from_mapping(settings.options)
    population = SimpleNamespace(fields={"gaussian": {"phi_share": 0.5}})
    # the network's thinned rows keeping every switch (collect.keep_switches=auto): a row brings
    # its 10 windows' switches, so 30,000 switches at 0.005 per window need 600,000 rows
    for switch, fits in ((5e-3, "rows"), (1e-4, "time"), (1e-9, "refused")):
        collection = inspection.collection_budget(settings, options, _fixed(switch=np.full(2, switch)),
                                                  population, 1e-5)  # fmt: skip
        refusals = inspection.check_printed(to_dict(icfg), {}, {}, collection, True)
        sets = recommendation.collection_overrides(collection)
        assert collection["windows_per_row"] == 10 and "dense" not in collection
        if fits == "refused":
            assert collection["advised"] == [] and "GiB" in collection["refused"], refusals
        else:
            assert refusals == [] and collection["advised"] == sets, (fits, refusals)
            # a run too short: the longer run first, then more cells
            rows = "collect.n_per_state=" + ("30000000" if fits == "time" else "600000")
            assert sets[0][0] == rows, sets
            assert len(sets) == (2 if fits == "time" else 1), collection
            if fits == "time":
                assert sets[0][1].startswith("collect.max_time=")
                assert sets[1][1].startswith("collect.n_cells=")
    # without (collect.keep_switches=false), a run too short at collect's thinning (every 10th
    # window) is first offered every window recorded: the same rows from a tenth of the time
    tcfg = compose_cfg(
        "inspect", ["model=sbml", f"model.spec={spec}", "collect.keep_switches=false"]
    )
    thinned = InspectSettings.from_config(tcfg)
    collection = inspection.collection_budget(thinned, options, _fixed(switch=np.full(2, 1e-3)),
                                              population, 1e-5)  # fmt: skip
    sets = recommendation.collection_overrides(collection)
    assert inspection.check_printed(to_dict(tcfg), {}, {}, collection, True) == []
    assert sets[0][:2] == ["collect.n_per_state=30000000", "collect.record_every=1"], sets
    # ~1,700 s recording every window: within collect.max_time, not within its twice-the-time
    # cap, so the dense sets name a longer run (or more cells) too
    assert sets[0][2] == "collect.max_time=3400", sets
    assert len(sets) == 4 and collection["windows_per_row"] == 1
    assert len(checks) >= 10  # the distinct settings checked


def test_the_collection_is_timed_as_the_next_command_collects(tmp_path, compose_cfg) -> None:
    """The run the inspector's next command makes, timed with the blackout it adds (fewer
    windows recordable: exp(-0.025 x 20) = 0.61 of them against exp(-0.1 x 1) = 0.90), and
    collect.max_time advised at twice that time (a cap: collect stops once it has its rows;
    Wilkinson's immigration-death stopped short at the estimate, its collection's cells in the
    rarer lump less often than the population's). The command then runs through the checks."""
    from surrogate.diagnosis.recommendation import COLLECT_TIME_MARGIN
    from surrogate.simulate.transitions import recorded_share

    spec = _switch_yaml(tmp_path)
    cfg = compose_cfg("inspect", ["model=sbml", f"model.spec={spec}", "collect.keep_switches=false",
                                  "collect.record_every=1"])  # fmt: skip
    settings = InspectSettings.from_config(cfg)
    options = InspectOptions.from_mapping(settings.options)
    population = SimpleNamespace(fields={"gaussian": {"phi_share": 0.05}})
    blackout = ["collect.blackout_time=20", "collect.perturb_rate=0.025"]
    fixed = _fixed(switch=np.full(2, 5e-3))  # 30,000 switches need 6e6 rows per origin
    plain = inspection.collection_budget(settings, options, fixed, population, 1e-5)
    dark = inspection.collection_budget(settings, options, fixed, population, 1e-5, blackout)
    c = inspection._collect_source(settings).options  # the collection the inspector times
    eq = float(c["equilibration_time"])
    assert dark["blackout"] == blackout and plain["blackout"] == []
    ratio = recorded_share(0.1, 1.0) / recorded_share(0.025, 20.0)
    for lump in (0, 1):
        got = (dark["seconds_needed"][lump] - eq) / (plain["seconds_needed"][lump] - eq)
        assert got == pytest.approx(ratio, rel=1e-9), lump
    longest = max(dark["seconds_needed"])
    assert longest > float(c["max_time"])  # the default collect.max_time is too short
    cap = eq + COLLECT_TIME_MARGIN * (longest - eq)
    assert cap <= dark["max_time_needed"] < 1.1 * cap
    assert dark["n_cells_needed"] == int(np.ceil(int(c["n_cells"]) * (cap - eq)
                                                 / (float(c["max_time"]) - eq)))  # fmt: skip
    # the cap is the margin over the estimate: advised where the estimate alone would fit
    fits = inspection.collection_budget(settings, options, _fixed(switch=np.full(2, 0.03)),
                                        population, 1e-5)  # fmt: skip
    assert max(fits["seconds_needed"]) < float(c["max_time"])
    assert ("max_time_needed" in fits) == (eq + COLLECT_TIME_MARGIN
                                           * (max(fits["seconds_needed"]) - eq) > c["max_time"])  # fmt: skip
    sets = recommendation.collection_overrides(dark)
    command = inspection.next_command(to_dict(cfg), settings.setup.overrides(),
                                      {"blackout": blackout}, {"advised": sets})  # fmt: skip
    assert command["dropped"] == [] and "collect.blackout_time=20" in command["command"]
    assert f"collect.max_time={dark['max_time_needed']:g}" in command["command"]


def test_relaxation_with_plain_classes_auto_chooses_shared_bins(config, chooser) -> None:
    """`classes: auto` picks the lump's own count's bins, one lump each, which relaxation
    refuses after the choice (and after a whole collection, run stage by stage); with
    gp.class_moves=relaxation it now asks for bins both lumps share. Declared otherwise
    (`shared: false`), it is refused up front, naming the key."""
    relax = ["gp=classes", "gp.class_moves=relaxation"]
    assert check_advice(config, relax, "classes: auto") is None
    assert chooser and set(chooser) == {True}  # every stage's model alike
    done = len(chooser)
    assert check_advice(config, ["gp=classes"], "classes: auto") is None
    assert set(chooser[done:]) == {False}  # learned moves: the chooser's own choice
    done = len(chooser)
    refused = check_advice(config, relax, "classes: {auto: {shared: false}}")
    assert refused is not None and "model.classes.auto.shared is false" in refused
    assert len(chooser) == done  # refused before the choice
    kept = SbmlAgentModel.relaxation_config(
        {"spec": SPEC, "classes": {"auto": {"bins": 6, "over": {"inducer": [0, 0.1]}}}}
    )
    assert kept["classes"] == {"auto": {"bins": 6, "over": {"inducer": [0, 0.1]}, "shared": True}}


def test_coarser_classes_name_their_edges_and_run(config) -> None:
    """The verdict's "coarser classes" named no setting; now the sparse class merged with its
    neighbour, as the edges that do it, checked like every remedy: an end bin merges inwards,
    bins both lumps share lose the edge in both, and no edge left is no advice."""
    own = CountClasses("D", ((1.0,), (3.0,)), ("off", "on"))
    merged, neighbour = coarser_classes(own, "on|D>=3")
    assert merged.edges == ((1.0,), ()) and neighbour == "on|D<3"
    override = classes_override(merged)
    assert override == "++model.classes={species: D, edges: {off: [1], on: []}}"
    assert check_advice(config, ["gp=classes", override]) is None
    shared = CountClasses("P", ((2.0, 4.0, 6.0), (2.0, 4.0, 6.0)), ("off", "on"))
    merged, neighbour = coarser_classes(shared, "off|2<=P<4", shared=True)
    assert merged.edges == ((2.0, 6.0), (2.0, 6.0)) and neighbour == "off|4<=P<6"
    assert classes_override(merged) == "++model.classes={species: P, edges: [2, 6]}"
    assert coarser_classes(CountClasses("P", ((2.0,), (2.0,)), ("off", "on")), "on|P<2") is None
    assert coarser_classes(own, "on|D>=9") is None
    expression = CountClasses("P + 2 * D", ((3.0, 5.0), (3.0, 5.0)), ("off", "on"))
    found = coarser_classes(expression, "on|P + 2 * D>=5")
    assert found is not None and classes_override(found[0]) == (
        "++model.classes={expression: 'P + 2 * D', edges: [3]}")  # fmt: skip
    assert check_advice(config, ["gp=classes", classes_override(found[0])]) is None


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ([], []),
        (["model=sbml", f"model.spec={SPEC}", "collect.n_per_state=690280"],
         ["model.spec=" + SPEC, "collect.n_per_state=690280"]),
        (["gp=classes"], ["gp=classes"]),
    ],
)  # fmt: skip
def test_the_check_at_scale_a_trusted_run_names_is_its_models_and_runs(
    compose_cfg, overrides: list[str], named: list[str]
) -> None:
    """A trusted verdict names `scripts/fidelity.py` with the run's model, collection and a
    chain the run named (it once named the bare command, E. coli's, for every model): the
    command's overrides pass fidelity's checks and check the same model."""
    from surrogate.stages import fidelity as fidelity_stage
    from surrogate.stages import train as train_stage
    from surrogate.stages.reproduce import fidelity_command

    tr = train_stage.validate(compose_cfg("train", overrides))
    command = fidelity_command(tr)
    assert command.startswith("python scripts/fidelity.py")
    assert all(n in command.split() for n in named) and "seed=" not in command
    assert f"`{command}`" in Verdict(trust=True).markdown(confirm=command)
    settings = fidelity_stage.validate(compose_cfg("fidelity", command.split()[2:]))
    assert settings.setup.model.name == tr.setup.model.name
    train = settings.candidates[0].train  # trained on the run's collection and chain
    assert train.source.options == tr.source.options and train.kind == tr.kind


def test_the_next_command_the_inspector_prints_runs_and_drops_what_is_refused(config) -> None:
    """The inspection report's next run: reproduce with the inspected settings, the advised
    collection and the pilot's gp overrides, as one command the stages' checks pass; a
    collection the checks refuse together is left out and named, never printed."""
    from surrogate.stages.inspection import next_command

    setup = ["model=sbml", f"model.spec={SPEC}", "field=gaussian", "dt=0.05", "seed=0"]
    advice = {"kind": "phases", "overrides": ["gp.choice.by=measure"]}
    out = next_command(config, setup, advice, {"advised": [["collect.n_per_state=690280"]]})
    assert out == {"command": " ".join(["python3 scripts/reproduce.py", *setup,
                                        "collect.n_per_state=690280", "gp.choice.by=measure"]),
                   "dropped": []}  # fmt: skip
    assert check_advice(config, out["command"].split()[2:]) is None
    bad = next_command(config, setup, advice, {"advised": [["collect.n_per_state=-5"]]})
    assert bad["command"].split()[2:] == [*setup, "gp.choice.by=measure"]
    assert bad["dropped"][0].startswith("collect.n_per_state=-5 gp.choice.by=measure: ")
    refused = {**advice, "refused": "no"}  # a refused pilot advice is not printed here either
    assert next_command(config, setup, refused, {})["command"].split()[2:] == setup
    # the pilot's rows lagged a jump: its blackout joins the collection, checked as one
    lagged = {**advice, "blackout": list(BLACKOUT)}
    out = next_command(config, setup, lagged, {"advised": [["collect.n_per_state=690280"]]})
    assert out["command"].split()[2:] == [*setup, "collect.n_per_state=690280", *BLACKOUT,
                                          "gp.choice.by=measure"]  # fmt: skip
    assert check_advice(config, out["command"].split()[2:]) is None
    # a burn-in the report calls too short is in the command, checked with the rest
    from surrogate.stages.inspection import burn_in_overrides

    short = {"applies": True, "enough": False, "needed_s": 480.0}
    burn = burn_in_overrides(short, yaml_model=True)
    assert burn == ["++model.burn_in=480"]
    out = next_command(config, setup, advice, {"advised": [["collect.n_per_state=690280"]]}, burn)
    assert out["command"].split()[2:] == [*setup, *burn, "collect.n_per_state=690280",
                                          "gp.choice.by=measure"]  # fmt: skip
    assert check_advice(config, out["command"].split()[2:]) is None
    rebuilt = apply_overrides(config, out["command"].split()[2:])
    assert rebuilt["model"]["burn_in"] == 480
    # not where it is enough, refused, or the model is no yaml
    assert burn_in_overrides({**short, "enough": True}, yaml_model=True) == []
    assert burn_in_overrides({**short, "refused": "no"}, yaml_model=True) == []
    assert burn_in_overrides(short, yaml_model=False) == []
    # a burn-in the stages refuse is dropped with the collection, and named
    bad = next_command(config, setup, advice, {}, ["++model.burn_in=-1"])
    assert bad["command"].split()[2:] == [*setup, "gp.choice.by=measure"]
    assert bad["dropped"][0].startswith("++model.burn_in=-1 gp.choice.by=measure: ")


@pytest.mark.parametrize("model", ["sbml", "ecoli"])
def test_the_wider_collection_the_verdict_advises_runs(compose_cfg, model: str) -> None:
    """Runs outside the trained inputs: the verdict advises collect's jumps twice as far from
    the peak, as the model's own key (``model.body.perturbation`` of a yaml network,
    ``model.perturbation`` of E. coli), and the stages' checks accept it and read the new
    radius (the gene switch's exponential field came back inside its collection this way)."""
    from surrogate.config import build_model

    extra = ["model=sbml", f"model.spec={SPEC}"] if model == "sbml" else []
    config = to_dict(compose_cfg("reproduce", extra))
    built = build_model(config["model"])
    wider = built.wider_collection()
    radius = float(built.perturbation_options["radius"])
    assert wider == (f"++{built.perturbation_key}.radius={2 * radius:g}",)
    outside = {"exponential": {"share_outside": 0.5, "sampled_cell_steps": 1000, "inputs": {
        "L": {"share_below": 0.5, "share_above": 0.0, "seen": [0.0, 0.1],
              "trained": [0.01, 0.1]}}}}  # fmt: skip
    check = memo_check({}, config, model)
    v = verdict_of(lump_names=("off", "on"), outside_warning=0.01, tolerance=0.03,
                   kind=chain_kind("phi", "none", "learned"), network=model == "sbml",
                   n_per_state=1000, check=check, diagnostic={"phi0": UNBIASED, "phi1": UNBIASED},
                   failures={"exponential": ["off"]}, outside=outside, wider_collection=wider)  # fmt: skip
    assert [r.overrides for _, r in v.remedies if r.overrides] == [wider] and not v.dropped
    assert check_advice(config, list(wider)) is None
    rebuilt = build_model(apply_overrides(config, list(wider))["model"])
    assert rebuilt.perturbation_options["radius"] == 2 * radius

"""Advice that runs: every setting the verdict and the inspector print passes the stages'
own checks (issue 52), and a class that cannot exist is refused before collection."""

from __future__ import annotations

import itertools
from typing import Any

import pytest

from surrogate.config import to_dict
from surrogate.errors import ConfigError
from surrogate.kinds import chain_kind
from surrogate.stages import inspection
from surrogate.stages.advice import applied, tried_remedies, verdict
from surrogate.stages.advice_check import apply_overrides, check_advice

SPEC = "examples/gene_switch/model.yaml"  # D >= 2 is on; 25 states
UNBIASED = {"rel_bias": 0.0, "rel_bias_se": 0.01, "settling_z": 0.0}
SHARED = {"species": "P", "edges": [2, 4]}  # P runs 0-8 in both lumps


@pytest.fixture
def config(compose_cfg) -> dict[str, Any]:
    return to_dict(compose_cfg("reproduce", ["model=sbml", f"model.spec={SPEC}"]))


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
        out["outside"] = {"gaussian": {**sparse, "classes": True}}
    elif branch == "drift":
        out["class_shares"] = {"t": 100.0, "total_variation": 0.1, "p_value": 1e-6,
                               "drift": True}  # fmt: skip
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
        chains.items(), ("memory", "biased", "sparse", "sparse_classes", "drift")
    ):
        base = apply_overrides(config, groups)
        base["model"]["classes"] = SHARED

        def check(overrides, what, base=base, name=name):
            key = (name, *overrides)
            if key not in seen:
                seen[key] = check_advice(base, overrides)
            return seen[key]

        v = verdict(lump_names=("off", "on"), outside_warning=0.01, tolerance=0.03,
                    kind=chain_kind(*kind), network=True, n_per_state=1000, max_age=2.0,
                    check=check, **_measurements(branch))  # fmt: skip
        assert not v.trust
        for _, remedy in v.remedies:
            printed += bool(remedy.overrides)
            assert check(remedy.overrides, "") is None, (name, branch, remedy)
            assert all(
                f"`{o}`" in remedy.text or o.lstrip("+") in remedy.text for o in remedy.overrides
            ), remedy  # the strings checked are printed
        dropped += len(v.dropped)
    assert printed >= 10


def test_nan_or_missing_measurements_are_not_measured_never_trust() -> None:
    """Issue 54 item 7: a NaN bias (a reference that never left a lump), an absent
    diagnostic or an absent outside-training report made the verdict trust the run."""
    args: dict[str, Any] = {"lump_names": ("off", "on"), "failures": {"gaussian": []},
                            "outside_warning": 0.01, "tolerance": 0.03, "network": True,
                            "kind": chain_kind("phi", "none", "learned"), "n_per_state": 100}  # fmt: skip
    inside = {"gaussian": {"share_outside": 0.0, "inputs": {}}}
    full = {"phi0": UNBIASED, "phi1": UNBIASED}
    assert verdict(diagnostic=full, outside=inside, **args).trust
    cases = {
        "bias leaving on": ({"phi0": UNBIASED, "phi1": {**UNBIASED, "rel_bias": float("nan")}},
                            inside),
        "diagnostic (none": (None, inside),
        "diagnostic leaving off": ({"phi1": UNBIASED}, inside),
        "field gaussian": (full, {"gaussian": None}),
    }  # fmt: skip
    for what, (diagnostic, outside) in cases.items():
        v = verdict(diagnostic=diagnostic, outside=outside, **args)
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
    args: dict[str, Any] = {"diagnostic": {"phi0": UNBIASED, "phi1": UNBIASED},
                            "lump_names": ("off", "on"), "failures": {"g": ["off"]},
                            "outside": {"g": {"share_outside": 0.0, "inputs": {}}},
                            "outside_warning": 0.01, "tolerance": 0.03, "network": True,
                            "kind": chain_kind("phi", "age", "learned"), "n_per_state": 20000,
                            "max_age": 4.0}  # fmt: skip
    assert "gp.max_age=8" in verdict(**args).causes[0][2]
    step = verdict(**args, tried=tried).causes[0][2]
    assert "`gp.max_age=8`" not in step and "collect.n_per_state=80000`" not in step
    assert "tried: `gp.max_age=4` ran" in step and "gp=classes" in step


def test_collection_advice_names_the_run_it_needs_and_it_runs(config) -> None:
    """collect.max_time too short: the advice gives the max_time, or the cells, that fit the
    rows (the report printed 'too short' with no value to set)."""
    collection = {"recommended_n_per_state": 5000, "max_time": 200.0,
                  "seconds_needed": [900.0, 450.0], "max_time_needed": 900.0,
                  "n_cells_needed": 460}  # fmt: skip
    sets = inspection.collection_overrides(collection)
    assert sets == [
        ["collect.n_per_state=5000", "collect.max_time=900"],
        ["collect.n_per_state=5000", "collect.n_cells=460"],
    ]
    advice = {"abstraction": "clock", "overrides": ["gp=clock", "gp.max_age=4"], "yaml": ""}
    burn = {"applies": True, "enough": False, "needed_s": 30.0}
    assert inspection.check_printed(config, advice, burn, collection, True) == []
    assert collection["advised"] == sets and "refused" not in advice
    bad = {"abstraction": "classes", "overrides": ["gp=classes"],
           "yaml": "classes: {species: D, edges: [1, 3]}"}  # fmt: skip
    (refusal,) = inspection.check_printed(config, bad, {}, {}, True)
    assert "cannot occur" in bad["refused"] and refusal.startswith("the abstraction")

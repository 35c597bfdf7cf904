"""A fidelity check against the previous check of the same model and size: the advice it
followed, whether the count then fell, and a reused check's log naming a later check that
followed its advice for fewer passes (surrogate/stages/check_history.py)."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from surrogate.stages import check_history
from surrogate.stages.check_history import (
    PREVIOUS,
    compare_with_previous,
    describe,
    describe_not_advised,
    followed_for_worse,
    tried_in_vain,
    warn_followed_for_worse,
)

REMEDY = ["++model.classes=auto", "collect.keep_switches=true"]
STEM = "model=cerena_n=1000_T=200_seeds=0+1"


def _config(**changes: Any) -> dict[str, Any]:
    config: dict[str, Any] = {
        "model": {"spec": "m.yaml"},
        "collect": {"keep_switches": False},
        "fidelity": {"fields": ["gaussian", "linear"], "duration_tolerance": 0.03,
                     "ks_max": 1.0, "ks_factor": 1.5, "alpha": 0.05, "start": [2.0, 0.0],
                     "equilibration_time": 10.0, "train_seeds": [0, 1], "sim_seed": 5000},
    }  # fmt: skip
    for key, value in changes.items():
        group, name = key.split("__")
        config[group] = {**config.get(group, {}), name: value}
    return config


def _check(root: Path, tag: str, config: dict[str, Any], passed: int,
           summary: dict[str, Any], when: int) -> Path:  # fmt: skip
    d = root / f"{STEM}-{tag}"
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({"passed": passed, "checks": 24, **summary}))
    (d / "manifest.json").write_text(json.dumps({"stage": "fidelity", "config": config,
                                                 "passed": passed, "checks": 24}))  # fmt: skip
    os.utime(d / "manifest.json", ns=(when, when))
    return d


def test_a_followed_remedy_that_passed_fewer_is_said_to_and_found_from_the_first(tmp_path):
    """CERENA's route: 20 of 24 printed the classes remedy; followed, 17. The second check's
    record says it followed that advice for fewer; the first, reused, names the second."""
    first = _check(tmp_path, "a", _config(), 20, {"wider_choice": REMEDY}, 1_000)
    now = _config(model__classes="auto", collect__keep_switches=True)
    record = compare_with_previous(tmp_path / f"{STEM}-b", now, 17, 24)
    assert record == {"directory": first.name, "passed": 20, "checks": 24, "printed": True,
                      "followed": [REMEDY], "now": 17, "fewer": True}  # fmt: skip
    text = describe(record, 24)
    assert "passed 20 of 24" in text and "it passes 17 of 24, fewer" in text
    assert "Keep the previous command's settings" in text
    second = _check(tmp_path, "b", now, 17, {PREVIOUS: record}, 2_000)
    later = followed_for_worse(first, _config())
    assert later == [{"directory": second.name, "passed": 17, "checks": 24,
                      "followed": [REMEDY]}]  # fmt: skip
    assert followed_for_worse(second, now) == []  # nothing followed the second's advice
    # the first made again (force): compared with neither the second, which followed it
    assert compare_with_previous(first, _config(), 20, 24) is None
    # the advice is not printed again for settings like the first's (drawn again, say)
    drawn = _config(fidelity__sim_seed=15000)
    tried = tried_in_vain(tmp_path / f"{STEM}-c", drawn)
    assert tried == {" ".join(REMEDY): {"directory": second.name, "passed": 17, "checks": 24,
                                         "before": "20 of 24"}}  # fmt: skip
    assert describe_not_advised(tried).startswith(f"Not advised again: `{' '.join(REMEDY)}`")
    assert tried_in_vain(tmp_path / f"{STEM}-c", now) == {}  # already followed: nothing to keep


def test_a_reused_check_logs_the_later_check_that_followed_its_advice_for_fewer(
    tmp_path, caplog
) -> None:
    first = _check(tmp_path, "a", _config(), 20, {"wider_choice": REMEDY}, 1_000)
    now = _config(model__classes="auto", collect__keep_switches=True)
    record = compare_with_previous(tmp_path / f"{STEM}-b", now, 17, 24)
    _check(tmp_path, "b", now, 17, {PREVIOUS: record}, 2_000)
    with caplog.at_level(logging.WARNING, logger=check_history.__name__):
        warn_followed_for_worse(first, _config(), 20)
    assert "was followed in" in caplog.text and "passed 17 of 24" in caplog.text
    assert "keep this command's settings" in caplog.text


def test_a_followed_remedy_that_gained_and_a_check_that_followed_none(tmp_path) -> None:
    _check(tmp_path, "a", _config(), 17, {"wider_choice": REMEDY, "draw_again": ["x=1"]}, 1)
    now = _config(model__classes="auto", collect__keep_switches=True)
    record = compare_with_previous(tmp_path / f"{STEM}-b", now, 22, 24)
    assert record is not None and record["followed"] and not record["fewer"]
    assert describe(record, 24).endswith("it passes 22 of 24.")
    # the same settings drawn again: no remedy followed (draw_again is a diagnosis)
    drawn = compare_with_previous(tmp_path / f"{STEM}-c", _config(fidelity__sim_seed=15000),
                                  15, 24)  # fmt: skip
    assert drawn is not None and drawn["followed"] == [] and not drawn["fewer"]
    assert "followed none of the advice" in describe(drawn, 24)


def test_the_previous_check_is_the_one_whose_advice_was_followed(tmp_path) -> None:
    """A followed B: an unrelated check made between them is not taken for B's previous; the
    counts compare as shares (another set of check times changes the total); a previous
    check that printed no advice is not said to have printed some."""
    first = _check(tmp_path, "a", _config(), 20, {"wider_choice": REMEDY}, 1)
    _check(tmp_path, "m", _config(gp__n_inducing=12), 21, {}, 2)  # unrelated, newer
    now = _config(model__classes="auto", collect__keep_switches=True)
    record = compare_with_previous(tmp_path / f"{STEM}-b", now, 21, 30)
    assert record is not None and record["directory"] == first.name
    assert record["followed"] == [REMEDY] and record["fewer"]  # 21 of 30 < 20 of 24
    assert not compare_with_previous(tmp_path / f"{STEM}-b", now, 26, 30)["fewer"]
    plain = compare_with_previous(tmp_path / f"{STEM}-b", _config(gp__n_inducing=16), 20, 24)
    assert plain is not None and plain["directory"] == f"{STEM}-m" and not plain["printed"]
    assert describe(plain, 24).endswith("passed 21 of 24.")


def test_a_model_name_with_brackets_finds_its_previous_check(tmp_path) -> None:
    stem = "model=m[1]_n=10_T=2_seeds=0"
    d = tmp_path / f"{stem}-a"
    d.mkdir()
    (d / "summary.json").write_text(json.dumps({"wider_choice": REMEDY}))
    (d / "manifest.json").write_text(json.dumps({"stage": "fidelity", "config": _config(),
                                                 "passed": 3, "checks": 4}))  # fmt: skip
    record = compare_with_previous(tmp_path / f"{stem}-b", _config(), 3, 4)
    assert record is not None and record["directory"] == d.name


def test_only_checks_of_the_same_model_size_and_thresholds_are_compared(tmp_path) -> None:
    _check(tmp_path, "a", _config(), 20, {"wider_choice": REMEDY}, 1)
    (tmp_path / "model=cerena_n=2000_T=200_seeds=0+1-z").mkdir()  # another size: not read
    now = _config(model__classes="auto", collect__keep_switches=True)
    assert compare_with_previous(tmp_path / f"{STEM}-b",
                                 {**now, "fidelity": {**now["fidelity"],
                                                      "duration_tolerance": 0.05}},
                                 17, 24) is None  # fmt: skip
    half = tmp_path / f"{STEM}-h"  # a check with no manifest yet (killed): not read
    half.mkdir()
    (half / "summary.json").write_text("{}")
    record = compare_with_previous(tmp_path / f"{STEM}-b", now, 17, 24)
    assert record is not None and record["directory"] == f"{STEM}-a"
    assert compare_with_previous(tmp_path / "model=other_n=1000_T=200_seeds=0+1-b", now, 17,
                                 24) is None  # fmt: skip
    assert describe(None, 24) == ""


def test_the_fidelity_stage_records_the_comparison_and_a_reused_check_warns(
    compose_cfg, caplog
) -> None:
    """The wiring, on two small checks: the second, made with advice the first printed (put
    into its summary here), records what it followed and says so in its report; the first,
    reused, logs the second where it passed fewer (its count raised here to make it so)."""
    from surrogate.stages import fidelity
    from tests.stages.test_fidelity import SMALL

    first = fidelity.run(compose_cfg("fidelity", SMALL))
    assert json.loads((first / "summary.json").read_text())[PREVIOUS] is None
    summary = json.loads((first / "summary.json").read_text())
    (first / "summary.json").write_text(json.dumps({**summary, "wider_choice":
                                                    ["gp.n_inducing=12"]}))  # fmt: skip
    manifest = json.loads((first / "manifest.json").read_text())
    (first / "manifest.json").write_text(json.dumps({**manifest, "passed": 100}))
    second = fidelity.run(compose_cfg("fidelity", [*SMALL, "gp.n_inducing=12"]))
    record = json.loads((second / "summary.json").read_text())[PREVIOUS]
    assert record["directory"] == first.name and record["followed"] == [["gp.n_inducing=12"]]
    assert record["fewer"] and record["passed"] == 100
    assert "which this check followed" in (second / "fidelity.md").read_text()
    with caplog.at_level(logging.WARNING):
        assert fidelity.run(compose_cfg("fidelity", SMALL)) == first  # reused
    assert f"was followed in {second.name}" in caplog.text

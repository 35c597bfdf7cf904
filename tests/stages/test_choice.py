"""The measured choice's settings (surrogate/stages/choice.py): bad values refused by key."""

from __future__ import annotations

import pytest

from surrogate.errors import ConfigError
from surrogate.stages.choice import ChoiceSettings, candidates, check_windows, validate


@pytest.mark.parametrize(
    ("options", "key"),
    [
        ({"max_ages": [1.0, 0.0]}, "choose.max_ages"),
        ({"max_ages": "2"}, "choose.max_ages"),
        ({"n_cells": 1.5}, "choose.n_cells"),
        ({"t_end": -1}, "choose.t_end"),
        ({"tie_se": 0}, "choose.tie_se"),
        ({"equilibration_time": -1.0}, "choose.equilibration_time"),
        ({"cells": 10}, "choose"),
    ],
)
def test_bad_choose_settings_are_refused_by_key(options: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        ChoiceSettings.from_config(options)


def test_candidates_follow_the_model() -> None:
    """K lumps only where the model declares classes; one clock per cap; the hidden phases
    (a registered candidate) last."""
    settings = ChoiceSettings.from_config({"max_ages": [1, 3]})

    class Plain:
        pass

    names = list(candidates(settings, Plain()))
    assert names == ["two-state", "clock max_age=1", "clock max_age=3", "phases"]
    assert candidates(settings, Plain())["phases"]["lumps"] == "phases"  # a registered candidate
    assert candidates(settings, Plain())["clock max_age=3"]["max_age"] == 3.0


def test_a_cap_named_twice_is_refused_with_the_list_that_passes() -> None:
    """[1, 1.0] was one candidate, listed once, silently."""
    with pytest.raises(ConfigError, match=r"choose\.max_ages=\[1, 1\.0, 2\] names a cap twice.*"
                                          r"use choose\.max_ages=\[1\.0, 2\.0\]"):  # fmt: skip
        ChoiceSettings.from_config({"max_ages": [1, 1.0, 2]})
    assert ChoiceSettings.from_config({"max_ages": [1.0, 2.0]}).max_ages == (1.0, 2.0)


def test_one_held_out_cell_is_refused() -> None:
    """One cell gives the paired difference no SE: no candidate could tie the best."""
    with pytest.raises(ConfigError, match=r"choose\.n_cells=1 .*use choose\.n_cells=2 or more"):
        ChoiceSettings.from_config({"n_cells": 1})
    assert ChoiceSettings.from_config({"n_cells": 2}).n_cells == 2


def test_a_held_out_run_shorter_than_a_window_is_refused() -> None:
    """t_end < dt was rounded up to one window, silently."""
    with pytest.raises(ConfigError, match=r"choose\.t_end=0\.01 s is shorter than one window "
                                          r"\(dt=0\.05 s\).*use choose\.t_end=50"):  # fmt: skip
        check_windows(ChoiceSettings.from_config({"t_end": 0.01}), 0.05)
    check_windows(ChoiceSettings.from_config({"t_end": 50.0}), 0.05)


def test_a_cap_below_a_window_is_refused() -> None:
    """The clock counts whole windows: a cap of 0.01 s at dt 0.05 s ran as 0.05 s."""
    with pytest.raises(ConfigError, match=r"choose\.max_ages has cap\(s\) \[0\.01\] below one "
                                          r"window.*choose\.max_ages=\[2\.0\]"):  # fmt: skip
        check_windows(ChoiceSettings.from_config({"max_ages": [0.01, 2.0]}), 0.05)
    check_windows(ChoiceSettings.from_config({"max_ages": [2.0]}), 0.05)


def test_validate_checks_the_windows_before_any_work(compose_cfg) -> None:
    """The choice's validation (before the collection) reads the model's dt."""
    with pytest.raises(ConfigError, match=r"choose\.t_end=0\.01 s"):
        validate(compose_cfg("choose", ["choose.t_end=0.01"]))

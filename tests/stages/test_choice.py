"""The measured choice's settings (surrogate/stages/choice.py): bad values refused by key."""

from __future__ import annotations

import pytest

from surrogate.errors import ConfigError
from surrogate.stages.choice import ChoiceSettings, candidates


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

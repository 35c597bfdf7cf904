"""The inspection's typed options: built from the validated ``inspect`` keys, every key
carried unchanged, a missing or unknown key refused by name."""

from __future__ import annotations

import dataclasses

import pytest

from surrogate.diagnosis.options import InspectOptions
from surrogate.errors import ConfigError
from surrogate.stages.settings.inspection import inspect_defaults


def test_every_inspect_key_is_an_option_with_its_value() -> None:
    """The shipped keys and the options' fields are the same set, and each value is carried
    as given (an integer stays one, so every figure written from it is unchanged)."""
    defaults = inspect_defaults()
    options = InspectOptions.from_mapping(defaults)
    assert {f.name for f in dataclasses.fields(InspectOptions)} == set(defaults)
    for key, value in defaults.items():
        got = getattr(options, key)
        assert got == (tuple(value) if key == "quantiles" else value), key
        assert type(got) is (tuple if key == "quantiles" else type(value)), key
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.n_cells = 1  # type: ignore[misc]


def test_a_missing_or_unknown_key_is_refused_by_name() -> None:
    defaults = inspect_defaults()
    with pytest.raises(ConfigError, match=r"missing inspect\.n_cells"):
        InspectOptions.from_mapping({k: v for k, v in defaults.items() if k != "n_cells"})
    with pytest.raises(ConfigError, match=r"unknown inspect\.n_cell\b"):
        InspectOptions.from_mapping({**defaults, "n_cell": 3})

"""The one check of a settings mapping with known keys (surrogate.validation.known_keys)."""

from __future__ import annotations

import pytest

from surrogate.errors import ConfigError
from surrogate.validation import known_keys, yaml_hint


def test_a_mapping_with_known_keys_comes_back_as_a_dict() -> None:
    given = {"lags": [1, 2]}
    out = known_keys(given, ("n_cells", "lags"), "gp.relaxation", required=("lags",))
    assert out == given and type(out) is dict and out is not given


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (
            {"every": 1, "n_cells": 5},
            r"unknown gp.relaxation setting\(s\) \['every'\]; allowed: "
            r"\['n_cells', 'lags'\]",
        ),
        ({1: 2, "b": 3}, r"unknown gp.relaxation setting\(s\) \[1, 'b'\]"),  # any key type
        ({"n_cells": 5}, r"gp.relaxation needs the setting\(s\) \['lags'\]"),
        (7, r"gp.relaxation must be a mapping of settings \['n_cells', 'lags'\], got 7"),
        ("1e3", r"got '1e3' \(YAML reads 1e3 as a string"),
    ],
)
def test_unknown_missing_and_wrong_types_are_named(value, message) -> None:
    with pytest.raises(ConfigError, match=message):
        known_keys(value, ("n_cells", "lags"), "gp.relaxation", required=("lags",))


def test_the_shape_says_what_a_non_mapping_should_be() -> None:
    with pytest.raises(ConfigError, match=r"model.classes must be auto or a mapping, got 3"):
        known_keys(3, ("edges",), "model.classes", shape="auto or a mapping")


def test_yaml_hint() -> None:
    assert yaml_hint("1e308") == " (YAML reads 1e308 as a string: write 1.0e+308)"
    assert yaml_hint("0.5").startswith(" (a number in quotes") and yaml_hint(0.5) == ""

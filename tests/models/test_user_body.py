"""A user's own body, named by `_target_` in the model's yaml: built without editing the
package's registry, its members checked when it is built."""

from __future__ import annotations

from typing import Any

import pytest

from surrogate.errors import ConfigError
from surrogate.models.bodies import build_body
from surrogate.models.bodies.walker import Walker


class SlowWalker(Walker):
    """A user's body: the library walker at a chosen speed (stands for any user class)."""

    def __init__(self, options: dict[str, Any], where: str) -> None:
        self.factor = float(options.pop("factor", 0.5))
        super().__init__(options, where)


class NotABody:
    def __init__(self, options: dict[str, Any], where: str) -> None:
        self.options = options


def test_a_user_body_by_target_is_built_with_its_options() -> None:
    body = build_body({"_target_": f"{__name__}.SlowWalker", "factor": 0.25})
    assert isinstance(body, SlowWalker) and body.factor == 0.25
    assert body.variable_names == build_body({"kind": "walker"}).variable_names


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (
            {"_target_": "no_such_module.Body"},
            r"model.body._target_: cannot import 'no_such_module",
        ),
        ({"_target_": f"{__name__}.NotABody"}, r"lacks the body members \['variable_names'"),
        ({"_target_": f"{__name__}.SlowWalker", "kind": "walker"}, r"`kind` .* or `_target_`"),
    ],
)
def test_a_bad_user_body_is_refused_by_name(options, message) -> None:
    with pytest.raises(ConfigError, match=message):
        build_body(options)

"""The body kinds a model's yaml can name (``body.kind``) and :func:`build_body`, which builds
one from its options. A new body is registered here."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from surrogate.errors import ConfigError
from surrogate.models.bodies.chemotaxis import RunAndTumbleBody
from surrogate.models.bodies.static import StaticAgent
from surrogate.models.bodies.walker import Walker

#: body kinds and their classes
BODY_KINDS: dict[str, type] = {
    "chemotaxis": RunAndTumbleBody,
    "walker": Walker,
    "static": StaticAgent,
}


def build_body(options: Mapping[str, Any], where: str = "model.body") -> Any:
    """The library body ``options["kind"]`` with the other options as its parameters."""
    if not isinstance(options, Mapping):
        raise ConfigError(f"{where} must be a mapping with a `kind` ({sorted(BODY_KINDS)}), got "
                          f"{options!r}")  # fmt: skip
    params = dict(options)
    kind = params.pop("kind", None)
    if kind not in BODY_KINDS:
        raise ConfigError(f"{where}.kind must be one of {sorted(BODY_KINDS)}, got {kind!r}")
    return BODY_KINDS[kind](params, where)


__all__ = ["BODY_KINDS", "build_body"]

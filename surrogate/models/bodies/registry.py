"""The body kinds a model's yaml can name (``body.kind``) and :func:`build_body`, which builds
one from its options. A new body is registered here."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.models.base import AgentBody
from surrogate.models.bodies.chemotaxis import RunAndTumbleBody
from surrogate.models.bodies.static import StaticAgent
from surrogate.models.bodies.walker import Walker


class LibraryBody(AgentBody, Protocol):
    """What a library body gives beyond :class:`~surrogate.models.base.AgentBody` (what the
    SBML agent reads): its variables, derived inputs, perturbation options, dt check and
    figure labels."""

    @property
    def variable_names(self) -> tuple[str, ...]: ...
    @property
    def derived(self) -> Mapping[str, Callable[[Tensor], Tensor]]: ...
    @property
    def perturbation_options(self) -> Mapping[str, Any]: ...

    def validate(self, dt: float) -> None:
        """Refuse a time step the body cannot be stepped with (ConfigError)."""
        ...

    def observable_label(self, name: str) -> str:
        """Figure label of an observable."""
        ...


#: body kinds and their classes (each built as ``cls(options, where)``)
BODY_KINDS: dict[str, Callable[[Mapping[str, Any], str], LibraryBody]] = {
    "chemotaxis": RunAndTumbleBody,
    "walker": Walker,
    "static": StaticAgent,
}


def build_body(options: Mapping[str, Any], where: str = "model.body") -> LibraryBody:
    """The library body ``options["kind"]`` with the other options as its parameters."""
    if not isinstance(options, Mapping):
        raise ConfigError(f"{where} must be a mapping with a `kind` ({sorted(BODY_KINDS)}), got "
                          f"{options!r}")  # fmt: skip
    params = dict(options)
    kind = params.pop("kind", None)
    if kind not in BODY_KINDS:
        raise ConfigError(f"{where}.kind must be one of {sorted(BODY_KINDS)}, got {kind!r}")
    return BODY_KINDS[kind](params, where)


__all__ = ["BODY_KINDS", "LibraryBody", "build_body"]

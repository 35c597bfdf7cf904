"""The body kinds a model's yaml can name (``body.kind``) and :func:`build_body`, which builds
one from its options. A library body is registered here; a user's own body needs no edit of the
package: the yaml names its class by ``_target_`` (``body: {_target_: my_module.MyBody, ...}``),
built as the library's are (``cls(options, where)``) and checked against :class:`LibraryBody`."""

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


#: what :func:`build_body` checks a user's body class gives (:class:`LibraryBody`'s members
#: beyond what every body has, and the body contract's core)
BODY_MEMBERS = ("variable_names", "derived", "perturbation_options", "validate",
                "observable_label", "initial_state", "inputs")  # fmt: skip


def _user_body(target: Any, params: dict[str, Any], where: str) -> LibraryBody:
    """The user's body class ``target`` (a dotted path) built from ``params``, its members
    checked so a missing one is named now, not deep in a run."""
    from hydra.utils import get_class

    try:
        cls = get_class(str(target))
    except Exception as exc:  # ImportError, AttributeError, ValueError: the path is wrong
        raise ConfigError(f"{where}._target_: cannot import {target!r} ({exc})") from None
    body = cls(params, where)
    missing = [m for m in BODY_MEMBERS if not hasattr(body, m)]
    if missing:
        raise ConfigError(f"{where}._target_: {target} lacks the body members {missing} "
                          f"(surrogate.models.bodies.registry.LibraryBody)")  # fmt: skip
    return body


def build_body(options: Mapping[str, Any], where: str = "model.body") -> LibraryBody:
    """The library body ``options["kind"]``, or the user's class ``options["_target_"]``, with
    the other options as its parameters."""
    if not isinstance(options, Mapping):
        raise ConfigError(f"{where} must be a mapping with a `kind` ({sorted(BODY_KINDS)}), got "
                          f"{options!r}")  # fmt: skip
    params = dict(options)
    if "_target_" in params:
        target = params.pop("_target_")
        if "kind" in params:
            raise ConfigError(f"{where}: give `kind` (a library body) or `_target_` (your own "
                              f"class), not both")  # fmt: skip
        return _user_body(target, params, where)
    kind = params.pop("kind", None)
    if kind not in BODY_KINDS:
        raise ConfigError(f"{where}.kind must be one of {sorted(BODY_KINDS)}, got {kind!r}")
    return BODY_KINDS[kind](params, where)


__all__ = ["BODY_KINDS", "BODY_MEMBERS", "LibraryBody", "build_body"]

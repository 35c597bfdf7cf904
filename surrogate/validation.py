"""Checks of settings that every layer shares: a mapping with known keys, and the hint for a
number YAML read as text.

This module sits beside :mod:`surrogate.errors` (it imports nothing else of the package), so the
models, the grid, the GP layer and the stages all check a settings mapping the same way and
say the same thing. The number checks of the stages' settings (``positive``, ``non_negative``)
live in :mod:`surrogate.config`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from surrogate.errors import ConfigError

__all__ = ["known_keys", "yaml_hint"]


def known_keys(
    value: Any,
    allowed: Iterable[str],
    where: str,
    required: Iterable[str] = (),
    shape: str | None = None,
) -> dict[str, Any]:
    """``value`` as a dict, refusing anything but a mapping, a key outside ``allowed`` and a
    missing ``required`` key, each by name.

    Args:
        value: The setting as given (a mapping, or anything a config may hold).
        allowed: The keys it may have, listed in this order in the messages.
        where: The setting's name in messages (e.g. ``"gp.relaxation"``).
        required: The keys it must have (each also in ``allowed``).
        shape: What it must be, for the message when it is not a mapping (default: "a mapping
            of settings [<allowed>]").

    Returns:
        A plain dict of ``value``'s items.

    Raises:
        ConfigError: ``<where> must be ...``, ``unknown <where> setting(s) [...]; allowed:
            [...]`` or ``<where> needs the setting(s) [...]``.

    Example:
        >>> known_keys({"lags": [1, 2]}, ("n_cells", "lags"), "gp.relaxation")
        {'lags': [1, 2]}
        >>> known_keys({"every": 1}, ("n_cells", "lags"), "gp.relaxation")
        Traceback (most recent call last):
        ...
        surrogate.errors.ConfigError: unknown gp.relaxation setting(s) ['every']; allowed: ['n_cells', 'lags']
    """
    keys = list(allowed)
    if not isinstance(value, Mapping):
        want = shape if shape is not None else f"a mapping of settings {keys}"
        raise ConfigError(f"{where} must be {want}, got {value!r}{yaml_hint(value)}")
    unknown = sorted((k for k in value if k not in keys), key=str)
    if unknown:
        raise ConfigError(f"unknown {where} setting(s) {unknown}; allowed: {keys}")
    missing = [k for k in required if k not in value]
    if missing:
        raise ConfigError(f"{where} needs the setting(s) {missing}; allowed: {keys}")
    return dict(value)


def yaml_hint(value: Any) -> str:
    """A hint for a number YAML read as a string, else ``""``: PyYAML reads ``1e308`` or
    ``1e-3`` (no decimal point, or an unsigned exponent) as text, and a quoted number too.

    Example:
        >>> yaml_hint("1e308")
        ' (YAML reads 1e308 as a string: write 1.0e+308)'
    """
    if not isinstance(value, str):
        return ""
    text = value.strip()
    try:
        finite = math.isfinite(float(text))
    except ValueError:
        return ""
    if not finite:  # nan, inf: YAML's own spellings are .nan, .inf
        return ""
    mantissa, e, exponent = text.lower().partition("e")
    if not e:
        return f" (a number in quotes is a string: write {text} without them)"
    mantissa += "" if "." in mantissa else ".0"
    exponent = exponent if exponent[:1] in ("+", "-") else f"+{exponent}"
    return f" (YAML reads {text} as a string: write {mantissa}e{exponent})"

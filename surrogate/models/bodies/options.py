"""Typed reading of a library body's parameters: each one checked and refused by its name."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from surrogate.errors import ConfigError
from surrogate.validation import yaml_hint

__all__ = ["number"]


def number(options: Mapping[str, Any], key: str, where: str, minimum: float = 0.0) -> float:
    """``options[key]`` as a finite float >= ``minimum``, else a ConfigError naming
    ``where.key`` and the value (a string, a bool or a list are the wrong type)."""
    value = options[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{where}.{key} must be a finite number, got {value!r}{yaml_hint(value)}")
    if value < minimum:
        raise ConfigError(f"{where}.{key} must be >= {minimum:g}, got {value!r}")
    return float(value)

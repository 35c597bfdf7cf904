"""The error raised for SBML files surrogate cannot read."""

from __future__ import annotations

from surrogate.errors import ConfigError

__all__ = ["SbmlError"]


class SbmlError(ConfigError):
    """An SBML file is invalid or uses a construct surrogate does not support.

    The message names the construct and the id of the element that uses it.
    """

"""The error raised for SBML files surrogate cannot read, and the warning for what it reads
differently from the file's flags."""

from __future__ import annotations

from surrogate.errors import ConfigError

__all__ = ["SbmlError", "SbmlWarning"]


class SbmlError(ConfigError):
    """An SBML file is invalid or uses a construct surrogate does not support.

    The message names the construct and the id of the element that uses it.
    """


class SbmlWarning(UserWarning):
    """The file was read in a way its flags do not say, by a documented rule (e.g. a reaction
    flagged reversible whose law is one-way, read as irreversible); the message lists every
    element concerned."""

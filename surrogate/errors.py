"""Exception types: every user-facing failure names the setting or file at fault."""

from __future__ import annotations


class SurrogateError(Exception):
    """Base class of all errors raised deliberately by surrogate."""


class ConfigError(SurrogateError, ValueError):
    """A setting is invalid; the message names the setting and what is allowed."""


class KernelUnsupported(ConfigError):
    """A model's compiled per-cell kernel cannot run this combination (the message says what);
    ``backend=auto`` then keeps the torch step."""


class ArtefactError(SurrogateError, RuntimeError):
    """An artefact is corrupt, truncated or was made with other settings."""


class MissingArtefactError(ArtefactError, FileNotFoundError):
    """An artefact from an earlier stage is missing; the message says which command makes it."""


class NumericalError(SurrogateError, FloatingPointError):
    """NaN or infinite values where finite numbers are required."""


class CompileError(SurrogateError, RuntimeError):
    """``torch.compile`` failed where the settings ask for a compiled run (its results would not
    be the compiled run's)."""


class EventCapError(SurrogateError, RuntimeError):
    """An SSA stopped a window at its cap on events (the compiled SSA's ``max_events``, the
    batched SSA's ``max_rounds``): raised where the cap is hit, so callers catch the type, not
    a message's wording."""


class RunawayError(ConfigError, RuntimeError):
    """A network's cell made more SSA events in one window than its cap (a count growing
    without bound); a ``RuntimeError`` too, as the SSAs' own cap is."""

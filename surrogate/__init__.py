"""surrogate: statistical abstraction of multi-scale stochastic agent simulations."""

from __future__ import annotations

__version__ = "0.1.0"

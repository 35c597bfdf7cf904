"""surrogate: statistical abstraction of multi-scale stochastic agent simulations."""

from __future__ import annotations

# first, before anything imports torch: idle OpenMP threads sleep, not spin (surrogate.threads)
import surrogate.threads  # noqa: F401

__version__ = "0.1.0"

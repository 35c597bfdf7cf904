"""The random rows a pure function asks the simulator for (:class:`Randoms`).

Kept apart from :mod:`surrogate.models.base` so that :mod:`surrogate.models.capabilities`,
which base's :class:`~surrogate.models.base.Model` reads optional capabilities through, needs
nothing of base at import time. Import it from :mod:`surrogate.models.base`, which re-exports it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Randoms:
    """Random numbers a pure function needs per cell and step, drawn by the simulator in bulk.

    Attributes:
        uniform: rows of float32 U[0, 1).
        uniform64: rows of float64 U[0, 1) (probabilities below float32 resolution).
        normal: rows of float32 N(0, 1).
    """

    uniform: int = 0
    uniform64: int = 0
    normal: int = 0


__all__ = ["Randoms"]

"""What the inspection measures at fixed inputs (items 3, 4 and 6): occupancy, settling,
relaxation and memory of phi at each grid point, as :class:`FixedInputs`, exactly
(:mod:`surrogate.diagnosis.exact`) or by simulation (:mod:`surrogate.diagnosis.simulated`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from surrogate.evaluate.dynamics import Oscillation

#: :attr:`FixedInputs.method`: measured on the network's generator, or on simulated cells (the
#: inspection's words; ``exact`` here is no decision=exact layer, issue 40)
EXACT_METHOD, SIMULATED_METHOD = "exact", "simulated"


@dataclass
class FixedInputs:
    """Occupancy, settling, relaxation and memory of phi at the grid's fixed inputs.

    Attributes:
        method: :data:`EXACT_METHOD` (the generator) or :data:`SIMULATED_METHOD`.
        occupancy, occupancy_se: ``(G,)`` the stationary P(phi = 1) at each grid point.
        settled: ``(G,)`` whether the point settled within the horizon.
        settle_phi: ``(G,)`` the settling time of phi's occupancy (s).
        settle_network: ``(G,)`` the largest settling time of a species' mean count (s).
        species_settle: per species, its settling time at the median point (s).
        curves: the median point's mean counts and occupancy over time (for the figure).
        horizon: the run's (or the exact curve's) length (s).
        relaxation: the lump's relaxation time at the median point (s) and how it was
            measured.
        hazards: per origin, the hazard of leaving it against the time since phi changed.
        memory: whether phi's switching has memory at the median point (None: it never
            switches there).
        switch: ``(2,)`` P(phi changes over a window | phi = 0, 1) at the median point.
        events: mean SSA events per window at stationarity at the median point (networks).
        species_law: per species, its stationary values and weights at the median point.
        stopped: the stationary share of the median point's cells (or probability, exactly)
            in a state where no reaction can fire (networks; None otherwise): near 1, the
            network runs down to an absorbing state (a closed system that consumes its
            substrate, a decay with no source) and phi stops changing.
        stopped_state: the most frequent such state (``{species: count}``), for the message.
        oscillation: whether phi oscillates at the median point (:func:`oscillation_dict`:
            its autocorrelation's negative lobe, period and, simulated, the durations of its
            segments); None where not measured.
        cells: cells per grid point (simulated).
        notes: what the budget cut.
        cost: estimated seconds of simulation.
    """

    method: str
    occupancy: np.ndarray
    occupancy_se: np.ndarray
    settled: np.ndarray
    settle_phi: np.ndarray
    settle_network: np.ndarray | None
    species_settle: dict[str, float]
    curves: dict[str, Any]
    horizon: float
    relaxation: dict[str, Any]
    hazards: list[dict[str, Any] | None]
    memory: bool | None
    switch: np.ndarray
    events: float | None
    species_law: dict[str, tuple[np.ndarray, np.ndarray]]
    stopped: float | None = None
    stopped_state: dict[str, int] | None = None
    oscillation: dict[str, Any] | None = None
    cells: int = 0
    notes: list[str] = field(default_factory=list)
    cost: float = 0.0

    @property
    def exact(self) -> bool:
        """Whether it was measured on the generator (:data:`EXACT_METHOD`), not on cells."""
        return self.method == EXACT_METHOD

    @property
    def settling_curves(self) -> bool:
        """Whether the median point's curves over time were kept (the settling figure): phi's
        curve, which every kept set of curves has."""
        return self.curves.get("phi") is not None


def hazard_dict(h: Any, dt: float) -> dict[str, Any] | None:
    if h is None:
        return None
    return {"age_s": (h.edges * dt).tolist(), "rows": h.rows.tolist(),
            "hazard": h.hazard.tolist(), "se": h.se.tolist(), "pooled": h.pooled,
            "chi2": h.chi2, "df": h.df, "p_value": h.p_value, "effect": h.effect,
            "flat_from_s": h.flat_from * dt}  # fmt: skip


def oscillation_dict(
    found: Oscillation, dt: float, segments: Sequence[np.ndarray] | None = None
) -> dict[str, Any]:
    """An :class:`~surrogate.evaluate.dynamics.Oscillation` for inspect.json, with each lump's
    complete segments (:func:`~surrogate.evaluate.dynamics.segment_durations`, windows):
    their number, mean (s), coefficient of variation (1 for a memoryless lump's exponential
    durations; below 1 where the hazard rises with the age) and 90th percentile (s)."""
    out: dict[str, Any] = {k: (None if isinstance(v, float) and math.isnan(v) else v)
                           for k, v in vars(found).items()}  # fmt: skip
    out["segments"] = None
    if segments is not None:
        out["segments"] = [
            {"count": int(d.size), "mean_s": float(d.mean() * dt),
             "cv": float(d.std() / d.mean()), "q90_s": float(np.quantile(d, 0.9) * dt)}
            if d.size >= 2 else None for d in segments
        ]  # fmt: skip
    return out


__all__ = [
    "EXACT_METHOD",
    "SIMULATED_METHOD",
    "FixedInputs",
    "hazard_dict",
    "oscillation_dict",
]

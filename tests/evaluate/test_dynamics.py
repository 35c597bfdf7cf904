"""Dynamics measured from phi's series (surrogate/evaluate/dynamics.py), against series whose
answer is known by construction."""

from __future__ import annotations

import numpy as np

from surrogate.evaluate.dynamics import switch_hazards


def cycle(cells: int, windows: int, length: int) -> np.ndarray:
    """``cells x windows`` phi alternating every ``length`` windows, each cell at its own
    phase: a cell leaves its lump exactly at age ``length - 1`` (windows since phi changed)."""
    k = np.arange(windows)[None, :] + np.arange(cells)[:, None]
    return (k // length) % 2


def ages_of(series: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row (a window with a known age): the origin, the age and whether phi changed, by
    walking each cell's windows one by one (independent of switch_hazards' vectorised code)."""
    origin, ages, switched = [], [], []
    for row in series:
        age = None
        for k in range(row.size - 1):
            if k > 0 and row[k] != row[k - 1]:
                age = 0
            elif age is not None:
                age += 1
            if age is not None:
                origin.append(row[k])
                ages.append(age)
                switched.append(row[k + 1] != row[k])
    return np.array(origin), np.array(ages), np.array(switched)


def test_hazard_bins_hold_the_ages_their_edges_say() -> None:
    """A cycle of 5 windows per lump leaves at age 4 and never before: the bins 0, 1, 2-3, 4-7
    (edges 0, 1, 2, 4) have hazards 0, 0, 0, 1. Bins that held ages 1-2 and 3-6 under the
    labels 1 and 2 (before) put the switch in the bin labelled 2, a hazard of 1/4 there."""
    series = cycle(40, 400, 5)
    for h in switch_hazards(series, min_expected=1.0):
        assert h is not None
        assert h.edges.tolist() == [0, 1, 2, 4]
        np.testing.assert_allclose(h.hazard, [0.0, 0.0, 0.0, 1.0])
        assert h.flat_from == 4


def test_hazard_bin_rows_are_the_rows_between_their_edges() -> None:
    """On a memoryless telegraph the rows and switches of each bin are those whose age lies
    in ``[edges[b], edges[b + 1])`` (the last bin open-ended), counted row by row."""
    rng = np.random.default_rng(5)
    series = np.cumsum(rng.random((30, 600)) < 0.15, axis=1) % 2
    origin, ages, switched = ages_of(series)
    for v, h in enumerate(switch_hazards(series)):
        assert h is not None
        upper = np.append(h.edges[1:], np.inf)
        for b, (lo, hi) in enumerate(zip(h.edges, upper, strict=True)):
            rows = (origin == v) & (ages >= lo) & (ages < hi)
            assert h.rows[b] == rows.sum()
            assert h.switches[b] == switched[rows].sum()

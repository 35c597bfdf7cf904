"""The windows each row of a transitions table stands for: the :data:`WINDOWS` column of a
collection that keeps every switch (``collect.keep_switches``,
:mod:`surrogate.simulate.transitions`), read by everything that sums over rows (psi's bins, the
support histograms, the after-jump rates, collect's counts)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

#: the column: ``record_every`` for a row where phi held (one recorded of that many windows), 1
#: where it changed (every switch recorded); a table without it counts each row once
WINDOWS = "windows"


def row_windows(table: Mapping[str, Any]) -> np.ndarray | None:
    """The windows each row of a transitions ``table`` (a DataFrame, or a chunk of one as a
    dict of columns) stands for, or None where it has no :data:`WINDOWS` column (one each).

    Example:
        >>> row_windows({"phi": [0, 1], "windows": [10.0, 1.0]})
        array([10.,  1.])
    """
    return np.asarray(table[WINDOWS], dtype=np.float64) if WINDOWS in table else None


def origin_windows(table: Mapping[str, Any]) -> np.ndarray | None:
    """The windows the rows from each origin (phi = 0, 1) stand for, or None where rows carry
    no :data:`WINDOWS` column.

    Example:
        >>> origin_windows({"phi": [0, 0, 1], "windows": [10.0, 1.0, 10.0]})
        array([11., 10.])
    """
    windows = row_windows(table)
    if windows is None:
        return None
    return np.bincount(np.asarray(table["phi"], dtype=np.int64), weights=windows, minlength=2)


def origin_rows(table: Mapping[str, Any], record_every: int) -> np.ndarray:
    """The rows from each origin (phi = 0, 1) as a thinned collection counts them: the rows
    themselves, or, where rows carry :data:`WINDOWS` (every switch kept), their windows over
    ``record_every`` (a switch off the thinned steps counts ``1 / record_every``).

    Example:
        >>> origin_rows({"phi": [0, 0, 1], "windows": [10.0, 1.0, 10.0]}, 10)
        array([1.1, 1. ])
    """
    windows = origin_windows(table)
    if windows is None:
        phi = np.asarray(table["phi"], dtype=np.int64)
        return np.bincount(phi, minlength=2).astype(np.float64)
    return windows / record_every


__all__ = ["WINDOWS", "origin_rows", "origin_windows", "row_windows"]

"""Contiguous phi sequences per cell from a table of recorded windows.

:func:`~surrogate.simulate.transitions.record_occupancy` with ``record_every=1`` records every
window of every cell as one row (the inputs, ``phi``, ``phi_next``, ``cell``, ``t``).
A chain with hidden states (:mod:`surrogate.gp.phases`) or a held-out score of a kind reads
them as sequences: each cell's inputs per window and its phi at each window's edges.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ConfigError

#: the columns a sequence table needs besides its inputs
SEQUENCE_COLUMNS = ("cell", "t", "phi", "phi_next")


def phi_sequences(table: pd.DataFrame, input_names: Sequence[str]) -> tuple[Tensor, Tensor]:
    """Each cell's windows in time order as tensors.

    Args:
        table: one row per window (``cell``, ``t``, ``phi``, ``phi_next`` and the inputs), every
            cell recorded at the same ``T`` consecutive windows (as
            :func:`~surrogate.simulate.transitions.record_occupancy` with ``record_every=1``
            gives them).
        input_names: the inputs' columns, in the order of the last axis of the result.

    Returns:
        ``inputs`` ``n x T x d`` float64 (the inputs during each window) and ``phi``
        ``n x (T + 1)`` int64 (phi at the start of each window, then after the last one);
        cells in ascending ``cell`` order.

    Raises:
        ConfigError: a column is missing, cells have different numbers of windows, or a cell's
            windows do not chain (``phi_next`` of one window is not ``phi`` of the next: rows
            thinned or perturbed).

    Example:
        >>> rows = pd.DataFrame({"cell": [0, 0, 1, 1], "t": [0.0, 0.1, 0.0, 0.1],
        ...                      "phi": [0, 1, 1, 1], "phi_next": [1, 1, 1, 0],
        ...                      "x": [0.1, 0.2, 0.3, 0.4]})
        >>> z, phi = phi_sequences(rows, ["x"])
        >>> tuple(z.shape), phi.tolist()
        ((2, 2, 1), [[0, 1, 1], [1, 1, 0]])
    """
    missing = [c for c in (*SEQUENCE_COLUMNS, *input_names) if c not in table.columns]
    if missing:
        raise ConfigError(f"a sequence table needs the columns {missing}: record every window "
                          f"(record_occupancy with record_every=1)")  # fmt: skip
    if len(table) == 0:
        raise ConfigError("a sequence table needs at least one window")
    ordered = table.sort_values(["cell", "t"], kind="stable")
    counts = ordered.groupby("cell", sort=True).size().to_numpy()
    if (counts != counts[0]).any():
        raise ConfigError(f"every cell needs the same number of windows; got {counts.min()} to "
                          f"{counts.max()}")  # fmt: skip
    n, steps = len(counts), int(counts[0])
    phi = ordered["phi"].to_numpy(np.int64).reshape(n, steps)
    nxt = ordered["phi_next"].to_numpy(np.int64).reshape(n, steps)
    if (phi[:, 1:] != nxt[:, :-1]).any():
        raise ConfigError("a cell's windows do not chain (phi_next of a window is not phi of "
                          "the next): the rows were thinned or perturbed")  # fmt: skip
    z = ordered[list(input_names)].to_numpy(np.float64, copy=True)
    z = z.reshape(n, steps, len(input_names))
    edges = np.concatenate([phi, nxt[:, -1:]], axis=1)
    return torch.from_numpy(z), torch.from_numpy(edges)


__all__ = ["SEQUENCE_COLUMNS", "phi_sequences"]

"""Phi sequences from recorded windows (:func:`phi_sequences`): each cell's windows in time
order whatever the rows' order, and tables that are not every window of every cell refused."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from surrogate.errors import ConfigError
from surrogate.simulate.sequences import phi_sequences


def _windows(n: int = 3, steps: int = 5, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    phi = rng.integers(0, 2, (n, steps + 1))
    return pd.DataFrame({
        "cell": np.repeat(np.arange(n), steps), "t": np.tile(np.arange(steps) * 0.1, n),
        "phi": phi[:, :-1].ravel(), "phi_next": phi[:, 1:].ravel(),
        "x": rng.random(n * steps), "y": rng.random(n * steps)}), phi  # fmt: skip


def test_sequences_are_each_cells_windows_in_order() -> None:
    table, phi = _windows()
    shuffled = table.sample(frac=1.0, random_state=1)
    z, edges = phi_sequences(shuffled, ["y", "x"])
    assert z.shape == (3, 5, 2) and edges.shape == (3, 6)
    assert np.array_equal(edges.numpy(), phi)
    assert np.allclose(z[1, 2].numpy(), table.loc[7, ["y", "x"]].to_numpy(float))


def test_tables_that_are_not_every_window_are_refused() -> None:
    table, _ = _windows()
    with pytest.raises(ConfigError, match=r"needs the columns \['z'\]"):
        phi_sequences(table, ["z"])
    with pytest.raises(ConfigError, match="the same number of windows; got 4 to 5"):
        phi_sequences(table.drop(index=0), ["x"])
    thinned = table.copy()
    thinned.loc[1, "phi"] = 1 - thinned.loc[1, "phi"]
    thinned.loc[0, "phi_next"] = thinned.loc[1, "phi"]  # window 0 chains, window 1 does not
    thinned.loc[1, "phi_next"] = 1 - table.loc[2, "phi"]
    with pytest.raises(ConfigError, match="do not chain"):
        phi_sequences(thinned, ["x"])
    with pytest.raises(ConfigError, match="at least one window"):
        phi_sequences(table.iloc[:0], ["x"])

"""The K-lumps chain's learned law (surrogate.gp.classes): continuation-ratio binary GPs."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.errors import ArtefactError
from surrogate.gp.classes import fit_class_law
from surrogate.gp.training import GPSettings

SETTINGS = GPSettings(seed=0, bins=50, epochs=300, n_inducing=16, kernel="matern52")


def true_law(z: np.ndarray) -> np.ndarray:
    """A 3-class law ``n x 3 x 3`` varying with z in [0, 1]: class 2 is never reached from 0,
    and 1 -> 0 is rare (a constant step)."""
    n = z.shape[0]
    law = np.zeros((n, 3, 3))
    law[:, 0, 0] = 0.6 + 0.3 * z
    law[:, 0, 1] = 1.0 - law[:, 0, 0]
    law[:, 1, 0] = 0.002
    law[:, 1, 2] = 0.2 + 0.4 * z
    law[:, 1, 1] = 1.0 - law[:, 1, 0] - law[:, 1, 2]
    law[:, 2, 1] = 0.5 - 0.3 * z
    law[:, 2, 2] = 1.0 - law[:, 2, 1]
    return law


def sample(n: int, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.0, 1.0, n)
    origin = rng.integers(0, 3, n)
    p = true_law(z)[np.arange(n), origin]  # (n, 3)
    u = rng.uniform(size=n)
    nxt = (u[:, None] >= p.cumsum(1)).sum(1).clip(max=2)
    return pd.DataFrame({"z": z, "phi_class": origin, "phi_class_next": nxt})


def test_the_learned_law_is_the_law_within_its_sampling_error() -> None:
    """60,000 windows (~20,000 per origin): every learned probability within 4 binomial
    standard errors of a 1/10 slice of the data (a conservative band for a smooth fit that
    pools the slice's neighbours), rows summing to 1, an unreached destination at 0."""
    data = sample(60_000)
    law, metrics = fit_class_law(data, ["z"], 3, {"z": (0.0, 1.0)}, SETTINGS, nodes=[11],
                                 progress=False)  # fmt: skip
    assert law.shape == (3, 11, 3)
    torch.testing.assert_close(law.sum(-1), torch.ones(3, 11, dtype=torch.float64))
    assert float(law[0, :, 2].abs().max()) == 0.0  # never reached from class 0
    z = np.linspace(0.0, 1.0, 11)
    truth = torch.tensor(true_law(z)).permute(1, 0, 2)  # (origin, node, dest)
    n_slice = 20_000 / 10
    se = torch.sqrt(truth * (1 - truth) / n_slice)
    inner = slice(1, 10)  # the edges' bins are half-filled
    assert bool(((law - truth).abs()[:, inner] <= 4 * se[:, inner] + 1e-3).all()), (
        (law - truth).abs().max()
    )
    assert metrics["constant_steps"] >= 1  # 1 -> 0 has ~40 events: a constant rate
    assert math.isclose(float(law[1, 5, 0]), 0.002, abs_tol=0.0015)


def test_a_table_without_class_columns_or_with_an_empty_class_is_refused() -> None:
    data = sample(3_000)
    with pytest.raises(ArtefactError, match="phi_class"):
        fit_class_law(data.drop(columns="phi_class"), ["z"], 3, {"z": (0.0, 1.0)}, SETTINGS)
    with pytest.raises(ArtefactError, match="no rows from class 3"):
        fit_class_law(data, ["z"], 4, {"z": (0.0, 1.0)}, SETTINGS, progress=False)

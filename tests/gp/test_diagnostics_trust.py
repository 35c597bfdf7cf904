"""The empirical diagnostic's statistics to trust a learned psi by: the bias's cluster-robust
standard error, the calibration test and the settling check, on occupancy rows whose switching
law is known."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.gp.diagnostics import cluster_se, psi_errors


def _occupancy(seed: int, drift: float = 0.0, cells: int = 400, steps: int = 250) -> pd.DataFrame:
    """Cells alternating between phi = 0 and 1, leaving 0 with p0(z) = 0.1 + 0.1 z and 1 with
    0.05 (z uniform in [0, 1] per window); ``drift``: p0 grows by that much over the run."""
    rng = np.random.default_rng(seed)
    rows = []
    phi = rng.integers(0, 2, cells)
    for k in range(steps):
        z = rng.uniform(0, 1, cells)
        p0 = 0.1 + 0.1 * z + drift * k / steps
        leave = rng.uniform(size=cells) < np.where(phi == 0, p0, 0.05)
        nxt = np.where(leave, 1 - phi, phi)
        rows.append(pd.DataFrame({"z": z, "phi": phi, "phi_next": nxt, "cell": np.arange(cells),
                                  "t": k * 0.05}))  # fmt: skip
        phi = nxt
    return pd.concat(rows, ignore_index=True)


def _psi(scale: float):
    """psi(phi, z): P(phi' = 1) with the true law's switching times ``scale`` from phi = 0."""

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        p0 = scale * (0.1 + 0.1 * z[:, 0].double())
        return torch.where(phi == 0, p0, 1 - 0.05 * torch.ones_like(p0))

    return psi


def test_the_true_psi_is_unbiased_within_its_error_and_calibrated() -> None:
    out, _ = psi_errors(_psi(1.0), _occupancy(0), ["z"])
    for p in (0, 1):
        s = out[f"phi{p}"]
        assert abs(s["rel_bias"]) < 3 * s["rel_bias_se"]
        assert s["calibration_p"] > 0.001
        assert abs(s["settling_z"]) < 4


def test_a_biased_psi_is_seen_with_its_error_and_fails_calibration() -> None:
    out, _ = psi_errors(_psi(1.2), _occupancy(1), ["z"])
    s = out["phi0"]
    assert abs(s["rel_bias"] - 0.2) < 4 * s["rel_bias_se"] and s["rel_bias"] > 6 * s["rel_bias_se"]
    assert s["calibration_p"] < 1e-6
    assert s["predicted_duration_error"] == pytest.approx(1 / (1 + s["rel_bias"]) - 1)


def test_a_population_still_settling_shows_in_its_halves() -> None:
    out, _ = psi_errors(_psi(1.0), _occupancy(2, drift=0.1), ["z"])
    assert out["phi0"]["settling_z"] < -6  # the second half switches more


def test_cells_moving_to_other_inputs_are_settled() -> None:
    """The inputs rise over the run (cells moving up a field) under a fixed law: the raw
    switching frequency rises between the halves (-9 SE here); what psi predicts at the
    inputs does too, so the residual, the settling check, does not."""
    occupancy = _occupancy(3, cells=400, steps=250)
    occupancy["z"] = np.clip(occupancy["t"] / occupancy["t"].max() + 0.1 * (occupancy["z"] - 0.5),
                             0, 1)  # fmt: skip
    rng = np.random.default_rng(4)  # outcomes drawn again from the law at the moved inputs
    p0 = 0.1 + 0.1 * occupancy["z"].to_numpy()
    leave = rng.uniform(size=len(occupancy)) < np.where(occupancy["phi"] == 0, p0, 0.05)
    occupancy["phi_next"] = np.where(leave, 1 - occupancy["phi"], occupancy["phi"])
    out, _ = psi_errors(_psi(1.0), occupancy, ["z"])
    assert abs(out["phi0"]["settling_z"]) < 4
    sel = occupancy["phi"] == 0
    raw = (occupancy["phi_next"] != occupancy["phi"])[sel].to_numpy(float)
    half = occupancy["t"][sel].to_numpy() < occupancy["t"][sel].median()
    se = np.hypot(
        *(cluster_se(raw[h], occupancy["cell"][sel].to_numpy()[h]) for h in (half, ~half))
    )
    assert (raw[half].mean() - raw[~half].mean()) / se < -6  # what the raw halves read


def test_cluster_se_counts_correlated_windows_once_per_cell() -> None:
    """Cells with their own constant rate: the windows of a cell are one cluster, so the
    standard error is the spread of the cells' means over sqrt(cells), far above the binomial."""
    rng = np.random.default_rng(0)
    rates = rng.uniform(0.0, 0.4, 200)
    values = (rng.uniform(size=(200, 500)) < rates[:, None]).astype(float)
    cells = np.repeat(np.arange(200), 500)
    se = cluster_se(values.ravel(), cells)
    assert se == pytest.approx(values.mean(1).std(ddof=1) / np.sqrt(200), rel=0.05)
    assert se > 5 * np.sqrt(values.mean() * (1 - values.mean()) / values.size)

"""Rows that stand for several windows (surrogate/gp/windows.py, a collection that keeps every
switch): psi's bins, the held-out metrics and the fit read a weighted row as that many rows."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.gp import GPSettings, fit_psi
from surrogate.gp.binned import bin_inputs
from surrogate.gp.metrics import classification_metrics
from surrogate.gp.training import fit_classifier
from surrogate.gp.windows import WINDOWS, origin_rows, row_windows


def test_a_row_standing_for_w_windows_bins_as_w_copies() -> None:
    gen = torch.Generator().manual_seed(0)
    z = torch.rand(500, 2, generator=gen)
    y = (torch.rand(500, generator=gen) < 0.3).float()
    w = torch.randint(1, 5, (500,), generator=gen).float()
    copies = torch.repeat_interleave(torch.arange(500), w.long())
    weighted = bin_inputs(z, y, 6, w)
    replicated = bin_inputs(z[copies], y[copies], 6)
    for a, b in zip(weighted, replicated, strict=True):
        torch.testing.assert_close(a, b)


def test_weighted_metrics_are_the_replicated_rows_metrics() -> None:
    rng = np.random.default_rng(1)
    p = rng.random(400)
    y = (rng.random(400) < p).astype(float)
    w = rng.integers(1, 6, 400).astype(float)
    copies = np.repeat(np.arange(400), w.astype(int))
    weighted = classification_metrics(p, y, weights=w)
    replicated = classification_metrics(p[copies], y[copies])
    for key in ("base_rate", "mean_log_predictive", "brier", "brier_baseline", "brier_gain",
                "accuracy"):  # fmt: skip
        assert weighted[key] == pytest.approx(replicated[key], rel=1e-12)
    for a, b in zip(weighted["calibration"], replicated["calibration"], strict=True):
        assert a["n"] == b["n"] and a["observed_frequency"] == pytest.approx(
            b["observed_frequency"]) if b["n"] else a["n"] == 0  # fmt: skip
    assert weighted["n"] == 400  # the rows, not the windows
    with pytest.raises(ValueError, match="weights"):
        classification_metrics(p, y, weights=-w)


def telegraph(n: int, seed: int) -> pd.DataFrame:
    """Windows at x in [0, 1] from phi = 0 and 1, leaving at 0.02 + 0.04 x per window."""
    rng = np.random.default_rng(seed)
    x = rng.random(n)
    phi = rng.integers(0, 2, n)
    switched = rng.random(n) < 0.02 + 0.04 * x
    return pd.DataFrame({"x": x.astype(np.float32), "phi": phi,
                         "phi_next": np.where(switched, 1 - phi, phi)})  # fmt: skip


def case_control(table: pd.DataFrame, every: int, seed: int) -> pd.DataFrame:
    """Every switch, one in ``every`` held windows (at random), each with its windows."""
    switched = (table["phi"] != table["phi_next"]).to_numpy()
    keep = switched | (np.random.default_rng(seed).random(len(table)) < 1.0 / every)
    out = table[keep].copy()
    out[WINDOWS] = np.where(switched[keep], 1.0, float(every))
    return out.reset_index(drop=True)


def test_psi_fitted_on_kept_switches_is_the_every_window_psi() -> None:
    """On every switch and a tenth of the held windows, weighted, psi is the true leaving
    probability within 4 standard errors of a 0.1-wide slice's rate (~1,200 switches each,
    SE ~3 %); read unweighted the same rows give ~7x the rate."""
    rows = case_control(telegraph(400_000, 2), 10, 3)
    settings = GPSettings(n_inducing=16, bins=40, epochs=300, lr=0.05, seed=0)
    psi = fit_psi(rows, ["x"], settings, progress=False)
    x = torch.tensor([[0.2], [0.5], [0.8]])
    true = 0.02 + 0.04 * x[:, 0].double()
    for phi in (0, 1):
        leave = psi(torch.full((3,), phi), x).double()
        leave = leave if phi == 0 else 1.0 - leave
        slice_switches = 400_000 / 2 * 0.1 * true  # a 0.1-wide slice's switches
        assert ((leave - true).abs() < 4 * true / slice_switches.sqrt()).all(), leave
    plain = fit_psi(rows.drop(columns=WINDOWS), ["x"], settings, progress=False)
    assert (plain(torch.zeros(3, dtype=torch.long), x).double() > 4 * true).all()


def test_weighted_rows_need_binned_training_and_positive_windows() -> None:
    x, y = torch.rand(100, 1), (torch.rand(100) < 0.5).float()
    with pytest.raises(ConfigError, match="binned training"):
        fit_classifier(x, y, GPSettings(n_inducing=5, epochs=1, bins=0), progress=False,
                       rows=torch.ones(100))  # fmt: skip
    with pytest.raises(Exception, match="positive"):
        fit_classifier(x, y, GPSettings(n_inducing=5, epochs=1, bins=10), progress=False,
                       rows=torch.zeros(100))  # fmt: skip


def test_origin_rows_count_a_switch_as_a_fraction_of_a_thinned_row() -> None:
    table = {"phi": np.array([0, 0, 0, 1]), WINDOWS: np.array([5.0, 1.0, 1.0, 5.0])}
    np.testing.assert_allclose(origin_rows(table, 5), [1.4, 1.0])
    assert row_windows({"phi": [0]}) is None
    np.testing.assert_allclose(origin_rows({"phi": np.array([0, 1, 1])}, 5), [1.0, 2.0])


def test_the_figures_data_frequencies_read_the_windows() -> None:
    """psi's figure overlays the data's own switching frequency: on kept switches, weighted,
    each of two bins within 4 binomial s.e. of the windows' rate there (unweighted: ~7x)."""
    from surrogate.gp import binned_frequencies

    rows = case_control(telegraph(200_000, 4), 10, 5)
    centre, freq, se = binned_frequencies(rows, "x", phi=0, bins=2)
    true = 0.02 + 0.04 * centre
    assert (np.abs(freq - true) < 4 * se).all(), (freq, true, se)
    _, plain, _ = binned_frequencies(rows.drop(columns=WINDOWS), "x", phi=0, bins=2)
    assert (plain > 4 * true).all()

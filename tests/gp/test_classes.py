"""The K-lumps chain's learned law (surrogate.gp.classes): one-vs-rest binary GPs, and the
weight of an expected label (surrogate.gp.binned.label_weight)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.errors import ArtefactError, NumericalError
from surrogate.gp.binned import label_weight
from surrogate.gp.classes import ClassFitOptions, fit_class_law
from surrogate.gp.settings import GPSettings
from surrogate.gp.training import fit_classifiers

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
    law, metrics = fit_class_law(data, ["z"], 3, {"z": (0.0, 1.0)}, SETTINGS,
                                 ClassFitOptions(nodes=[11], progress=False))  # fmt: skip
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
        fit_class_law(data, ["z"], 4, {"z": (0.0, 1.0)}, SETTINGS, ClassFitOptions(progress=False))


def test_an_expected_labels_weight_is_its_inverse_dispersion() -> None:
    """Labels that are means of 10 Bernoulli draws have dispersion 1/10: the weight is 10,
    within 5 % at 100,000 rows (the estimate's s.d. there is 0.05, measured over replicates),
    and on average over 50 draws of 200 rows in 100 bins within 10 % (s.d. of that mean 0.2;
    without the bins' lost degree of freedom it came out 17); 0/1 outcomes get 1, noise-free
    labels the cap; non-finite labels and a cap below 1 are refused."""
    rng = np.random.default_rng(0)

    def draw(n: int, m: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        z = torch.tensor(rng.uniform(0.0, 1.0, (n, 1)), dtype=torch.float32)
        p = 0.1 + 0.6 * z[:, 0].double().numpy()
        return z, torch.tensor(rng.binomial(m, p) / m), p

    z, y, p = draw(100_000, 10)
    assert label_weight(z, y, 100, cap=1e9) == pytest.approx(10.0, rel=0.05)
    assert label_weight(z, y, 100, cap=5.0) == 5.0
    small = [label_weight(*draw(200, 10)[:2], 100, cap=1e9) for _ in range(50)]
    assert float(np.mean(small)) == pytest.approx(10.0, rel=0.10)
    z1, y1, _ = draw(100_000, 1)
    assert label_weight(z1, y1, 100, cap=1000.0) == pytest.approx(1.0, abs=0.05)
    assert label_weight(z, torch.tensor(p), 100, cap=1000.0) == 1000.0
    with pytest.raises(ValueError, match="cap"):
        label_weight(z, y, 100, cap=0.5)
    with pytest.raises(NumericalError, match="finite"):
        label_weight(z, torch.full_like(y, float("nan")), 100, cap=10.0)
    with pytest.raises(ValueError, match="3 weights for 1"):
        fit_classifiers([(z[:100], torch.tensor(p[:100]).float())], SETTINGS, weights=[1, 2, 3])


def test_a_mixture_of_label_sources_gets_the_inverse_of_its_mean_dispersion() -> None:
    """One pooled weight per GP (the documented choice): rows with dispersions 1/w_k in shares
    f_k get 1 / sum_k f_k / w_k, so half noise-free labels and half 0/1 outcomes get 2 (the
    outcomes over-weighted 2x, as label_weight's docstring says), and a quarter of 10-draw
    means with three quarters of outcomes 1 / (0.25 / 10 + 0.75) = 1.29. Within 3 % at 100,000
    rows: the estimate's s.d. there is 0.4 % and 0.2 % (30 replicates)."""
    rng = np.random.default_rng(1)
    n = 100_000
    z = torch.tensor(rng.uniform(0.0, 1.0, (n, 1)), dtype=torch.float32)
    p = 0.1 + 0.6 * z[:, 0].double().numpy()
    outcome = rng.binomial(1, p).astype(np.float64)
    half = torch.tensor(np.where(rng.uniform(size=n) < 0.5, p, outcome))
    assert label_weight(z, half, 100, cap=1e9) == pytest.approx(2.0, rel=0.03)
    quarter = torch.tensor(np.where(rng.uniform(size=n) < 0.25, rng.binomial(10, p) / 10, outcome))
    assert label_weight(z, quarter, 100, cap=1e9) == pytest.approx(1 / (0.025 + 0.75), rel=0.03)


def tail_table(n: int, seed: int = 0) -> tuple[pd.DataFrame, np.ndarray]:
    """Two classes; z ~ Beta(1, 4), so rows thin out towards z = 1; from class 0 the chance
    of class 1 is q(z) = 0.01 exp(3 z), and each row carries it as its expected label (a
    class that pins the internal state: noise-free labels)."""
    rng = np.random.default_rng(seed)
    z = rng.beta(1.0, 4.0, n)
    q = 0.01 * np.exp(3.0 * z)
    nxt = (rng.uniform(size=n) < q).astype(int)
    table = pd.DataFrame({"z": z, "phi_class": 0, "phi_class_next": nxt,
                          "phi_class_next_expected_0": 1 - q, "phi_class_next_expected_1": q})  # fmt: skip
    back = pd.DataFrame({"z": z[:2000], "phi_class": 1, "phi_class_next": 1,
                         "phi_class_next_expected_0": 0.0, "phi_class_next_expected_1": 1.0})  # fmt: skip
    return pd.concat([table, back], ignore_index=True), z


def test_weighted_expected_labels_pin_a_sparse_tail() -> None:
    """Noise-free expected labels, weighted by their inverse dispersion (capped at 1,000),
    hold the law where rows are sparse: at the 95th and 99th percentiles of z (~600 and ~120
    rows in a 0.1-wide window of 20,000) within 4 standard errors of a binomial proportion
    over 1,000 x those rows (the noise the weighted likelihood assumes; the labels have none,
    so the band bounds the fit's smoothing bias, a heuristic bound); counted as 0/1 draws
    (weight 1) the same data leaves that band at one of them at least (the fit bends towards
    its prior where rows are few)."""
    table, z = tail_table(20_000)
    nodes = np.linspace(0.0, 1.0, 101)
    errors = {}
    for cap in (1000.0, 1.0):
        law, metrics = fit_class_law(table, ["z"], 2, {"z": (0.0, 1.0)}, SETTINGS,
                                     ClassFitOptions(nodes=[101], progress=False,
                                                     max_weight=cap))  # fmt: skip
        assert metrics["0"]["row_weight"]["1"] == pytest.approx(min(cap, 1000.0))
        errors[cap] = law[0, :, 1].numpy() - 0.01 * np.exp(3.0 * nodes)
    outside = []
    for quantile in (0.95, 0.99):
        at = float(np.quantile(z, quantile))
        k = round(at * 100)
        q = 0.01 * np.exp(3.0 * at)
        rows = int(((z > at - 0.05) & (z < at + 0.05)).sum())
        band = 4 * math.sqrt(q * (1 - q) / (1000 * rows))
        assert abs(errors[1000.0][k]) <= band, (quantile, errors[1000.0][k], band)
        outside.append(abs(errors[1.0][k]) > band)
    assert any(outside)


def test_a_rare_destination_with_expected_labels_gets_its_surface() -> None:
    """With expected labels, events are counted by label mass: a destination with ~5 expected
    events (q from 0.0003 to 0.006) gets a GP that follows q(z)'s trend (from z = 0.1 to 0.9 it
    grows e^2.4 = 11x: the GP's within a factor 2 of that, its constant mean label 1x), while
    0/1 outcomes keep the constant."""
    rng = np.random.default_rng(1)
    z = rng.uniform(0.0, 1.0, 2000)
    q = 0.0003 * np.exp(3.0 * z)
    table = pd.DataFrame({"z": z, "phi_class": 0, "phi_class_next": (rng.uniform(size=2000) < q).astype(int),
                          "phi_class_next_expected_0": 1 - q, "phi_class_next_expected_1": q})  # fmt: skip
    back = table.assign(phi_class=1, phi_class_next=1, phi_class_next_expected_0=0.0,
                        phi_class_next_expected_1=1.0)  # fmt: skip
    data = pd.concat([table, back], ignore_index=True)
    law, metrics = fit_class_law(data, ["z"], 2, {"z": (0.0, 1.0)}, SETTINGS,
                                 ClassFitOptions(nodes=[11], progress=False))  # fmt: skip
    assert metrics["min_events"] == 1.0 and "1" in metrics["0"]["row_weight"]
    growth = float(law[0, 9, 1] / law[0, 1, 1])
    assert math.exp(2.4) / 2 < growth < 2 * math.exp(2.4), growth
    _, outcome = fit_class_law(data, ["z"], 2, {"z": (0.0, 1.0)}, SETTINGS,
                               ClassFitOptions(nodes=[11], progress=False,
                                               expected=False))  # fmt: skip
    assert outcome["min_events"] == 50 and outcome["constant_steps"] >= 1


def test_the_class_diagnostic_scores_leaving_the_lump_where_cells_live() -> None:
    """class_law_errors: a law equal to the reference has no bias; one whose switch out of class
    1's lump is 10 % too likely has +10 % exactly; the empirical reference is the rows' observed
    switches (a class never visited is left out). Classes a | b, c are the two lumps."""
    from surrogate.gp.diagnostics import class_law_errors

    data = sample(20_000)
    names, lumps = ("a", "b", "c"), (0, 1, 1)

    def truth(rows: pd.DataFrame) -> np.ndarray:
        return true_law(rows["z"].to_numpy())[np.arange(len(rows)), rows["phi_class"].to_numpy()]

    def law(origin: torch.Tensor, z: torch.Tensor, boost: float = 1.0) -> torch.Tensor:
        p = torch.tensor(true_law(z[:, 0].double().numpy()))[torch.arange(len(z)), origin]
        p[:, 0] = torch.where(origin == 1, p[:, 0] * boost, p[:, 0])  # b -> a leaves b's lump
        return p / p.sum(1, keepdim=True) if boost == 1.0 else p

    exact = class_law_errors(law, data, ["z"], names, lumps, truth)
    assert exact["reference"] == "exact"
    assert all(abs(exact[n]["rel_bias"]) < 1e-6 for n in ("a", "b"))  # z in float32
    assert exact["c"]["mean_switching_reference"] == 0.0  # c never leaves its lump: no bias
    boosted = class_law_errors(lambda o, z: law(o, z, 1.1), data, ["z"], names, lumps, truth)
    assert boosted["b"]["rel_bias"] == pytest.approx(0.1, abs=1e-6)
    empirical = class_law_errors(law, data[data.phi_class < 2], ["z"], names, lumps)
    assert "c" not in empirical and empirical["a"]["share"] + empirical["b"]["share"] == 1.0
    left = data[(data.phi_class == 0)]
    assert empirical["a"]["mean_switching_reference"] == pytest.approx(
        (left.phi_class_next > 0).mean()
    )

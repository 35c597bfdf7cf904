"""A fitted classifier against its own training rows (surrogate/gp/own_rows.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from surrogate.gp.fitted import FittedClassifier
from surrogate.gp.own_rows import TOLERANCE, describe, own_rows_check, unwarp
from surrogate.gp.training import GPSettings, fit_classifier

pytestmark = pytest.mark.usefixtures("one_torch_thread")

BINS = 200
X = np.linspace(0.0, 10.0, BINS)[:, None]
TRUE_P = 0.02 + 0.03 * np.sin(X[:, 0] / 2) ** 2  # a switching probability per window, 2-5 %


def _rows(per_bin: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = np.full(BINS, per_bin)
    return n, rng.binomial(n.astype(np.int64), TRUE_P).astype(np.float64)


def test_the_law_that_drew_the_rows_is_not_off_them() -> None:
    # 2e6 rows, ~6e4 switches: eight groups of ~7,500 (SE ~1.2 %); the family-wise 1 % test
    # over them flags no group of the true law (one fixed draw)
    n, k = _rows(10_000)
    check = own_rows_check(TRUE_P, X, n, k)
    assert check is not None and check["off"] == []
    assert len(check["groups"]) == 8 and check["event"] == "y=1"
    assert check["observed"] == pytest.approx(k.sum())
    for g in check["groups"]:
        assert abs(g["ratio"] - 1) < 4 * 1 / math.sqrt(g["observed"]), g
    # the critical value is Bonferroni's over the groups: Phi^-1(1 - 0.01 / 16)
    assert check["critical_z"] == pytest.approx(3.227, abs=1e-3)


def test_a_law_twenty_percent_high_where_x_is_large_is_off_there_only() -> None:
    n, k = _rows(10_000)
    p = np.where(X[:, 0] > 7.5, 1.2 * TRUE_P, TRUE_P)
    check = own_rows_check(p, X, n, k)
    assert check["off"], check["largest"]
    for g in check["off"]:  # the groups reaching past 7.5 s, the one wholly past it 1.2
        assert g["hi"] > 7.5 and 1 + TOLERANCE < g["ratio"] < 1.25
    assert max(g["ratio"] for g in check["off"]) == pytest.approx(1.2, abs=0.03)
    assert check["largest"]["z"] > check["critical_z"]
    assert "largest miss kt 8.19-9.15, +18.7 %" in describe(check, ["kt"])


def test_a_miss_under_the_tolerance_is_not_off_however_many_rows() -> None:
    # 1e9 rows: a 2 % miss is ~40 SE, but below the 3 % that moves a mean duration by 3 %
    n = np.full(BINS, 5e6)
    k = n * TRUE_P
    check = own_rows_check(TRUE_P * (1 + 0.02), X, n, k)
    assert check["largest"]["z"] > 40 and check["off"] == []
    assert TOLERANCE == 0.03


def test_a_large_miss_on_few_switches_is_not_off() -> None:
    # ~700 switches: groups of ~100 (SE 10 %); a 15 % miss is 1.5 SE
    n, k = _rows(100, seed=1)
    check = own_rows_check(TRUE_P * 1.15, X, n, k)
    assert len(check["groups"]) == int(k.sum() // 100) == 7 and check["off"] == []
    assert own_rows_check(TRUE_P, X, n / 100, np.floor(k / 100)) is None  # < 100 switches


def test_the_rarer_outcome_is_counted() -> None:
    # p(y = 1) near 1 (staying): the switches are the y = 0 rows
    n, k = _rows(10_000)
    check = own_rows_check(1 - TRUE_P, X, n, n - k)
    assert check["event"] == "y=0" and check["observed"] == pytest.approx(k.sum())
    assert check["off"] == []


def test_each_axis_is_grouped_and_a_log_axis_read_back() -> None:
    rng = np.random.default_rng(2)
    x = rng.uniform(0, 2, size=(400, 2))
    n = np.full(400, 5000.0)
    p = np.full(400, 0.05)
    check = own_rows_check(p, x, n, rng.binomial(5000, 0.05, 400).astype(float))
    assert {g["axis"] for g in check["groups"]} == {0, 1}
    assert unwarp(math.log1p(4.0 / 0.25), "age", {"age": 0.25}) == pytest.approx(4.0)
    assert unwarp(3.0, "kt", {"age": 0.25}) == 3.0
    with pytest.raises(ValueError, match="differ in length"):
        own_rows_check(p[:3], x, n, n)


def _data(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(40_000, 1, generator=gen) * 10
    p = 0.02 + 0.2 * torch.exp(-((x[:, 0] - 5) ** 2))  # a narrow peak the fit must reach
    return x, (torch.rand(40_000, generator=gen) < p).float()


def test_a_fit_stopped_short_is_off_its_rows_and_newtons_is_not() -> None:
    x, y = _data()
    base = dict(bins=100, n_inducing=16, validation_fraction=0.1, seed=0)
    short = fit_classifier(x, y, GPSettings(**base, optimizer="adam", epochs=5, lr=0.01),
                           progress=False)  # fmt: skip
    newton = fit_classifier(x, y, GPSettings(**base, optimizer="newton", epochs=100),
                            progress=False)  # fmt: skip
    assert short.own_rows is not None and short.own_rows["off"]
    assert newton.own_rows is not None and newton.own_rows["off"] == []
    # the training part's rows: the fit's own bins hold all its switches
    assert newton.own_rows["observed"] == pytest.approx(
        float(y.sum()) - newton.validation["base_rate"] * newton.n_val, rel=0.05
    )
    again = FittedClassifier.from_state(newton.to_state())
    assert again.own_rows == newton.own_rows  # saved with the fit

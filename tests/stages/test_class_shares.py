"""The K-lumps chain's class shares against the full model's: a chi-square test of homogeneity
that can fail, on counts with a known answer."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from surrogate.stages.train import SHARES_ALPHA, share_test

NAMES = ("off|a", "off|b", "on|a", "on|b")


def test_equal_shares_do_not_drift_and_a_shift_does() -> None:
    same = share_test(np.array([100, 100, 100, 100]), np.array([100, 100, 100, 100]), 50.0,
                      NAMES)  # fmt: skip
    assert same["p_value"] == 1.0 and not same["drift"] and same["total_variation"] == 0.0
    # 400 cells each, 10 points of share moved between two classes: chi-square on 3 dof
    full, chain = np.array([100, 100, 100, 100]), np.array([140, 60, 100, 100])
    shifted = share_test(full, chain, 50.0, NAMES)
    want = stats.chi2_contingency(np.stack([full, chain]))
    assert shifted["p_value"] == float(want.pvalue) < SHARES_ALPHA and shifted["drift"]
    assert shifted["total_variation"] == pytest.approx(0.1, abs=1e-12)
    assert shifted["full"]["off|a"] == 0.25 and shifted["chain"]["off|a"] == 0.35


def test_classes_neither_population_holds_are_dropped() -> None:
    with_empty = share_test(np.array([50, 0, 50, 0]), np.array([60, 0, 40, 0]), 10.0, NAMES)
    without = stats.chi2_contingency(np.array([[50, 50], [60, 40]]))
    assert with_empty["p_value"] == float(without.pvalue)
    assert share_test(np.array([5, 0, 0, 0]), np.array([7, 0, 0, 0]), 1.0, NAMES)["p_value"] == 1.0

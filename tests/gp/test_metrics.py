"""classification_metrics against hand computation on tiny arrays."""

from __future__ import annotations

import json
import math
import statistics

import numpy as np
import pytest
import torch

from surrogate.errors import NumericalError
from surrogate.gp import classification_metrics

P = [0.9, 0.2, 0.6, 0.0]
Y = [1, 0, 0, 1]


def test_hand_computed_scores() -> None:
    met = classification_metrics(np.array(P), np.array(Y), n_bins=2)
    assert met["n"] == 4
    assert met["base_rate"] == 0.5
    # Squared errors 0.01, 0.04, 0.36, 1.0.
    assert met["brier"] == pytest.approx(1.41 / 4, abs=1e-12)
    assert met["brier_baseline"] == pytest.approx(0.25, abs=1e-12)
    assert met["brier_skill"] == pytest.approx(1 - 0.3525 / 0.25, abs=1e-12)
    # Baseline minus model per sample: 0.24, 0.21, -0.11, -0.75.
    diffs = [0.24, 0.21, -0.11, -0.75]
    assert met["brier_gain"] == pytest.approx(sum(diffs) / 4, abs=1e-12)
    assert met["brier_gain_se"] == pytest.approx(statistics.stdev(diffs) / 2, abs=1e-12)
    # p = 0 for an observed 1 is clipped to 1e-7, so the penalty is log(1e-7), not -inf.
    expected_lp = (math.log(0.9) + math.log(0.8) + math.log(0.4) + math.log(1e-7)) / 4
    assert met["mean_log_predictive"] == pytest.approx(expected_lp, rel=1e-9)
    assert met["accuracy"] == 0.5  # predictions 1, 0, 1, 0 vs 1, 0, 0, 1


def test_calibration_bins() -> None:
    met = classification_metrics(torch.tensor(P), torch.tensor(Y), n_bins=2)
    low, high = met["calibration"]
    assert (low["bin_lo"], low["bin_hi"], high["bin_lo"], high["bin_hi"]) == (0, 0.5, 0.5, 1)
    assert low["n"] == 2 and high["n"] == 2
    assert low["mean_predicted"] == pytest.approx(0.1)  # p = 0.2, 0.0
    assert low["observed_frequency"] == pytest.approx(0.5)  # y = 0, 1
    assert high["mean_predicted"] == pytest.approx(0.75)  # p = 0.9, 0.6
    assert high["observed_frequency"] == pytest.approx(0.5)  # y = 1, 0


def test_bin_edges_and_empty_bins() -> None:
    # p = 1.0 belongs to the last bin; p = 0.5 to the upper of two bins; 0.1-wide bins 1..8 empty.
    met = classification_metrics([1.0, 0.5, 0.0], [1, 1, 0], n_bins=10)
    counts = [b["n"] for b in met["calibration"]]
    assert counts == [1, 0, 0, 0, 0, 1, 0, 0, 0, 1]
    assert met["calibration"][1]["mean_predicted"] is None
    assert met["calibration"][1]["observed_frequency"] is None
    two = classification_metrics([1.0, 0.5, 0.0], [1, 1, 0], n_bins=2)
    assert [b["n"] for b in two["calibration"]] == [1, 2]


def test_tensor_and_array_inputs_agree_and_are_json() -> None:
    a = classification_metrics(np.array(P), np.array(Y))
    b = classification_metrics(torch.tensor(P, dtype=torch.float64), torch.tensor(Y))
    assert a == b
    json.dumps(a, allow_nan=False)  # strict JSON: plain floats, no NaN
    assert all(type(a[k]) is float for k in ("brier", "brier_skill", "mean_log_predictive"))


def test_constant_labels_skill_undefined() -> None:
    met = classification_metrics([0.9, 0.8], [1, 1])
    assert met["brier_baseline"] == 0.0
    assert met["brier_skill"] is None


def test_bad_inputs() -> None:
    with pytest.raises(NumericalError):
        classification_metrics([0.5, float("nan")], [0, 1])
    with pytest.raises(ValueError, match="only 0 and 1"):
        classification_metrics([0.5, 0.5], [0, 2])
    with pytest.raises(ValueError, match="length"):
        classification_metrics([0.5, 0.5], [0, 1, 1])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        classification_metrics([1.5], [1])

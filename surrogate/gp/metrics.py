"""Scores for probabilistic binary classifiers and their fits, returned as JSON-able plain
Python values."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from torch import Tensor

from surrogate.errors import NumericalError

P_CLIP = 1e-7


def _as_array(a: Tensor | np.ndarray | Any, name: str) -> np.ndarray:
    if isinstance(a, Tensor):
        a = a.detach().cpu().numpy()
    arr = np.asarray(a, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(arr)):
        raise NumericalError(f"classification_metrics: {name} contains NaN or infinite values")
    return arr


def classification_metrics(
    p: Tensor | np.ndarray,
    y: Tensor | np.ndarray,
    n_bins: int = 10,
    weights: Tensor | np.ndarray | None = None,
) -> dict[str, Any]:
    """Score predicted probabilities ``p`` = p(y = 1) against binary outcomes ``y``; with
    ``weights`` (the windows each row of a collection that keeps every switch stands for),
    every mean and count below is weighted by them (``n`` stays the rows, the standard error
    uses Kish's effective sample size).

    Returns a dict of plain floats/ints:

    - ``mean_log_predictive``: mean of log p(y_i | x_i), with p clipped to [1e-7, 1 - 1e-7] so a
      single confident miss gives a large but finite penalty.
    - ``brier``: mean (p - y)^2.
    - ``brier_baseline``: Brier score of the constant predictor equal to this set's base rate,
      i.e. ``base_rate * (1 - base_rate)``.
    - ``brier_skill``: 1 - brier / brier_baseline (``None`` when the baseline is 0, i.e. y is
      constant, where the skill is undefined).
    - ``brier_gain`` and ``brier_gain_se``: baseline minus model Brier score, and the standard
      error of that difference from the per-sample squared-error differences; a gain several
      s.e. above 0 means the classifier beats the constant predictor beyond sampling noise.
    - ``accuracy`` (threshold 0.5), ``base_rate``, ``n``.
    - ``calibration``: one dict per equal-width bin of p over [0, 1] with ``bin_lo``,
      ``bin_hi``, ``n``, ``mean_predicted`` and ``observed_frequency`` (``None`` for empty bins).
    """
    if isinstance(n_bins, bool) or not isinstance(n_bins, int) or n_bins < 1:
        raise ValueError(f"n_bins must be a positive integer, got {n_bins!r}")
    pa = _as_array(p, "p")
    ya = _as_array(y, "y")
    if pa.shape != ya.shape:
        raise ValueError(f"p and y differ in length: {pa.size} vs {ya.size}")
    if pa.size == 0:
        raise ValueError("classification_metrics needs at least one sample")
    if np.any((ya != 0) & (ya != 1)):
        raise ValueError("y must contain only 0 and 1")
    if np.any((pa < 0) | (pa > 1)):
        raise ValueError("p must lie in [0, 1]")
    wa = np.ones_like(pa) if weights is None else _as_array(weights, "weights")
    if wa.shape != pa.shape or np.any(wa <= 0):
        raise ValueError("weights must be one positive number per sample")

    def mean(a: np.ndarray) -> float:
        return float(np.average(a, weights=wa))

    n = pa.size
    base_rate = mean(ya)
    pc = np.clip(pa, P_CLIP, 1.0 - P_CLIP)
    log_pred = np.where(ya == 1, np.log(pc), np.log1p(-pc))
    sq_model = (pa - ya) ** 2
    sq_base = (base_rate - ya) ** 2
    brier = mean(sq_model)
    brier_baseline = mean(sq_base)
    diff = sq_base - sq_model
    effective = wa.sum() ** 2 / (wa**2).sum()  # Kish's; n where every weight is one
    spread = math.sqrt(mean((diff - mean(diff)) ** 2) * n / (n - 1)) if n > 1 else 0.0
    gain_se = spread / math.sqrt(effective) if n > 1 else None

    # Bin index: equal-width bins, with p == 1 put into the last bin rather than a bin of its own.
    idx = np.minimum((pa * n_bins).astype(np.int64), n_bins - 1)
    counts = np.bincount(idx, weights=wa, minlength=n_bins)
    sum_p = np.bincount(idx, weights=pa * wa, minlength=n_bins)
    sum_y = np.bincount(idx, weights=ya * wa, minlength=n_bins)
    calibration = []
    for b in range(n_bins):
        c = round(float(counts[b]))
        calibration.append(
            {
                "bin_lo": b / n_bins,
                "bin_hi": (b + 1) / n_bins,
                "n": c,
                "mean_predicted": float(sum_p[b] / counts[b]) if c else None,
                "observed_frequency": float(sum_y[b] / counts[b]) if c else None,
            }
        )

    return {
        "n": int(n),
        "base_rate": base_rate,
        "mean_log_predictive": mean(log_pred),
        "brier": brier,
        "brier_baseline": brier_baseline,
        "brier_skill": (1.0 - brier / brier_baseline) if brier_baseline > 0 else None,
        "brier_gain": mean(diff),
        "brier_gain_se": gain_se,
        "accuracy": mean(((pa >= 0.5) == (ya == 1)).astype(np.float64)),
        "calibration": calibration,
    }


def last_tenth_drop(history: Sequence[float]) -> float | None:
    """How far the loss (per point) fell over the last tenth of its steps: near zero where
    the fit has flattened; None for fewer than ten steps.

    Example:
        >>> last_tenth_drop([1.0] * 5 + [0.5] * 4 + [0.4])
        0.09999999999999998
    """
    n = len(history)
    if n < 10:
        return None
    return float(history[n - 1 - n // 10]) - float(history[-1])


__all__ = ["classification_metrics", "last_tenth_drop"]

"""A fitted classifier against its own training rows: the switches it predicts over groups of
its bins, per input, beside those the rows hold.

Held-out metrics (Brier, log predictive) say whether a classifier generalises; they barely move
when a fit stops short of its optimum, because a probability off by a third where a few
percent of the rows live costs little on average. Summing the predicted and the observed
events over groups of the fit's own bins shows it directly: Tyson's switch clock at 10 s,
scored by L-BFGS (200 iterations, 64 inducing points), predicted 0.88-1.50 times the switches
its own rows held per 2-wide bin of its input, where Newton's fit of the same model held
0.97-1.05 (docs/choice.md, "Scored at Newton's optimum"). Each group holds about the same
number of events (the rarer outcome: switches), so each has a standard error; a group is
**off** where its relative miss passes :data:`TOLERANCE` and its z-score the family-wise 1 %
critical value over all groups (Bonferroni), so neither a trivial miss on millions of rows nor
a noisy one on a few is flagged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from statistics import NormalDist
from typing import Any

import numpy as np

#: a group's relative miss that counts, beside its z-score: the choice's and the fidelity
#: check's duration tolerance (3 %), since a switching probability off by r shifts a mean
#: sojourn by about r
TOLERANCE = 0.03
#: groups per input axis, and the fewest events a group holds (SE <= 10 %)
GROUPS = 8
MIN_EVENTS = 100.0
#: the family-wise error rate of the groups' z-scores
ALPHA = 0.01


def own_rows_check(
    p: np.ndarray,
    x: np.ndarray,
    n: np.ndarray,
    k: np.ndarray,
    groups: int = GROUPS,
    min_events: float = MIN_EVENTS,
) -> dict[str, Any] | None:
    """Predicted against observed events over groups of bins, along each input axis.

    Args:
        p: ``L`` predicted probabilities p(y = 1) at the bins' mean inputs.
        x: ``L x d`` the bins' mean inputs (the classifier's input space).
        n: ``L`` rows per bin (the windows they stand for, where weighted).
        k: ``L`` outcomes y = 1 per bin (expected labels summed, where fractional).
        groups: at most this many groups per axis, each with about the same number of events.
        min_events: the fewest events a group holds (fewer groups where the rows hold fewer).

    Returns:
        Plain values: ``event`` (``"y=1"`` or ``"y=0"``, the rarer outcome counted),
        ``observed`` and ``predicted`` totals, ``groups`` (one dict per group: ``axis``,
        ``lo`` and ``hi`` (its bins' extreme mean inputs on that axis), ``observed``,
        ``predicted``, ``ratio`` = predicted / observed, ``z`` = (predicted - observed) /
        sqrt(observed)), ``largest`` (the group of largest ``|z|``), ``critical_z``, ``off``
        (the groups past both :data:`TOLERANCE` and ``critical_z``) and ``tolerance``; None
        where the rows hold fewer than ``min_events`` events.

    Example:
        >>> x = np.linspace(0, 1, 50)[:, None]
        >>> n = np.full(50, 1000.0)
        >>> check = own_rows_check(np.full(50, 0.1), x, n, n * 0.1)
        >>> round(check["largest"]["ratio"], 3), check["off"]
        (1.0, [])
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1)
    x = np.asarray(x, dtype=np.float64)
    x = x.reshape(x.shape[0], -1) if x.ndim else x.reshape(1, 1)
    n = np.asarray(n, dtype=np.float64).reshape(-1)
    k = np.asarray(k, dtype=np.float64).reshape(-1)
    if not (p.size == x.shape[0] == n.size == k.size):
        raise ValueError(f"p, x, n and k differ in length: {p.size}, {x.shape[0]}, {n.size}, "
                         f"{k.size} (one per bin)")  # fmt: skip
    rare_is_one = k.sum() <= (n - k).sum()
    observed = k if rare_is_one else n - k
    predicted = n * (p if rare_is_one else 1.0 - p)
    total = float(observed.sum())
    if not total >= min_events:
        return None
    per_axis = max(1, min(groups, int(total // min_events)))
    found = []
    for axis in range(x.shape[1]):
        order = np.argsort(x[:, axis], kind="stable")
        before = np.cumsum(observed[order]) - observed[order]  # events in the bins below
        group = np.minimum((before / total * per_axis).astype(np.int64), per_axis - 1)
        for g in np.unique(group):
            bins = order[group == g]
            obs, pred = float(observed[bins].sum()), float(predicted[bins].sum())
            if obs <= 0:
                continue
            found.append({
                "axis": axis, "lo": float(x[bins, axis].min()), "hi": float(x[bins, axis].max()),
                "observed": obs, "predicted": pred, "ratio": pred / obs,
                "z": (pred - obs) / math.sqrt(obs),
            })  # fmt: skip
    critical = NormalDist().inv_cdf(1.0 - ALPHA / (2 * max(len(found), 1)))
    largest = max(found, key=lambda g: abs(g["z"]))
    off = [g for g in found if abs(g["z"]) > critical and abs(g["ratio"] - 1.0) > TOLERANCE]
    return {
        "event": "y=1" if rare_is_one else "y=0",
        "observed": total,
        "predicted": float(predicted.sum()),
        "groups": found,
        "largest": largest,
        "critical_z": critical,
        "tolerance": TOLERANCE,
        "off": off,
    }


def unwarp(value: float, name: str, warps: Mapping[str, float] | None) -> float:
    """An input's value read back from a log axis (``log(1 + v / knee)``), else itself."""
    knee = (warps or {}).get(name)
    return value if knee is None else knee * math.expm1(value)


def describe(check: Mapping[str, Any], input_names: Sequence[str],
             warps: Mapping[str, float] | None = None) -> str:  # fmt: skip
    """One line for a log: the range of the groups' predicted / observed events and the
    largest miss, where (its input's range, read back from a log axis) and by how many SE.

    Example:
        >>> x = np.linspace(0, 1, 50)[:, None]
        >>> n = np.full(50, 1000.0)
        >>> describe(own_rows_check(np.full(50, 0.1), x, n, n * 0.1), ["kt"])
        'predicted / observed switches 1.000-1.000 over 8 groups (5000 observed); largest miss kt 0-0.122, +0.0 % (0.0 SE)'
    """
    ratios = [g["ratio"] for g in check["groups"]]
    big = check["largest"]
    name = input_names[big["axis"]]
    lo, hi = (unwarp(big[e], name, warps) for e in ("lo", "hi"))
    return (
        f"predicted / observed switches {min(ratios):.3f}-{max(ratios):.3f} over "
        f"{len(ratios)} groups ({check['observed']:.0f} observed); largest miss {name} "
        f"{lo:.3g}-{hi:.3g}, {100 * (big['ratio'] - 1):+.1f} % ({big['z']:.1f} SE)"
    )


def summary(check: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """A check in four numbers (for tables of many classifiers): the ``low`` and ``high``
    ratio over its groups, the ``ratio`` and ``z`` of its group of largest ``|z|``, and
    ``off`` (any group off); None for None.

    Example:
        >>> summary(None)
    """
    if not check:
        return None
    ratios = [g["ratio"] for g in check["groups"]]
    return {"low": min(ratios), "high": max(ratios), "ratio": check["largest"]["ratio"],
            "z": check["largest"]["z"], "off": bool(check["off"])}  # fmt: skip


def largest_miss(summaries: Mapping[str, Mapping[str, Any] | None]) -> dict[str, Any] | None:
    """Over several classifiers' :func:`summary` (name -> summary, None where a fit has no
    check), the one of largest ``|z|``: ``classifier``, its ``ratio`` and ``z``, and ``off``
    (any classifier off); None where none has a check.

    Example:
        >>> largest_miss({"psi_0": {"low": 0.9, "high": 1.1, "ratio": 1.1, "z": 2.0,
        ...                         "off": False}, "psi_1": None})["classifier"]
        'psi_0'
    """
    found = [(name, s) for name, s in summaries.items() if s]
    if not found:
        return None
    name, big = max(found, key=lambda ns: abs(ns[1]["z"]))
    return {"classifier": name, "ratio": big["ratio"], "z": big["z"],
            "off": any(s["off"] for _, s in found)}  # fmt: skip


__all__ = ["ALPHA", "GROUPS", "MIN_EVENTS", "TOLERANCE", "describe", "largest_miss",
           "own_rows_check", "summary", "unwarp"]  # fmt: skip

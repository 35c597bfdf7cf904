"""Exact reference moments for the DSMTS-style models, computed independently of the reader.

Propensities are re-typed here by hand from the models' descriptions (not taken from the SBML
reader), and the law of the state at each time is the chemical master equation solved by a
matrix exponential over a finite state space (or a closed form). Also the tolerances: z-scores
with a Bonferroni-corrected normal quantile for the mean, and the asymptotic variance of the
sample variance (delta method) for the standard deviation.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.stats


@dataclass(frozen=True)
class Moments:
    """Exact mean, variance and fourth central moment of a scalar statistic at one time."""

    mean: float
    var: float
    mu4: float


def chain_moments(
    up: Callable[[int], float],
    down: Callable[[int], float],
    start: int,
    top: int,
    times: Sequence[float],
    value: Callable[[np.ndarray], np.ndarray] | None = None,
) -> list[Moments]:
    """Moments of a birth-death chain on {0..top} (X -> X+1 at up(X), X -> X-1 at down(X)).

    ``up(top)`` must be 0 (a finite chain) or negligible (the caller checks the truncated mass
    via ``truncated_mass``). ``value`` maps the chain state to the reported statistic.
    """
    n = top + 1
    q = np.zeros((n, n))
    for x in range(n):
        if x < top:
            q[x, x + 1] = up(x)
        if x > 0:
            q[x, x - 1] = down(x)
        q[x, x] = -q[x].sum()
    states = np.arange(n, dtype=float)
    values = states if value is None else value(states)
    out = []
    p0 = np.zeros(n)
    p0[start] = 1.0
    for t in times:
        p = p0 @ scipy.linalg.expm(q * t)
        p = p.clip(min=0.0)
        p /= p.sum()
        mean = float(p @ values)
        centred = values - mean
        out.append(Moments(mean, float(p @ centred**2), float(p @ centred**4)))
    return out


def truncated_mass(
    up: Callable[[int], float],
    down: Callable[[int], float],
    start: int,
    top: int,
    t: float,
    margin: int = 50,
) -> float:
    """Probability the chain truncated at ``top + margin`` sits above ``top`` at time ``t``."""
    n = top + margin + 1
    q = np.zeros((n, n))
    for x in range(n):
        if x < n - 1:
            q[x, x + 1] = up(x)
        if x > 0:
            q[x, x - 1] = down(x)
        q[x, x] = -q[x].sum()
    p0 = np.zeros(n)
    p0[start] = 1.0
    p = p0 @ scipy.linalg.expm(q * t)
    return float(p[top + 1 :].sum())


def poisson_moments(mean: float) -> Moments:
    """A Poisson law: variance = mean, fourth central moment = m + 3 m^2."""
    return Moments(mean, mean, mean + 3 * mean**2)


def z_bonferroni(alpha: float, comparisons: int) -> float:
    """Two-sided normal quantile for ``comparisons`` tests at family-wise false-alarm ``alpha``."""
    return float(scipy.stats.norm.ppf(1 - alpha / (2 * comparisons)))


def check_moments(sample: np.ndarray, exact: Moments, z: float, label: str) -> tuple[float, float]:
    """Assert the sample mean and sd agree with ``exact``; return their z-scores.

    Mean: (m - mu) / (sigma / sqrt(N)). Sd: s - sigma over sqrt((mu4 - sigma^4) / N) / (2 sigma),
    the delta-method standard error from the asymptotic variance of the sample variance.
    """
    n = sample.size
    sigma = math.sqrt(exact.var)
    mean_z = (sample.mean() - exact.mean) / (sigma / math.sqrt(n))
    sd_se = math.sqrt(max(exact.mu4 - exact.var**2, 0.0) / n) / (2 * sigma)
    sd_z = (sample.std(ddof=1) - sigma) / sd_se
    assert abs(mean_z) < z, (
        f"{label}: mean {sample.mean():.4f} vs exact {exact.mean:.4f} (z = {mean_z:.2f}, "
        f"limit {z:.2f}, N = {n})"
    )
    assert abs(sd_z) < z, (
        f"{label}: sd {sample.std(ddof=1):.4f} vs exact {sigma:.4f} (z = {sd_z:.2f}, "
        f"limit {z:.2f}, N = {n})"
    )
    return float(mean_z), float(sd_z)

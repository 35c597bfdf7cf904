"""How wrong a learned psi is where it matters: where the population actually lives.

A learned psi can be accurate on average over its training data (perturbed on purpose, far from
steady state) and still be 10-40 % off on the thin band where the population spends its time,
which is what sets the run and tumble durations and the drift. This diagnostic scores the two
*switching* probabilities (leaving phi = 0: psi_0; leaving phi = 1: 1 - psi_1) against a
reference, weighted by the full model's occupancy (rows of an unperturbed full-model run:
inputs and phi at sampled steps):

* ``reference = exact``: the internal model's exact lumped psi at each occupied point;
* ``reference = empirical`` (no exact psi): the observed switching frequency of the occupancy
  run itself in equal-count bins of the abstraction's inputs (1-D) -- noisy, so the binomial
  standard error is reported with it.

Per origin state: ``rel_bias`` = (mean learned - mean reference) / mean reference of the
occupancy-weighted switching probability (it predicts the relative error of the mean segment
duration, with the opposite sign: ``predicted_duration_error`` = 1 / (1 + rel_bias) - 1),
``mean_abs_rel_error`` (the mean of |learned - reference| / reference over occupied points) and
its 90th percentile. With the empirical reference, also (the statistics to trust it by):

* ``rel_bias_se``: the bias's standard error, cluster-robust over cells (a cell's windows are
  not independent), so a bias within about two of them is not distinguishable from none;
* ``calibration_chi2``, ``calibration_dof``, ``calibration_p``: a calibration test over the
  bins: sum of ((observed - learned) / se)^2, se the binomial standard error of the learned
  value (the null) times the bin's design effect (its cluster-robust over binomial variance),
  against chi-square with one degree of freedom per bin (a small p: the learned psi departs
  from the full model somewhere the population lives);
* ``settling_z``: the observed switching frequency of the run's first half minus its second
  half, each less what the learned psi predicts at its rows' inputs, in standard errors (a
  population still drifting from its start: a large |z|; cells moving to other inputs or a
  clock's rows of known age starting later in the record: none).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

if TYPE_CHECKING:
    from matplotlib.figure import Figure

from surrogate.gp.lookup import PsiFunction


def switching(phi: np.ndarray, p_one: np.ndarray) -> np.ndarray:
    """P(leave phi within dt) from p(phi' = 1): p for phi = 0, 1 - p for phi = 1."""
    return np.where(phi == 0, p_one, 1.0 - p_one)


@torch.no_grad()
def psi_errors(
    psi: PsiFunction,
    occupancy: pd.DataFrame,
    inputs: list[str] | tuple[str, ...],
    exact: Callable[[pd.DataFrame], np.ndarray] | None = None,
    bins: int = 20,
) -> tuple[dict[str, Any], pd.DataFrame]:
    """Score ``psi`` on ``occupancy`` (columns ``inputs``, ``phi``, ``phi_next``).

    Args:
        psi: the learned ``psi(phi, z)``.
        occupancy: rows of an unperturbed full-model run (see
            :func:`surrogate.simulate.transitions.record_occupancy`).
        inputs: the psi's input columns.
        exact: ``rows -> (n x 2)`` exact P(phi' = 1 | phi = 0, 1) at each row, or None for the
            empirical reference (binned over the first input).

    Returns:
        (metrics dict, per-row (exact) or per-bin (empirical) frame for figures).
    """
    from scipy import stats  # ~1.7 s to import: only where used

    phi = occupancy["phi"].to_numpy(np.int64, copy=True)
    z = torch.from_numpy(occupancy[list(inputs)].to_numpy(np.float32, copy=True))
    learned = switching(phi, psi(torch.as_tensor(phi), z).double().cpu().numpy())
    out: dict[str, Any] = {"reference": "exact" if exact is not None else "empirical",
                           "n_occupancy": len(occupancy)}  # fmt: skip
    if exact is not None:
        ref_both = exact(occupancy)
        reference = switching(phi, ref_both[np.arange(len(phi)), phi])
        frame = pd.DataFrame({"phi": phi, **{n: occupancy[n].to_numpy() for n in inputs},
                              "learned": learned, "reference": reference})  # fmt: skip
        for p in (0, 1):
            sel = phi == p
            out[f"phi{p}"] = _scores(learned[sel], reference[sel], np.ones(sel.sum()))
        return out, frame
    # empirical: equal-count bins of the first input, per origin state
    observed = (occupancy["phi_next"].to_numpy() != phi).astype(float)
    cells = (occupancy["cell"].to_numpy() if "cell" in occupancy
             else np.arange(len(occupancy)))  # fmt: skip
    times = occupancy["t"].to_numpy(float) if "t" in occupancy else np.zeros(len(occupancy))
    rows = []
    for p in (0, 1):
        sel = np.flatnonzero(phi == p)
        if sel.size == 0:
            continue
        x = occupancy[inputs[0]].to_numpy(float)[sel]
        edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
        idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
        for b in range(len(edges) - 1):
            m = idx == b
            if m.sum() == 0:
                continue
            f = observed[sel][m].mean()
            n_b, lb = int(m.sum()), float(learned[sel][m].mean())
            binomial = float(np.sqrt(max(f * (1 - f), 1e-12) / n_b))
            clustered = cluster_se(observed[sel][m], cells[sel][m])
            # the design effect of a cell's correlated windows, applied to the standard error
            # the learned value would give (the test's null: the learned psi is right)
            deff = max(1.0, (clustered / binomial) ** 2) if 0 < f < 1 else 1.0
            rows.append({"phi": p, inputs[0]: float(x[m].mean()), "n": n_b,
                         "learned": lb, "reference": float(f),
                         "reference_se": max(clustered, binomial),
                         "null_se": float(np.sqrt(max(lb * (1 - lb), 1e-12) * deff / n_b))})  # fmt: skip
    frame = pd.DataFrame(rows)
    for p in (0, 1):
        f = frame[frame["phi"] == p]
        if not len(f):
            continue
        scores = _scores(f["learned"].to_numpy(), f["reference"].to_numpy(),
                         f["n"].to_numpy(float))  # fmt: skip
        sel = phi == p
        mean_obs = float(observed[sel].mean())
        se = cluster_se(observed[sel], cells[sel])
        bias = scores["rel_bias"]
        scores["rel_bias_se"] = (1 + bias) * se / mean_obs if mean_obs > 0 else float("nan")
        z = (f["reference"] - f["learned"]) / f["null_se"]
        chi2 = float((z**2).sum())
        scores.update(calibration_chi2=chi2, calibration_dof=len(f),
                      calibration_p=float(stats.chi2.sf(chi2, len(f))))  # fmt: skip
        # what psi does not predict at each window's inputs: where the cells move to other
        # inputs (a field) or a clock's rows start later in the record (the rows before a
        # cell's first switch, of unknown age, are left out), the switching frequency moves
        # between the halves and the residual does not (Vilar's log clock: -5.7 standard
        # errors raw, no residual drift; session 35)
        half = times[sel] < np.median(times[sel])
        residual = observed[sel] - learned[sel]
        a, b = residual[half], residual[~half]
        se_ab = math.hypot(cluster_se(a, cells[sel][half]), cluster_se(b, cells[sel][~half]))
        scores["settling_z"] = float((a.mean() - b.mean()) / se_ab) if se_ab > 0 else 0.0
        out[f"phi{p}"] = scores
    return out, frame


def cluster_se(values: np.ndarray, clusters: np.ndarray) -> float:
    """Standard error of the mean of ``values``, cluster-robust over ``clusters`` (e.g. the
    cells whose windows they are): sqrt(sum_c (sum_{i in c} (v_i - mean))^2) / n, with the
    small-sample factor G / (G - 1) over G clusters."""
    n = values.size
    if n < 2:
        return float("nan")
    _, idx = np.unique(clusters, return_inverse=True)
    g = int(idx.max()) + 1
    sums = np.bincount(idx, weights=values - values.mean(), minlength=g)
    factor = g / (g - 1) if g > 1 else 1.0
    return float(math.sqrt(factor * (sums**2).sum()) / n)


def _scores(learned: np.ndarray, reference: np.ndarray, weight: np.ndarray) -> dict[str, float]:
    w = weight / weight.sum()
    mean_l, mean_r = float((w * learned).sum()), float((w * reference).sum())
    bias = (mean_l - mean_r) / mean_r if mean_r > 0 else float("nan")
    rel = np.abs(learned - reference) / np.maximum(reference, 1e-12)
    order = np.argsort(rel)
    cdf = np.cumsum(w[order])
    p90 = float(rel[order][min(np.searchsorted(cdf, 0.9), len(rel) - 1)])
    return {
        "n": int(weight.sum()),
        "mean_switching_learned": mean_l,
        "mean_switching_reference": mean_r,
        "rel_bias": bias,
        "predicted_duration_error": 1 / (1 + bias) - 1 if bias > -1 else float("nan"),
        "mean_abs_rel_error": float((w * rel).sum()),
        "p90_abs_rel_error": p90,
    }


@torch.no_grad()
def class_law_errors(
    law: Callable[[Tensor, Tensor], Tensor],
    occupancy: pd.DataFrame,
    inputs: list[str] | tuple[str, ...],
    class_names: tuple[str, ...],
    class_lumps: tuple[int, ...],
    exact: Callable[[pd.DataFrame], np.ndarray] | None = None,
    origin: str = "phi_class",
    destination: str = "phi_class_next",
) -> dict[str, Any]:
    """Score a K-lumps chain's law where the population lives: per origin class, the
    occupancy-weighted probability of leaving its lump (the switch the agent feels), learned
    against a reference, as :func:`psi_errors` scores psi.

    Args:
        law: ``(origin classes (n,), inputs (n x d)) -> n x C``, the chain's law
            (:meth:`~surrogate.simulate.classes.ClassTable.law`).
        occupancy: rows of an unperturbed full-model run with ``inputs``, ``origin`` and
            ``destination`` (classes).
        inputs: the law's input columns.
        class_names: the ``C`` classes' names; class_lumps: each one's phi.
        exact: ``rows -> n x C``, the exact law from each row's class (then the per-row
            scores of :func:`psi_errors`); None: the rows' observed switches (the mean only,
            with its binomial standard error).

    Returns:
        ``{class name: scores}`` for every class the population visits, each with ``share``
        (its part of the occupancy; ``rel_bias`` None where the reference never leaves the
        lump), and ``reference``.
    """
    a_col = occupancy[origin].to_numpy(np.int64)
    z = torch.from_numpy(occupancy[list(inputs)].to_numpy(np.float32, copy=True))
    lumps = np.asarray(class_lumps)
    out: dict[str, Any] = {"reference": "exact" if exact is not None else "empirical"}
    for a, name in enumerate(class_names):
        sel = np.flatnonzero(a_col == a)
        if sel.size == 0:
            continue
        other = lumps != lumps[a]
        learned = law(torch.full((sel.size,), a), z[sel]).double().cpu().numpy()[:, other].sum(1)
        if exact is not None:
            reference = exact(occupancy.iloc[sel])[:, other].sum(1)
            scores: dict[str, Any] = _scores(learned, reference, np.ones(sel.size))
        else:
            nxt = occupancy[destination].to_numpy(np.int64)[sel]
            observed = float((lumps[nxt] != lumps[a]).mean())
            mean_l = float(learned.mean())
            scores = {"n": int(sel.size), "mean_switching_learned": mean_l,
                      "mean_switching_reference": observed,
                      "rel_bias": (mean_l - observed) / observed if observed > 0 else float("nan"),
                      "rel_se": math.sqrt((1 - observed) / (observed * sel.size))
                      if observed > 0 else float("nan")}  # fmt: skip
        if not math.isfinite(scores["rel_bias"]):  # a class that never leaves its lump
            scores["rel_bias"] = None
        scores["share"] = sel.size / len(a_col)
        out[name] = scores
    return out


def plot_psi_errors(
    frame: pd.DataFrame, inputs: list[str] | tuple[str, ...], lump_names: tuple[str, str]
) -> Figure:
    """Learned vs reference switching probability over the occupied inputs (first input on
    the x axis), with the occupancy histogram; one panel per origin state."""
    import matplotlib.pyplot as plt

    name = inputs[0]
    fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex="col", constrained_layout=True,
                             gridspec_kw={"height_ratios": [3, 1]})  # fmt: skip
    for col, p in enumerate((0, 1)):
        f = frame[frame["phi"] == p].sort_values(name)
        ax, hist = axes[0, col], axes[1, col]
        if len(f) == 0:
            continue
        x = f[name].to_numpy()
        if "reference_se" in f:  # empirical bins
            ax.errorbar(x, f["reference"], yerr=f["reference_se"], fmt="o", ms=3, color="black",
                        label="full model (binned)")  # fmt: skip
            ax.plot(x, f["learned"], "-", color="tab:blue", label="learned psi")
            hist.bar(x, f["n"], width=np.gradient(x) if len(x) > 1 else 1.0, color="grey")
        else:
            order = np.argsort(x)
            stride = max(1, len(order) // 3000)
            sel = order[::stride]
            ax.plot(x[sel], f["reference"].to_numpy()[sel], ".", ms=2, color="black",
                    label="exact lumped psi")  # fmt: skip
            ax.plot(x[sel], f["learned"].to_numpy()[sel], ".", ms=2, color="tab:blue",
                    label="learned psi")  # fmt: skip
            hist.hist(x, bins=60, color="grey")
        ax.set_title(f"leaving {lump_names[p]} (phi = {p}), occupancy-weighted")
        ax.set_ylabel("P(switch within dt)")
        ax.legend(fontsize=8, markerscale=4)
        hist.set_xlabel(name)
        hist.set_ylabel("occupancy")
    return fig


def exact_reference(internal: Any, dt: float) -> Callable[[pd.DataFrame], np.ndarray]:
    """``rows -> (n x 2)`` exact psi of ``internal`` at the rows' signal columns."""

    def reference(rows: pd.DataFrame) -> np.ndarray:
        signal: Tensor = torch.as_tensor(
            rows[list(internal.signal_names)].to_numpy(np.float64), dtype=torch.float64
        )
        return internal.exact_psi(signal, dt).cpu().numpy()

    return reference


__all__ = ["cluster_se", "exact_reference", "plot_psi_errors", "psi_errors", "switching"]

"""Bins of a slow count that relax, not random-walk (``gp.class_moves=relaxation``).

A K-lumps chain learns every class-to-class move from one-window transitions
(:func:`~surrogate.gp.classes.fit_class_law`). Where the classes are bins of a *slow* count
(a protein that settles over minutes, the auto-regulatory network's total protein) that is the
wrong law for the bins: the count jitters across a bin edge within seconds and back, every
crossing is counted as a move, and a Markov chain over the bins turns that mean-reverting jitter
into a random walk that mixes the bins in ~50 s where the count takes ~1,000 s (measured,
docs/fidelity.md). The moves are also rare per window (~1e-3), so each is learned from a few
dozen events of a few hundred slow trajectories.

This law keeps what the windows measure well, the lump's flips given the bin, and builds the
bins' moves from two things that do not depend on crossings:

* ``pi(bin | z)``: the bins' stationary law at the inputs, from burned-in full-model cells at
  inputs spread like the collection's (one GP per bin against the rest, normalised);
* ``tau``: the count's relaxation time, from the same cells held at their inputs: the
  autocorrelation of the bin index (less its stationary mean at the cell's inputs) over lags of
  minutes, fitted as ``A exp(-s / tau)`` (``A < 1`` absorbs the edge jitter).

Per window each cell keeps its bin with probability ``exp(-dt / tau)``, else redraws it from
``pi(. | z)``; then its lump moves by the learned flip law of its (lump, bin). This kernel has
``pi(. | z)`` as its stationary law and relaxes every function of the bin as ``exp(-t / tau)``,
the count's measured time, whatever the jitter at the edges.

The classes must be bins shared by both lumps (``class_bins``: a flip keeps the bin).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ArtefactError, ConfigError
from surrogate.gp.lookup import grid_nodes
from surrogate.gp.settings import GPSettings
from surrogate.gp.training import fit_classifiers

#: gp.class_moves choices: the one-window law of every move, or bins that relax (this module)
CLASS_MOVES = ("learned", "relaxation")
#: the relaxation law's construction, in every such fit's identity (bump when it changes)
RELAXATION_VERSION = 1
#: the fewest burned-in cells of the stationary sample, and the cells per bin above that
#: (gp.relaxation.n_cells: null): pi(bin | z) is one GP per bin, so its noise grows with the bins
#: at a fixed sample. Measured on the auto-regulatory network (docs/fidelity.md): 8 bins at 600
#: cells (~75 per bin) missed one mean duration by 0.009 points, 16 bins at 2,400 (150 per bin)
#: passed 24 of 24 checks; 150 per bin puts a typical bin's share at ~8 % relative error.
DEFAULT_CELLS = 600
CELLS_PER_BIN = 150
#: default lags (s) of the stationary sample
DEFAULT_LAGS = (50.0, 100.0, 150.0, 200.0)
#: column names of the stationary sample: the bin at lag 0 and after each lag
BIN_COLUMN = "bin_{}"


def relaxation_cells(n_bins: int, n_cells: int | None = None) -> int:
    """The stationary sample's cells: ``n_cells`` where given, else :data:`CELLS_PER_BIN` per
    bin and at least :data:`DEFAULT_CELLS` (``n_bins`` bins shared by both lumps).

    Example:
        >>> relaxation_cells(16), relaxation_cells(3), relaxation_cells(16, 800)
        (2400, 600, 800)
    """
    if n_cells is not None:
        return int(n_cells)
    return max(DEFAULT_CELLS, CELLS_PER_BIN * int(n_bins))


def check_shared_bins(class_bins: Sequence[int] | None, class_lumps: Sequence[int]) -> int:
    """The number of bins ``B`` of classes that are (lump, bin) pairs with the same ``B`` bins
    in both lumps, else a ConfigError saying why relaxation cannot run."""
    if class_bins is None:
        raise ConfigError(
            "gp.class_moves=relaxation needs classes that are bins of one count shared by both "
            "lumps (the model's class_bins): one list of edges for both lumps of a count that "
            "is not the lump's own threshold count (whose bins across the threshold hold one "
            "lump each), or classes: {auto: {shared: true}}; else gp.class_moves=learned"
        )
    pairs = sorted(zip(class_lumps, class_bins, strict=True))
    n_bins = max(class_bins) + 1
    want = [(lump, b) for lump in (0, 1) for b in range(n_bins)]
    if pairs != want:
        raise ConfigError(
            f"gp.class_moves=relaxation needs each of the {n_bins} bins once in each lump; the "
            f"classes' (lump, bin) pairs are {pairs}"
        )
    return n_bins


def stationary_bin_law(
    z: Tensor,
    bins: Tensor,
    n_bins: int,
    grid: Tensor,
    settings: GPSettings,
    progress: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[Tensor, dict[str, Any]]:
    """``pi(bin | z)`` on ``grid`` from stationary samples: one GP per bin against the rest.

    Args:
        z: ``n x d`` inputs of burned-in cells.
        bins: ``(n,)`` int64, each cell's bin.
        n_bins: ``B``.
        grid: ``N x d`` nodes to tabulate on.
        settings: the GPs' settings.

    Returns:
        ``N x B`` float64 probabilities (rows sum to 1) and metrics (each bin's sample count).
    """
    counts = torch.bincount(bins, minlength=n_bins)
    problems, plan = [], {}
    for b in range(n_bins):
        hit = (bins == b).to(torch.float32)
        if 0 < int(counts[b]) < bins.numel():
            problems.append((z, hit, hit))
            plan[b] = len(problems) - 1
    fitted = fit_classifiers(problems, settings, progress=progress, device=device,
                             desc="stationary bins") if problems else []  # fmt: skip
    law = torch.zeros(grid.shape[0], n_bins, dtype=torch.float64)
    for b in range(n_bins):
        if b in plan:
            clf = fitted[plan[b]]
            with torch.no_grad():
                law[:, b] = clf.predict_proba(grid.to(clf.device)).double().cpu().clamp(0, 1)
        else:  # every sample or none in this bin
            law[:, b] = float(counts[b]) / bins.numel()
    total = law.sum(-1, keepdim=True)
    if bool((total <= 0).any()) or not torch.isfinite(law).all():
        raise ArtefactError("the stationary bin law vanishes or is not finite on its domain")
    return law / total, {"samples_per_bin": [int(c) for c in counts]}


def relaxation_time(
    bins: np.ndarray, mean: np.ndarray, lags: Sequence[float]
) -> tuple[float, dict[str, Any]]:
    """The count's relaxation time from its bin index at lag 0 and after each lag.

    Args:
        bins: ``n x (1 + L)`` bin indices of cells held at their inputs (lag 0 first).
        mean: ``(n,)`` the stationary mean bin index at each cell's inputs.
        lags: the ``L`` lags (s), increasing.

    Returns:
        ``tau`` (s; ``inf`` where the correlation does not decay) and metrics: the
        correlations per lag and the fitted jitter factor ``A``.
    """
    r = bins.astype(np.float64) - mean[:, None]
    s0 = r[:, 0]
    rho = [float((s0 * r[:, j]).sum() / math.sqrt((s0**2).sum() * (r[:, j] ** 2).sum()))
           for j in range(1, r.shape[1])]  # fmt: skip
    s = np.asarray(lags, dtype=np.float64)
    ok = np.asarray(rho) > 0.02
    metrics: dict[str, Any] = {"lags": [float(v) for v in s], "correlation": rho}
    if ok.sum() < 2:
        raise ArtefactError(
            f"the count's correlation is gone by the lags {list(s)} s ({rho}): its bins are not "
            "slow; use gp.class_moves=learned (or shorter gp.relaxation.lags)"
        )
    slope, intercept = np.polyfit(s[ok], np.log(np.asarray(rho)[ok]), 1)
    tau = math.inf if slope >= 0 else -1.0 / slope
    metrics.update(relaxation_time=tau, jitter_factor=float(math.exp(intercept)))
    return tau, metrics


def relaxation_class_law(
    learned: Tensor,
    stationary: Tensor,
    class_bins: Sequence[int],
    class_lumps: Sequence[int],
    tau: float,
    dt: float,
) -> Tensor:
    """The K-lumps chain's law with bins that relax.

    Args:
        learned: ``C x N x C`` the one-window law learned from transitions; only its moves
            within a bin (the lump's flips) are kept.
        stationary: ``N x B`` ``pi(bin | z)`` at the same nodes.
        class_bins: ``C`` bins; class_lumps: ``C`` lumps.
        tau: the count's relaxation time (s).
        dt: the window (s).

    Returns:
        ``C x N x C`` float64: keep the bin with ``exp(-dt / tau)``, else redraw it from
        ``pi``; then the flip law of (lump, bin).
    """
    c = learned.shape[0]
    bins = torch.tensor(list(class_bins))
    lumps = torch.tensor(list(class_lumps))
    same = (bins[:, None] == bins[None, :]).to(torch.float64)  # C x C
    flip = learned.double() * same[:, None, :]
    total = flip.sum(-1, keepdim=True)
    if bool((total <= 0).any()):
        raise ArtefactError("the learned law gives a class no move within its bin")
    flip = flip / total
    # the class of lump l with bin b: origin of the flip after a redraw
    index = {(int(lumps[k]), int(bins[k])): k for k in range(c)}
    stay = math.exp(-dt / tau) if math.isfinite(tau) else 1.0
    law = stay * flip
    for a in range(c):
        for b in range(c):  # redraw to bin(b), then flip from (lump(a), bin(b)) to b
            via = index[(int(lumps[a]), int(bins[b]))]
            law[a, :, b] += (1.0 - stay) * stationary[:, int(bins[b])] * flip[via, :, b]
    return law


@dataclass(frozen=True)
class RelaxationSpec:
    """What :func:`fit_relaxation_law` tabulates over, beside the data.

    Attributes:
        sizes: grid nodes per input (the learned law's ``n_1..n_d``).
        class_bins: the bin of each class.
        class_lumps: the lump of each class.
        lags: the increasing lags (s) the sample's ``bin_1 .. bin_L`` were read after.
        dt: the window (s).
    """

    sizes: Sequence[int]
    class_bins: Sequence[int]
    class_lumps: Sequence[int]
    lags: Sequence[float]
    dt: float


def fit_relaxation_law(
    learned: Tensor,
    sample: pd.DataFrame,
    input_names: Sequence[str],
    domain: Mapping[str, tuple[float, float]],
    spec: RelaxationSpec,
    settings: GPSettings,
    progress: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[Tensor, dict[str, Any]]:
    """:func:`relaxation_class_law` from a stationary sample (columns ``input_names`` and
    ``bin_0 .. bin_L``, see :func:`surrogate.simulate.transitions.record_stationary_bins`).

    Args:
        learned: ``C x n_1..n_d x C`` the learned class law.
        sample: the stationary sample.
        input_names: the ``d`` inputs.
        domain: ``{input: (lo, hi)}``, the grid's span.
        spec: the grid, the classes' bins and lumps, the lags and the window.
        settings: the GP settings of the stationary bin law.
        progress: show the fit's progress bar.
        device: where to fit.

    Returns:
        ``C x n_1..n_d x C`` law and metrics (tau, correlations, samples per bin).
    """
    sizes, class_bins, class_lumps = spec.sizes, spec.class_bins, spec.class_lumps
    lags, dt = spec.lags, spec.dt
    n_bins = check_shared_bins(class_bins, class_lumps)
    names = list(input_names)
    grid = grid_nodes([domain[n] for n in names], list(sizes)).to(torch.float32)
    z = torch.tensor(sample[names].to_numpy(dtype="float32"))
    columns = [BIN_COLUMN.format(j) for j in range(len(lags) + 1)]
    bins = sample[columns].to_numpy().astype(np.int64)
    pi, metrics = stationary_bin_law(z, torch.from_numpy(bins[:, 0]), n_bins, grid, settings,
                                     progress=progress, device=device)  # fmt: skip
    # the stationary mean bin at each sampled cell's inputs (nearest node of the grid)
    at = _nearest_nodes(z, grid, sizes)
    mean = (pi[at] * torch.arange(n_bins, dtype=torch.float64)).sum(-1).numpy()
    tau, timing = relaxation_time(bins, mean, lags)
    metrics.update(timing)
    c = learned.shape[0]
    law = relaxation_class_law(learned.reshape(c, -1, c), pi, class_bins, class_lumps, tau, dt)
    metrics["keep_bin_per_window"] = math.exp(-dt / tau) if math.isfinite(tau) else 1.0
    return law.reshape(c, *sizes, c), metrics


def _nearest_nodes(z: Tensor, grid: Tensor, sizes: Sequence[int]) -> Tensor:
    """Index of the grid node nearest each row of ``z`` (grid as :func:`grid_nodes` lays it)."""
    lo, hi = grid.min(0).values, grid.max(0).values
    index = torch.zeros(z.shape[0], dtype=torch.int64)
    stride = 1
    for axis in reversed(range(len(sizes))):
        n = sizes[axis]
        span = float(hi[axis] - lo[axis])
        pos = torch.zeros(z.shape[0]) if n == 1 or span == 0 else (z[:, axis] - lo[axis]) / span
        k = (pos.clamp(0, 1) * (n - 1)).round().long()
        index += k * stride
        stride *= n
    return index


__all__ = [
    "BIN_COLUMN",
    "CELLS_PER_BIN",
    "CLASS_MOVES",
    "DEFAULT_CELLS",
    "DEFAULT_LAGS",
    "RELAXATION_VERSION",
    "RelaxationSpec",
    "check_shared_bins",
    "fit_relaxation_law",
    "relaxation_cells",
    "relaxation_class_law",
    "relaxation_time",
    "stationary_bin_law",
]

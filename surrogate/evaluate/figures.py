"""Figures comparing a reference (full) run with a candidate (abstracted) run.

Figures are built on ``matplotlib.figure.Figure`` directly rather than through ``pyplot``, so
they render with the Agg canvas whatever backend is configured, never open a window, and are
not kept alive by pyplot's figure registry. Save them with ``surrogate.io.save_figure``.
Their margins are fixed in inches rather than found by a layout engine: constrained layout
measures every tick label before drawing, which doubled the cost of saving (about 0.5 s of
the 1.1 s an evaluation spent on its three figures).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from surrogate.evaluate.ks import BinnedSample, Distribution, ExactSample, compare_distributions
from surrogate.evaluate.runs import SimulationRun, mean_std_over_time

COLOURS: tuple[str, str] = ("tab:blue", "tab:orange")


def _panels(
    figsize: tuple[float, float], n: int, gap: float, left: float = 0.8, **kwargs: Any
) -> tuple[Figure, np.ndarray]:
    """A figure of ``n`` panels in a row with fixed margins (inches): ``left`` for the first
    panel's tick labels and axis label, ``gap`` between panels, room below for the x label
    and above for titles."""
    fig = Figure(figsize=figsize)
    width, height = figsize
    right, bottom, top = 0.15, 0.55, 0.35
    panel = (width - left - right - (n - 1) * gap) / n
    fig.subplots_adjust(left=left / width, right=1 - right / width, bottom=bottom / height,
                        top=1 - top / height, wspace=gap / panel)  # fmt: skip
    return fig, fig.subplots(1, n, squeeze=False, **kwargs)[0]


def plot_observable_histograms(
    reference: SimulationRun,
    candidate: SimulationRun,
    times: Sequence[float],
    labels: tuple[str, str] = ("full", "abstract"),
    bins: int = 20,
    name: str | None = None,
    axis_label: str | None = None,
) -> Figure:
    """The paper's Figure 4: histograms of an observable (default: the first, e.g. the distance
    from the peak) over all cells, one panel per record time.

    Both models are overlaid as step histograms (densities, so unequal cell counts compare) on
    about ``bins`` bins shared by all panels, so panels are comparable across time too: from
    every cell's value when both runs recorded them all, else from the histograms (the shared
    bins are then whole groups of the recorded grid's bins, spanning the values present; the
    values outside the grid, if any, are left out of the panel but not of its normalisation).
    Each panel's title gives the KS distance between the two runs (the comparison table's).
    """
    if not times:
        raise ValueError("plot_observable_histograms needs at least one time")
    name = name or reference.observable_names[0]
    dists = [
        (reference.observable_distribution(name, t), candidate.observable_distribution(name, t))
        for t in times
    ]
    flat = [d for pair in dists for d in pair]
    exact = all(isinstance(d, ExactSample) and d.counts is None for d in flat)
    if exact:
        values = [d.values for d in flat]  # type: ignore[union-attr]
        edges = np.histogram_bin_edges(np.concatenate(values), bins=bins)
    else:
        edges = _shared_edges(flat, bins)
    fig, axes = _panels((3.2 * len(times), 3.0), len(times), 0.15, sharex=True, sharey=True)
    for ax, t, pair in zip(axes, times, dists, strict=True):
        for dist, label, colour in zip(pair, labels, COLOURS, strict=True):
            if exact:
                ax.hist(dist.values, bins=edges, density=True, histtype="step", lw=1.5,  # type: ignore[union-attr]
                        color=colour, label=f"{label} (n={dist.n})")  # fmt: skip
            else:
                density = np.diff(dist.below(edges)) / (dist.n * np.diff(edges))
                ax.stairs(density, edges, lw=1.5, color=colour, label=f"{label} (n={dist.n})")
        ks = compare_distributions(*pair, name=f"{name} at t={t:g}")["ks"]
        ax.set_title(f"t = {t:g} s (KS {ks:.3f})", fontsize=10)
        ax.set_xlabel(axis_label or name)
    axes[0].set_ylabel("density")
    axes[0].legend(fontsize=8)
    return fig


def _shared_edges(dists: Sequence[Distribution], bins: int) -> np.ndarray:
    """About ``bins`` bins spanning the values of ``dists``, made of whole bins of the (first)
    recorded grid, so every binned distribution's counts in them are exact."""
    grid = next(d.edges for d in dists if isinstance(d, BinnedSample))
    lo, hi = np.inf, -np.inf
    for d in dists:
        if isinstance(d, BinnedSample):
            filled = np.flatnonzero(d.counts[1:-1])
            if filled.size:
                lo, hi = min(lo, d.edges[filled[0]]), max(hi, d.edges[filled[-1] + 1])
        else:
            v = d.values
            lo, hi = min(lo, float(np.min(v))), max(hi, float(np.max(v)))
    if not lo < hi:  # every value outside the grid or in one bin
        lo, hi = grid[0], grid[-1]
    first = int(np.clip(np.searchsorted(grid, lo, side="right") - 1, 0, grid.size - 2))
    last = int(np.clip(np.searchsorted(grid, hi, side="left"), first + 1, grid.size - 1))
    step = max(1, -(-(last - first) // bins))
    idx = np.arange(first, last + step, step)
    return grid[np.unique(np.minimum(idx, grid.size - 1))]


def plot_observable_over_time(
    reference: SimulationRun,
    candidate: SimulationRun,
    labels: tuple[str, str] = ("full", "abstract"),
    separate: bool = False,
    name: str | None = None,
    axis_label: str | None = None,
) -> Figure:
    """The paper's Figure 5: mean of an observable (default: the first, e.g. the distance from
    the peak) and a ±1 s.d. band against time.

    Both models share one axis by default; ``separate=True`` gives the paper's layout of one
    panel per model (shared y-axis).
    """
    fig, axes = _panels((9.0 if separate else 5.5, 3.5), 2 if separate else 1, 0.15, sharey=True)
    for i, (run, label, colour) in enumerate(
        zip((reference, candidate), labels, COLOURS, strict=True)
    ):
        ax = axes[i] if separate else axes[0]
        _mean_band(ax, run, label, colour, name)
        if separate:
            ax.set_title(label, fontsize=10)
    for ax in axes:
        ax.set_xlabel("t (s)")
        ax.legend(fontsize=8)
    axes[0].set_ylabel(axis_label or name or reference.observable_names[0])
    return fig


def drift_band(ax: Axes, t: np.ndarray, se: np.ndarray, label: str) -> None:
    """The noise band of a drift plot: where a second run's mean falls 95 % of the time around
    the reference's (+- 1.96 sqrt(2) s.e., the s.e. ``se`` of the reference's mean at times
    ``t``), and the zero line."""
    half = 1.96 * np.sqrt(2.0) * np.asarray(se, dtype=float)
    ax.fill_between(t, -half, half, color="grey", alpha=0.3, lw=0, label=label)
    ax.axhline(0.0, color="k", lw=1)


def plot_drift(
    reference: SimulationRun,
    candidate: SimulationRun,
    repeat: SimulationRun | None = None,
    labels: tuple[str, str] = ("full", "abstract"),
    name: str | None = None,
    axis_label: str | None = None,
) -> Figure:
    """The drift at a glance: the candidate's mean observable minus the reference's, against
    time, on the reference's noise band (the 95 % range of a second run's mean at the
    reference's size: +- 1.96 sqrt(2) s.d. / sqrt(n)), with the second full run where there is
    one. A gap outside the band is a drift the candidate gets wrong.
    """
    ref = mean_std_over_time(reference, name).set_index("t")
    fig, axes = _panels((5.5, 3.5), 1, 0.15)
    ax = axes[0]
    se = ref["std"].fillna(0.0).to_numpy() / np.sqrt(ref["n"].to_numpy())
    drift_band(ax, ref.index.to_numpy(), se, f"{labels[0]}: 95 % band of a 2nd run")
    runs = [(candidate, labels[1], COLOURS[1], "-")]
    if repeat is not None:
        runs.append((repeat, f"2nd {labels[0]} run", "k", "--"))
    for run, label, colour, style in runs:
        ms = mean_std_over_time(run, name).set_index("t")
        common = ref.index.intersection(ms.index)
        gap = ms.loc[common, "mean"] - ref.loc[common, "mean"]
        ax.plot(common.to_numpy(), gap.to_numpy(), color=colour, ls=style, lw=1.5, label=label)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"mean {axis_label or name or reference.observable_names[0]} - {labels[0]}'s")
    ax.legend(fontsize=8)
    return fig


def _mean_band(ax: Axes, run: SimulationRun, label: str, colour: str, name: str | None) -> None:
    ms = mean_std_over_time(run, name)
    t, mean, std = ms["t"].to_numpy(), ms["mean"].to_numpy(), ms["std"].fillna(0.0).to_numpy()
    ax.plot(t, mean, color=colour, lw=1.5, label=f"{label} mean")
    ax.fill_between(
        t, mean - std, mean + std, color=colour, alpha=0.2, lw=0, label=f"{label} ±1 s.d."
    )


def plot_duration_histograms(
    reference: SimulationRun,
    candidate: SimulationRun,
    labels: tuple[str, str] = ("full", "abstract"),
    bins: int = 40,
) -> Figure:
    """Duration histograms of each lump (e.g. run and tumble; two panels, densities on a log
    y-axis).

    All durations are used (not the KS subsample; from the lattice histograms when the runs
    have them, which give the same figure as the values); each panel's bins are shared by both
    models. A kind with no durations in either run gets an empty panel saying so.
    """
    kinds = list(reversed(reference.lump_names))
    fig, axes = _panels((9.0, 3.5), len(kinds), 0.8)
    for ax, kind in zip(axes, kinds, strict=True):
        pair = (reference.duration_distribution(kind), candidate.duration_distribution(kind))
        ax.set_title(f"{kind} durations", fontsize=10, y=1.0)
        ax.set_xlabel("duration (s)")
        present = [d for d in pair if d.n]
        if not present:
            ax.text(
                0.5, 0.5, f"no {kind} durations", ha="center", va="center", transform=ax.transAxes
            )
            continue
        lo = min(float(np.min(d.values)) for d in present)
        hi = max(float(np.max(d.values)) for d in present)
        edges = np.histogram_bin_edges([lo, hi], bins=bins)
        for dist, label, colour in zip(pair, labels, COLOURS, strict=True):
            if dist.n:
                counts, _ = np.histogram(dist.values, bins=edges, weights=dist.counts)
                density = counts / (dist.n * np.diff(edges))
                ax.stairs(density, edges, lw=1.5, color=colour, label=f"{label} (n={dist.n})")
        ax.set_yscale("log")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("density")
    return fig

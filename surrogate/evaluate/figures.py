"""Figures comparing a reference (full) run with a candidate (abstracted) run.

Figures are built on ``matplotlib.figure.Figure`` directly rather than through ``pyplot``, so
they render with the Agg canvas whatever backend is configured, never open a window, and are
not kept alive by pyplot's figure registry. Save them with ``surrogate.io.save_figure``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from surrogate.evaluate.statistics import (
    SimulationRun,
    compare_samples,
    mean_std_over_time,
    observable_at,
)

COLOURS: tuple[str, str] = ("tab:blue", "tab:orange")


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
    from the peak), one panel per record time.

    Both models are overlaid as step histograms (densities, so unequal cell counts compare) on
    bins shared by all panels, so panels are comparable across time too. Each panel's title
    gives the KS distance between the two samples.
    """
    if not times:
        raise ValueError("plot_observable_histograms needs at least one time")
    name = name or reference.observable_names[0]
    samples = [
        (observable_at(reference, name, t), observable_at(candidate, name, t)) for t in times
    ]
    edges = np.histogram_bin_edges(np.concatenate([np.concatenate(s) for s in samples]), bins=bins)
    fig = Figure(figsize=(3.2 * len(times), 3.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(times), sharex=True, sharey=True))
    for ax, t, (ref, cand) in zip(axes, times, samples, strict=True):
        for values, label, colour in zip((ref, cand), labels, COLOURS, strict=True):
            ax.hist(
                values,
                bins=edges,
                density=True,
                histtype="step",
                lw=1.5,
                color=colour,
                label=f"{label} (n={values.size})",
            )
        ks = compare_samples(ref, cand, name=f"{name} at t={t:g}")["ks"]
        ax.set_title(f"t = {t:g} s (KS {ks:.3f})", fontsize=10)
        ax.set_xlabel(axis_label or name)
    axes[0].set_ylabel("density")
    axes[0].legend(fontsize=8)
    return fig


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
    fig = Figure(figsize=(9.0 if separate else 5.5, 3.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, 2 if separate else 1, sharey=True))
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

    All durations are used (not the KS subsample); each panel's bins are shared by both models.
    A kind with no durations in either run gets an empty panel saying so.
    """
    fig = Figure(figsize=(9.0, 3.5), layout="constrained")
    kinds = list(reversed(reference.lump_names))
    axes = fig.subplots(1, len(kinds))
    for ax, kind in zip(axes, kinds, strict=True):
        pair = (reference.durations_of(kind), candidate.durations_of(kind))
        pooled = np.concatenate(pair)
        ax.set_title(f"{kind} durations", fontsize=10)
        ax.set_xlabel("duration (s)")
        if pooled.size == 0:
            ax.text(
                0.5, 0.5, f"no {kind} durations", ha="center", va="center", transform=ax.transAxes
            )
            continue
        edges = np.histogram_bin_edges(pooled, bins=bins)
        for values, label, colour in zip(pair, labels, COLOURS, strict=True):
            if values.size:
                ax.hist(
                    values,
                    bins=edges,
                    density=True,
                    histtype="step",
                    lw=1.5,
                    color=colour,
                    label=f"{label} (n={values.size})",
                )
        ax.set_yscale("log")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("density")
    return fig

"""Kymographs of runs in a channel: the cells' density and the read species' concentration over
x (horizontal) and t (vertical), one column of panels per run, so a full and an abstracted run
sit side by side on shared colour scales (issue 39).

Built on ``matplotlib.figure.Figure`` with margins fixed in inches, as
:mod:`surrogate.evaluate.figures`; save with ``surrogate.io.save_figure(..., crop=False)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from surrogate.evaluate.band import front_position
from surrogate.simulate.profiles import Profiles

__all__ = ["plot_kymograph"]

#: the panels' rows: what each shows, its colour map
ROWS: tuple[tuple[str, str], ...] = (("density", "viridis"), ("concentration", "magma"))


def _time_edges(t: np.ndarray) -> np.ndarray:
    """``(T + 1,)`` edges around the record times ``t`` (``(T,)``): midpoints, and half an
    interval beyond either end (one record: +- 0.5 s)."""
    if t.size == 1:
        return np.array([t[0] - 0.5, t[0] + 0.5])
    mid = 0.5 * (t[1:] + t[:-1])
    return np.concatenate([[2 * t[0] - mid[0]], mid, [2 * t[-1] - mid[-1]]])


def _show(ax: Axes, x_edges: np.ndarray, t: np.ndarray, values: np.ndarray, cmap: str,
          vmax: float) -> object:  # fmt: skip
    """``values`` (``(T, n_x)``) as an image over the columns and record times: ``imshow``
    when both are evenly spaced (cheap for many records), else ``pcolormesh``."""
    t_edges = _time_edges(t)
    even = np.allclose(np.diff(x_edges), x_edges[1] - x_edges[0]) and np.allclose(
        np.diff(t_edges), t_edges[1] - t_edges[0])  # fmt: skip
    if even:
        return ax.imshow(values, origin="lower", aspect="auto", interpolation="nearest",
                         extent=(x_edges[0], x_edges[-1], t_edges[0], t_edges[-1]),
                         cmap=cmap, vmin=0.0, vmax=vmax)  # fmt: skip
    return ax.pcolormesh(x_edges, t_edges, values, cmap=cmap, vmin=0.0, vmax=vmax)


def _scale(values: Sequence[np.ndarray]) -> float:
    """The colour scale's top for runs' ``(T, n_x)`` ``values``: the largest finite value after
    the first record (of the first record when there is no other; 1 when none is positive)."""
    later = [v[1:] if v.shape[0] > 1 else v for v in values]
    finite = [v[np.isfinite(v)] for v in later]
    top = max((float(v.max()) for v in finite if v.size), default=0.0)
    return top if top > 0 else 1.0


def plot_kymograph(
    runs: Sequence[Profiles],
    labels: Sequence[str] | None = None,
    front: bool = True,
    direction: int = 1,
) -> Figure:
    """Density (fraction of the run's cells per mm, so populations of different sizes compare)
    and the read species' y-averaged concentration (mM) over x and t: two rows, one column per
    run (e.g. full and abstract), each row on one colour scale across runs, from 0 to the
    row's largest value after the first record (a run's first record is its start, often every
    cell in one column, which would leave the band dark; it saturates instead).

    Args:
        runs: the runs' profiles (:func:`~surrogate.simulate.profiles.read_profiles`).
        labels: a title per run (default: ``run 1``, ...).
        front: draw the depletion front (:func:`~surrogate.evaluate.band.front_position`) on
            every panel.
        direction: the band's direction for the front (+1: towards larger x).
    """
    if not runs:
        raise ValueError("plot_kymograph needs at least one run's profiles")
    labels = list(labels) if labels is not None else [f"run {i + 1}" for i in range(len(runs))]
    if len(labels) != len(runs):
        raise ValueError(f"{len(labels)} labels for {len(runs)} runs")
    data = {"density": [p.density for p in runs],
            "concentration": [p.read_concentration() for p in runs]}  # fmt: skip
    n = len(runs)
    width, height = 0.9 + 3.6 * n + 1.1, 6.0
    left, right, bottom, top, hgap, vgap = 0.8, 1.1, 0.55, 0.35, 0.2, 0.55
    fig = Figure(figsize=(width, height))
    panel_w = (width - left - right - (n - 1) * hgap) / n
    panel_h = (height - bottom - top - vgap) / 2
    fig.subplots_adjust(left=left / width, right=1 - right / width, bottom=bottom / height,
                        top=1 - top / height, wspace=hgap / panel_w, hspace=vgap / panel_h)  # fmt: skip
    axes = fig.subplots(2, n, squeeze=False, sharex=True, sharey=True)
    for row, (what, cmap) in enumerate(ROWS):
        vmax = _scale(data[what])
        image = None
        for col, (p, values) in enumerate(zip(runs, data[what], strict=True)):
            ax = axes[row, col]
            image = _show(ax, p.edges, p.t, values, cmap, vmax)
            if front:
                x = front_position(p.centres, p.read_concentration(), direction=direction)
                ax.plot(x, p.t, color="white", lw=1.0, ls="--",
                        label="front (c = c0 / 2)")  # fmt: skip
            if row == 0:
                ax.set_title(f"{labels[col]} (n={p.n_cells})", fontsize=10)
            else:
                ax.set_xlabel("x (mm)")
            ax.set_xlim(p.edges[0], p.edges[-1])
        axes[row, 0].set_ylabel("t (s)")
        unit = "fraction of cells per mm" if what == "density" else f"{runs[0].read} (mM)"
        bar = fig.colorbar(image, ax=list(axes[row]), fraction=0.05, pad=0.02)  # type: ignore[arg-type]
        bar.set_label(f"{what}: {unit}", fontsize=8)
    if front:
        axes[1, 0].legend(fontsize=7, loc="upper right")
    return fig

"""Figures and tables of a learned psi (cf. Figure 3 of the paper), over its declared inputs.

One input: p(phi' = 1) against it for both origin states, with the binned frequencies of the
training transitions and, where known, the exact lumped psi. Two inputs: filled contours with
the training transitions overlaid. More: the first two inputs, the others at their midpoint.
The caller selects the backend (``matplotlib.use("Agg")`` in batch jobs); nothing here shows a
window.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import torch

from surrogate.gp.lookup import PsiFunction
from surrogate.gp.windows import row_windows

if TYPE_CHECKING:
    from matplotlib.figure import Figure

MAX_POINTS_PER_PANEL = 2_000
Range = tuple[float, float]


@torch.no_grad()
def _evaluate(psi: PsiFunction, grid: np.ndarray) -> dict[int, np.ndarray]:
    z = torch.as_tensor(grid, dtype=torch.float32)
    out = {}
    for phi in (0, 1):
        phis = torch.full((z.shape[0],), phi, dtype=torch.long)
        out[phi] = psi(phis, z).detach().cpu().double().numpy()
    return out


def _axes(
    domain: Mapping[str, Range], names: Sequence[str], size: Sequence[int]
) -> list[np.ndarray]:
    return [
        np.linspace(domain[n][0], domain[n][1], int(s)) for n, s in zip(names, size, strict=True)
    ]


def psi_grid_frame(
    psi: PsiFunction,
    domain: Mapping[str, Range],
    names: Sequence[str],
    size: Sequence[int] | None = None,
) -> pd.DataFrame:
    """p(phi' = 1) on a regular grid over ``domain``: columns ``phi``, one per input, ``p``.

    ``size`` defaults to 200 nodes for one input, 50 per axis otherwise.
    """
    names = list(names)
    size = size or ((200,) if len(names) == 1 else (50,) * len(names))
    axes = _axes(domain, names, size)
    mesh = np.meshgrid(*axes, indexing="ij")
    grid = np.stack([g.reshape(-1) for g in mesh], -1)
    p = _evaluate(psi, grid)
    frames = [
        pd.DataFrame({"phi": phi, **{n: grid[:, i] for i, n in enumerate(names)}, "p": p[phi]})
        for phi in (0, 1)
    ]
    out = pd.concat(frames, ignore_index=True)
    out["phi"] = out["phi"].astype("int64")
    return out


def binned_frequencies(
    data: pd.DataFrame, name: str, phi: int, bins: int = 30
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres, frequency of phi' = 1 and its binomial s.e. of the transitions from ``phi`` in
    equal-count bins of input ``name`` (the data's own estimate of psi); rows that stand for
    several windows (a collection that keeps every switch) weighted by them."""
    rows = data[data["phi"] == phi]
    x = rows[name].to_numpy(float)
    y = rows["phi_next"].to_numpy(float)
    if x.size == 0:
        return np.empty(0), np.empty(0), np.empty(0)
    windows = row_windows(rows)
    w = np.ones_like(x) if windows is None else windows
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    count = np.bincount(idx, weights=w, minlength=len(edges) - 1)
    ok = count > 0
    freq = np.bincount(idx, weights=y * w, minlength=len(edges) - 1)[ok] / count[ok]
    centre = np.bincount(idx, weights=x * w, minlength=len(edges) - 1)[ok] / count[ok]
    # the binomial s.e. of a bin's windows (of its switches, where every one is kept)
    se = np.sqrt(freq * (1 - freq) / count[ok])
    return centre, freq, se


def plot_psi(
    psi: PsiFunction,
    domain: Mapping[str, Range],
    names: Sequence[str],
    data: pd.DataFrame | None = None,
    lump_names: tuple[str, str] = ("0", "1"),
    exact: Callable[[np.ndarray], np.ndarray] | None = None,
    guide: tuple[np.ndarray, np.ndarray] | None = None,
    seed: int = 0,
) -> Figure:
    """The learned psi over its inputs (see the module docstring).

    Args:
        psi: ``psi(phi, z)``.
        domain: ``{name: (lo, hi)}`` box to draw.
        names: the psi's input names, in column order.
        data: training transitions (columns ``names``, ``phi``, ``phi_next``) to overlay.
        lump_names: names of phi = 0 and 1 for titles.
        exact: for one input, ``z (n,) -> (n x 2)`` exact P(phi' = 1 | phi) to draw beside.
        guide: for two inputs, a curve ``(first input values, second input values)`` to draw
            (e.g. the adapted methylation m0(L)).
    """
    names = list(names)
    if len(names) == 1:
        return _plot_curves(psi, domain, names[0], data, lump_names, exact)
    return _plot_surfaces(psi, domain, names, data, lump_names, guide, seed)


def _plot_curves(
    psi: PsiFunction,
    domain: Mapping[str, Range],
    name: str,
    data: pd.DataFrame | None,
    lump_names: tuple[str, str],
    exact: Callable[[np.ndarray], np.ndarray] | None,
) -> Figure:
    import matplotlib.pyplot as plt  # lazily, so importing surrogate.gp never picks a backend

    z = _axes(domain, [name], [400])[0]
    p = _evaluate(psi, z[:, None])
    ref = exact(z) if exact is not None else None
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    for ax, phi in zip(axes, (0, 1), strict=True):
        # the switching probability: leaving the origin state
        switch = p[phi] if phi == 0 else 1.0 - p[phi]
        ax.plot(z, switch, color="tab:blue", lw=2, label="learned psi")
        if ref is not None:
            ref_switch = ref[:, phi] if phi == 0 else 1.0 - ref[:, phi]
            ax.plot(z, ref_switch, color="black", ls="--", lw=1.5, label="exact lumped psi")
        if data is not None and len(data):
            c, f, se = binned_frequencies(data, name, phi)
            f = f if phi == 0 else 1.0 - f
            ax.errorbar(c, f, yerr=se, fmt="o", ms=3, color="tab:red", alpha=0.7,
                        label="collected transitions (binned)")  # fmt: skip
        ax.set_xlabel(name)
        ax.set_ylabel(f"P(leave {lump_names[phi]} within dt)")
        ax.set_title(f"from {lump_names[phi]} (phi = {phi})")
        ax.set_ylim(-0.02, 1.02)
        ax.legend(fontsize=8)
    return fig


def _plot_surfaces(
    psi: PsiFunction,
    domain: Mapping[str, Range],
    names: list[str],
    data: pd.DataFrame | None,
    lump_names: tuple[str, str],
    guide: tuple[np.ndarray, np.ndarray] | None,
    seed: int,
) -> Figure:
    import matplotlib.pyplot as plt

    a, b = names[0], names[1]
    xa, xb = _axes(domain, [a, b], [120, 120])
    mesh = np.meshgrid(xa, xb, indexing="ij")
    cols = [mesh[0].reshape(-1), mesh[1].reshape(-1)]
    for extra in names[2:]:  # further inputs at the middle of their range
        cols.append(np.full_like(cols[0], 0.5 * sum(domain[extra])))
    p = _evaluate(psi, np.stack(cols, -1))
    rng = np.random.default_rng(seed)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True, constrained_layout=True)
    levels = np.linspace(0.0, 1.0, 21)
    contour = None
    for ax, phi in zip(axes, (1, 0), strict=True):
        # second input on the x axis (the paper draws L across, m up)
        contour = ax.contourf(xb, xa, p[phi].reshape(len(xa), len(xb)), levels=levels,
                              cmap="viridis", vmin=0.0, vmax=1.0)  # fmt: skip
        if data is not None and len(data):
            rows = data[data["phi"] == phi]
            if len(rows) > MAX_POINTS_PER_PANEL:
                rows = rows.iloc[rng.choice(len(rows), MAX_POINTS_PER_PANEL, replace=False)]
            for nxt, colour in ((1, "magenta"), (0, "cyan")):
                sel = rows[rows["phi_next"] == nxt]
                ax.scatter(sel[b], sel[a], s=3, c=colour, alpha=0.5, linewidths=0,
                           label=f"next = {lump_names[nxt]}")  # fmt: skip
        if guide is not None:
            ga, gb = (np.asarray(v, dtype=float) for v in guide)
            ax.plot(gb, ga, color="white", ls="--", lw=2, label="steady state")
        ax.set_xlim(domain[b])
        ax.set_ylim(domain[a])
        ax.set_xlabel(b)
        ax.set_title(f"current phi = {lump_names[phi]}")
        if (data is not None and len(data)) or guide is not None:
            ax.legend(loc="upper left", fontsize=7, markerscale=3, framealpha=0.6)
    axes[0].set_ylabel(a)
    assert contour is not None  # one panel per phi
    fig.colorbar(contour, ax=list(axes), label=f"p(phi' = {lump_names[1]})")
    return fig


def plot_training_history(histories: dict[str, Sequence[float]]) -> Figure:
    """Training loss (negative ELBO per point) per epoch, one line per classifier, and beside
    it each loss above its lowest value on a log axis: the first panel's scale hides a loss
    still falling by 1e-4 per point, which moved Tyson's L2 means by ~5 % (docs/fidelity.md,
    "The clock's fit"); the second shows whether the fit has flattened.

    ``histories`` maps a label to its loss history, e.g.
    ``{"psi_0": psi.psi_0.history, "psi_1": psi.psi_1.history}``.
    """
    import matplotlib.pyplot as plt

    fig, (ax, gap) = plt.subplots(1, 2, figsize=(9.5, 3.5), constrained_layout=True)
    for label, hist in histories.items():
        loss = np.asarray(hist, dtype=float)
        epochs = np.arange(1, len(loss) + 1)
        ax.plot(epochs, loss, label=label)
        if len(loss) and np.isfinite(loss).any():
            above = loss - np.nanmin(loss)
            gap.plot(epochs, np.where(above > 0, above, np.nan), label=label)
    ax.set_xlabel("epoch")
    ax.set_ylabel("negative ELBO per point")
    ax.legend()
    gap.set_yscale("log")
    gap.set_xlabel("epoch")
    gap.set_ylabel("above its lowest (log)")
    return fig


__all__ = ["binned_frequencies", "plot_psi", "plot_training_history", "psi_grid_frame"]

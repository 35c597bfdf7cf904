"""Figures and tables of the learned psi surfaces (cf. Figure 3 of the paper).

The caller selects the backend (``matplotlib.use("Agg")`` in batch jobs); nothing here shows a
window.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import torch

from surrogate.gp.lookup import PsiFunction

if TYPE_CHECKING:
    from matplotlib.figure import Figure

MAX_POINTS_PER_PANEL = 2_000
PHI_NAMES = {1: "RUN", 0: "TUMBLE"}


@torch.no_grad()
def _grid(
    psi: PsiFunction,
    m_range: tuple[float, float],
    L_range: tuple[float, float],
    size: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """Node vectors and p over the (m, L) grid, shape (n_m, n_L), for phi = 0 and 1."""
    m = np.linspace(float(m_range[0]), float(m_range[1]), int(size[0]))
    L = np.linspace(float(L_range[0]), float(L_range[1]), int(size[1]))
    mm, ll = np.meshgrid(m, L, indexing="ij")
    m_t = torch.as_tensor(mm.reshape(-1), dtype=torch.float32)
    l_t = torch.as_tensor(ll.reshape(-1), dtype=torch.float32)
    p = {}
    for phi in (0, 1):
        phis = torch.full_like(m_t, phi, dtype=torch.long)
        p[phi] = psi(phis, m_t, l_t).detach().cpu().double().numpy().reshape(mm.shape)
    return m, L, p


def psi_grid_frame(
    psi: PsiFunction,
    m_range: tuple[float, float],
    L_range: tuple[float, float],
    size: tuple[int, int] = (50, 50),
) -> pd.DataFrame:
    """p(RUN next) on a regular (m, L) grid for both phi: columns ``phi``, ``m``, ``L``, ``p``."""
    m, L, p = _grid(psi, m_range, L_range, size)
    mm, ll = np.meshgrid(m, L, indexing="ij")
    frames = [
        pd.DataFrame(
            {"phi": phi, "m": mm.reshape(-1), "L": ll.reshape(-1), "p": p[phi].reshape(-1)}
        )
        for phi in (0, 1)
    ]
    out = pd.concat(frames, ignore_index=True)
    out["phi"] = out["phi"].astype("int64")
    return out


def plot_psi_surfaces(
    psi: PsiFunction,
    data: pd.DataFrame | None,
    m_range: tuple[float, float],
    L_range: tuple[float, float],
    adapted_curve: tuple[np.ndarray, np.ndarray] | None = None,
    size: tuple[int, int] = (120, 120),
    seed: int = 0,
) -> Figure:
    """Two panels (current phi = RUN, phi = TUMBLE): filled contours of p(RUN next) over (L, m).

    Ligand L is on the x axis and methylation m on the y axis. Training transitions from
    ``data`` (columns m, L, phi, phi_next) are overlaid, coloured by ``phi_next``, at most
    2,000 per panel (a fixed-seed subsample). ``adapted_curve`` is ``(L_values, m0_values)``,
    the adapted methylation level m0(L), drawn as a line.
    """
    import matplotlib.pyplot as plt  # lazily, so importing surrogate.gp never picks a backend

    m, L, p = _grid(psi, m_range, L_range, size)
    rng = np.random.default_rng(seed)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True, constrained_layout=True)
    levels = np.linspace(0.0, 1.0, 21)
    contour = None
    for ax, phi in zip(axes, (1, 0), strict=True):
        contour = ax.contourf(L, m, p[phi], levels=levels, cmap="viridis", vmin=0.0, vmax=1.0)
        if data is not None and len(data):
            rows = data[data["phi"] == phi]
            if len(rows) > MAX_POINTS_PER_PANEL:
                rows = rows.iloc[rng.choice(len(rows), MAX_POINTS_PER_PANEL, replace=False)]
            # Colours chosen to stand out on viridis: next-RUN points mostly sit on the yellow
            # (p ~ 1) region, next-TUMBLE points on the dark one.
            for nxt, colour in ((1, "magenta"), (0, "cyan")):
                sel = rows[rows["phi_next"] == nxt]
                ax.scatter(
                    sel["L"],
                    sel["m"],
                    s=3,
                    c=colour,
                    alpha=0.5,
                    linewidths=0,
                    label=f"next = {PHI_NAMES[nxt]}",
                )
        if adapted_curve is not None:
            L_curve, m_curve = (np.asarray(a, dtype=float) for a in adapted_curve)
            ax.plot(L_curve, m_curve, color="white", ls="--", lw=2, label="adapted $m_0(L)$")
        ax.set_xlim(L_range)
        ax.set_ylim(m_range)
        ax.set_xlabel("ligand L (mM)")
        ax.set_title(f"current state $\\phi$ = {PHI_NAMES[phi]}")
        if (data is not None and len(data)) or adapted_curve is not None:
            ax.legend(loc="upper left", fontsize=7, markerscale=3, framealpha=0.6)
    axes[0].set_ylabel("methylation m")
    fig.colorbar(contour, ax=list(axes), label="p($\\phi'$ = RUN)")
    return fig


def plot_training_history(histories: dict[str, Sequence[float]]) -> Figure:
    """Training loss (negative ELBO per point) per epoch, one line per classifier.

    ``histories`` maps a label to its loss history, e.g.
    ``{"psi_0": psi.psi_tumble.history, "psi_1": psi.psi_run.history}``.
    """
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.5), constrained_layout=True)
    for label, hist in histories.items():
        ax.plot(np.arange(1, len(hist) + 1), np.asarray(hist, dtype=float), label=label)
    ax.set_xlabel("epoch")
    ax.set_ylabel("negative ELBO per point")
    ax.legend()
    return fig


__all__ = ["plot_psi_surfaces", "plot_training_history", "psi_grid_frame"]

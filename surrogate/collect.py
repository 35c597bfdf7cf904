"""The collect stage: perturbed micro-trajectories of the full model -> transitions table.

Every ``record_every`` steps each cell contributes one transition (m, L, phi, phi_next): the
RUN property before and after a window dt run at inputs (m, L). Cells that stay near steady
state only visit a thin band around the switching boundary m ~ m0(L), so cells are sporadically
*perturbed* (moved to a random point in a disc around the field's peak, as in the paper), which
puts their methylation out of adaptation with the new L while it relaxes.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from surrogate.config import (
    build_field,
    build_params,
    non_negative,
    positive,
    resolve_device,
    seed_everything,
    to_dict,
    validate_common,
)
from surrogate.errors import ConfigError, NumericalError
from surrogate.io import MANIFEST, make_once, save_figure, write_manifest, write_parquet
from surrogate.paths import collect_command, collect_dir, collect_settings
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator

log = logging.getLogger(__name__)

TRANSITIONS = "transitions.parquet"
COVERAGE_FIGURE = "coverage.png"


SAMPLINGS = ("radius", "area")


def random_in_disc(
    n: int,
    centre: tuple[float, float],
    radius: float,
    device: torch.device,
    sampling: str = "radius",
) -> torch.Tensor:
    """``n`` random points (mm, (n, 2)) in a disc: distance from the centre uniform in
    [0, radius] (``radius``: more points near the peak, where the fields' high L lives) or
    uniform over the disc's area (``area``)."""
    u = torch.rand(n, device=device)
    r = radius * (u if sampling == "radius" else torch.sqrt(u))
    theta = torch.rand(n, device=device) * (2 * math.pi)
    offset = torch.stack([r * torch.cos(theta), r * torch.sin(theta)], -1)
    return offset + torch.tensor(centre, device=device)


def collect_transitions(
    simulator: Simulator,
    n_cells: int,
    n_per_state: int,
    perturb_rate: float,
    perturb_radius: float,
    perturb_sampling: str = "radius",
    record_every: int = 1,
    equilibration_time: float = 10.0,
    max_time: float = 2000.0,
    progress: bool = True,
) -> pd.DataFrame:
    """Simulate the full model with perturbations until ``n_per_state`` transitions from each
    origin state are recorded; return a random subsample of exactly ``n_per_state`` per origin.

    Columns: ``m``, ``L``, ``phi``, ``phi_next`` (0 = TUMBLE, 1 = RUN), ``cell``, ``t`` (start of
    the window) and ``perturbed`` (the cell was moved just before this window).
    """
    device, dt, field = simulator.device, simulator.dt, simulator.field
    # cells start spread over the disc the perturbations use, adapted to where they are
    start = random_in_disc(n_cells, field.peak, perturb_radius, device, perturb_sampling)
    state = simulator.initial_state(n_cells, start, equilibration_time)

    jump_probability = perturb_rate * dt
    chunks: list[dict[str, np.ndarray]] = []
    counts = np.zeros(2, dtype=np.int64)
    max_steps = math.ceil(max_time / dt)
    bar = tqdm(
        total=2 * n_per_state, desc="collect transitions", disable=not progress, mininterval=1.0
    )
    cells = torch.arange(n_cells, device=device)
    with torch.no_grad():
        for k in range(max_steps):
            jump = torch.rand(n_cells, device=device) < jump_probability
            target = random_in_disc(n_cells, field.peak, perturb_radius, device, perturb_sampling)
            state.position = torch.where(jump.unsqueeze(-1), target, state.position)
            rec = simulator.step(state)
            # every cell on thinned steps, plus every cell just perturbed: the step after a jump
            # is where off-boundary inputs meet the "wrong" origin state (RUN far above m0(L),
            # TUMBLE far below), which steady-state sampling almost never sees
            rows = cells if (k + 1) % record_every == 0 else jump.nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            chunk = {
                "m": rec.methylation[rows].float().cpu().numpy(),
                "L": rec.ligand[rows].float().cpu().numpy(),
                "phi": rec.run_before[rows].to(torch.int8).cpu().numpy(),
                "phi_next": rec.run_after[rows].to(torch.int8).cpu().numpy(),
                "cell": rows.cpu().numpy(),
                "t": np.full(rows.numel(), k * dt),
                "perturbed": jump[rows].cpu().numpy(),
            }
            # the rows are on the host already, so the check is free; NaN/inf must not reach
            # the table (clamping turns an infinite L into m = m_max, so L is checked too)
            if not (np.isfinite(chunk["m"]).all() and np.isfinite(chunk["L"]).all()):
                raise NumericalError(
                    f"collect: NaN/inf in the recorded (m, L) at t={k * dt:g} s; the field "
                    f"returned NaN/inf concentrations or the dynamics diverged"
                )
            chunks.append(chunk)
            new = np.bincount(chunk["phi"], minlength=2)
            bar.update(
                int(
                    np.minimum(counts + new, n_per_state).sum()
                    - np.minimum(counts, n_per_state).sum()
                )
            )
            counts += new
            if (counts >= n_per_state).all():
                break
    bar.close()
    if not (counts >= n_per_state).all():
        raise ConfigError(
            f"collect reached collect.max_time={max_time:g} s with only {counts.tolist()} transitions "
            f"(TUMBLE, RUN) of the {n_per_state} wanted per origin state; raise collect.max_time or "
            f"collect.n_cells, or lower collect.n_per_state"
        )
    table = pd.DataFrame({k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]})
    # a random (seeded) subsample per origin spreads the kept rows over the whole collection
    gen = np.random.default_rng(int(torch.randint(0, 2**31 - 1, (1,)).item()))
    keep = np.concatenate(
        [
            np.sort(
                gen.choice(
                    np.flatnonzero(table["phi"].to_numpy() == phi), n_per_state, replace=False
                )
            )
            for phi in (0, 1)
        ]
    )
    out = table.iloc[np.sort(keep)].reset_index(drop=True)
    out["phi"] = out["phi"].astype(np.int8)
    out["phi_next"] = out["phi_next"].astype(np.int8)
    return out


def validate(cfg: Mapping[str, Any]) -> None:
    """All checks of a collect config, before any work starts."""
    validate_common(cfg)
    c = cfg["collect"]
    positive(c, "n_per_state", "collect.", integer=True)
    positive(c, "n_cells", "collect.", integer=True)
    positive(c, "record_every", "collect.", integer=True)
    positive(c, "perturb_radius", "collect.")
    positive(c, "max_time", "collect.")
    non_negative(c, "equilibration_time", "collect.")
    rate = non_negative(c, "perturb_rate", "collect.")
    if rate * float(cfg["dt"]) > 1.0:
        raise ConfigError(
            f"collect.perturb_rate={rate:g}/s cannot be met with dt={cfg['dt']:g} s: at most one "
            f"perturbation per step, so the rate must be <= 1/dt = {1 / float(cfg['dt']):g}/s"
        )
    if c.get("perturb_sampling", "radius") not in SAMPLINGS:
        raise ConfigError(
            f"collect.perturb_sampling must be one of {list(SAMPLINGS)}, "
            f"got {c.get('perturb_sampling')!r}"
        )


def plot_coverage(table: pd.DataFrame, params: Any) -> Any:
    """Scatter of the recorded (m, L) points by origin state, with the adapted curve m0(L)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from surrogate.models.ecoli import adapted_methylation

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True, sharey=True)
    L_grid = np.linspace(0.0, max(float(table["L"].max()), 1e-3), 200)
    m0 = adapted_methylation(torch.tensor(L_grid), params).numpy()
    for ax, (phi, label) in zip(axes, ((1, "origin RUN"), (0, "origin TUMBLE")), strict=True):
        rows = table[table["phi"] == phi]
        rows = rows.sample(min(len(rows), 4000), random_state=0)
        for nxt, colour in ((1, "tab:blue"), (0, "tab:red")):
            pts = rows[rows["phi_next"] == nxt]
            ax.scatter(
                pts["L"],
                pts["m"],
                s=3,
                alpha=0.5,
                c=colour,
                label=f"next {'RUN' if nxt else 'TUMBLE'}",
            )
        ax.plot(L_grid, m0, "k--", lw=1, label="adapted m0(L)")
        ax.set_title(f"{label} (n={int((table['phi'] == phi).sum())})")
        ax.set_xlabel("L (mM)")
    axes[0].set_ylabel("methylation m")
    axes[0].legend(markerscale=3, fontsize=8)
    fig.suptitle("Collected transitions: coverage of (m, L)")
    return fig


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Run (or reuse) the collect stage of ``cfg``; return its artefact directory."""
    validate(cfg)
    out = collect_dir(cfg)
    return make_once(out, collect_settings(cfg), collect_command(cfg), lambda _: _collect(cfg, out),
                     what="transitions", force=force)  # fmt: skip


def _collect(cfg: Mapping[str, Any], out: Path) -> None:
    """Simulate, then write the table, the figure and (last) the manifest into ``out``."""
    device = resolve_device(cfg.get("device", "cpu"))
    seed_everything(int(cfg["seed"]))
    params = build_params(cfg["model"])
    c = cfg["collect"]
    simulator = Simulator(
        FullDecision(params), build_field(cfg["field"]), params, float(cfg["dt"]), device
    )
    t0 = time.perf_counter()
    table = collect_transitions(
        simulator,
        n_cells=int(c["n_cells"]),
        n_per_state=int(c["n_per_state"]),
        perturb_rate=float(c["perturb_rate"]),
        perturb_radius=float(c["perturb_radius"]),
        perturb_sampling=str(c.get("perturb_sampling", "radius")),
        record_every=int(c["record_every"]),
        equilibration_time=float(c["equilibration_time"]),
        max_time=float(c["max_time"]),
        progress=bool(cfg.get("progress", True)),
    )
    wall = time.perf_counter() - t0
    # from here the directory reads as incomplete until the new manifest is written last
    (out / MANIFEST).unlink(missing_ok=True)
    write_parquet(out / TRANSITIONS, table)
    save_figure(out / COVERAGE_FIGURE, plot_coverage(table, params))
    counts = {
        f"{'run' if phi else 'tumble'}_to_{'run' if nxt else 'tumble'}": int(
            ((table["phi"] == phi) & (table["phi_next"] == nxt)).sum()
        )
        for phi in (0, 1)
        for nxt in (0, 1)
    }
    write_manifest(
        out,
        stage="collect",
        config=to_dict(cfg),
        seed=int(cfg["seed"]),
        settings=collect_settings(cfg),
        device=str(device),
        wall_time_s=wall,
        n_rows=len(table),
        counts_per_origin={
            "tumble": int((table["phi"] == 0).sum()),
            "run": int((table["phi"] == 1).sum()),
        },
        counts=counts,
        domain={
            "m": [float(table["m"].min()), float(table["m"].max())],
            "L": [float(table["L"].min()), float(table["L"].max())],
        },
    )
    log.info("collected %d transitions in %.1f s; artefacts in %s", len(table), wall, out)

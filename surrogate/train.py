"""The train stage: transitions table -> GP classifiers psi0 / psi1 -> artefact directory.

Also the Python API to load a trained abstraction::

    from surrogate.train import load_abstraction
    psi = load_abstraction("data/train/field=gaussian_...")
    p_run = psi(phi, m, L)   # batched p(phi' = RUN | phi, m, L)
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from surrogate.collect import TRANSITIONS
from surrogate.config import (
    build_params,
    grid_shape,
    resolve_device,
    seed_everything,
    to_dict,
    validate_common,
)
from surrogate.errors import ArtefactError, ConfigError, NumericalError
from surrogate.gp import (
    GPSettings,
    PsiClassifier,
    fit_psi,
    load_psi,
    plot_psi_surfaces,
    plot_training_history,
    psi_grid_frame,
    save_psi,
)
from surrogate.io import (
    MANIFEST,
    make_once,
    read_parquet,
    require_artefact,
    save_figure,
    write_csv,
    write_json,
    write_manifest,
)
from surrogate.paths import (
    collect_command,
    collect_dir,
    collect_settings,
    train_command,
    train_dir,
    train_settings,
)

log = logging.getLogger(__name__)

PSI = "psi.pt"
METRICS = "train_metrics.json"
GRID = "psi_grid.csv"
SURFACES_FIGURE = "psi_surfaces.png"
HISTORY_FIGURE = "training_history.png"
REQUIRED_COLUMNS = ("m", "L", "phi", "phi_next")


def gp_settings(cfg: Mapping[str, Any]) -> GPSettings:
    """Validated GP settings of a config (the run's seed drives initialisation and splits)."""
    gp = {k: v for k, v in to_dict(cfg["gp"]).items() if k != "grid_size"}  # presentation only
    return GPSettings.from_config({**gp, "seed": int(cfg["seed"])})


def validate(cfg: Mapping[str, Any]) -> None:
    """All checks of a train config, before any work starts."""
    validate_common(cfg)
    settings = gp_settings(cfg)
    # the stage reports held-out metrics, so it needs a validation split (GPSettings allows 0)
    if not 0.0 < settings.validation_fraction < 1.0:
        raise ConfigError(
            f"gp.validation_fraction must lie in (0, 1) for the train stage (it reports held-out "
            f"metrics), got {settings.validation_fraction!r}"
        )
    # checked here, not after collect has run: each classifier trains on its origin state's rows
    n_per_state = cfg["collect"].get("n_per_state")
    if isinstance(n_per_state, int) and not isinstance(n_per_state, bool) and n_per_state > 0:
        n_train = n_per_state - round(settings.validation_fraction * n_per_state)
        if settings.n_inducing > n_train:
            raise ConfigError(
                f"gp.n_inducing={settings.n_inducing} exceeds the {n_train} training points per "
                f"classifier (collect.n_per_state={n_per_state} minus the validation split); "
                f"lower gp.n_inducing or raise collect.n_per_state"
            )
    grid_shape(cfg["gp"].get("grid_size", [50, 50]), "gp.grid_size")


def load_transitions(cfg: Mapping[str, Any]) -> tuple[pd.DataFrame, Path]:
    """The collected transitions this config trains on, checked against its settings."""
    directory = collect_dir(cfg)
    manifest = require_artefact(
        directory, collect_settings(cfg), collect_command(cfg), "collected transitions"
    )
    table = read_parquet(directory / TRANSITIONS, made_by=collect_command(cfg))
    missing = [c for c in REQUIRED_COLUMNS if c not in table.columns]
    if missing:
        raise ArtefactError(f"{directory / TRANSITIONS} lacks column(s) {missing}")
    if len(table) != manifest.get("n_rows", len(table)):
        raise ArtefactError(
            f"{directory / TRANSITIONS} has {len(table)} rows but its manifest says {manifest['n_rows']}; "
            f"re-create it with `{collect_command(cfg)}`"
        )
    values = table[["m", "L"]].to_numpy(dtype=np.float64)
    if not np.isfinite(values).all():
        raise NumericalError(f"{directory / TRANSITIONS} contains NaN or infinite m/L values")
    return table, directory


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Run (or reuse) the train stage of ``cfg``; return its artefact directory."""
    validate(cfg)
    out = train_dir(cfg)
    return make_once(out, train_settings(cfg), train_command(cfg),
                     lambda data: _train(cfg, out, *data), what="abstraction", force=force,
                     prepare=lambda: load_transitions(cfg))  # fmt: skip


def _train(cfg: Mapping[str, Any], out: Path, table: pd.DataFrame, source: Path) -> None:
    """Fit both classifiers, then write the model, tables, figures and (last) the manifest."""
    device = resolve_device(cfg.get("device", "cpu"))
    settings = gp_settings(cfg)
    seed_everything(int(cfg["seed"]))
    t0 = time.perf_counter()
    try:
        psi = fit_psi(table, settings, progress=bool(cfg.get("progress", True)), device=device)
    except NumericalError as exc:
        # nothing was written: a previous complete abstraction in `out` (if any) is kept
        err = NumericalError(f"{exc} Nothing was written to {out}.")
        err.partial = getattr(exc, "partial", None)  # type: ignore[attr-defined]
        raise err from exc
    wall = time.perf_counter() - t0
    psi.to("cpu")

    metrics = {
        name: {
            "validation": clf.validation,
            "n_train": clf.n_train,
            "n_val": clf.n_val,
            "train_seconds": clf.train_seconds,
            "final_loss": clf.history[-1] if clf.history else None,
        }
        for name, clf in (("psi_tumble", psi.psi_tumble), ("psi_run", psi.psi_run))
    }
    metrics["train_seconds_total"] = wall
    domain = psi.domain
    params = build_params(cfg["model"])
    grid = psi_grid_frame(
        psi, domain["m"], domain["L"], size=tuple(cfg["gp"].get("grid_size", [50, 50]))
    )
    if not np.isfinite(grid["p"].to_numpy()).all():
        # a model that predicts NaN must not reach the simulations (NaN < u is always False)
        raise NumericalError(
            f"the trained classifiers predict NaN/inf on their own (m, L) domain; nothing was "
            f"written to {out}. Try a smaller gp.lr (now {settings.lr}) or more gp.epochs"
        )
    # from here the directory reads as incomplete until the new manifest is written last
    (out / MANIFEST).unlink(missing_ok=True)
    save_psi(out / PSI, psi, {"settings": train_settings(cfg), "source": str(source)})
    write_json(out / METRICS, metrics)
    write_csv(out / GRID, grid)
    save_figure(
        out / SURFACES_FIGURE,
        plot_psi_surfaces(
            psi, table, domain["m"], domain["L"], adapted_curve=adapted_curve(domain["L"], params)
        ),
    )
    save_figure(
        out / HISTORY_FIGURE,
        plot_training_history(
            {"psi_tumble": psi.psi_tumble.history, "psi_run": psi.psi_run.history}
        ),
    )
    write_manifest(
        out,
        stage="train",
        config=to_dict(cfg),
        seed=int(cfg["seed"]),
        settings=train_settings(cfg),
        source=str(source),
        device=str(device),
        wall_time_s=wall,
        domain={k: list(v) for k, v in domain.items()},
        brier={n: metrics[n]["validation"]["brier"] for n in ("psi_tumble", "psi_run")},
        brier_baseline={
            n: metrics[n]["validation"]["brier_baseline"] for n in ("psi_tumble", "psi_run")
        },
    )
    for name in ("psi_tumble", "psi_run"):
        v = metrics[name]["validation"]
        log.info(
            "%s: held-out Brier %.4f (constant predictor %.4f), log predictive %.4f, accuracy %.3f",
            name, v["brier"], v["brier_baseline"], v["mean_log_predictive"], v["accuracy"],
        )  # fmt: skip
    log.info("trained both classifiers in %.1f s; artefacts in %s", wall, out)


def adapted_curve(
    L_range: tuple[float, float], params: Any, n: int = 200
) -> tuple[np.ndarray, np.ndarray]:
    """(L, m0(L)) over ``L_range``: the steady-state boundary drawn on the surfaces."""
    from surrogate.models.ecoli import adapted_methylation

    L = np.linspace(L_range[0], L_range[1], n)
    return L, adapted_methylation(torch.tensor(L), params).numpy()


def resolve_abstraction(cfg: Mapping[str, Any]) -> Path:
    """The train directory a config points to, or a clear error naming the command that makes it."""
    directory = train_dir(cfg)
    require_artefact(
        directory,
        train_settings(cfg),
        train_command(cfg),
        "trained abstraction",
        after=collect_command(cfg),
    )
    return directory


def load_abstraction(
    source: str | os.PathLike | Mapping[str, Any], device: str | torch.device = "cpu"
) -> PsiClassifier:
    """Load a trained abstraction from its artefact directory (or from the config that made it).

    Returns a :class:`~surrogate.gp.PsiClassifier`: ``psi(phi, m, L)`` gives
    p(phi' = RUN | phi, m, L) for tensors of any length, under ``torch.no_grad()``, chunked.
    """
    directory = resolve_abstraction(source) if isinstance(source, Mapping) else Path(source)
    psi, _ = load_psi(directory / PSI, device=device)
    return psi

"""The train stage: transitions table -> GP classifiers psi_0 / psi_1 -> artefact directory.

``python scripts/train.py [gp.inputs=signal|inputs|[names]] [gp.kernel=...]`` trains on the
collected transitions of the same settings, or on any external table with ``transitions=PATH``
(CSV or Parquet with the input columns, ``phi`` and ``phi_next``, e.g. tracked cells). The fit
(``data/fit/...``: ``psi.pt``, ``fit_metrics.json``, the training history; what simulations
load) is reused whatever ``gp.diagnostic`` and ``gp.grid_size`` say; the train directory
(``data/train/...``) holds a copy of it, ``psi_grid.csv``, ``train_metrics.json`` (held-out
scores, and the diagnostic: the switching probabilities' error where the full model's
population lives), figures and the manifest. Also the Python API to load a trained
abstraction::

    from surrogate.stages.train import load_abstraction
    psi = load_abstraction("data/train/model=ecoli_...")
    p = psi(phi, z)   # z: n x d in the order of psi.input_names
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from surrogate.config import seed_everything, to_dict
from surrogate.diagnosis.cost import duration
from surrogate.diagnosis.jumps import (
    MIN_SETTLED_ROWS,
    SETTLED_AFTER,
    lagging_window,
    settled_rows,
)
from surrogate.diagnosis.remedies import DURATION_TOLERANCE, diagnostic_cells_needed
from surrogate.errors import ArtefactError, ConfigError, NumericalError
from surrogate.gp import (
    PsiClassifier,
    PsiLookupTable,
    fit_psi,
    last_tenth_drop,
    load_psi,
    plot_psi,
    plot_training_history,
    psi_grid_frame,
    save_psi,
)
from surrogate.gp.diagnostics import class_law_errors, plot_psi_errors, psi_errors
from surrogate.gp.own_rows import describe
from surrogate.gp.windows import WINDOWS, row_windows
from surrogate.io import (
    MANIFEST,
    make_once,
    read_csv,
    read_json,
    read_manifest,
    read_parquet,
    require_artefact,
    save_figure,
    write_atomic,
    write_csv,
    write_json,
    write_manifest,
)
from surrogate.kinds import load_class_chain as load_class_chain  # the Python API's
from surrogate.kinds.chains import TWO_STATE
from surrogate.models.base import Model
from surrogate.models.capabilities import (
    class_count_of,
    exact_class_step_of,
    has_exact_psi,
    lump_classes_of,
    signal_bounds_of,
)
from surrogate.simulate.classes import (
    CLASS,
    CLASS_NEXT,
    ClassDecision,
    ClassTable,
    exact_class_table,
    reclassify,
)
from surrogate.simulate.decision import ExactPsi
from surrogate.simulate.loop import Simulator
from surrogate.simulate.memory import AGE, can_age, clock_rows, exact_age_table
from surrogate.simulate.precompile import precompile_in_background
from surrogate.simulate.support import TrainingHistogram
from surrogate.stages import budget
from surrogate.stages.artefacts import (
    DIAGNOSTIC_FIGURE,
    FIT_METRICS,
    GRID,
    HISTORY_FIGURE,
    METRICS,
    PSI,
    SURFACES_FIGURE,
    TRANSITIONS,
)
from surrogate.stages.choice import settle
from surrogate.stages.occupancy import occupancy
from surrogate.stages.settings import CollectSettings, TrainSettings

log = logging.getLogger(__name__)

LABELS = ("phi", "phi_next")


def validate(cfg: Mapping[str, Any]) -> TrainSettings:
    """All checks of a train config and its estimated cost (the collection and diagnostic it
    needs), before any work starts; the typed settings."""
    settings = TrainSettings.from_config(cfg)
    settings.kind.check_train(settings)
    budget.check(cfg, budget.train_work(settings), "train")
    return settings


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Run (or reuse) the train stage of ``cfg``; return its artefact directory. With
    ``gp=auto`` (measuring) the choice of the kind is made first where it is not stored
    (:func:`~surrogate.stages.choice.settle`)."""
    return train(settle(validate, cfg, fit_candidate), config=to_dict(cfg), force=force)


def fit_candidate(settings: TrainSettings) -> Path:
    """The fit of a measured choice's candidate (made or reused): its transitions loaded and
    checked, then :func:`fit`."""
    table, source = load_transitions(settings)
    return fit(settings, table, source)


def train(
    settings: TrainSettings,
    config: Mapping[str, Any] | None = None,
    force: bool = False,
) -> Path:
    """Run (or reuse) the train stage described by ``settings``: the fit (:func:`fit`, reused
    whatever the diagnostic and grid settings), then this directory's copy of it, its
    diagnostic, grid and figures. The model's kernel (for the diagnostic's occupancy run) is
    compiled in a background process during the fit when it is not cached."""
    out = settings.directory
    if settings.measured_choice() is not None:
        log.info("gp=auto: %s, the measured choice (%s)", settings.auto_recipe,
                 settings.measured_choice())  # fmt: skip
    elif settings.auto_recipe is not None:
        log.info("gp=auto: %s (model %r %s); gp=svgp or gp=classes to choose", {
            "classes": "the K-lumps chain, gp=classes' recipe",
            "svgp": "the two-state chain, gp=svgp's recipe"}[settings.auto_recipe],
            settings.setup.model.name, "declares classes finer than phi"
            if settings.kind.classes else "declares no classes, or a clock is asked")  # fmt: skip

    def make(data: tuple[pd.DataFrame, str]) -> None:  # data: load_transitions' (table, source)
        _train(settings, out, *data, config, force)

    return make_once(out, settings.identity(), settings.command(), make,
                     what="abstraction", force=force,
                     prepare=lambda: load_transitions(settings))  # fmt: skip


def fit(
    settings: TrainSettings,
    table: pd.DataFrame,
    source: str,
    config: Mapping[str, Any] | None = None,
    force: bool = False,
) -> Path:
    """Run (or reuse) the fit of ``settings`` on ``table`` (from ``source``): both classifiers,
    their held-out scores and training history, in ``settings.fit_directory``."""
    out = settings.fit_directory
    return make_once(out, settings.fit_identity(), settings.command(),
                     lambda _: _fit(settings, out, table, source, config), what="fit",
                     force=force)  # fmt: skip


def shared_psi_settings(settings: TrainSettings) -> TrainSettings | None:
    """The two-state chain's train settings whose fit is ``settings``' psi, where its kind
    shares the two-state psi (:attr:`~surrogate.kinds.base.ChainKind.shares_psi`): the same
    collection, GP settings and inputs, without the kind's own keys; None for a kind that fits
    its own. Their fit directory is the one ``gp=svgp`` with the same settings makes and reuses.
    """
    if not settings.kind.shares_psi:
        return None
    gp_config = {k: v for k, v in settings.gp_config.items() if k not in settings.kind.gp_keys}
    gp_config["lumps"], gp_config["history"] = TWO_STATE.lumps, TWO_STATE.history
    return dataclasses.replace(settings, kind=TWO_STATE, gp_config=gp_config, auto_recipe=None,
                               choice_directory=None)  # fmt: skip


def load_transitions(settings: TrainSettings) -> tuple[pd.DataFrame, str]:
    """The transitions this abstraction trains on, checked: (table, where it came from)."""
    source = settings.source
    if isinstance(source, CollectSettings):
        directory = source.directory
        manifest = require_artefact(directory, source.identity(), source.command(),
                                    "collected transitions")  # fmt: skip
        table = read_parquet(directory / TRANSITIONS, made_by=source.command())
        if len(table) != manifest.get("n_rows", len(table)):
            raise ArtefactError(
                f"{directory / TRANSITIONS} has {len(table)} rows but its manifest says "
                f"{manifest['n_rows']}; re-create it with `{source.command()}`"
            )
        where = str(directory)
        table = _settled(settings, table, manifest.get("after_jump"), where)
    else:
        path = source.path
        try:
            table = pd.read_csv(path) if path.suffix.lower() == ".csv" else read_parquet(path)
        except (OSError, ValueError) as exc:
            raise ArtefactError(f"cannot read the transitions table {path}: {exc}") from exc
        where = str(path)
        table = _settled(settings, table, None, where)
    left_out = table.attrs.get("jump_rows")  # kept through the steps below, for the manifest
    count = class_count_of(settings.setup.model.internal)
    if count is not None:  # the classes of these settings' bins, from the rows' count
        table = reclassify(table, count)
    table = settings.kind.training_rows(table, settings.max_age, where, source)
    label = settings.label_column(table.columns)
    settings.check_label_column(label, where)
    needed = list(dict.fromkeys([*settings.inputs, *LABELS, label]))
    missing = [c for c in needed if c not in table.columns]
    if missing:
        raise ArtefactError(
            f"{where} lacks column(s) {missing}: the abstraction needs its inputs "
            f"{list(settings.inputs)} and {needed[len(settings.inputs):]} (it has "
            f"{list(table.columns)})"
            + (" (collect it with collect.expected_labels=true, or train with "
               "gp.labels=outcome)" if label in missing else "")
        )  # fmt: skip
    values = table[list(settings.inputs)].to_numpy(dtype=np.float64)
    if not np.isfinite(values).all():
        raise NumericalError(f"{where} contains NaN or infinite values in {list(settings.inputs)}")
    labels = table[list(LABELS)].to_numpy()
    if not np.isin(labels, (0, 1)).all():
        raise ArtefactError(f"{where}: phi and phi_next must be 0 or 1")
    if label not in LABELS:
        p = table[label].to_numpy(dtype=np.float64)
        if not (np.isfinite(p).all() and (p >= 0).all() and (p <= 1).all()):
            raise ArtefactError(f"{where}: {label} must be probabilities in [0, 1]")
    windows = row_windows(table)
    if windows is not None:
        if not (np.isfinite(windows).all() and (windows > 0).all()):
            raise ArtefactError(f"{where}: {WINDOWS} (the windows each row stands for) must be "
                                f"positive numbers")  # fmt: skip
        if label not in LABELS:
            raise ConfigError(
                f"{where} keeps every switch (collect.keep_switches=true: its rows stand for "
                f"{WINDOWS} each), which the outcomes' fit weights; {label} is the window's "
                f"law given its state, which does not need the switches kept: train with "
                f"gp.labels=outcome, or collect with collect.keep_switches=false"
            )
    if left_out is not None:
        table.attrs["jump_rows"] = left_out
    return table, where


#: the collections whose left-out rows this process has logged
_SAID: set[tuple[str, str, float]] = set()


def _settled(
    settings: TrainSettings, table: pd.DataFrame, lag: Mapping[str, Any] | None, where: str
) -> pd.DataFrame:
    """``table`` without the rows soon after a jump where ``gp.jump_rows`` leaves them out
    (auto: where collect measured them lagging, its manifest's ``after_jump`` ``lag``,
    :func:`~surrogate.diagnosis.jumps.lagging_window`; drop: whatever was measured), each
    origin keeping at least :data:`~surrogate.diagnosis.jumps.MIN_SETTLED_ROWS` rows (else all
    are kept, with a warning). What was left out is recorded in ``table.attrs["jump_rows"]``
    for the fit's manifest."""
    mode = settings.jump_rows
    window = SETTLED_AFTER if mode == "drop" else lagging_window(lag) if mode == "auto" else None
    if window is None:
        return table
    if "since_jump" not in table.columns:
        if mode == "drop":
            raise ArtefactError(f"{where} has no `since_jump` column, so gp.jump_rows=drop cannot "
                                f"tell the rows soon after a jump; use gp.jump_rows=keep")  # fmt: skip
        return table
    keep = settled_rows(table["since_jump"].to_numpy(), settings.setup.dt, window)
    phi = table["phi"].to_numpy()
    kept = {int(p): int((keep & (phi == p)).sum()) for p in (0, 1)}
    lumps = settings.setup.model.internal.lump_names
    record: dict[str, Any] = {"mode": mode, "window_s": window, "rows": len(table),
                              "kept": int(keep.sum())}  # fmt: skip
    if min(kept.values()) < MIN_SETTLED_ROWS:
        log.warning("train: gp.jump_rows=%s would keep %s rows more than %g s after a jump, "
                    "under %d for an origin: training on every row (collect with "
                    "collect.blackout_time=%g to record settled rows only)", mode,
                    {lumps[p]: n for p, n in kept.items()}, window, MIN_SETTLED_ROWS,
                    window)  # fmt: skip
        out = table
        record["kept"] = len(table)
    else:
        why = (
            "collect measured them lagging (its warning, the manifest's after_jump)"
            if mode == "auto"
            else "gp.jump_rows=drop"
        )
        said = (where, mode, window)
        if said not in _SAID:  # once per collection: each candidate of a choice loads it
            _SAID.add(said)
            log.info("train: %d of %d rows kept, those %g s or more after a jump (or before "
                     "the first): the rows sooner after one left out, as %s; gp.jump_rows=keep "
                     "trains on every row", record["kept"], len(table), window, why)  # fmt: skip
        out = table.loc[keep].reset_index(drop=True)
    out.attrs["jump_rows"] = record
    return out


def _fit(
    settings: TrainSettings,
    out: Path,
    table: pd.DataFrame,
    source: str,
    config: Mapping[str, Any] | None,
) -> None:
    """Fit both classifiers on ``settings.fit_threads`` threads, score them, then write the
    classifiers, their metrics, the history figure and (last) the manifest."""
    job, model = settings.job, settings.setup.model
    lumps = model.internal.lump_names
    shared = shared_psi_settings(settings)
    # the two-state fit made (or reused) where gp=svgp finds it: psi fitted once for both
    psi_dir = fit(shared, table, source) if shared is not None else None
    seed_everything(settings.seed)
    t0 = time.perf_counter()
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(settings.fit_threads)
        if psi_dir is None:
            psi = fit_psi(table, settings.inputs, settings.gp, progress=job.progress,
                          device=job.device, lump_names=lumps,
                          label=settings.label_column(table.columns),
                          warps=settings.input_warps(),
                          processes=threads // settings.fit_threads)  # fmt: skip
        else:
            psi, _ = load_psi(psi_dir / PSI, device=job.device)
            log.info("psi: the two-state fit's, %s", psi_dir)
        chain = settings.kind.fit_given_psi(settings, table, psi)  # the kind's own, if any
    except NumericalError as exc:
        # nothing was written: a previous complete fit in `out` (if any) is kept
        err = NumericalError(f"{exc} Nothing was written to {out}.")
        err.partial = getattr(exc, "partial", None)  # type: ignore[attr-defined]
        raise err from exc
    finally:
        torch.set_num_threads(threads)
    wall = time.perf_counter() - t0
    psi.to("cpu")
    grid = psi_grid_frame(psi, psi.domain, psi.input_names)
    if not np.isfinite(grid["p"].to_numpy()).all():
        # a model that predicts NaN must not reach the simulations (NaN < u is always False)
        raise NumericalError(
            f"the trained classifiers predict NaN/inf on their own input domain; nothing was "
            f"written to {out}. Try a smaller gp.lr (now {settings.gp.lr}) or more gp.epochs"
        )
    if psi_dir is None:
        metrics: dict[str, Any] = {
            f"psi_{phi}": {
                "origin": lumps[phi],
                "validation": clf.validation,
                "n_train": clf.n_train,
                "n_val": clf.n_val,
                "train_seconds": clf.train_seconds,
                "final_loss": clf.history[-1] if clf.history else None,
                "last_tenth_drop": last_tenth_drop(clf.history),
                "own_rows": clf.own_rows,
            }
            for phi, clf in enumerate(psi.classifiers)
        }
        log_own_rows(metrics, psi.input_names, settings.input_warps())
        for name, m in metrics.items():
            if m["last_tenth_drop"] is not None:
                log.info("%s: loss per point fell %.2g over the last tenth of its steps (the "
                         "training history figure's right panel shows whether it flattened)",
                         name, m["last_tenth_drop"])  # fmt: skip
    else:  # the classifiers' scores as their fit wrote them
        fitted = read_json(psi_dir / FIT_METRICS, made_by=settings.command())
        metrics = {"psi_0": fitted["psi_0"], "psi_1": fitted["psi_1"], "psi_fit": str(psi_dir)}
    metrics["train_seconds_total"] = wall
    metrics["inputs"] = list(settings.inputs)
    # from here the directory reads as incomplete until the new manifest is written last
    (out / MANIFEST).unlink(missing_ok=True)
    save_psi(out / PSI, psi, {"settings": settings.fit_identity(), "source": source})
    metrics.update(settings.kind.write(out, chain, settings.fit_identity()))
    write_json(out / FIT_METRICS, metrics)
    if psi_dir is None:
        save_figure(out / HISTORY_FIGURE, plot_training_history(
            {f"psi_{p} ({lumps[p]})": c.history for p, c in enumerate(psi.classifiers)}))  # fmt: skip
    else:
        write_atomic(out / HISTORY_FIGURE, partial(shutil.copyfile, psi_dir / HISTORY_FIGURE))
    write_manifest(
        out,
        stage="fit",
        config=dict(config) if config is not None else settings.fit_identity(),
        seed=settings.seed,
        settings=settings.fit_identity(),
        source=source,
        device=str(job.device),
        wall_time_s=wall,
        fit_threads=settings.fit_threads,  # the fit's result depends on it (float reductions)
        label_column=settings.label_column(table.columns),
        inputs=list(settings.inputs),
        domain={k: list(v) for k, v in psi.domain.items()},
        # diagnostic, not part of the fit's identity: where the training rows are sparse
        support_histogram=support_histogram(table, settings.inputs),
        # the rows soon after a jump left out (gp.jump_rows), where any were
        **({"jump_rows": table.attrs["jump_rows"]} if "jump_rows" in table.attrs else {}),
        **class_support(table, settings),
    )
    for name in ("psi_0", "psi_1"):
        v = metrics[name]["validation"]
        log.info(
            "%s (from %s): held-out Brier %.4f (constant predictor %.4f), log predictive %.4f",
            name, metrics[name]["origin"], v["brier"], v["brier_baseline"], v["mean_log_predictive"],
        )  # fmt: skip
    log.info("trained both classifiers in %.1f s on %d thread(s); fit in %s", wall,
             settings.fit_threads, out)  # fmt: skip


def log_own_rows(
    metrics: Mapping[str, Any], input_names: Sequence[str], warps: Mapping[str, float] | None
) -> None:
    """Each classifier against its own training rows, one log line each; a warning where a
    group of them is off (:mod:`surrogate.gp.own_rows`): the fit stopped short of its rows."""
    for name in ("psi_0", "psi_1"):
        check = metrics[name].get("own_rows")
        if not check:
            continue
        line = describe(check, input_names, warps)
        if check["off"]:
            log.warning("%s (from %s) is off its own rows: %s, past %.0f %% and %.1f SE: the "
                        "fit stopped short of them or smooths over them (the training history "
                        "figure shows whether its loss flattened; docs/performance.md, \"A fit "
                        "against its own rows\")", name, metrics[name]["origin"], line,
                        100 * check["tolerance"], check["critical_z"])  # fmt: skip
        else:
            log.info("%s (from %s) against its own rows: %s", name, metrics[name]["origin"],
                     line)  # fmt: skip


def support_histogram(table: pd.DataFrame, inputs: Sequence[str]) -> dict[str, Any] | None:
    """The training rows' histogram over the abstraction's inputs (the switch clock, capped
    by construction, excepted), per state
    (:class:`~surrogate.simulate.support.TrainingHistogram`), for the fit's manifest: the
    simulator's support monitor counts the cell-steps in its sparse bins. None where no input
    is left."""
    names = [n for n in inputs if n != AGE]
    if not names:
        return None
    phi = table["phi"].to_numpy(dtype=np.int64)
    switched = phi != table["phi_next"].to_numpy(dtype=np.int64)
    values = table[names].to_numpy(dtype=np.float64)
    return TrainingHistogram.of_rows(values, phi, switched, names,
                                     windows=row_windows(table)).as_dict()  # fmt: skip


def class_support(table: pd.DataFrame, settings: TrainSettings) -> dict[str, Any]:
    """A K-lumps fit's ``support_class_histogram`` (:func:`support_class_histogram` over the
    model's classes), for its manifest beside the per-state one; nothing for any other chain
    (its manifest keeps the keys it had)."""
    classes = lump_classes_of(settings.setup.model.internal) if settings.kind.classes else None
    hist = None if classes is None else support_class_histogram(table, settings.inputs,
                                                                  classes.names)  # fmt: skip
    return {} if hist is None else {"support_class_histogram": hist}


def support_class_histogram(
    table: pd.DataFrame, inputs: Sequence[str], classes: Sequence[str]
) -> dict[str, Any] | None:
    """The training rows' histogram over the abstraction's inputs per K-lumps class, the
    class each row's window starts in (collect's ``phi_class``, the origin whose law the
    K-lumps fit learns from it), with each class's share of rows that leave it
    (``phi_class_next`` differs: the rows a bin needs follow from it,
    :meth:`~surrogate.simulate.support.TrainingHistogram.of_rows`). The same bins as
    :func:`support_histogram`'s (the same rows); the simulator checks each cell of a K-lumps
    chain against its own class's rows. None where no input is left or the table has no
    class columns."""
    names = [n for n in inputs if n != AGE]
    if not names or CLASS not in table.columns or CLASS_NEXT not in table.columns:
        return None
    origin = table[CLASS].to_numpy(dtype=np.int64)
    moved = origin != table[CLASS_NEXT].to_numpy(dtype=np.int64)
    values = table[names].to_numpy(dtype=np.float64)
    return TrainingHistogram.of_rows(values, origin, moved, names, classes,
                                     windows=row_windows(table)).as_dict()  # fmt: skip


def _train(
    settings: TrainSettings,
    out: Path,
    table: pd.DataFrame,
    source: str,
    config: Mapping[str, Any] | None,
    force: bool = False,
) -> None:
    """The fit (made or reused), then its diagnostic, grid and figures; the fit's files are
    copied in, the manifest written last."""
    job, model = settings.job, settings.setup.model
    lumps = model.internal.lump_names
    precompile_in_background(model, job.device)  # the diagnostic's kernel, during the fit
    fit_dir = fit(settings, table, source, config, force)
    psi, _ = load_psi(fit_dir / PSI)
    fit_manifest = read_manifest(fit_dir, made_by=settings.command())
    metrics: dict[str, Any] = read_json(fit_dir / FIT_METRICS, made_by=settings.command())
    grid = psi_grid_frame(psi, psi.domain, psi.input_names, settings.grid_size)
    if not np.isfinite(grid["p"].to_numpy()).all():
        raise NumericalError(f"the classifiers of {fit_dir} predict NaN/inf on the grid "
                             f"gp.grid_size={settings.grid_size}; nothing was written to {out}")  # fmt: skip
    exact_fn = exact_psi_function(model, settings.setup.dt)  # the reference of both below
    diagnostic, frame = diagnose(psi, settings, model, exact_fn)
    diagnosed = grown_diagnostic(diagnostic, settings)  # the cells that judge it, or None
    if diagnosed is not None:
        grown_from = int(settings.diagnostic["n_cells"])
        diagnostic, frame = diagnose(psi, diagnosed, model, exact_fn)
        diagnostic["grown_from"] = grown_from
    diagnosed = diagnosed or settings
    metrics["diagnostic"] = diagnostic
    chain = settings.kind.load(fit_dir)
    if isinstance(chain, ClassTable):  # a chain over classes: scored class by class
        metrics["class_diagnostic"] = diagnose_classes(chain, diagnosed, model)
        metrics["class_shares"] = class_share_drift(chain, diagnosed, model)
    # from here the directory reads as incomplete until the new manifest is written last
    (out / MANIFEST).unlink(missing_ok=True)
    own = (PSI, HISTORY_FIGURE, *settings.kind.files)
    for name in own:  # the fit's own files, for whoever reads this directory
        write_atomic(out / name, partial(shutil.copyfile, fit_dir / name))
    write_json(out / METRICS, metrics)
    write_csv(out / GRID, grid)
    exact = _exact_curve(model, settings, exact_fn) if len(psi.input_names) == 1 else None
    save_figure(out / SURFACES_FIGURE, plot_psi(psi, psi.domain, psi.input_names, table, lumps,
                                                exact=exact))  # fmt: skip
    if frame is not None:
        save_figure(out / DIAGNOSTIC_FIGURE, plot_psi_errors(frame, psi.input_names, lumps))
    write_manifest(
        out,
        stage="train",
        config=dict(config) if config is not None else settings.identity(),
        seed=settings.seed,
        settings=settings.identity(),
        source=source,
        fit=str(fit_dir),
        device=str(job.device),
        wall_time_s=metrics["train_seconds_total"],
        fit_threads=fit_manifest["fit_threads"],
        label_column=fit_manifest["label_column"],
        inputs=list(settings.inputs),
        domain=fit_manifest["domain"],
        support_histogram=fit_manifest.get("support_histogram"),  # None: an older fit
        **{k: fit_manifest[k] for k in ("support_class_histogram",) if k in fit_manifest},
        brier={n: metrics[n]["validation"]["brier"] for n in ("psi_0", "psi_1")},
        brier_baseline={n: metrics[n]["validation"]["brier_baseline"] for n in ("psi_0", "psi_1")},
        diagnostic=diagnostic,
    )
    for p in (0, 1):
        d = diagnostic.get(f"phi{p}")
        if d:
            log.info(
                "leaving %s where the population lives: switching probability %.4f vs %s %.4f "
                "(bias %+.1f %%, mean |error| %.1f %%)", lumps[p], d["mean_switching_learned"],
                diagnostic["reference"], d["mean_switching_reference"], 100 * d["rel_bias"],
                100 * d["mean_abs_rel_error"],
            )  # fmt: skip
    for name, d in metrics.get("class_diagnostic", {}).items():
        if isinstance(d, dict):
            log.info(
                "K lumps, leaving %s (%.0f %% of the population) where it lives: %.4f vs %s "
                "%.4f (bias %s)", name, 100 * d["share"], d["mean_switching_learned"],
                metrics["class_diagnostic"]["reference"], d["mean_switching_reference"],
                percent(d["rel_bias"]),
            )  # fmt: skip
    shares = metrics.get("class_shares") or {}
    if shares.get("p_value") is not None:
        log.info("K lumps, class shares after %g s: the chain's against the full model's, total "
                 "variation %.3f, chi-square p = %.2g%s", shares["t"], shares["total_variation"],
                 shares["p_value"], " (they drift)" if shares["drift"] else "")  # fmt: skip
    log.info("abstraction of %s: diagnostic and grid in %s", fit_dir, out)


#: the longest a grown diagnostic may take, forecast from the first run's time (the stages'
#: warning threshold: a run past it is the user's to start, as the verdict advises)
GROW_MAX_SECONDS = budget.WARN_SECONDS


def grown_diagnostic(
    diagnostic: Mapping[str, Any], settings: TrainSettings
) -> TrainSettings | None:
    """``settings`` with the diagnostic cells that judge psi's bias, where its empirical
    reference could not: a lump's relative error on the bias above
    :data:`~surrogate.diagnosis.remedies.DURATION_TOLERANCE` (the verdict's "reference too
    noisy to judge") gets the cells that bring it under
    (:func:`~surrogate.diagnosis.remedies.diagnostic_cells_needed`, what the verdict would
    advise as ``gp.diagnostic.n_cells``), up to ``gp.diagnostic.max_cells``; None where the
    reference judges (or is exact), the ceiling leaves no more cells, or the larger run would
    take more than :data:`GROW_MAX_SECONDS` at the first one's pace. The occupancy run is
    made again at that size (the same run ``gp.diagnostic.n_cells`` would make): a run of the
    model the user would otherwise start after reading the verdict (Vilar's oscillator: 1,000
    cells, +- 4.6 %, a second 6.6-minute reproduce run at 4,300; docs/choice.md)."""
    d = settings.diagnostic
    cells, ceiling = int(d["n_cells"]), int(d.get("max_cells") or 0)
    if diagnostic.get("reference") != "empirical":
        return None
    errors = {p: s.get("rel_bias_se") for p in (0, 1)
              if isinstance(s := diagnostic.get(f"phi{p}"), Mapping)}  # fmt: skip
    noisy = {p: float(e) for p, e in errors.items()
             if isinstance(e, int | float) and math.isfinite(e) and e > DURATION_TOLERANCE}  # fmt: skip
    if not noisy:
        return None
    lumps = settings.setup.model.internal.lump_names
    what = ", ".join(f"leaving {lumps[p]} +- {100 * e:.1f} %" for p, e in noisy.items())
    head = (f"the diagnostic's reference at {cells} cells cannot judge psi's bias ({what}, "
            f"against {100 * DURATION_TOLERANCE:.0f} %)")  # fmt: skip
    needed = min(diagnostic_cells_needed(cells, max(noisy.values()), DURATION_TOLERANCE), ceiling)
    if needed <= cells:
        log.warning("%s; gp.diagnostic.max_cells=%d leaves no more cells", head, ceiling)
        return None
    wall = read_manifest(settings.occupancy().directory).get("wall_time_s")
    made = float(wall) if isinstance(wall, int | float) else None
    forecast = made * needed / cells if made is not None else None
    if made is not None and forecast is not None and forecast > GROW_MAX_SECONDS:
        log.warning("%s; %d cells would take ~%s at the %s its cells took (more than %s): not "
                    "made here (gp.diagnostic.n_cells=%d makes it)", head, needed,
                    duration(forecast), duration(made), duration(GROW_MAX_SECONDS), needed)  # fmt: skip
        return None
    took = (f", ~{duration(forecast)} at the {duration(made)} its {cells} cells took"
            if made is not None and forecast is not None else "")  # fmt: skip
    log.info("%s: made again at %d cells (gp.diagnostic.max_cells=%d)%s", head, needed, ceiling,
             took)  # fmt: skip
    return dataclasses.replace(settings, diagnostic={**d, "n_cells": needed})


def percent(fraction: float | None) -> str:
    """A relative error as ``+1.2 %`` (``-`` where there is none)."""
    return "-" if fraction is None else f"{100 * fraction:+.1f} %"


#: signal nodes of the exact class law the class diagnostic scores against
EXACT_CLASS_NODES = 4096


def class_diagnostic_by_lump(classes: Mapping[str, Any], internal: Any) -> dict[str, Any]:
    """The K-lumps chain's class diagnostic as per-lump scores: the share-weighted chance of
    leaving each lump, learned against the reference (the standard error, where the reference
    is empirical, from the classes' binomial errors)."""
    declared = lump_classes_of(internal)
    out: dict[str, Any] = {"reference": classes.get("reference")}
    if declared is None:
        return out
    for p in (0, 1):
        rows = [classes[n] for n, lump in zip(declared.names, declared.lumps, strict=True)
                if lump == p and isinstance(classes.get(n), dict)]  # fmt: skip
        w = sum(r["share"] for r in rows)
        if not rows or w <= 0:
            continue
        learned = sum(r["share"] * r["mean_switching_learned"] for r in rows) / w
        ref = sum(r["share"] * r["mean_switching_reference"] for r in rows) / w
        if ref <= 0:
            continue
        scores: dict[str, Any] = {"rel_bias": learned / ref - 1}
        if all(r.get("rel_se") is not None for r in rows):  # empirical reference
            var = sum((r["share"] * r["mean_switching_reference"] * r["rel_se"]) ** 2
                      for r in rows) / (w * ref) ** 2  # fmt: skip
            scores["rel_bias_se"] = (1 + scores["rel_bias"]) * var**0.5
        out[f"phi{p}"] = scores
    return out


def diagnose_classes(chain: ClassTable, settings: TrainSettings, model: Model) -> dict[str, Any]:
    """The K-lumps chain's law where an unperturbed full-model population lives (the occupancy
    run of :func:`diagnose`): per origin class, the chance of leaving its lump, learned against
    the model's exact class law of adapted cells where it has one (else the run's observed
    switches; :func:`~surrogate.gp.diagnostics.class_law_errors`)."""
    rows = occupancy(settings.occupancy())
    internal = model.internal
    if CLASS not in rows.columns:  # an occupancy run made before the model declared classes
        return {"reference": None, "note": f"the occupancy run has no {CLASS} column"}
    exact = None
    if (exact_class_step_of(internal) is not None and signal_bounds_of(internal)
            and len(internal.signal_names) == 1):  # fmt: skip
        # the exact law tabulated, as the fidelity stage's reference row reads it (per row:
        # one matrix exponential each, ~50x slower for the same figures to 1e-6)
        table = exact_class_table(internal, settings.setup.dt, EXACT_CLASS_NODES)
        names = list(internal.signal_names)

        def exact(part: pd.DataFrame) -> np.ndarray:
            z = torch.from_numpy(part[names].to_numpy(np.float32, copy=True))
            origin = torch.from_numpy(part[CLASS].to_numpy(np.int64))
            return table.law(origin, z).double().numpy()

    return class_law_errors(chain.law, rows, list(settings.inputs), chain.class_names,
                            chain.class_lumps, exact)  # fmt: skip


#: the chain's share run's seed is the fit's plus this (not the occupancy run's cells)
SHARES_SEED_OFFSET = 2_000_003
#: class shares drift where the chi-square test of the chain's against the full model's rejects
#: at this level (one test per fit)
SHARES_ALPHA = 1e-3


def class_share_drift(chain: ClassTable, settings: TrainSettings, model: Model) -> dict[str, Any]:
    """Whether the K-lumps chain keeps the full model's class shares: the chain run as the
    diagnostic's occupancy run was (its cells, start, equilibration and duration, in the
    training field), its classes at the end against the full model's at its last record, by a
    chi-square test of homogeneity (cells are independent; classes neither population holds
    dropped). A chain whose every class switches right where cells live can still drift into
    other classes when its moves between classes are wrong (docs/fidelity.md: the
    auto-regulatory network's bins)."""
    rows = occupancy(settings.occupancy())
    names = chain.class_names
    if CLASS not in rows.columns:
        return {"p_value": None, "note": f"the occupancy run has no {CLASS} column"}
    last = rows[rows["t"] == rows["t"].max()]
    full = np.bincount(last[CLASS].to_numpy(np.int64), minlength=len(names))
    d = settings.diagnostic
    seed_everything(settings.seed + SHARES_SEED_OFFSET)
    device = settings.job.device
    layer = ClassDecision(chain.to(device), model.internal,
                          model.featurizer(chain.input_names), "abstract")  # fmt: skip
    simulator = Simulator(model, layer, settings.setup.field, settings.setup.dt, device,
                          backend="torch")  # fmt: skip
    state = simulator.initial_state(int(d["n_cells"]), torch.tensor(d["start"]),
                                    float(d["equilibration_time"]))  # fmt: skip
    simulator.advance(state, max(1, round(float(last["t"].iloc[0]) / settings.setup.dt)))
    ours = np.bincount(layer.cls.cpu().numpy(), minlength=len(names))
    chain.to("cpu")
    return share_test(full, ours, float(last["t"].iloc[0]), names)


def share_test(
    full: np.ndarray, chain: np.ndarray, t: float, names: Sequence[str]
) -> dict[str, Any]:
    """Chi-square test of homogeneity of two populations' class counts ``(C,)`` each."""
    from scipy import stats  # ~1.7 s to import: only where used

    keep = (full + chain) > 0
    p_full, p_chain = full / max(full.sum(), 1), chain / max(chain.sum(), 1)
    out: dict[str, Any] = {
        "t": t, "n_full": int(full.sum()), "n_chain": int(chain.sum()),
        "full": {n: float(v) for n, v in zip(names, p_full, strict=True)},
        "chain": {n: float(v) for n, v in zip(names, p_chain, strict=True)},
        "total_variation": float(0.5 * np.abs(p_full - p_chain).sum()),
    }  # fmt: skip
    if keep.sum() < 2:
        return {**out, "chi2": 0.0, "p_value": 1.0, "drift": False}
    test = stats.chi2_contingency(np.stack([full[keep], chain[keep]]))
    return {**out, "chi2": float(test.statistic), "p_value": float(test.pvalue),
            "drift": bool(test.pvalue < SHARES_ALPHA)}  # fmt: skip


def exact_psi_function(model: Model, dt: float) -> Any:
    """The model's exact lumped psi as ``psi(phi, signal)``: tabulated over the signal's bounds
    when the model declares them (1e-5-accurate and fast), else computed directly; None when
    the model has no exact psi."""
    internal = model.internal
    if not has_exact_psi(internal):
        return None
    exact = ExactPsi(internal, dt)
    bounds = signal_bounds_of(internal)
    try:
        if bounds:
            ranges = [bounds[n] for n in internal.signal_names]
            return PsiLookupTable.from_function(exact, ranges, internal.signal_names)
        exact(torch.zeros(1, dtype=torch.long), torch.zeros(1, len(internal.signal_names)))
    except NotImplementedError:
        return None
    return exact


def diagnose(
    psi: PsiClassifier, settings: TrainSettings, model: Model, exact_fn: Any = None
) -> tuple[dict[str, Any], pd.DataFrame | None]:
    """The learned psi's switching probabilities against the exact psi (or the full model's
    binned frequencies) where an unperturbed full-model population lives (``gp.diagnostic``:
    its start, size and length), on the field the data was collected in. ``exact_fn``: the
    model's :func:`exact_psi_function` (None: the empirical reference). The learned psi is
    scored as the simulations use it (:func:`_as_simulated`)."""
    t0 = time.perf_counter()
    rows = occupancy(settings.occupancy())
    reference = None
    if settings.kind.clock:
        rows = clock_rows(rows, settings.max_age)
        # the exact psi with a clock where the model has one, else the empirical reference
        exact_fn = None
        if can_age(model.internal):
            table = exact_age_table(model.internal, settings.setup.dt, settings.max_age)
            names = [*model.internal.signal_names, AGE]

            def reference(rows: pd.DataFrame) -> np.ndarray:
                s = torch.from_numpy(rows[names].to_numpy(np.float32, copy=True))
                n = len(rows)
                return np.stack(
                    [table(torch.full((n,), p), s).double().numpy() for p in (0, 1)], -1
                )

    if exact_fn is not None:
        names = list(model.internal.signal_names)

        def reference(rows: pd.DataFrame) -> np.ndarray:
            s = torch.from_numpy(rows[names].to_numpy(np.float32, copy=True))
            n = len(rows)
            psi = rows_table(exact_fn, s, names)
            return np.stack([psi(torch.full((n,), p), s).double().numpy() for p in (0, 1)], -1)

    metrics, frame = psi_errors(_as_simulated(psi), rows, list(settings.inputs), reference)
    metrics["settings"] = dict(settings.diagnostic)
    metrics["seconds"] = time.perf_counter() - t0
    return metrics, frame


#: nodes per axis of the exact psi tabulated over the diagnostic's rows (by the signal's
#: dimension; beyond, each row is computed): a matrix exponential per node instead of per row
ROWS_TABLE_NODES = {1: 256, 2: 48}


def rows_table(exact_fn: Any, signal: Tensor, names: Sequence[str]) -> Any:
    """``exact_fn`` as a lookup table over the range of the ``n x k`` ``signal`` rows where it is
    no table yet and ``k`` is at most 2 (the exact psi of a model that declares no signal
    bounds: a 151-state network's 200,000 diagnostic rows would be 200,000 matrix
    exponentials), else ``exact_fn`` itself."""
    nodes = ROWS_TABLE_NODES.get(signal.shape[1])
    if isinstance(exact_fn, PsiLookupTable) or nodes is None or signal.shape[0] <= nodes:
        return exact_fn
    lo, hi = signal.min(0).values.double(), signal.max(0).values.double()
    pad = 1e-6 * (1.0 + hi.abs())  # a constant signal still spans a range
    ranges = [(float(a), float(b)) for a, b in zip(lo - pad, hi + pad, strict=True)]
    return PsiLookupTable.from_function(exact_fn, ranges, names, (nodes,) * signal.shape[1])


#: inputs up to which the diagnostic scores the learned psi through its lookup table
TABLE_MAX_INPUTS = 2


def _as_simulated(psi: PsiClassifier) -> PsiClassifier | PsiLookupTable:
    """The learned psi as the simulations use it by default: its lookup table over its domain
    (the classifier within ~1e-5 there; 200k occupied points in ~0.05 s instead of ~1 s of
    GP predictions), or the classifier itself beyond ``TABLE_MAX_INPUTS`` inputs."""
    if len(psi.input_names) > TABLE_MAX_INPUTS:
        return psi
    ranges = [psi.domain[n] for n in psi.input_names]
    return PsiLookupTable.from_function(psi, ranges, psi.input_names)


def _exact_curve(model: Model, settings: TrainSettings, exact_fn: Any) -> Any:
    """For a 1-D psi over the model's signal: z -> exact (n x 2), for the figure."""
    internal = model.internal
    if list(settings.inputs) != list(internal.signal_names):
        return None
    if exact_fn is None:
        return None

    def curve(z: np.ndarray) -> np.ndarray:
        s = torch.as_tensor(z, dtype=torch.float32)[:, None]
        return np.stack(
            [exact_fn(torch.full((len(z),), p), s).double().numpy() for p in (0, 1)], -1
        )

    return curve


def resolve_abstraction(settings: TrainSettings) -> Path:
    """The fit directory of ``settings`` (what simulations load), or a clear error naming the
    command that makes it."""
    directory = settings.fit_directory
    require_artefact(directory, settings.fit_identity(), settings.command(),
                     "trained abstraction", after=settings.input_command())  # fmt: skip
    return directory


def load_abstraction(
    source: str | os.PathLike | TrainSettings, device: str | torch.device = "cpu"
) -> PsiClassifier:
    """Load a trained abstraction from its train or fit directory, or from the train settings
    that made it (``load_abstraction(validate(cfg))`` for a config: settings are built once, at
    the caller's edge).

    Returns a :class:`~surrogate.gp.PsiClassifier`: ``psi(phi, z)`` gives p(phi' = 1 | phi, z)
    for ``z`` (``n x d``) in the order of ``psi.input_names``, under ``torch.no_grad()``.

    Raises:
        TypeError: for a raw config (a mapping): build its settings first.
    """
    if isinstance(source, TrainSettings):
        directory = resolve_abstraction(source)
    elif isinstance(source, Mapping):
        raise TypeError(
            "load_abstraction takes a directory or TrainSettings, not a config: "
            "load_abstraction(surrogate.stages.train.validate(cfg))"
        )
    else:
        directory = Path(source)
    psi, _ = load_psi(directory / PSI, device=device)
    return psi


def read_metrics(directory: str | Path) -> dict[str, Any]:
    """The ``train_metrics.json`` of a train directory."""
    return read_json(Path(directory) / METRICS, made_by="python scripts/train.py")


def read_grid(directory: str | Path) -> pd.DataFrame:
    """The ``psi_grid.csv`` of a train directory."""
    return read_csv(Path(directory) / GRID, made_by="python scripts/train.py")

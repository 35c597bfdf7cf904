"""The K-lumps chain's fit and artefact, which :class:`~surrogate.kinds.klumps.KLumps`
delegates to (moved from stages/train.py unchanged, which re-exports :func:`load_class_chain`):
the kinds sit below the stages, so a train settings object comes in as the members it reads
(:class:`~surrogate.kinds.base.FitSettings`, a Protocol the type checker holds it to)."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from torch import Tensor

from surrogate.config import seed_everything
from surrogate.errors import ArtefactError
from surrogate.gp.class_relaxation import RelaxationSpec, fit_relaxation_law
from surrogate.gp.classes import ClassFitOptions, fit_class_law
from surrogate.io import load_tensors
from surrogate.kinds.base import FitSettings
from surrogate.kinds.files import CLASS_CHAIN
from surrogate.models.capabilities import class_bins_of, expected_class_next_of, lump_classes_of
from surrogate.simulate.classes import ClassTable, expected_class_column
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import record_stationary_bins

log = logging.getLogger(__name__)


def _fit_class_chain(
    settings: FitSettings, table: pd.DataFrame, domain: Mapping[str, tuple[float, float]]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The K-lumps chain (gp.lumps=classes) of the train settings ``settings`` (:class:`~surrogate.kinds.base.FitSettings`:
    the kinds sit below the stages) over the two-state fit's domain: its table's state and its
    metrics."""
    model = settings.setup.model
    classes = lump_classes_of(model.internal)
    assert classes is not None  # the settings checked it
    expected = settings.gp_config.get("labels", "outcome") != "outcome"
    columns = [expected_class_column(b) for b in range(len(classes.names))]
    if (expected and expected_class_next_of(model.internal) is not None
            and settings.collected
            and not all(c in table.columns for c in columns)):  # fmt: skip
        raise ArtefactError(
            f"the transitions of {settings.input_command()} lack the expected class labels "
            f"{columns[0]}..: they were collected before the model gave them; delete "
            f"{settings.source.directory} and collect again, or train with gp.labels=outcome"
        )
    options = ClassFitOptions(progress=settings.job.progress, device=settings.job.device,
                              expected=expected, min_events=settings.min_events,
                              max_weight=settings.max_label_weight)  # fmt: skip
    law, metrics = fit_class_law(table, settings.inputs, len(classes.names), dict(domain),
                                 settings.gp, options)  # fmt: skip
    log.info("K-lumps chain over %d classes: %d classifiers, %d constant steps", len(classes.names),
             metrics["classifiers"], metrics["constant_steps"])  # fmt: skip
    if settings.kind.relaxation:
        law, metrics["relaxation"] = _relaxation_law(settings, law, domain)
    chain = ClassTable(law, [domain[n] for n in settings.inputs], settings.inputs, classes.names,
                       classes.lumps, settings.setup.dt)  # fmt: skip
    return chain.to_state(), metrics


#: the stationary sample's seed is the fit's plus this (its cells are not collect's first cells)
RELAXATION_SEED_OFFSET = 1_000_003


def _relaxation_law(
    settings: FitSettings, learned: Tensor, domain: Mapping[str, tuple[float, float]]
) -> tuple[Tensor, dict[str, Any]]:
    """The learned law with bins that relax (gp.class_moves=relaxation): a stationary sample
    of burned-in full-model cells where collect starts them, held at their inputs."""
    setup, job = settings.setup, settings.job
    model = setup.model
    declared = lump_classes_of(model.internal)
    bins = class_bins_of(model.internal)
    assert declared is not None and bins is not None  # the settings checked them
    seed_everything(settings.seed + RELAXATION_SEED_OFFSET)
    t0 = time.perf_counter()
    simulator = Simulator(model, FullDecision(model.internal), setup.field, setup.dt, job.device)
    perturbation = model.body.perturbation(setup.field, model.perturbation_options)
    log.info("class moves by relaxation: %d burned-in full-model cells held at their inputs "
             "for %g s", settings.relaxation_cells, settings.relaxation_lags[-1])  # fmt: skip
    sample = record_stationary_bins(simulator, perturbation, settings.relaxation_cells,
                                    settings.relaxation_lags, settings.inputs, bins)  # fmt: skip
    sizes = list(learned.shape[1:-1])
    spec = RelaxationSpec(sizes, bins, declared.lumps, settings.relaxation_lags, setup.dt)
    law, metrics = fit_relaxation_law(learned, sample, settings.inputs, domain, spec, settings.gp,
                                      progress=job.progress, device=job.device)  # fmt: skip
    metrics["seconds"] = time.perf_counter() - t0
    log.info("the count's relaxation time %.0f s (correlation %s at lags %s s); its bins kept "
             "per window with probability %.6f", metrics["relaxation_time"],
             ", ".join(f"{r:.3f}" for r in metrics["correlation"]),
             ", ".join(f"{v:g}" for v in settings.relaxation_lags),
             metrics["keep_bin_per_window"])  # fmt: skip
    return law, metrics


def load_class_chain(
    directory: str | os.PathLike, device: str | torch.device = "cpu"
) -> ClassTable:
    """The K-lumps chain's law of a fit or train directory (``gp.lumps=classes``)."""
    path = Path(directory) / CLASS_CHAIN
    obj = load_tensors(path, made_by="python scripts/train.py gp.lumps=classes")
    if not isinstance(obj, dict) or "class_chain" not in obj:
        raise ArtefactError(f"{path} is not a saved class chain (no 'class_chain' entry)")
    return ClassTable.from_state(obj["class_chain"]).to(device)

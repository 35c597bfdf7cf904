"""The measured choice of the chain kind (issue 52; opt-in: ``python scripts/choose.py``).

Fits the candidate kinds on one collection (the two-state chain, the switch clock at a few
``choose.max_ages``, K lumps where the model declares classes, and every registered kind that
declares itself a :attr:`~surrogate.kinds.base.ChainKind.candidate` with its recipe), records a
held-out full-model run at the training inputs (every step of ``choose.n_cells`` cells for
``choose.t_end`` s, another seed than the collection's), scores each kind on it
(:func:`~surrogate.kinds.scoring.score_kind`: log-likelihood per window of the observed phi
sequences, simulated durations' KS) and picks the best (:func:`~surrogate.kinds.scoring.choose`).
The chosen kind is then trained as ``scripts/train.py`` with its overrides would (where
simulate finds it with the same overrides); the score table goes into ``data/choice/...``
(``choice.json``, ``scores.csv``, the manifest) and beside the chosen train directory's files
(``choice.json``), and the log says why.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import torch

from surrogate.config import group_config, seed_everything, to_dict
from surrogate.errors import ConfigError
from surrogate.io import artefact_dir, write_csv, write_json, write_manifest
from surrogate.kinds.base import CHAIN_KINDS, LayerRequest
from surrogate.kinds.scoring import Choice, KindScore, choose, score_kind
from surrogate.models.capabilities import lump_classes_of
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.sequences import phi_sequences
from surrogate.simulate.transitions import record_occupancy
from surrogate.stages import train as train_stage
from surrogate.stages.collect import collect
from surrogate.stages.settings import CollectSettings, TrainSettings
from surrogate.validation import known_keys

log = logging.getLogger(__name__)

#: the held-out run's seed is the job's plus this (its cells are not the collection's)
HELDOUT_SEED_OFFSET = 7_919
CHOICE = "choice.json"
SCORES = "scores.csv"
OPTIONS = ("max_ages", "n_cells", "t_end", "equilibration_time", "tie_se")


@dataclass(frozen=True)
class ChoiceSettings:
    """``choose.*`` validated: the clock's caps, the held-out run and the tie rule."""

    max_ages: tuple[float, ...]
    n_cells: int
    t_end: float
    equilibration_time: float
    tie_se: float

    @classmethod
    def from_config(cls, options: Mapping[str, Any]) -> ChoiceSettings:
        """The ``choose`` group checked, each bad value refused with its key."""
        options = known_keys(options, OPTIONS, "choose")
        ages = options.get("max_ages", (1.0, 2.0, 5.0))
        if (isinstance(ages, str) or not isinstance(ages, Sequence)
                or any(isinstance(a, bool) or not isinstance(a, int | float) or not a > 0
                       or not math.isfinite(a) for a in ages)):  # fmt: skip
            raise ConfigError(f"choose.max_ages must be a list of seconds > 0, got {ages!r}")
        caps = [float(a) for a in ages]
        if len(set(caps)) != len(caps):
            # one candidate per cap: a repeat would be fitted once and listed once, silently
            unique = list(dict.fromkeys(caps))
            raise ConfigError(f"choose.max_ages={list(ages)!r} names a cap twice; each is one "
                              f"candidate: use choose.max_ages={unique!r}")  # fmt: skip
        n_cells = _number(options, "n_cells", 100, integer=True)
        if n_cells < 2:
            # the tie rule reads the SE of the paired per-cell difference: one cell has none
            raise ConfigError(f"choose.n_cells={n_cells} held-out cell gives the paired "
                              f"difference no standard error (the tie rule's): use "
                              f"choose.n_cells=2 or more (default 100)")  # fmt: skip
        return cls(tuple(caps), n_cells,
                   _number(options, "t_end", 50.0), _number(options, "equilibration_time", 10.0,
                                                            zero=True),
                   _number(options, "tie_se", 1.0))  # fmt: skip


def _number(options: Mapping[str, Any], key: str, default: float, integer: bool = False,
            zero: bool = False) -> Any:  # fmt: skip
    """``choose.<key>``: a positive number (an integer, or >= 0 where ``zero``)."""
    value = options.get(key, default)
    kind = int if integer else int | float
    if isinstance(value, bool) or not isinstance(value, kind) or not (
            value >= 0 if zero else value > 0) or not math.isfinite(value):  # fmt: skip
        what = "an integer" if integer else "a number"
        raise ConfigError(f"choose.{key} must be {what} {'>=' if zero else '>'} 0, got {value!r}")
    return int(value) if integer else float(value)


def candidates(settings: ChoiceSettings, internal: Any) -> dict[str, dict[str, Any]]:
    """The candidates' names and their gp groups (the shipped recipes as they are): the
    two-state chain (``gp=svgp``), the clock at each cap (``gp=clock gp.max_age=...``), K lumps
    (``gp=classes``) where the model's ``internal`` model declares classes, and each other
    registered candidate kind's recipe."""
    out = {"two-state": group_config("gp", "svgp")}
    for age in settings.max_ages:
        out[f"clock max_age={age:g}"] = {**group_config("gp", "clock"), "max_age": age}
    if lump_classes_of(internal) is not None:
        out["classes"] = group_config("gp", "classes")
    shipped = {"svgp", "clock", "classes"}
    for kind in CHAIN_KINDS:
        if kind.candidate and kind.recipe not in shipped:
            out[kind.recipe] = group_config("gp", kind.recipe)
            shipped.add(kind.recipe)
    return out


def validate(cfg: Mapping[str, Any]) -> tuple[ChoiceSettings, dict[str, TrainSettings]]:
    """The choice's settings and every candidate's train settings, checked before any work."""
    settings = ChoiceSettings.from_config(cfg.get("choose") or {})
    base = to_dict(cfg)
    first = train_stage.validate({**base, "gp": group_config("gp", "svgp")})
    check_windows(settings, first.setup.dt)
    trains = {name: train_stage.validate({**base, "gp": gp})
              for name, gp in candidates(settings, first.setup.model.internal).items()}  # fmt: skip
    return settings, trains


def check_windows(settings: ChoiceSettings, dt: float) -> None:
    """Refuse a held-out run or a clock cap shorter than one window of ``dt`` s: both are
    counted in whole windows, at least one, so either would silently be one window.

    Raises:
        ConfigError: ``choose.t_end`` or a cap in ``choose.max_ages`` below ``dt``, named with
            the value that passes.
    """
    if settings.t_end < dt:
        raise ConfigError(f"choose.t_end={settings.t_end:g} s is shorter than one window "
                          f"(dt={dt:g} s): the held-out run would record one window of {dt:g} "
                          f"s; use choose.t_end={max(dt, 50.0):g} (the default) or any value >= "
                          f"{dt:g}")  # fmt: skip
    short = [a for a in settings.max_ages if a < dt]
    if short:
        kept = [a for a in settings.max_ages if a >= dt] or [max(1.0, dt)]
        raise ConfigError(f"choose.max_ages has cap(s) {short} below one window (dt={dt:g} s): "
                          f"the clock counts whole windows, so its layer would cap it at one "
                          f"window, not as asked; use caps >= {dt:g}, e.g. "
                          f"choose.max_ages={kept!r}")  # fmt: skip


def run(cfg: Mapping[str, Any]) -> Path:
    """Fit and score the candidates, choose, train the chosen; return the choice directory."""
    settings, trains = validate(cfg)
    return choose_kind(settings, trains, to_dict(cfg))


def choose_kind(
    settings: ChoiceSettings, trains: Mapping[str, TrainSettings], config: Mapping[str, Any]
) -> Path:
    """:func:`run` on validated settings."""
    t0 = time.perf_counter()
    first = next(iter(trains.values()))
    if isinstance(first.source, CollectSettings):
        collect(first.source)  # one collection for every candidate (reused where it exists)
    setup, job = first.setup, first.job
    model = setup.model
    fits: dict[str, tuple[TrainSettings, Path, float]] = {}
    for name, tr in trains.items():
        start = time.perf_counter()
        table, source = train_stage.load_transitions(tr)
        fits[name] = (tr, train_stage.fit(tr, table, source), time.perf_counter() - start)
        log.info("choice: %s fitted (or reused) in %.1f s", name, fits[name][2])
    start = time.perf_counter()
    seed_everything(first.seed + HELDOUT_SEED_OFFSET)
    simulator = Simulator(model, FullDecision(model.internal), setup.field, setup.dt, job.device,
                          backend="auto")  # fmt: skip
    heldout = record_occupancy(simulator, settings.n_cells, settings.t_end,
                               torch.tensor(first.diagnostic["start"]), record_every=1,
                               equilibration_time=settings.equilibration_time)  # fmt: skip
    inputs, phi = phi_sequences(heldout, model.internal.input_names)
    inputs = inputs.to(torch.float32)  # the layers read float32 inputs, as simulate gives them
    heldout_seconds = time.perf_counter() - start
    log.info("choice: held-out full-model run, %d cells x %d windows, in %.1f s",
             inputs.shape[0], inputs.shape[1], heldout_seconds)  # fmt: skip
    scores: list[KindScore] = []
    for i, (name, (tr, fit_dir, fit_seconds)) in enumerate(fits.items()):
        start = time.perf_counter()
        request = LayerRequest.of_fit(model, tr, "lookup", None, torch.device("cpu"))
        layer, _ = tr.kind.decision_layer(request, fit_dir)
        s = score_kind(name, tr.kind, layer, inputs, phi, setup.dt, model.internal.lump_names,
                       seed=first.seed + i)  # fmt: skip
        scores.append(KindScore(s.name, s.complexity, s.log_likelihood, s.per_cell, s.durations,
                                fit_seconds, time.perf_counter() - start))  # fmt: skip
    choice = choose(scores, settings.tie_se)
    chosen = trains[choice.chosen]
    train_dir = train_stage.train(chosen, config=config)
    overrides = " ".join(chosen.gp_overrides())
    _log(choice, overrides)
    identity = {"candidates": {n: t.fit_identity() for n, t in trains.items()},
                "choose": vars(settings), "seed": first.seed}  # fmt: skip
    out = artefact_dir(job.data_dir, "choice", {"model": model.name}, identity)
    record = {"chosen": choice.chosen, "reason": choice.reason, "overrides": overrides,
              "train": str(train_dir), "scores": choice.table,
              "heldout": {"cells": int(inputs.shape[0]), "windows": int(inputs.shape[1]),
                          "seconds": heldout_seconds}}  # fmt: skip
    write_json(out / CHOICE, record)
    write_csv(out / SCORES, pd.DataFrame(choice.table))
    write_json(train_dir / CHOICE, record)  # beside the chosen fit, for whoever reads it
    write_manifest(out, stage="choice", config=dict(config), seed=first.seed, settings=identity,
                   chosen=choice.chosen, reason=choice.reason, train=str(train_dir),
                   scores=choice.table, wall_time_s=time.perf_counter() - t0)  # fmt: skip
    return out


def _log(choice: Choice, overrides: str) -> None:
    """The score table and the reason, in the log."""
    for row in choice.table:
        on = [k for k in row if k.endswith("_ks")]
        log.info("choice: %-18s log-lik/window %.5f (%+.2e, SE %.1e)  %s  fit %.1f s, score "
                 "%.1f s", row["kind"], row["log_likelihood_per_window"], row["diff_from_best"],
                 row["diff_se"], "  ".join(f"{k} {row[k]:.3f} (crit {row[k + '_critical_05']:.3f})"
                                           for k in on),
                 row["fit_seconds"], row["score_seconds"])  # fmt: skip
    log.info("choice: %s, because %s; simulate with `%s`", choice.chosen, choice.reason,
             overrides)  # fmt: skip

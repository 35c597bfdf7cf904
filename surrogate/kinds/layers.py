"""The chains' decision layers, which the kinds' ``decision_layer`` and ``exact_layer`` delegate
to (moved from stages/simulate.py unchanged, which re-exports them): the learned abstraction
(:func:`abstract_decision`, :func:`learned_class_decision`) and the model's exact law
(:func:`exact_decision`, :func:`exact_clock_decision`, :func:`exact_class_decision`)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from surrogate.gp import PsiClassifier, PsiLookupTable
from surrogate.kinds.decision import mode_kind
from surrogate.kinds.fits import load_class_chain
from surrogate.models.base import FeatureMap, Model
from surrogate.models.capabilities import signal_bounds_of
from surrogate.simulate.classes import ClassDecision, exact_class_table
from surrogate.simulate.decision import AbstractDecision, DecisionLayer, ExactDecision, ExactPsi
from surrogate.simulate.memory import (
    MemoryDecision,
    exact_age_table,
    has_history,
    tabulate_with_clock,
)

log = logging.getLogger(__name__)


def learned_class_decision(
    model: Model,
    directory: Path,
    device: torch.device,
    name: str = "abstract",
    start: str = "internal",
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The learned K-lumps chain (``gp.lumps=classes``) of a fit directory on ``device``, its
    cells starting as ``start`` says (:class:`ClassDecision`)."""
    table = load_class_chain(directory, device)
    featurize = model.featurizer(table.input_names)
    log.info("K-lumps chain over %d classes, table %s over %s", table.n_classes, table.shape,
             table.input_names)  # fmt: skip
    return ClassDecision(table, model.internal, featurize, name, start=start), {
        "inputs": list(table.input_names),
        "lumps": "classes",
        "classes": list(table.class_names),
        "start": start,
    }


def abstract_decision(
    model: Model,
    psi: PsiClassifier,
    dt: float,
    max_age: float,
    mode: str,
    size: Sequence[int] | None,
    device: torch.device,
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The learned abstraction ``psi`` (loaded on ``device``) as a decision layer over
    ``model``: a lookup table of it, or the classifier every step in closed form with cached
    factors (checked against the classifier). With a switch clock (psi's last input, from
    ``gp.history=age``) the chain keeps one per cell, capped at ``max_age`` s, ticking every
    ``dt``; ``size`` is the table's nodes per input (null: the default)."""
    info: dict[str, Any] = {"inputs": list(psi.input_names)}
    memory = has_history(psi.input_names)
    featurize = model.featurizer(psi.input_names[:-1] if memory else psi.input_names)

    def layer(run_probability: Any) -> DecisionLayer:
        if memory:  # the switch clock is psi's last input (gp.history=age)
            return MemoryDecision(run_probability, model.internal, featurize, max_age, dt=dt)
        return AbstractDecision(run_probability, model.internal, featurize)

    if mode_kind(mode).table:
        ranges = [psi.domain[n] for n in psi.input_names]
        if memory:  # a clock node at every step: each cell reads its clock's node
            lead = tuple(size[:-1]) if size else None
            table = tabulate_with_clock(psi, ranges[:-1], psi.input_names, dt, max_age,
                                        lead).to(device)  # fmt: skip
        else:
            table = PsiLookupTable.from_function(psi, ranges, psi.input_names, size).to(device)
        info["lookup_max_deviation"] = float(table.max_deviation(psi))
        log.info("lookup table %s: max |table - classifier| = %.2e", table.shape,
                 info["lookup_max_deviation"])  # fmt: skip
        return layer(table), info
    # classifier every step: the same predictive in closed form with cached factors (no gpytorch,
    # no host sync per step); its agreement with the classifier is checked and recorded
    from surrogate.gp.fast import CachedPsi

    cached = CachedPsi.from_classifier(psi)
    info["cached_max_deviation"] = cached.max_deviation(psi)
    log.info("cached classifier: max |cached - classifier| = %.2e", info["cached_max_deviation"])
    return layer(cached), info


def exact_decision(
    model: Model, dt: float, mode: str, size: Sequence[int] | None, device: torch.device
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The chain driven by the model's exact lumped psi: ``direct`` (exp(Q dt) per cell and
    step) or ``lookup`` (a table over the signal's bounds, checked against direct)."""
    internal = model.internal
    if not mode_kind(mode).table:  # direct
        return ExactDecision(internal, dt), {}
    bounds = signal_bounds_of(internal) or {}
    ranges = [bounds[n] for n in internal.signal_names]
    exact = ExactPsi(internal, dt)
    table = PsiLookupTable.from_function(exact, ranges, internal.signal_names, size).to(device)
    deviation = table.max_deviation(exact, n_check=2048)
    log.info("exact psi table %s: max |table - exact| = %.2e", table.shape, deviation)
    return ExactDecision(internal, dt, table), {"lookup_max_deviation": deviation}


def exact_clock_decision(
    model: Model, dt: float, max_age: float, device: torch.device, name: str = "exact"
) -> MemoryDecision:
    """The chain driven by the exact psi with a switch clock (``decision.history=age``): a
    table over the signal and the clock, capped at ``max_age`` s; ``name`` labels the layer."""
    table = exact_age_table(model.internal, dt, max_age).to(device)
    featurize = FeatureMap(model.internal, model.internal.signal_names)
    log.info("exact psi with a switch clock: table %s over %s", table.shape, table.input_names)
    return MemoryDecision(table, model.internal, featurize, max_age, name, dt)


def exact_class_decision(
    model: Model, dt: float, device: torch.device, name: str = "exact"
) -> ClassDecision:
    """The K-lumps chain driven by the exact class-to-class law of adapted cells
    (``decision.lumps=classes``): the limit of a learned one."""
    table = exact_class_table(model.internal, dt).to(device)
    featurize = FeatureMap(model.internal, model.internal.signal_names)
    log.info("exact K-lumps chain over %d classes: table %s", table.n_classes, table.shape)
    return ClassDecision(table, model.internal, featurize, name)

"""The chains' decision layers that the kinds share, which :class:`~surrogate.kinds.base.ChainKind`'s
``decision_layer`` and ``exact_layer`` delegate to (moved from stages/simulate.py unchanged,
which re-exports them): the learned psi as a layer (:func:`psi_decision`: its lookup table or
its classifier, which a kind's layer wraps), the chain over phi's (:func:`abstract_decision`) and
the model's exact lumped psi (:func:`exact_decision`). A kind's own layers live in its module
(the switch clock's in :mod:`surrogate.kinds.clock`, K lumps' in :mod:`surrogate.kinds.klumps`)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import torch

from surrogate.gp import PsiClassifier, PsiLookupTable
from surrogate.kinds.decision import mode_kind
from surrogate.models.base import Model
from surrogate.models.capabilities import signal_bounds_of
from surrogate.simulate.decision import AbstractDecision, DecisionLayer, ExactDecision, ExactPsi

log = logging.getLogger(__name__)


def psi_decision(
    psi: PsiClassifier,
    mode: str,
    device: torch.device,
    layer: Callable[[Any], DecisionLayer],
    tabulate: Callable[[list[tuple[float, float]]], PsiLookupTable],
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The learned abstraction ``psi`` (loaded on ``device``) as the decision layer ``layer``
    makes of a run probability, in ``mode``: a lookup table of it (``tabulate`` of psi's
    domain's ranges, one per input), or the classifier every step in closed form with cached
    factors (checked against the classifier); and facts about it for the manifest."""
    info: dict[str, Any] = {"inputs": list(psi.input_names)}
    if mode_kind(mode).table:
        table = tabulate([psi.domain[n] for n in psi.input_names]).to(device)
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


def abstract_decision(
    model: Model,
    psi: PsiClassifier,
    mode: str,
    size: Sequence[int] | None,
    device: torch.device,
) -> tuple[DecisionLayer, dict[str, Any]]:
    """The learned abstraction ``psi`` of a chain over phi (loaded on ``device``) as a decision
    layer over ``model``: a lookup table of it (``size``: its nodes per input, null: the
    default), or the classifier every step (:func:`psi_decision`). A psi with a switch clock is
    the clock's (:meth:`SwitchClock.decision_layer <surrogate.kinds.clock.SwitchClock.decision_layer>`)."""
    featurize = model.featurizer(psi.input_names)
    return psi_decision(
        psi, mode, device, lambda run: AbstractDecision(run, model.internal, featurize),
        lambda ranges: PsiLookupTable.from_function(psi, ranges, psi.input_names, size),
    )  # fmt: skip


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

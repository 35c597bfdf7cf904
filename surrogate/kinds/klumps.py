"""K lumps (``gp.lumps=classes``, ``decision.lumps=classes``) as one kind module: the chain over
the model's classes finer than phi, a table (lookup mode only) that may start from its
stationary law; ``gp.class_moves``: every move learned, or bins of a slow count that relax. It
holds its gp keys (:data:`GP_CLASSES`), its refusals (:meth:`KLumps.check_fit`,
:meth:`~KLumps.configure`, :meth:`~KLumps.check_exact`, :meth:`~KLumps.check_mode`), its fit
identity, its artefact and its layers (:func:`learned_class_decision`,
:func:`exact_class_decision`); its fit is :mod:`surrogate.kinds.fits`' and its engine blocks
:mod:`surrogate.simulate.classes`' (:class:`ClassTable`, :class:`ClassDecision`)."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.gp.class_relaxation import (
    DEFAULT_CELLS,
    DEFAULT_LAGS,
    RELAXATION_VERSION,
    check_shared_bins,
)
from surrogate.gp.classes import CLASS_LAW_VERSION, DEFAULT_MAX_LABEL_WEIGHT, MIN_EVENTS
from surrogate.gp.training import GPSettings
from surrogate.io import save_tensors
from surrogate.kinds.base import (
    AUTO_RECIPES,
    PROBABILITY_FLOOR,
    ChainKind,
    FitSettings,
    LayerRequest,
    register_chain_kind,
)
from surrogate.kinds.decision import DecisionMode
from surrogate.kinds.files import CLASS_CHAIN
from surrogate.kinds.fits import _fit_class_chain, load_class_chain
from surrogate.models.base import FeatureMap, Model
from surrogate.models.capabilities import class_bins_of, exact_class_step_of, lump_classes_of
from surrogate.simulate.classes import (
    STARTS,
    ClassDecision,
    ClassTable,
    can_classify,
    exact_class_table,
)
from surrogate.simulate.decision import DecisionLayer

log = logging.getLogger(__name__)

#: keys of the gp group that only a fit of the K-lumps chain reads (gp.lumps=classes)
GP_CLASSES = ("lumps", "min_events", "max_label_weight", "class_moves", "relaxation")


@register_chain_kind
@dataclass(frozen=True)
class KLumps(ChainKind):
    """The chain over the model's classes finer than phi (``gp.lumps=classes``,
    :mod:`surrogate.simulate.classes`): a table (lookup mode only) that may start from its
    stationary law; ``class_moves``: every move learned, or bins of a slow count that relax
    (:mod:`surrogate.gp.class_relaxation`)."""

    lumps = "classes"
    class_moves_choices = ("learned", "relaxation")
    gp_keys = GP_CLASSES
    title = "K-lumps"
    classes = True
    recipe = AUTO_RECIPES[0]
    starts = STARTS
    files = (CLASS_CHAIN,)
    complexity = 2
    candidate = True
    law_version = ("class_law_version", CLASS_LAW_VERSION)

    moves: str = "learned"

    @classmethod
    def make(cls, class_moves: str) -> ChainKind:
        return cls(class_moves)

    @property
    def class_moves(self) -> str:
        """gp.class_moves: learned | relaxation."""
        return self.moves

    @property
    def relaxation(self) -> bool:
        return self.moves == "relaxation"

    @classmethod
    def check_fit(cls, history: str, internal: Any, model_name: str) -> None:
        """The model must declare classes finer than phi; the chain takes no switch clock."""
        if lump_classes_of(internal) is None:
            raise ConfigError(
                f"gp.lumps=classes: model {model_name!r} declares no classes finer "
                f"than phi (class_names, class_lumps, classes on its internal model)"
            )
        if history != cls.history:
            raise ConfigError("gp.lumps=classes takes no switch clock: use gp.history=none")

    def configure(
        self,
        gp_config: Mapping[str, Any],
        gp: GPSettings,
        inputs: tuple[str, ...],
        internal: Any,
        model_name: str,
    ) -> tuple[GPSettings, tuple[str, ...]]:
        """Bins that relax must be bins of one count shared by the lumps."""
        if self.relaxation:
            declared = lump_classes_of(internal)
            assert declared is not None  # check_fit checked it
            check_shared_bins(class_bins_of(internal), declared.lumps)
        return gp, inputs

    @classmethod
    def check_exact(cls, history: str, mode: DecisionMode, internal: Any, model_name: str) -> None:
        """The exact K-lumps chain is a table without a clock over a model with classes and
        their exact law over one signal."""
        if (
            history != cls.history or not mode.table or not can_classify(internal)
            or exact_class_step_of(internal) is None or len(internal.signal_names) != 1
        ):  # fmt: skip
            raise ConfigError(
                f"decision.lumps=classes needs decision.mode=lookup, no clock and a model "
                f"with classes and their exact law over one signal (exact_class_step); "
                f"model {model_name!r}, mode {mode.name!r}, history {history!r}"
            )

    def fit_identity(
        self,
        gp: Mapping[str, Any],
        min_events: float | None = None,
        max_label_weight: float = DEFAULT_MAX_LABEL_WEIGHT,
        relaxation_cells: int = DEFAULT_CELLS,
        relaxation_lags: Sequence[float] = DEFAULT_LAGS,
    ) -> dict[str, Any]:
        """The class law's options resolved, and its fit version: a change in either refits;
        learned class moves keep the identity they had before relaxation."""
        out = super().fit_identity(gp)
        out["min_events"] = dict(MIN_EVENTS) if min_events is None else min_events
        out["max_label_weight"] = max_label_weight
        out.pop("class_moves", None)
        out.pop("relaxation", None)
        if self.relaxation:
            out["class_moves"] = {"kind": self.class_moves, "cells": relaxation_cells,
                                  "lags": list(relaxation_lags),
                                  "version": RELAXATION_VERSION}  # fmt: skip
        return out

    def label(self) -> dict[str, Any]:
        return {"lumps": self.lumps}

    def check_mode(self, mode: DecisionMode) -> None:
        if not mode.table:
            raise ConfigError(
                "gp.lumps=classes: the K-lumps chain is a table (decision.mode=lookup), it has "
                f"no classifier mode; got decision.mode={mode.name!r}. The two-state chain has "
                "one: add gp=svgp (the default, gp=auto, runs K lumps for a model with classes)"
            )

    def fit(
        self, settings: FitSettings, table: pd.DataFrame, domain: Mapping[str, tuple[float, float]]
    ) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """The chain over the model's classes (:func:`_fit_class_chain`; its bins relaxing with
        gp.class_moves=relaxation)."""
        return _fit_class_chain(settings, table, domain)

    def write(
        self,
        directory: Path,
        fitted: tuple[dict[str, Any], dict[str, Any]] | None,
        identity: Mapping[str, Any],
    ) -> dict[str, Any]:
        """The class table's state as :data:`CLASS_CHAIN`; its metrics as ``class_chain``."""
        assert fitted is not None  # fit gives one
        table_state, metrics = fitted
        save_tensors(directory / CLASS_CHAIN, {"class_chain": table_state,
                                               "metadata": {"settings": dict(identity)}})  # fmt: skip
        return {"class_chain": metrics}

    def load(self, directory: str | os.PathLike, device: str | torch.device = "cpu") -> ClassTable:
        """The chain's class table (:func:`load_class_chain`)."""
        return load_class_chain(directory, device)

    def decision_layer(
        self, request: LayerRequest, directory: Path
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The class table, its cells starting as ``request.start`` says
        (:func:`learned_class_decision`; a table in lookup mode, checked by :meth:`check_mode`)."""
        return learned_class_decision(request.model, directory, request.device,
                                      start=request.start)  # fmt: skip

    def window_log_likelihoods(
        self, layer: DecisionLayer, inputs: Tensor, phi: Tensor, dt: float
    ) -> Tensor:
        """The forward algorithm over the classes, observing phi = the class's lump: the
        classes at the start from the chain's stationary law at the first inputs given the
        first phi, then each window's law given the inputs; each window's log scale."""
        if not isinstance(layer, ClassDecision):
            raise TypeError(f"K lumps scores a ClassDecision, got {layer!r}")
        table, n, steps = layer.table, inputs.shape[0], inputs.shape[1]
        lumps = table.lumps.to(phi.device)  # (C,) float 0/1
        # (n, T+1, C): whether each class is in the lump observed at each time
        agrees = (lumps[None, None, :] == phi.to(torch.float32)[:, :, None]).to(torch.float64)
        alpha = _featurized_law_start(layer, inputs[:, 0]) * agrees[:, 0]
        alpha = alpha / alpha.sum(1, keepdim=True).clamp_min(PROBABILITY_FLOOR)
        terms = torch.zeros(n, steps, dtype=torch.float64, device=phi.device)
        for t in range(steps):  # over windows and origin classes (cells in the batch)
            z = inputs[:, t] if layer.featurize is None else layer.featurize(inputs[:, t])
            moved = torch.zeros_like(alpha)
            for c in range(table.n_classes):
                origin = torch.full((n,), c, dtype=torch.int64, device=phi.device)
                moved = moved + alpha[:, c, None] * table.law(origin, z).to(torch.float64)
            moved = moved * agrees[:, t + 1]
            mass = moved.sum(1)
            terms[:, t] = mass.clamp_min(PROBABILITY_FLOOR).log()
            alpha = moved / mass.clamp_min(PROBABILITY_FLOOR)[:, None]
        return terms

    def start_sequences(self, layer: DecisionLayer, x0: Tensor, phi0: Tensor) -> None:
        """Each cell's class drawn from the chain's stationary law at ``x0`` given ``phi0``."""
        if not isinstance(layer, ClassDecision):
            raise TypeError(f"K lumps starts a ClassDecision, got {layer!r}")
        law = _featurized_law_start(layer, x0)
        law = law * (layer.table.lumps.to(phi0.device)[None, :] == phi0.float()[:, None])
        layer.cls = torch.multinomial(law.clamp_min(0.0) + 1e-300, 1).squeeze(1)

    def exact_layer(self, request: LayerRequest) -> tuple[DecisionLayer, dict[str, Any]]:
        """The exact class-to-class law's table (:func:`exact_class_decision`)."""
        return exact_class_decision(request.model, request.dt, request.device), self.label()


def _featurized_law_start(layer: ClassDecision, x: Tensor) -> Tensor:
    """The chain's stationary law at the inputs ``x`` (``n x d``) ``n x C`` (float64)."""
    z = x if layer.featurize is None else layer.featurize(x)
    return layer.table.stationary_at(z).to(torch.float64)


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
        "lumps": KLumps.lumps,
        "classes": list(table.class_names),
        "start": start,
    }


def exact_class_decision(
    model: Model, dt: float, device: torch.device, name: str = "exact"
) -> ClassDecision:
    """The K-lumps chain driven by the exact class-to-class law of adapted cells
    (``decision.lumps=classes``): the limit of a learned one."""
    table = exact_class_table(model.internal, dt).to(device)
    featurize = FeatureMap(model.internal, model.internal.signal_names)
    log.info("exact K-lumps chain over %d classes: table %s", table.n_classes, table.shape)
    return ClassDecision(table, model.internal, featurize, name)

"""The chain kinds (``gp.lumps``, ``gp.history``, ``gp.class_moves``) as objects:
:class:`ChainKind` and its kinds :class:`TwoStateChain`, :class:`SwitchClock` and
:class:`KLumps`; :func:`chain_kind` (the strings -> the kind), :func:`fit_chain` (the gp
group's chain, validated), :func:`exact_clock` and :func:`exact_chain` (``decision=exact``'s,
validated) and :func:`resolve_auto_lumps` (``gp.lumps=auto``). A kind's fit, artefact and layers
delegate to :mod:`surrogate.kinds.fits` and :mod:`surrogate.kinds.layers`."""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import pandas as pd
import torch

from surrogate.config import group_config, non_negative, positive
from surrogate.errors import ArtefactError, ConfigError
from surrogate.gp import load_psi
from surrogate.gp.class_relaxation import (
    CLASS_MOVES,
    DEFAULT_CELLS,
    DEFAULT_LAGS,
    RELAXATION_VERSION,
    check_shared_bins,
)
from surrogate.gp.classes import CLASS_LAW_VERSION, DEFAULT_MAX_LABEL_WEIGHT, MIN_EVENTS
from surrogate.gp.model import DEFAULT_MEAN
from surrogate.gp.training import GPSettings
from surrogate.io import save_tensors
from surrogate.kinds.decision import DecisionMode
from surrogate.kinds.files import CLASS_CHAIN, PSI
from surrogate.kinds.fits import _fit_class_chain, load_class_chain
from surrogate.kinds.layers import (
    abstract_decision,
    exact_class_decision,
    exact_clock_decision,
    exact_decision,
    learned_class_decision,
)
from surrogate.models.base import Model
from surrogate.models.capabilities import class_bins_of, exact_class_step_of, lump_classes_of
from surrogate.simulate.classes import LUMPINGS, STARTS, ClassTable, can_classify
from surrogate.simulate.decision import DecisionLayer
from surrogate.simulate.memory import AGE, can_age, clock_rows, history_setting
from surrogate.validation import known_keys

#: keys of the gp group that only a fit with a switch clock reads (gp.history=age)
GP_CLOCK = ("history", "max_age", "clock_bins")
#: keys of the gp group that only a fit of the K-lumps chain reads (gp.lumps=classes)
GP_CLASSES = ("lumps", "min_events", "max_label_weight", "class_moves", "relaxation")
#: gp.lumps=auto (conf/gp/auto.yaml, the default): the best measured chain for the model, as
#: these shipped recipes: the first where the model declares classes finer than phi, else the second
AUTO_RECIPES = ("classes", "svgp")


class ChainKind:
    """A kind of learned (or exact) chain: what the settings, train and simulate ask of it.

    The kinds are instances of the subclasses, made by :func:`chain_kind` only; compare them
    by their flags, never by their names.

    Example:
        >>> kind = chain_kind("phi", "age")
        >>> kind.clock, kind.classes, kind.history
        (True, False, 'age')
        >>> kind.fit_identity({"lumps": "phi", "history": "age", "max_age": 5.0, "bins": 200})
        {'history': 'age', 'max_age': 5.0, 'bins': 200}
    """

    #: the config's strings for this kind (gp.lumps, gp.history; gp.class_moves below)
    lumps: ClassVar[str] = "phi"
    history: ClassVar[str] = "none"
    #: psi also takes the switch clock (its last input): train records the clocks
    clock: ClassVar[bool] = False
    #: the chain runs over the model's classes (collect's class labels, a class table)
    classes: ClassVar[bool] = False
    #: the shipped conf/gp recipe a command names for it (a two-state fit's says gp=svgp,
    #: which the default, gp=auto, would not pick for a model with classes)
    recipe: ClassVar[str] = AUTO_RECIPES[1]
    #: where its cells may start (decision.initial)
    starts: ClassVar[tuple[str, ...]] = (STARTS[0],)
    #: its own artefact: the fit's files beyond the classifiers' (:data:`PSI`, which every
    #: kind fits), copied into the train directory with them
    files: ClassVar[tuple[str, ...]] = ()

    @property
    def class_moves(self) -> str:
        """gp.class_moves: how the chain's class moves are fitted (a chain over phi: learned)."""
        return "learned"

    @property
    def relaxation(self) -> bool:
        """Whether the K-lumps chain's bins relax to their stationary law
        (gp.class_moves=relaxation)."""
        return False

    def fit_identity(
        self,
        gp: Mapping[str, Any],
        min_events: float | None = None,
        max_label_weight: float = DEFAULT_MAX_LABEL_WEIGHT,
        relaxation_cells: int = DEFAULT_CELLS,
        relaxation_lags: Sequence[float] = DEFAULT_LAGS,
    ) -> dict[str, Any]:
        """The gp part of a fit's identity from the fit's gp keys ``gp``: the keys only other
        kinds read are dropped, so each fit keeps the identity (and the directory) it had
        before those kinds existed. The K-lumps options are read by :class:`KLumps` only."""
        drop = (() if self.clock else GP_CLOCK) + (() if self.classes else GP_CLASSES)
        if gp.get("mean", DEFAULT_MEAN) == DEFAULT_MEAN:  # fits before gp.mean keep theirs
            drop += ("mean",)
        return {k: v for k, v in gp.items() if k not in drop}

    def label(self) -> dict[str, Any]:
        """What the kind adds to an artefact directory's readable name (the two-state chain and
        the clock: nothing, as before K lumps)."""
        return {}

    def check_mode(self, mode: DecisionMode) -> None:
        """Refuse a learned run of this chain in ``mode`` (decision=abstract)."""

    def check_start(self, value: str, where: str) -> None:
        """Refuse a start (``decision.initial``, already one of :data:`STARTS`) this chain has
        no law for."""
        if value not in self.starts:
            raise ConfigError(
                f"{where}={value} starts a K-lumps chain from its stationary law (gp=classes); "
                f"the two-state chain starts from the internal model's initial law: use "
                f"{where}={self.starts[0]}"
            )

    # what train and simulate ask of the kind: its fit, its artefact, its decision layers

    def training_rows(
        self, table: pd.DataFrame, max_age: float, where: str, source: Any
    ) -> pd.DataFrame:
        """The rows of the transitions ``table`` (read from ``where``, made by ``source``: the
        collect settings or an external table) that the fit reads, as it reads them (a chain
        without a clock: all, as they are)."""
        return table

    def fit(
        self, settings: Any, table: pd.DataFrame, domain: Mapping[str, tuple[float, float]]
    ) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """What the kind fits beyond the classifiers psi, which train fits first for every kind
        (over their ``domain``), from the train settings ``settings`` and the transitions
        ``table``: its artefact's state and its metrics, or None (a chain over phi: psi is the
        whole chain)."""
        return None

    def write(
        self,
        directory: Path,
        fitted: tuple[dict[str, Any], dict[str, Any]] | None,
        identity: Mapping[str, Any],
    ) -> dict[str, Any]:
        """Write what :meth:`fit` gave (``fitted``) as the kind's :attr:`files` in a fit
        ``directory``, recording the fit's ``identity``; the fit metrics' entries it adds."""
        return {}

    def load(self, directory: str | os.PathLike, device: str | torch.device = "cpu") -> Any:
        """The kind's own artefact of a fit or train ``directory`` on ``device`` (None: the
        kind has none beyond psi)."""
        return None

    def decision_layer(
        self,
        model: Model,
        train: Any,
        directory: Path,
        mode: str,
        size: Sequence[int] | None,
        device: torch.device,
        start: str = "internal",
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The learned chain of the fit ``directory`` (made by the train settings ``train``)
        as a decision layer over ``model`` on ``device``, in ``mode`` (``size``: the table's
        nodes per input), and facts about it for the manifest: psi's lookup table or the
        classifier itself (:func:`abstract_decision`; a chain over phi starts its cells from
        the internal model, ``start`` is checked to say so)."""
        psi, _ = load_psi(Path(directory) / PSI, device=device)
        return abstract_decision(model, psi, train.setup.dt, train.max_age, mode, size, device)

    def exact_layer(
        self,
        model: Model,
        dt: float,
        mode: str,
        size: Sequence[int] | None,
        max_age: float,
        device: torch.device,
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The chain driven by the model's exact law (decision=exact, checked by
        :func:`exact_clock` and :func:`exact_chain`) over ``model`` at ``dt`` on ``device``,
        in ``mode`` (``size``: the table's nodes), a clock capped at ``max_age`` s; and facts
        about it for the manifest (:func:`exact_decision`)."""
        return exact_decision(model, dt, mode, size, device)


@dataclass(frozen=True)
class TwoStateChain(ChainKind):
    """The paper's chain over phi: psi of the inputs alone (``gp.lumps=phi``,
    ``gp.history=none``)."""


@dataclass(frozen=True)
class SwitchClock(ChainKind):
    """The chain over phi whose psi also reads the time since phi last changed
    (``gp.history=age``, capped at ``gp.max_age``): train records the clocks, simulate keeps
    one per cell (:mod:`surrogate.simulate.memory`)."""

    history = "age"
    clock = True

    def training_rows(
        self, table: pd.DataFrame, max_age: float, where: str, source: Any
    ) -> pd.DataFrame:
        """The rows whose clock is known, clipped at ``max_age`` (:func:`clock_rows`)."""
        try:
            return clock_rows(table, max_age)
        except KeyError as exc:
            raise ArtefactError(
                f"{where} has no switch clocks ({exc.args[0]}) for gp.history=age: it was "
                f"collected before collect recorded them; delete it and re-run "
                f"`{getattr(source, 'command', lambda: 'python3 scripts/collect.py')()}`"
            ) from exc

    def exact_layer(
        self,
        model: Model,
        dt: float,
        mode: str,
        size: Sequence[int] | None,
        max_age: float,
        device: torch.device,
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The exact psi with a switch clock (:func:`exact_clock_decision`, a table)."""
        return exact_clock_decision(model, dt, max_age, device), {}


@dataclass(frozen=True)
class KLumps(ChainKind):
    """The chain over the model's classes finer than phi (``gp.lumps=classes``,
    :mod:`surrogate.simulate.classes`): a table (lookup mode only) that may start from its
    stationary law; ``class_moves``: every move learned, or bins of a slow count that relax
    (:mod:`surrogate.gp.class_relaxation`)."""

    lumps = "classes"
    classes = True
    recipe = AUTO_RECIPES[0]
    starts = STARTS
    files = (CLASS_CHAIN,)

    moves: str = "learned"

    @property
    def class_moves(self) -> str:
        """gp.class_moves: learned | relaxation."""
        return self.moves

    @property
    def relaxation(self) -> bool:
        return self.moves == "relaxation"

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
        out["class_law_version"] = CLASS_LAW_VERSION
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
        self, settings: Any, table: pd.DataFrame, domain: Mapping[str, tuple[float, float]]
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
        self,
        model: Model,
        train: Any,
        directory: Path,
        mode: str,
        size: Sequence[int] | None,
        device: torch.device,
        start: str = "internal",
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The class table, its cells starting as ``start`` says (:func:`learned_class_decision`;
        a table in lookup mode, checked by :meth:`check_mode`)."""
        return learned_class_decision(model, directory, device, start=start)

    def exact_layer(
        self,
        model: Model,
        dt: float,
        mode: str,
        size: Sequence[int] | None,
        max_age: float,
        device: torch.device,
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The exact class-to-class law's table (:func:`exact_class_decision`)."""
        return exact_class_decision(model, dt, device), self.label()


TWO_STATE = TwoStateChain()
SWITCH_CLOCK = SwitchClock()


def chain_kind(
    lumps: str = "phi", history: str = "none", class_moves: str = "learned"
) -> ChainKind:
    """The kind named by the config's strings, already validated (:func:`fit_chain`,
    :func:`exact_chain`): the only place the names are compared.

    Raises:
        ValueError: a combination no kind has (classes with a clock, relaxing two-state bins).
    """
    if lumps == "classes" and history == "none":
        return KLumps(class_moves)
    if lumps == "phi" and class_moves == "learned":
        if history == "none":
            return TWO_STATE
        if history == "age":
            return SWITCH_CLOCK
    raise ValueError(f"no chain kind with lumps={lumps!r}, history={history!r}, "
                     f"class_moves={class_moves!r}")  # fmt: skip


class FitChain(NamedTuple):
    """The gp group's chain, validated (:func:`fit_chain`): its kind, the GP settings and the
    inputs it fits (a clock adds its axis), the clock's cap and the K-lumps law's options
    (validated for every fit, read by K lumps only)."""

    kind: ChainKind
    gp: GPSettings
    inputs: tuple[str, ...]
    max_age: float
    min_events: float | None
    max_label_weight: float
    relaxation_cells: int
    relaxation_lags: tuple[float, ...]


def fit_chain(
    gp_config: Mapping[str, Any],
    gp: GPSettings,
    inputs: tuple[str, ...],
    internal: object,
    model_name: str,
) -> FitChain:
    """The chain a fit's gp group asks for (``gp.history``, ``gp.max_age``, ``gp.lumps``,
    ``gp.class_moves`` and the K-lumps law's options), checked against the model's
    ``internal`` model (``model_name`` for the messages), with the GP settings ``gp`` over the
    model's abstraction ``inputs`` as the chain fits them: a switch clock is psi's last input,
    with its own bin count (``gp.clock_bins``)."""
    history, max_age = history_setting(gp_config.get("history"), gp_config.get("max_age", 5.0),
                                       "gp")  # fmt: skip
    if history == "age":
        if isinstance(gp.bins, int) and gp.bins:  # the clock's axis has its own bin count
            clock_bins = gp_config.get("clock_bins", gp.bins)
            gp = replace(gp, bins=(*[gp.bins] * len(inputs), clock_bins))  # validated again
        inputs = (*inputs, AGE)
    lumps = gp_config.get("lumps", "phi")
    if lumps not in LUMPINGS:
        raise ConfigError(f"gp.lumps must be one of {list(LUMPINGS)}, got {lumps!r}")
    if lumps == "classes":
        if lump_classes_of(internal) is None:
            raise ConfigError(
                f"gp.lumps=classes: model {model_name!r} declares no classes finer "
                f"than phi (class_names, class_lumps, classes on its internal model)"
            )
        if history != "none":
            raise ConfigError("gp.lumps=classes takes no switch clock: use gp.history=none")
    min_events = gp_config.get("min_events")  # null: by the labels
    if min_events is not None:
        min_events = non_negative(gp_config, "min_events", "gp.")
    max_label_weight = positive({"max_label_weight": DEFAULT_MAX_LABEL_WEIGHT, **gp_config},
                                "max_label_weight", "gp.")  # fmt: skip
    if max_label_weight < 1:
        raise ConfigError(f"gp.max_label_weight must be >= 1, got {max_label_weight!r}")
    moves, cells, lags = _class_moves(gp_config)
    if moves == "relaxation":
        if lumps != "classes":
            raise ConfigError("gp.class_moves=relaxation is a K-lumps option: use gp=classes")
        declared = lump_classes_of(internal)
        assert declared is not None  # lumps=classes checked it
        check_shared_bins(class_bins_of(internal), declared.lumps)
    kind = chain_kind(str(lumps), history, moves)
    return FitChain(kind, gp, inputs, max_age, None if min_events is None else float(min_events),
                    float(max_label_weight), cells, lags)  # fmt: skip


def _class_moves(gp_config: Mapping[str, Any]) -> tuple[str, int, tuple[float, ...]]:
    """``gp.class_moves`` and ``gp.relaxation`` ({n_cells, lags}) validated."""
    moves = gp_config.get("class_moves") or "learned"
    if moves not in CLASS_MOVES:
        raise ConfigError(f"gp.class_moves must be one of {list(CLASS_MOVES)}, got {moves!r}")
    options = known_keys(gp_config.get("relaxation") or {}, ("n_cells", "lags"), "gp.relaxation")
    cells = options.get("n_cells", DEFAULT_CELLS)
    if isinstance(cells, bool) or not isinstance(cells, int) or cells < 10:
        raise ConfigError(f"gp.relaxation.n_cells must be an integer >= 10, got {cells!r}")
    lags = options.get("lags", DEFAULT_LAGS)
    if (not isinstance(lags, Sequence) or isinstance(lags, str) or len(lags) < 2
            or any(isinstance(v, bool) or not isinstance(v, int | float) or not v > 0
                   or not math.isfinite(v) for v in lags)
            or any(b <= a for a, b in itertools.pairwise(lags))):  # fmt: skip
        raise ConfigError(f"gp.relaxation.lags must be at least two positive, increasing "
                          f"seconds, got {lags!r}")  # fmt: skip
    return str(moves), int(cells), tuple(float(v) for v in lags)


def exact_clock(
    config: Mapping[str, Any], mode: DecisionMode, internal: Any, model_name: str
) -> tuple[str, float]:
    """``decision=exact``'s ``decision.history`` and ``decision.max_age`` (of the decision group
    ``config``, run in ``mode``), checked against the model's ``internal`` model: an exact psi
    with a clock needs a table and the model's ``exact_age_psi``."""
    history, max_age = history_setting(config.get("history"), config.get("max_age", 5.0),
                                       "decision")  # fmt: skip
    if history == "age" and (not mode.table or not can_age(internal)):
        raise ConfigError(
            f"decision.history=age needs decision.mode=lookup and a model with an exact "
            f"psi over one signal with a clock (exact_age_psi); model "
            f"{model_name!r}, mode {mode.name!r}"
        )
    return history, max_age


def exact_chain(
    config: Mapping[str, Any], history: str, mode: DecisionMode, internal: Any, model_name: str
) -> ChainKind:
    """The chain ``decision=exact`` drives with the model's exact law: ``decision.lumps`` of the
    decision group ``config`` with the clock :func:`exact_clock` validated (``history``), run
    in ``mode``, checked against the model's ``internal`` model."""
    lumps = config.get("lumps", "phi")
    if lumps not in LUMPINGS:
        raise ConfigError(f"decision.lumps must be one of {list(LUMPINGS)}, got {lumps!r}")
    if lumps == "classes" and (
        history != "none" or not mode.table or not can_classify(internal)
        or exact_class_step_of(internal) is None or len(internal.signal_names) != 1
    ):  # fmt: skip
        raise ConfigError(
            f"decision.lumps=classes needs decision.mode=lookup, no clock and a model "
            f"with classes and their exact law over one signal (exact_class_step); "
            f"model {model_name!r}, mode {mode.name!r}, history {history!r}"
        )
    return chain_kind(str(lumps), history)


def resolve_auto_lumps(gp_config: Mapping[str, Any], model: Any) -> dict[str, Any]:
    """``gp_config`` with ``lumps: auto`` resolved to the best measured chain for ``model``: the
    K-lumps chain (``gp=classes``'s recipe) where its internal model declares classes finer than
    phi and no switch clock is asked for (``gp.history=none``), else the two-state chain
    (``gp=svgp``). A key the config sets to another value than ``gp=svgp``'s is the user's, and
    kept; every other key takes the chosen recipe's value, so ``gp=auto`` on E. coli is the same
    fit (the same directory) as ``gp=classes``. Any other ``lumps`` is returned unchanged.

    Example:
        >>> resolve_auto_lumps({**group_config("gp", "auto")}, ecoli)["n_inducing"]  # doctest: +SKIP
        32
    """
    config = dict(gp_config)
    if not is_auto(gp_config):
        return config
    classed = lump_classes_of(model.internal) is not None
    name = (
        AUTO_RECIPES[0] if classed and config.get("history", "none") == "none" else AUTO_RECIPES[1]
    )
    base, recipe = group_config("gp", "svgp"), group_config("gp", name)
    for key, value in recipe.items():
        if key not in config or (key in base and config[key] == base[key]):
            config[key] = value
    config["lumps"] = recipe.get("lumps", "phi")
    return config


def is_auto(gp_config: Mapping[str, Any]) -> bool:
    """Whether the gp group leaves the chain to :func:`resolve_auto_lumps` (``gp.lumps=auto``)."""
    return gp_config.get("lumps") == "auto"

"""The base of the chain kinds and their registry (issue 40): :class:`ChainKind` (the chain over
phi's behaviour, which every kind inherits and overrides where it differs),
:func:`register_chain_kind` (the class decorator a kind's module puts on its class),
:data:`CHAIN_KINDS` (the registered kinds) and :class:`LayerRequest` (what the kinds' layer
methods are asked for). A kind's module imports this one; :mod:`surrogate.kinds.chains`
imports the kinds' modules (``KIND_MODULES``) and looks the config's strings up here
(:func:`find_kind`, :func:`kind_values`)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar, Protocol, TypeVar

import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.gp import PsiClassifier, load_psi
from surrogate.gp.class_relaxation import DEFAULT_CELLS, DEFAULT_LAGS
from surrogate.gp.classes import DEFAULT_MAX_LABEL_WEIGHT
from surrogate.gp.model import DEFAULT_MEAN
from surrogate.gp.training import GPSettings
from surrogate.kinds.decision import DecisionMode
from surrogate.kinds.files import PSI
from surrogate.kinds.layers import abstract_decision, exact_decision
from surrogate.models.base import Model
from surrogate.simulate.classes import STARTS
from surrogate.simulate.decision import AbstractDecision, DecisionLayer

#: gp.lumps=auto (conf/gp/auto.yaml, the default): the best measured chain for the model, as
#: these shipped recipes: the first where the model declares classes finer than phi, else the second
AUTO_RECIPES = ("classes", "svgp")
#: a layer's device where its request names none
CPU = torch.device("cpu")
#: the keys of the gp group that every fit reads besides the GP hyperparameters (the fields of
#: :class:`GPSettings`): no kind may claim them as its own (:func:`register_chain_kind`)
FIT_GP_KEYS = ("inputs", "grid_size", "diagnostic", "threads", "labels", "jump_rows")
#: gp.jump_rows: the rows soon after a jump (auto: left out where collect measured them lagging)
JUMP_ROWS = ("auto", "keep", "drop")


class FitSetup(Protocol):
    """What a kind reads of a fit's model setup (the train settings' ``setup``)."""

    @property
    def model(self) -> Model: ...

    @property
    def field(self) -> Any: ...

    @property
    def dt(self) -> float: ...


class FitJob(Protocol):
    """What a kind reads of a fit's job (the train settings' ``job``)."""

    @property
    def device(self) -> torch.device: ...

    @property
    def progress(self) -> bool: ...


class FitSettings(Protocol):
    """What a kind's fit and layers read of the train settings
    (:class:`~surrogate.stages.settings.train.TrainSettings` is one; the kinds sit below the
    stages, so they name the members they use rather than import the class)."""

    @property
    def setup(self) -> FitSetup: ...

    @property
    def job(self) -> FitJob: ...

    @property
    def source(self) -> Any: ...

    @property
    def gp(self) -> GPSettings: ...

    @property
    def gp_config(self) -> Mapping[str, Any]: ...

    @property
    def inputs(self) -> tuple[str, ...]: ...

    @property
    def kind(self) -> ChainKind: ...

    @property
    def seed(self) -> int: ...

    @property
    def max_age(self) -> float: ...

    @property
    def min_events(self) -> float | None: ...

    @property
    def max_label_weight(self) -> float: ...

    @property
    def relaxation_cells(self) -> int: ...

    @property
    def relaxation_lags(self) -> tuple[float, ...]: ...

    @property
    def collected(self) -> bool: ...

    def input_command(self) -> str: ...


@dataclass(frozen=True)
class LayerRequest:
    """What a kind's :meth:`~ChainKind.decision_layer` and :meth:`~ChainKind.exact_layer` are
    asked for: a layer over ``model`` on ``device`` in ``mode`` (``size``: the table's nodes per
    input, None: the default), stepping every ``dt`` s, a switch clock capped at ``max_age`` s,
    its cells starting as ``start`` says (``decision.initial``). A learned layer's ``dt`` and
    ``max_age`` are its fit's (:meth:`of_fit`)."""

    model: Model
    dt: float
    mode: str = "lookup"
    size: Sequence[int] | None = None
    device: torch.device = CPU
    max_age: float = 5.0
    start: str = "internal"

    @classmethod
    def of_fit(
        cls,
        model: Model,
        train: FitSettings,
        mode: str,
        size: Sequence[int] | None,
        device: torch.device,
        start: str = "internal",
    ) -> LayerRequest:
        """The request for the learned layer of the fit the train settings ``train`` (:class:`FitSettings`:
        the kinds sit below the stages) made: its ``dt`` and clock cap."""
        return cls(model, train.setup.dt, mode, size, device, train.max_age, start)


class ChainKind:
    """A kind of learned (or exact) chain: what the settings, train and simulate ask of it.

    The base gives the chain over phi's behaviour (psi is the whole chain: no fit or file of its
    own, psi's lookup table or classifier, the exact psi); a kind overrides what differs. The
    kinds are instances of the registered subclasses (:func:`register_chain_kind`), made by
    :func:`~surrogate.kinds.chains.chain_kind` only; compare them by their flags, never by their
    names.

    Example:
        >>> from surrogate.kinds import chain_kind
        >>> kind = chain_kind("phi", "age")
        >>> kind.clock, kind.classes, kind.history
        (True, False, 'age')
        >>> kind.fit_identity({"lumps": "phi", "history": "age", "max_age": 5.0, "bins": 200})
        {'history': 'age', 'max_age': 5.0, 'bins': 200}
    """

    #: the config's strings that select this kind: gp.lumps (decision.lumps), gp.history
    #: (decision.history) and the gp.class_moves it takes (an instance per value, :meth:`make`)
    lumps: ClassVar[str] = "phi"
    history: ClassVar[str] = "none"
    class_moves_choices: ClassVar[tuple[str, ...]] = ("learned",)
    #: the keys of the gp group that only this kind reads: the other kinds drop them from their
    #: fits' identities (so a fit keeps the identity it had before this kind existed)
    gp_keys: ClassVar[tuple[str, ...]] = ()
    #: the kind's name in messages (``gp.class_moves=relaxation is a K-lumps option``)
    title: ClassVar[str] = "two-state"
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
    #: how much the kind carries beyond phi, for the measured choice's ties (gp.choose: a
    #: candidate within the standard error of the best goes to the smallest): the two-state
    #: chain 0, the switch clock 1, K lumps 2; a new kind sets its own
    complexity: ClassVar[int] = 0
    #: the measured choice (gp.choose) fits and scores this kind with its :attr:`recipe`
    #: (``gp=<recipe>``) beside the shipped candidates: a registered kind joins by saying so
    candidate: ClassVar[bool] = False
    #: the fit identity's key and version of the kind's own fit method (a change refits), or
    #: None: the kind fits psi only
    law_version: ClassVar[tuple[str, int] | None] = None
    #: psi is the two-state chain's of the same collection and GP settings (the kind's own
    #: keys aside): train reuses that fit, or makes it where ``gp=svgp`` finds it, not a copy
    shares_psi: ClassVar[bool] = False

    @classmethod
    def make(cls, class_moves: str) -> ChainKind:
        """The kind's instance for ``gp.class_moves`` (one of :attr:`class_moves_choices`)."""
        return cls()

    @property
    def class_moves(self) -> str:
        """gp.class_moves: how the chain's class moves are fitted (a chain over phi: learned)."""
        return self.class_moves_choices[0]

    @property
    def relaxation(self) -> bool:
        """Whether the K-lumps chain's bins relax to their stationary law
        (gp.class_moves=relaxation)."""
        return False

    # the settings: the kind's refusals and the gp settings it fits

    @classmethod
    def check_fit(cls, history: str, internal: Any, model_name: str) -> None:
        """Refuse a fit asked for by this kind's ``gp.lumps`` with ``gp.history`` ``history`` over
        the model's ``internal`` model (``model_name`` for the message), before the kind is
        looked up (called on each kind whose :attr:`lumps` the config names)."""

    def configure(
        self,
        gp_config: Mapping[str, Any],
        gp: GPSettings,
        inputs: tuple[str, ...],
        internal: Any,
        model_name: str,
    ) -> tuple[GPSettings, tuple[str, ...]]:
        """The GP settings ``gp`` and the abstraction ``inputs`` as this kind fits them, from the
        gp group ``gp_config``, checked against the model's ``internal`` model (a chain over
        phi: as they are)."""
        return gp, inputs

    def input_warps(self, gp_config: Mapping[str, Any]) -> dict[str, float]:
        """The inputs psi reads on a log axis (name -> knee, s; :func:`~surrogate.gp.predictor.log_warp`)
        from the gp group ``gp_config`` (validated by :meth:`configure`): none for a chain over
        phi."""
        return {}

    def check_train(self, settings: FitSettings) -> None:
        """Refuse train ``settings`` this kind cannot fit, where the check reads more than the gp
        group (the model's ``dt``, the collection): called by the train stage's validation,
        before any work (a chain over phi: nothing to refuse)."""

    @classmethod
    def check_exact_history(cls, mode: DecisionMode, internal: Any, model_name: str) -> None:
        """Refuse ``decision=exact`` with this kind's ``decision.history`` in ``mode`` over the
        model's ``internal`` model (called on each kind whose :attr:`history` the config names)."""

    @classmethod
    def check_exact(cls, history: str, mode: DecisionMode, internal: Any, model_name: str) -> None:
        """Refuse ``decision=exact`` with this kind's ``decision.lumps`` and ``history`` in
        ``mode`` over the model's ``internal`` model (called on each kind whose :attr:`lumps`
        the config names)."""

    @classmethod
    def candidate_variants(cls, gp: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
        """More candidates of this kind the measured choice scores beside its recipe's group
        ``gp`` (as the clock is scored at several caps): name -> gp group; none by default."""
        return {}

    def fit_identity(
        self,
        gp: Mapping[str, Any],
        min_events: float | None = None,
        max_label_weight: float = DEFAULT_MAX_LABEL_WEIGHT,
        relaxation_cells: int = DEFAULT_CELLS,
        relaxation_lags: Sequence[float] = DEFAULT_LAGS,
    ) -> dict[str, Any]:
        """The gp part of a fit's identity from the fit's gp keys ``gp``: the keys only other
        kinds read (their :attr:`gp_keys`) are dropped, so each fit keeps the identity (and the
        directory) it had before those kinds existed; the kind's own and the strings that select
        it (where they are not the chain over phi's) are kept, with the kind's
        :attr:`law_version`. The K-lumps options are read by
        :class:`~surrogate.kinds.klumps.KLumps` only."""
        # the strings that select a kind other than the chain over phi stay: two kinds' fits
        # never share an identity
        own = {*self.gp_keys, *(a for a in ("lumps", "history")
                                if getattr(self, a) != getattr(ChainKind, a))}  # fmt: skip
        drop = kind_gp_keys() - own
        if gp.get("mean", DEFAULT_MEAN) == DEFAULT_MEAN:  # fits before gp.mean keep theirs
            drop.add("mean")
        if gp.get("optimizer", "adam") == "adam":  # fits before gp.optimizer keep theirs
            drop.add("optimizer")
        if gp.get("jump_rows", JUMP_ROWS[0]) == JUMP_ROWS[0]:  # and before gp.jump_rows
            drop.add("jump_rows")
        out = {k: v for k, v in gp.items() if k not in drop}
        if self.law_version is not None:
            out[self.law_version[0]] = self.law_version[1]
        return out

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
        self, settings: FitSettings, table: pd.DataFrame, domain: Mapping[str, tuple[float, float]]
    ) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """What the kind fits beyond the classifiers psi, which train fits first for every kind
        (over their ``domain``), from the train settings ``settings`` and the transitions
        ``table``: its artefact's state and its metrics, or None (a chain over phi: psi is the
        whole chain)."""
        return None

    def fit_given_psi(
        self, settings: FitSettings, table: pd.DataFrame, psi: PsiClassifier
    ) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """What train asks for once ``psi`` is fitted: :meth:`fit` over psi's domain; a kind
        that reads psi itself (the hidden phases match their means to it) overrides this."""
        return self.fit(settings, table, psi.domain)

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
        self, request: LayerRequest, directory: Path
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The learned chain of the fit ``directory`` as the decision layer ``request`` asks for
        (:meth:`LayerRequest.of_fit`), and facts about it for the manifest: psi's lookup table
        or the classifier itself (:func:`abstract_decision`; a chain over phi starts its cells
        from the internal model, ``request.start`` is checked to say so)."""
        psi, _ = load_psi(Path(directory) / PSI, device=request.device)
        return abstract_decision(request.model, psi, request.mode, request.size, request.device)

    # what the measured choice asks of the kind (surrogate.kinds.scoring)

    def window_log_likelihoods(
        self, layer: DecisionLayer, inputs: Tensor, phi: Tensor, dt: float
    ) -> Tensor:
        """The log-likelihood of each window's phi given the sequence before it and the
        inputs, under this kind's ``layer`` (its :meth:`decision_layer`): the terms whose sum
        is :meth:`sequence_log_likelihood`. The measured choice sums those after each
        sequence's first switch (``gp.choice.likelihood_from``).

        Args:
            layer: the kind's decision layer.
            inputs: ``n x T x d`` the model's inputs (``internal.input_names``) in each window.
            phi: ``n x (T + 1)`` phi (0/1) before the first window and after each.
            dt: the window (s).

        Returns:
            ``n x T`` float64: log p(phi_t+1 | phi_0..phi_t, inputs) for each window ``t``.

        Raises:
            NotImplementedError: the kind has no likelihood of phi sequences (each kind gives
                its own; the measured choice cannot score it).
        """
        raise NotImplementedError(
            f"the {self.title} chain ({type(self).__name__}) gives no log-likelihood of phi "
            f"sequences (window_log_likelihoods): the measured choice cannot score it"
        )

    def marginal_window_log_likelihoods(
        self,
        layer: DecisionLayer,
        inputs: Tensor,
        phi: Tensor,
        dt: float,
        ranked: Tensor | None = None,
    ) -> Tensor:
        """:meth:`window_log_likelihoods` with the kind's state before each sequence (what
        the record does not show) marginalised over its stationary law at the first inputs
        within the first phi's lump: the same terms for a kind whose likelihood starts there
        already (the two-state chain has no such state; K lumps and the hidden phases start
        from that law); a kind that starts otherwise overrides it (the switch clock, read
        settled at its cap as its layer starts a run). The measured choice's added clocks
        follow this score (a longer cap's guess of an unknown past is no memory). ``ranked``:
        the :meth:`window_log_likelihoods` already computed, not computed again."""
        return ranked if ranked is not None else self.window_log_likelihoods(layer, inputs, phi, dt)

    def sequence_log_likelihood(
        self, layer: DecisionLayer, inputs: Tensor, phi: Tensor, dt: float
    ) -> Tensor:
        """Each sequence's log p(phi_1..T | phi_0, inputs) (``(n,)`` float64): the sum of its
        :meth:`window_log_likelihoods`."""
        return self.window_log_likelihoods(layer, inputs, phi, dt).sum(1)

    def start_sequences(self, layer: DecisionLayer, x0: Tensor, phi0: Tensor) -> None:
        """Put ``layer`` where sequences that start in ``phi0`` (``(n,)``) at the inputs ``x0``
        (``n x d``) begin, before it is stepped from ``phi0`` (the measured choice's simulated
        durations): its own start (a clock starts settled, as it does in a run), without
        the internal model's draw of phi where the layer can skip it
        (:meth:`AbstractDecision.start_at`)."""
        if isinstance(layer, AbstractDecision):
            layer.start_at(x0, phi0)
        else:
            layer.initialize(x0)

    def exact_layer(self, request: LayerRequest) -> tuple[DecisionLayer, dict[str, Any]]:
        """The chain driven by the model's exact law (decision=exact, checked by
        :meth:`check_exact_history` and :meth:`check_exact`) as the layer ``request`` asks for;
        and facts about it for the manifest (:func:`exact_decision`)."""
        return exact_decision(request.model, request.dt, request.mode, request.size,
                              request.device)  # fmt: skip


def bernoulli_log_likelihood(p: Tensor, phi_next: Tensor) -> Tensor:
    """log P(phi' = ``phi_next``) for p(phi' = 1) = ``p`` (any shape, float64), the
    probabilities clamped away from 0 and 1 (a table's rounding must not give -inf)."""
    q = p.to(torch.float64).clamp(PROBABILITY_FLOOR, 1.0 - PROBABILITY_FLOOR)
    return torch.where(phi_next.bool(), q.log(), (-q).log1p())


#: the smallest probability a likelihood reads (a float32 table's rounding of 0 or 1)
PROBABILITY_FLOOR = 1e-12


#: the registered chain kinds, in the order their modules were imported
CHAIN_KINDS: list[type[ChainKind]] = []

K = TypeVar("K", bound=type[ChainKind])


def register_chain_kind(cls: K) -> K:
    """Register the chain kind ``cls`` (a class decorator): :func:`~surrogate.kinds.chains.
    chain_kind` selects it by its config strings (:attr:`ChainKind.lumps`,
    :attr:`~ChainKind.history`, :attr:`~ChainKind.class_moves_choices`), and the settings'
    messages list them.

    Raises:
        ValueError: another registered kind is selected by the same strings, or one of its
            :attr:`~ChainKind.gp_keys` is a key every fit reads (a GP hyperparameter,
            :data:`FIT_GP_KEYS`) or another kind's.
    """
    # a kind's keys are dropped from every other kind's fit (its hyperparameters and identity):
    # a shared key would change what the other kinds fit, and keep their directories
    shared_keys = {f.name for f in fields(GPSettings)} | set(FIT_GP_KEYS)
    for key in cls.gp_keys:
        owner = [o.__name__ for o in CHAIN_KINDS if o is not cls and key in o.gp_keys]
        if key in shared_keys or owner:
            whose = f"{owner[0]}'s" if owner else "read by every fit"
            raise ValueError(
                f"chain kind {cls.__name__}: gp_keys names gp.{key}, which is {whose}; a kind's "
                f"gp_keys are dropped from the other kinds' fits, so they must be its own: "
                f"read gp.{key} without claiming it, or give the kind a key of its own"
            )
    for other in CHAIN_KINDS:
        shared = set(other.class_moves_choices) & set(cls.class_moves_choices)
        if (other.lumps, other.history) == (cls.lumps, cls.history) and shared and other is not cls:
            raise ValueError(
                f"chain kinds {other.__name__} and {cls.__name__} are both selected by "
                f"lumps={cls.lumps!r}, history={cls.history!r}, class_moves={sorted(shared)}"
            )
    if cls not in CHAIN_KINDS:
        CHAIN_KINDS.append(cls)
    return cls


def kind_values(attribute: str) -> list[str]:
    """The config values that select a registered kind for ``attribute`` (``lumps``,
    ``history`` or ``class_moves_choices``): the base's (the chain over phi's) first, then the
    others in alphabetical order (not as registered: a test that imports one kind's module
    first would register it first, and the messages would change with the tests run)."""
    default = getattr(ChainKind, attribute)
    out: list[str] = list(default) if isinstance(default, tuple) else [default]
    others: set[str] = set()
    for kind in CHAIN_KINDS:
        value = getattr(kind, attribute)
        others.update(v for v in (value if isinstance(value, tuple) else (value,)) if v not in out)
    return out + sorted(others)


def kinds_with(**strings: str) -> list[type[ChainKind]]:
    """The registered kinds whose config strings are ``strings`` (``lumps=...``,
    ``history=...``)."""
    return [k for k in CHAIN_KINDS if all(getattr(k, a) == v for a, v in strings.items())]


def kind_gp_keys() -> set[str]:
    """The keys of the gp group that the registered kinds read (their :attr:`~ChainKind.gp_keys`):
    no GP hyperparameters."""
    return {k for kind in CHAIN_KINDS for k in kind.gp_keys}


_MADE: dict[tuple[type[ChainKind], str], ChainKind] = {}


def find_kind(lumps: str, history: str, class_moves: str) -> ChainKind | None:
    """The registered kind the config's strings select (one instance per kind and
    ``class_moves``), or None."""
    for cls in kinds_with(lumps=lumps, history=history):
        if class_moves in cls.class_moves_choices:
            if (cls, class_moves) not in _MADE:
                _MADE[cls, class_moves] = cls.make(class_moves)
            return _MADE[cls, class_moves]
    return None

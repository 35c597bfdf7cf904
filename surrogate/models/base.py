"""The seams of a multi-scale agent model, as the generic engine sees them.

An agent model has two layers (paper, Section 2.2):

* an :class:`InternalModel`: the agent's internal stochastic network (a reaction network on
  :mod:`surrogate.ctmc`), run for one window dt per step with its rates fixed by the inputs ``x``
  the body hands it, and read out as one boolean property phi (e.g. RUN) of its state;
* an :class:`AgentBody`: the agent's outer state (position, heading, slow processes such as
  methylation), the inputs it hands the internal model from the field and its own state, how
  phi moves it, what is observed of it, and how it is perturbed when training data is collected.

A :class:`Model` bundles the two with the model's own checks and evaluation hooks; the ``model``
config group selects one by ``_target_``. Engine code (:mod:`surrogate.simulate`,
:mod:`surrogate.gp`, the stages) only uses these protocols.

Conventions: cells live in the batch dimension; ``x`` is ``n x d`` float32 in the order of
``input_names``; phi travels as float 0/1 inside pure (fusable) functions, because compiled CPU
kernels handle boolean tensors with scalar loops. A *pure* function takes its random numbers as
arguments (drawn by the simulator in bulk, see :class:`Randoms`), never synchronises with the
host and never mutates its inputs, so the simulator can fuse a whole step into one function and
``torch.compile`` it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from surrogate.errors import ConfigError, KernelUnsupported
from surrogate.fields import Field
from surrogate.models.capabilities import (
    InternalState,
    cell_step_seconds_of,
    feature_names_of,
    features_fn_of,
)
from surrogate.models.packed import PackedDecision
from surrogate.models.randoms import Randoms
from surrogate.validation import known_keys, yaml_hint

#: seconds per cell and step assumed for a full model that gives no estimate of its own, and
#: for a two-state chain (abstraction or exact psi): the E. coli step's order (the numba kernel
#: measured 0.16-0.22 us per cell-step at 100 cells, the torch step ~1 us at 1e4 cells)
CELL_STEP_SECONDS = 1e-6
#: the default collection for a model whose full step costs at most CHEAP_CELL_STEP_SECONDS
#: per cell (E. coli): 100,000 transitions per origin from 2,000 cells, every 10th window
CHEAP_COLLECTION: dict[str, int] = {"n_per_state": 100_000, "n_cells": 2_000, "record_every": 10}
CHEAP_CELL_STEP_SECONDS = 1e-4
#: ... and for a costlier one (an SBML network with ~1e4 events per window, e.g. the phospho
#: network at ~0.5 ms per cell-step: ~5 minutes of collection on one core)
COSTLY_COLLECTION: dict[str, int] = {"n_per_state": 10_000, "n_cells": 500, "record_every": 5}
#: the default perturbation of a collection: jumps per second per cell and the seconds after a
#: jump without records (E. coli's: ~3 motor relaxation times); a network whose hidden state
#: settles more slowly after a jump sets its own (an SBML yaml's ``collect``)
COLLECT_PERTURBATION: dict[str, float] = {"perturb_rate": 0.1, "blackout_time": 1.0}

#: the body's outer state: named per-cell tensors, cells in dimension 0
BodyState = dict[str, Tensor]


class CellKernel(Protocol):
    """A model's compiled step over many steps per call (see :meth:`Model.cell_kernel`)."""

    def advance(self, state: Any, ended: Tensor, u: Tensor, u64: Tensor | None, z: Tensor) -> None:
        """Advance ``state`` (a ``PopulationState``) by ``ended.shape[0]`` steps in place,
        writing each step's ended segment lengths into ``ended`` (``steps x n`` int32), with
        the steps' random numbers ``u``/``u64``/``z`` (``steps x rows x n``) laid out as the
        simulator's torch step takes them."""
        ...

    def warm_up(self, state: Any) -> None:
        """Compile (or load from the cache) without changing ``state``."""
        ...


@runtime_checkable
class InternalModel(Protocol):
    """The internal layer of one agent type, batched over cells.

    Attributes:
        input_names: names of the columns of ``x`` (what the body hands in each step).
        feature_names: names of derived inputs :meth:`features` can compute from ``x`` (e.g. the
            signal the network's rates actually depend on); may be empty.
        signal_names: the features through which ``x`` enters the network's rates (a subset of
            ``input_names + feature_names``): the exact psi, and the default abstraction, are
            functions of these alone.
        lump_names: names of phi = 0 and phi = 1, e.g. ``("tumble", "run")``.
        randoms: what :meth:`fused_advance` needs per window.
        fusable: whether :meth:`fused_advance` exists (a pure window); an SSA with a
            data-dependent number of events is not.
    """

    # read-only for the engine: a plain attribute or a property satisfies each (a class attribute
    # may be narrower, e.g. tuple[str, str])
    @property
    def input_names(self) -> tuple[str, ...]: ...
    @property
    def feature_names(self) -> tuple[str, ...]: ...
    @property
    def signal_names(self) -> tuple[str, ...]: ...
    @property
    def lump_names(self) -> tuple[str, str]: ...
    @property
    def randoms(self) -> Randoms: ...
    @property
    def fusable(self) -> bool: ...

    def features(self, x: Tensor, names: Sequence[str]) -> Tensor:
        """Inputs or derived features ``names`` at inputs ``x`` (``n x d``) -> ``n x len(names)``."""
        ...

    def initial_state(self, x: Tensor) -> InternalState:
        """A state drawn from the network's stationary law at fixed inputs ``x`` (``n x d``)."""
        ...

    def advance(self, state: InternalState, x: Tensor, dt: float) -> InternalState:
        """The exact state after a window ``dt`` with inputs ``x`` held fixed (own RNG)."""
        ...

    def fused_advance(
        self, state: InternalState, x: Tensor, dt: float, u: Tensor, u64: Tensor | None
    ) -> tuple[InternalState, tuple[Tensor, ...]]:
        """Pure form of :meth:`advance`: ``u`` (``uniform x n``), ``u64`` (``uniform64 x n``).

        Returns the next state and auxiliary tensors (intermediates returned only so that a
        compiled step materialises them once; the simulator drops them).
        """
        ...

    def phi(self, state: InternalState) -> Tensor:
        """The property of each cell's state as float 0/1 ``(n,)``."""
        ...

    def concat_states(self, states: Sequence[InternalState]) -> InternalState:
        """Several populations' states as one, cells in order (for replicates in one batch).
        Optional: the engine's default concatenates each tensor along cells."""
        ...

    @property
    def exact_psi(self) -> Callable[[Tensor, float], Tensor] | None:
        """``exact_psi(signal, dt)``: exact lumped ``P(phi' = 1 | phi)`` ``n x 2`` at signals
        ``signal`` (``n x k``, in the order of ``signal_names``). Optional: a model gives it as
        a method, or leaves it out or sets (or returns, from a property) None."""
        ...

    # Optional, read only through surrogate.models.capabilities (which lists them all, with the
    # engine's defaults): feature_names/features, concat_states, fusable/fused_advance/randoms,
    # exact_psi, exact_age_psi(signal, dt, max_steps), signal_bounds ({signal: (lo, hi)}),
    # expected_phi_next(state, x, dt) -> (n,) float (P(phi = 1 after a window dt | this state,
    # inputs x), the window's expected label: collect.expected_labels, gp.labels=auto) and
    # cell_step_seconds(dt).


class Perturbation(Protocol):
    """How collect moves cells off their steady state (paper: "sporadic perturbation")."""

    def start(self, n_cells: int, device: torch.device) -> Tensor:
        """Where ``n_cells`` cells start when collecting (e.g. positions ``n x 2``)."""
        ...

    def apply(self, state: BodyState, mask: Tensor) -> BodyState:
        """Perturb the cells where ``mask`` (bool ``(n,)``) is true; return the new state."""
        ...


@runtime_checkable
class AgentBody(Protocol):
    """The outer layer of one agent type, batched over cells.

    Attributes:
        observable_names: what evaluation compares between models at record times, e.g.
            ``("distance",)``.
        randoms: what :meth:`move` needs per step.
        adapt_randoms: what :meth:`adapt` needs per step.

    Optional: ``histogram_grids``, ``{observable: (lo, hi, width)}`` for the recorded
    histograms (read through :func:`surrogate.models.capabilities.histogram_grids_of`; an
    observable without one gets a grid around its first recorded values).
    """

    @property
    def observable_names(self) -> tuple[str, ...]: ...
    @property
    def randoms(self) -> Randoms: ...
    @property
    def adapt_randoms(self) -> Randoms: ...

    def initial_state(self, n_cells: int, start: Tensor, field: Field, dt: float) -> BodyState:
        """``n_cells`` bodies at ``start`` (what :meth:`Perturbation.start` or the user gives),
        their slow internal processes drawn from their stationary law there (own RNG)."""
        ...

    def inputs(self, state: BodyState, field: Field, t: float) -> Tensor:
        """Pure: the inputs ``x`` (``n x d``) handed to the internal model at time ``t``."""
        ...

    def adapt(self, state: BodyState, x: Tensor, dt: float, u: Tensor, z: Tensor) -> BodyState:
        """Pure: one step of the body's slow internal processes at inputs ``x`` without moving
        (the only dynamics while the population equilibrates before cells move)."""
        ...

    def move(
        self,
        state: BodyState,
        phi_before: Tensor,
        phi_after: Tensor,
        x: Tensor,
        dt: float,
        u: Tensor,
        z: Tensor,
        extra: Tensor | None,
    ) -> BodyState:
        """Pure: one step of movement driven by phi (float 0/1 before and after the window) and
        the slow internal processes; ``u``/``z`` hold :attr:`randoms`' rows, ``extra`` what
        :meth:`sample_extra` drew (or None)."""
        ...

    def sample_extra(self, n_cells: int, device: torch.device) -> Tensor | None:
        """Random numbers :attr:`randoms` cannot express (e.g. non-integer Gamma angles), or None."""
        ...

    def observables(self, state: BodyState, field: Field) -> dict[str, Tensor]:
        """The observables ``(n,)`` of each cell, keyed by :attr:`observable_names`."""
        ...

    def check_inputs(self, x: Tensor) -> str | None:
        """A description of what is wrong with inputs ``x`` (e.g. negative concentrations), or
        None. Called at record times only (it synchronises with the host)."""
        ...

    def perturbation(self, field: Field, options: Mapping[str, Any]) -> Perturbation:
        """The perturbation collect uses, built from the model's ``perturbation`` options."""
        ...


class Model:
    """An agent model: an internal model, a body, and the model's checks and report hooks.

    Subclasses set :attr:`name`, :attr:`internal`, :attr:`body` and :attr:`perturbation_options`
    and may override the hooks. A model is selected by the ``model`` config group's ``_target_``
    (any callable returning a :class:`Model`), e.g. ``conf/model/ecoli.yaml``.
    """

    name: str = "model"
    internal: InternalModel
    body: AgentBody
    perturbation_options: Mapping[str, Any] = {}
    #: where the config sets :attr:`perturbation_options` (``model.perturbation``), for advice
    #: that changes them (:meth:`wider_collection`); None: nowhere a user can set
    perturbation_key: str | None = None

    #: the abstraction's default inputs (``gp.inputs=signal``): the internal model's signal
    default_abstraction_inputs: str = "signal"

    def cell_step_seconds(
        self, dt: float, full: bool = True, device: torch.device | str = "cpu"
    ) -> float:
        """Estimated wall time of one cell and step (s) under the full model (``full``,
        ``decision=full``: the internal model's own estimate on ``device``,
        ``cell_step_seconds(dt)``, where it gives one) or a chain (``full=False``; the chains
        and models without an estimate: :data:`CELL_STEP_SECONDS`). The stages multiply it by
        steps and cells to say, before they start, what a run will cost: an order of magnitude
        to refuse absurd runs by, with no accuracy guarantee (:mod:`surrogate.diagnosis.cost`)."""
        estimate = cell_step_seconds_of(self.internal, device)
        if full and estimate is not None:
            return float(estimate(dt))
        return CELL_STEP_SECONDS

    def wider_collection(self, factor: float = 2.0) -> tuple[str, ...]:
        """The overrides that send collect's perturbation ``factor`` times as far from the
        field's peak (its jumps' ``radius``): a collection of the inputs that cells further out
        read; empty where the model names no radius a user can set.

        Example:
            >>> m = Model()
            >>> m.perturbation_options, m.perturbation_key = {"radius": 3.0}, "model.perturbation"
            >>> m.wider_collection()
            ('++model.perturbation.radius=6',)
        """
        radius = self.perturbation_options.get("radius")
        if (self.perturbation_key is None or isinstance(radius, bool)
                or not isinstance(radius, int | float) or not radius > 0):  # fmt: skip
            return ()
        return (f"++{self.perturbation_key}.radius={factor * float(radius):g}",)

    def collect_defaults(self, dt: float) -> dict[str, float]:
        """The default collection budget (``n_per_state``, ``n_cells``, ``record_every``) and
        perturbation (``perturb_rate``, ``blackout_time``), used where the collect settings
        leave them null: :data:`CHEAP_COLLECTION` for a model whose full step costs at most
        :data:`CHEAP_CELL_STEP_SECONDS` per cell, else :data:`COSTLY_COLLECTION`, with
        :data:`COLLECT_PERTURBATION`. A model may override it with figures of its own."""
        cheap = self.cell_step_seconds(dt) <= CHEAP_CELL_STEP_SECONDS
        return {**(CHEAP_COLLECTION if cheap else COSTLY_COLLECTION), **COLLECT_PERTURBATION}

    def sources(self) -> dict[str, str]:
        """Digests of the files the model is read from beyond its config (e.g. an SBML file or
        a yaml spec), by role: part of every artefact's identity, so editing a file never
        reuses artefacts of its old content. The base model reads none."""
        return {}

    def full_model_identity(self, config: Mapping[str, Any]) -> dict[str, Any]:
        """What defines the full model's law, from the model's ``config``: a stored full-model
        reference's model identity (:mod:`surrogate.stages.reference`). The config and
        :meth:`sources`; a model whose config or files also carry abstraction-only settings
        (classes, a collection budget) leaves them out, so changing those keeps its reference."""
        sources = self.sources()
        return {"model": config, **({"model_sources": sources} if sources else {})}

    def rows_identity(self, config: Mapping[str, Any]) -> dict[str, Any]:
        """What defines a collection's rows where they store the count the model's classes
        bin (:func:`~surrogate.models.capabilities.class_count_of`), from the model's
        ``config``: the bins are applied when the rows are read, so a model whose config or
        files carry them leaves them out (the count stays). The config and :meth:`sources`."""
        sources = self.sources()
        return {"model": config, **({"model_sources": sources} if sources else {})}

    def validate(self, dt: float) -> None:
        """Refuse a time step this model cannot be simulated with (ConfigError naming why)."""

    def abstraction_inputs(self, choice: str | Sequence[str] | None) -> tuple[str, ...]:
        """The input columns of the abstraction: ``"signal"`` (the internal model's signal),
        ``"inputs"`` (the raw inputs the body hands in, the paper's choice), or explicit names."""
        internal = self.internal
        choice = self.default_abstraction_inputs if choice is None else choice
        if isinstance(choice, str):
            if choice == "signal":
                return tuple(internal.signal_names)
            if choice == "inputs":
                return tuple(internal.input_names)
            choice = [choice]
        names = tuple(str(c) for c in choice)
        features = feature_names_of(internal)
        known = (*internal.input_names, *features)
        unknown = [n for n in names if n not in known]
        if unknown or not names:
            raise ConfigError(
                f"gp.inputs: {list(names)} - model {self.name!r} provides inputs "
                f"{list(internal.input_names)} and features {list(features)}; use "
                f"one or more of those, 'signal' or 'inputs'"
            )
        return names

    def cell_kernel(self, decision: PackedDecision, field: Field, dt: float) -> CellKernel:
        """The model's compiled per-cell kernel for this decision layer and field (the
        simulator's ``backend=numba``): many steps per call, the same random numbers as the
        torch step. ``decision`` is the simulator's layer as the engine packed it (plain
        arrays, :mod:`surrogate.models.packed`); a kernel never reads the engine's classes.
        Raises :class:`KernelUnsupported` (naming what) where it has none; the base model has
        none."""
        raise KernelUnsupported(f"model {self.name!r} (it has no compiled per-cell step)")

    def kernel_precompiler(self) -> str | None:
        """``"module:function"`` of a zero-argument function that compiles this model's
        per-cell kernel into its on-disk cache, or None when there is nothing to compile (no
        kernel, or it is cached already). Stages run it in a background process
        (:func:`surrogate.simulate.precompile.precompile_in_background`) while they collect and
        train; the base model has no kernel."""
        return None

    def featurizer(self, names: Sequence[str]) -> Callable[[Tensor], Tensor]:
        """``x (n x d) -> z (n x len(names))``: the columns an abstraction over ``names`` needs."""
        return FeatureMap(self.internal, self.abstraction_inputs(list(names)))

    # ---- evaluation hooks ------------------------------------------------------------------
    def observable_label(self, name: str) -> str:
        """Axis label of an observable in figures."""
        return name

    def reference_table(self) -> Any:
        """A published table to print beside ours (e.g. the paper's Table 1), or None."""
        return None

    def describe(self) -> str:
        """One line on the model for reports."""
        return self.name

    def to_config(self) -> dict[str, Any]:
        """Plain description for manifests (the resolved config is recorded separately)."""
        return {"name": self.name}


class FeatureMap:
    """``x (n x d) -> z (n x k)``: the columns ``names`` of an internal model's inputs and
    features (the inputs themselves when ``names`` are its inputs).

    Two maps are equal when they compute the same columns of the same internal model, so
    decision layers over equal maps can share one evaluation (see ``simulate.batch``).
    """

    def __init__(self, internal: InternalModel, names: Sequence[str]) -> None:
        self.internal = internal
        self.names = tuple(names)
        self._identity = self.names == tuple(internal.input_names)
        self._features = features_fn_of(internal)

    def __call__(self, x: Tensor) -> Tensor:
        """The columns ``names`` at inputs ``x`` (``n x d``)."""
        return x if self._identity else self._features(x, self.names)

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, FeatureMap)
            and other.internal is self.internal
            and other.names == self.names
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"FeatureMap({list(self.names)})"


def check_options(
    options: Mapping[str, Any], allowed: Mapping[str, Any], where: str
) -> dict[str, Any]:
    """Merge ``options`` over ``allowed`` defaults, refusing unknown keys (and anything but a
    mapping, e.g. a bare number) by name."""
    return {**allowed, **known_keys(options, sorted(allowed), where)}


def burn_in_seconds(value: Any, name: str = "model.burn_in") -> float:
    """A burn-in duration: a finite number of seconds >= 0, else a ConfigError naming
    ``name`` (a negative one would silently mean none)."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value < 0
    ):
        raise ConfigError(f"{name} must be a finite number of seconds >= 0, got {value!r}"
                          f"{yaml_hint(value)}")  # fmt: skip
    return float(value)


__all__ = [
    "CELL_STEP_SECONDS",
    "CHEAP_COLLECTION",
    "COLLECT_PERTURBATION",
    "COSTLY_COLLECTION",
    "AgentBody",
    "BodyState",
    "CellKernel",
    "FeatureMap",
    "InternalModel",
    "InternalState",
    "KernelUnsupported",
    "Model",
    "Perturbation",
    "Randoms",
    "burn_in_seconds",
    "check_options",
]

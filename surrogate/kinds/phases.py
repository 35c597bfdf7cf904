"""Hidden phases (``gp.lumps=phases``) as one kind module: a chain whose states are each lump's
hidden phases, learned from phi sequences with no species named by the user
(:mod:`surrogate.gp.phases`). Its fit simulates its own sample (an unperturbed full-model
population where collect starts its cells, every window recorded:
:func:`~surrogate.simulate.transitions.record_occupancy`), chooses each lump's phase count by
held-out likelihood (or fits ``gp.phases.max_per_lump`` in every lump,
``gp.phases.counts=max``), and tabulates the law over the abstraction's inputs, each lump's
mean sojourn matched to psi's at every node (``gp.phases.means``); its layer
(:class:`~surrogate.simulate.phases.PhaseDecision`) keeps one hidden state per cell."""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from torch import Tensor

from surrogate.config import seed_everything
from surrogate.errors import ArtefactError, ConfigError
from surrogate.gp.phases import (
    STRUCTURES,
    PhaseFitSettings,
    PhaseLaw,
    PhaseSelection,
    grid_points,
    held_out_split,
    input_grid,
    match_leaving,
    select_phases,
    stationary_leaving,
    window_log_likelihoods,
)
from surrogate.gp.predictor import PsiClassifier
from surrogate.gp.training import GPSettings
from surrogate.io import load_tensors, save_tensors
from surrogate.kinds.base import ChainKind, FitSettings, LayerRequest, register_chain_kind
from surrogate.kinds.decision import DecisionMode
from surrogate.kinds.files import PHASE_CHAIN
from surrogate.simulate.classes import STARTS, ClassTable
from surrogate.simulate.decision import DecisionLayer, FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.phases import PhaseDecision
from surrogate.simulate.sequences import phi_sequences
from surrogate.simulate.transitions import record_occupancy
from surrogate.validation import known_keys

log = logging.getLogger(__name__)

#: keys of the gp group that only a fit of the hidden-phase chain reads (gp.lumps=phases)
GP_PHASES = ("phases",)
#: gp.phases' keys (conf/gp/phases.yaml holds their defaults)
PHASE_KEYS = ("max_per_lump", "counts", "per_lump", "structure", "bumps", "penalty", "nodes",
              "max_iterations", "n_cells", "t_end", "held_out", "means")  # fmt: skip
#: gp.phases.counts: ``max_per_lump`` phases in every lump, or counts chosen by held-out
#: likelihood from one per lump (a phase kept where its gain exceeds twice its standard error)
COUNTS = ("max", "held_out")
#: gp.phases.means: each lump's mean sojourn at each input from psi (the sequences' law
#: matched to it, :func:`~surrogate.gp.phases.match_leaving`) or from the sequences alone
MEANS = ("psi", "sequences")
#: the sequences' seed is the fit's plus this (its cells are not collect's first cells)
SEQUENCE_SEED_OFFSET = 2_000_003
#: a change in the fit's method refits (the fit identity carries it); 2: the table's means
#: matched to psi (gp.phases.means); 3: L-BFGS stops at a change of 1e-9 per window, not 1e-12
PHASE_LAW_VERSION = 3
#: the most entries (S x nodes^d x S) of the tabulated law: 2^28, 1 GiB as float32
MAX_TABLE_ENTRIES = 2**28


def _count(options: Mapping[str, Any], key: str, minimum: int) -> int:
    value = options[key]
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"gp.phases.{key} must be an integer >= {minimum}, got {value!r}")
    return value


def _number(options: Mapping[str, Any], key: str, low: float, high: float = math.inf) -> float:
    value = options[key]
    if (isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value)
            or not low <= value < high):  # fmt: skip
        raise ConfigError(f"gp.phases.{key} must be a number in [{low:g}, {high:g}), got "
                          f"{value!r}")  # fmt: skip
    return float(value)


@dataclass(frozen=True)
class PhaseSettings:
    """``gp.phases`` validated: the phase counts (``per_lump`` fixed; else ``max_per_lump`` in
    every lump with ``counts: max``, or chosen up to it by held-out likelihood on the
    ``held_out`` share of cells with ``counts: held_out``: ``per_lump`` None), the moves
    (``structure``), the fit's settings, the sample (``n_cells`` cells for ``t_end`` s) and
    where each lump's mean sojourn comes from (``means``, one of :data:`MEANS`)."""

    max_per_lump: int
    per_lump: tuple[int, int] | None
    structure: str
    fit: PhaseFitSettings
    n_cells: int
    t_end: float
    held_out: float
    means: str = "psi"

    @classmethod
    def from_config(cls, value: Any) -> PhaseSettings:
        """Validate ``gp.phases`` (every key required: conf/gp/phases.yaml gives them).

        Raises:
            ConfigError: a key missing, unknown or out of range, named.
        """
        if value is None:
            raise ConfigError("gp.phases is required with gp.lumps=phases: use gp=phases")
        options = known_keys(value, PHASE_KEYS, "gp.phases", required=PHASE_KEYS)
        per_lump = options["per_lump"]
        if per_lump is not None:
            if (isinstance(per_lump, str) or not isinstance(per_lump, Sequence)
                    or len(per_lump) != 2
                    or any(isinstance(k, bool) or not isinstance(k, int) or k < 1
                           for k in per_lump)):  # fmt: skip
                raise ConfigError(f"gp.phases.per_lump must be null or two integers >= 1 (the "
                                  f"phases of each lump), got {per_lump!r}")  # fmt: skip
            per_lump = (int(per_lump[0]), int(per_lump[1]))
        if options["counts"] not in COUNTS:
            raise ConfigError(f"gp.phases.counts must be one of {list(COUNTS)}, got "
                              f"{options['counts']!r}")  # fmt: skip
        max_per_lump = _count(options, "max_per_lump", 1)
        if per_lump is None and options["counts"] == "max":
            # the held-out likelihood can miss a slow lump's tail: docs/kinds.md, "Phase counts"
            per_lump = (max_per_lump, max_per_lump)
        if options["means"] not in MEANS:
            raise ConfigError(f"gp.phases.means must be one of {list(MEANS)}, got "
                              f"{options['means']!r}")  # fmt: skip
        if options["structure"] not in STRUCTURES:
            raise ConfigError(f"gp.phases.structure must be one of {list(STRUCTURES)}, got "
                              f"{options['structure']!r}")  # fmt: skip
        fit = PhaseFitSettings(bumps=_count(options, "bumps", 0),
                               penalty=_number(options, "penalty", 0.0),
                               nodes=_count(options, "nodes", 2),
                               max_iterations=_count(options, "max_iterations", 1))  # fmt: skip
        t_end = _number(options, "t_end", 0.0)
        if t_end <= 0:
            raise ConfigError(f"gp.phases.t_end must be positive, got {t_end!r}")
        held_out = _number(options, "held_out", 0.0, 1.0)
        if held_out <= 0:
            raise ConfigError("gp.phases.held_out must be in (0, 1): the phase counts are "
                              "chosen on held-out cells")  # fmt: skip
        n_cells = _count(options, "n_cells", 4)
        if min(held_out_split(n_cells, held_out)) < 2:
            # one held-out cell gives the paired gain no standard error: any gain adds a phase
            raise ConfigError(
                f"gp.phases.n_cells={n_cells} with gp.phases.held_out={held_out:g} leaves "
                f"{held_out_split(n_cells, held_out)} (held-out, fitted) cells; the phase counts "
                f"need >= 2 on either side: use gp.phases.n_cells="
                f"{smallest_split(held_out)} or more"
            )
        return cls(max_per_lump, per_lump, str(options["structure"]), fit,
                   n_cells, t_end, held_out, str(options["means"]))  # fmt: skip

    def states(self) -> int:
        """The most hidden states the chain may get (both lumps' phases)."""
        return sum(self.per_lump) if self.per_lump is not None else 2 * self.max_per_lump


def smallest_split(held_out: float) -> int:
    """The fewest cells (>= 4) that :func:`held_out_split` leaves two on either side of."""
    n = 4
    while min(held_out_split(n, held_out)) < 2:
        n += 1
    return n


@register_chain_kind
@dataclass(frozen=True)
class HiddenPhases(ChainKind):
    """The chain over each lump's hidden phases (``gp.lumps=phases``), learned from phi
    sequences (:mod:`surrogate.gp.phases`): a table (lookup mode only) that may start from its
    stationary law."""

    lumps = "phases"
    gp_keys = GP_PHASES
    title = "hidden-phase"
    recipe = "phases"
    starts = STARTS
    files = (PHASE_CHAIN,)
    #: above K lumps' 2: hidden states learned with nothing named, counts chosen by the fit
    complexity = 3
    candidate = True
    #: the fit reads psi's domain only, and its recipe is gp=svgp's plus gp.phases
    shares_psi = True
    law_version = ("phase_law_version", PHASE_LAW_VERSION)

    @classmethod
    def candidate_variants(cls, gp: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
        """Beside the counts the fit chooses, the most phases in every lump (``counts: max``),
        unless the counts are fixed or already the most: the fit's choice reads its own
        100 held-out cells and can miss a slow lump's tail that the choice's 1,000 see
        (CERENA's network: the fit took (3, 2), the choice's cells scored (3, 3) 3.8e-4 per
        window higher, and only (3, 3) held the population's durations; docs/kinds.md)."""
        phases = gp.get("phases")
        if (not isinstance(phases, Mapping) or phases.get("per_lump") is not None
                or phases.get("counts") == COUNTS[0]):  # fmt: skip
            return {}
        most = {**gp, "phases": {**phases, "counts": COUNTS[0]}}
        return {f"{cls.recipe} counts={COUNTS[0]}": most}

    def fit_identity(self, gp: Mapping[str, Any], *args: Any, **kwargs: Any) -> dict[str, Any]:
        """:meth:`ChainKind.fit_identity`, with ``gp.phases.counts`` left out where it is
        ``held_out`` (the rule before the key existed): those fits keep their identity."""
        phases = gp.get("phases")
        if isinstance(phases, Mapping) and phases.get("counts") == COUNTS[1]:
            gp = {**gp, "phases": {k: v for k, v in phases.items() if k != "counts"}}
        return super().fit_identity(gp, *args, **kwargs)

    @classmethod
    def check_fit(cls, history: str, internal: Any, model_name: str) -> None:
        """The hidden phases are the chain's memory: no switch clock besides."""
        if history != cls.history:
            raise ConfigError("gp.lumps=phases takes no switch clock: use gp.history=none")

    def configure(
        self,
        gp_config: Mapping[str, Any],
        gp: GPSettings,
        inputs: tuple[str, ...],
        internal: Any,
        model_name: str,
    ) -> tuple[GPSettings, tuple[str, ...]]:
        """``gp.phases`` validated (:class:`PhaseSettings`), its table no larger than
        :data:`MAX_TABLE_ENTRIES` over the ``inputs``."""
        phases = PhaseSettings.from_config(gp_config.get("phases"))
        s, nodes, d = phases.states(), phases.fit.nodes, len(inputs)
        if s * s * nodes**d > MAX_TABLE_ENTRIES:
            # the grid is tabulated after the sample and the fits: refused before them
            fits = int((MAX_TABLE_ENTRIES / (s * s)) ** (1.0 / d) + 1e-9)
            fix = (f"gp.phases.nodes={fits} or fewer" if fits >= 2
                   else "fewer phases (gp.phases.max_per_lump)")  # fmt: skip
            raise ConfigError(
                f"gp.phases.nodes={nodes} over {d} input(s) {list(inputs)} with up to {s} hidden "
                f"states makes a table of {s * s * nodes**d:.3g} entries (at most "
                f"{MAX_TABLE_ENTRIES:,}); use {fix}"
            )
        return gp, inputs

    def check_train(self, settings: FitSettings) -> None:
        """The sample must span two windows of ``dt``: one window shows no memory (its length
        is rounded to whole windows, at least one)."""
        phases = PhaseSettings.from_config(settings.gp_config.get("phases"))
        dt = settings.setup.dt
        if phases.t_end < 2 * dt - 1e-12:
            raise ConfigError(
                f"gp.phases.t_end={phases.t_end:g} s is shorter than two windows (dt={dt:g} s): "
                f"the sample's phi sequences would show no memory for the phases to learn; use "
                f"gp.phases.t_end={max(50.0, 2 * dt):g} (the recipe's) or any value >= "
                f"{2 * dt:g}"
            )

    @classmethod
    def check_exact(cls, history: str, mode: DecisionMode, internal: Any, model_name: str) -> None:
        """The hidden phases are learned: there is no exact law of them."""
        raise ConfigError("decision.lumps=phases: the hidden-phase chain is learned only "
                          "(decision=abstract gp=phases); decision=exact drives "
                          "decision.lumps=phi or classes")  # fmt: skip

    def label(self) -> dict[str, Any]:
        return {"lumps": self.lumps}

    def check_mode(self, mode: DecisionMode) -> None:
        if not mode.table:
            raise ConfigError(
                "gp.lumps=phases: the hidden-phase chain is a table (decision.mode=lookup), it "
                f"has no classifier mode; got decision.mode={mode.name!r}"
            )

    def fit(
        self, settings: FitSettings, table: pd.DataFrame, domain: Mapping[str, tuple[float, float]]
    ) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """The hidden-phase law (:func:`fit_phase_chain`) over the two-state fit's domain, with
        no psi to match its means to (``gp.phases.means=sequences`` only)."""
        return fit_phase_chain(settings, domain)

    def fit_given_psi(
        self, settings: FitSettings, table: pd.DataFrame, psi: PsiClassifier
    ) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """The hidden-phase law (:func:`fit_phase_chain`) over ``psi``'s domain, its means
        matched to ``psi``'s (``gp.phases.means=psi``)."""
        return fit_phase_chain(settings, psi.domain, psi)

    def write(
        self,
        directory: Path,
        fitted: tuple[dict[str, Any], dict[str, Any]] | None,
        identity: Mapping[str, Any],
    ) -> dict[str, Any]:
        """The table's and the law's states as :data:`PHASE_CHAIN`; metrics as
        ``phase_chain``."""
        assert fitted is not None  # fit gives one
        state, metrics = fitted
        save_tensors(directory / PHASE_CHAIN, {**state, "metadata": {"settings": dict(identity)}})
        return {"phase_chain": metrics}

    def load(self, directory: str | os.PathLike, device: str | torch.device = "cpu") -> PhaseLaw:
        """The chain's law over the inputs (:class:`PhaseLaw`, on the CPU: the layer reads the
        table, :func:`load_phase_chain`)."""
        return PhaseLaw.from_state(_read(directory)["phase_law"])

    def decision_layer(
        self, request: LayerRequest, directory: Path
    ) -> tuple[DecisionLayer, dict[str, Any]]:
        """The table as a :class:`PhaseDecision`, its cells starting as ``request.start``
        says."""
        table = load_phase_chain(directory, request.device)
        featurize = request.model.featurizer(table.input_names)
        layer = PhaseDecision(table, request.model.internal, featurize, start=request.start)
        log.info("hidden-phase chain over %s, table %s over %s", table.class_names, table.shape,
                 table.input_names)  # fmt: skip
        return layer, {"inputs": list(table.input_names), "lumps": self.lumps,
                       "states": list(table.class_names), "start": request.start}  # fmt: skip

    def window_log_likelihoods(
        self, layer: DecisionLayer, inputs: Tensor, phi: Tensor, dt: float
    ) -> Tensor:
        """The exact marginal likelihood over the hidden phases by the fit's own forward pass
        (:func:`~surrogate.gp.phases.window_log_likelihoods`, the forward half of
        :func:`~surrogate.gp.phases.expected_moves`), per window: each window's law is the layer's table
        read at the window's inputs as its draw reads it (between nodes, the multilinear mix
        the stochastic rounding averages to); the first state from the stationary law within
        phi_0's lump at the first window (:meth:`PhaseDecision.start_law`, as the layer starts
        its cells)."""
        if not isinstance(layer, PhaseDecision):
            raise TypeError(f"the hidden-phase chain scores a PhaseDecision, got {layer!r}")
        table, (n, steps, d) = layer.table, inputs.shape
        x = inputs.reshape(n * steps, d).to(table.device)
        z = x if layer.featurize is None else layer.featurize(x)
        s = table.n_classes
        # one law per window of each cell (nT x S x S): the table between its nodes
        moves = torch.stack([table.law(torch.full((n * steps,), a, device=z.device), z)
                             for a in range(s)], dim=1).to(torch.float64)  # fmt: skip
        node = torch.arange(n * steps, dtype=torch.int64).reshape(n, steps)
        start = layer.start_law(inputs[:, 0], phi[:, 0])
        return window_log_likelihoods(moves, table.lumps.long(), node, phi.long(), start)

    def start_sequences(self, layer: DecisionLayer, x0: Tensor, phi0: Tensor) -> None:
        """Each cell's hidden state drawn from :meth:`PhaseDecision.start_law` at ``x0`` given
        ``phi0``."""
        if not isinstance(layer, PhaseDecision):
            raise TypeError(f"the hidden-phase chain starts a PhaseDecision, got {layer!r}")
        law = layer.start_law(x0, phi0)
        layer.state = torch.multinomial(law + 1e-300, 1).squeeze(1)


def phase_table(
    law: PhaseLaw,
    input_names: Sequence[str],
    lump_names: Sequence[str],
    dt: float,
    nodes: int,
    leaving: Callable[[Tensor], Tensor] | None = None,
) -> ClassTable:
    """``law`` tabulated on the grid of ``nodes`` per input its fit read the inputs on; with
    ``leaving`` (the grid's points ``G x d`` -> each lump's one-window leave probability
    ``G x 2``, e.g. psi's: :func:`psi_leaving`), each lump's moves out of it matched to it at
    every node (:func:`~surrogate.gp.phases.match_leaving`)."""
    axes = input_grid(law.basis.bounds, nodes)
    points = grid_points(axes)
    with torch.no_grad():
        moves = law.moves(points)  # G x S x S
        if leaving is not None:
            moves = match_leaving(moves, law.layout.lumps(), leaving(points))[0]
    s = law.layout.n_states
    probabilities = moves.reshape(*[len(a) for a in axes], s, s).movedim(-2, 0)
    return ClassTable(probabilities, law.basis.bounds, input_names,
                      law.layout.names(lump_names), law.layout.lumps().tolist(), dt)  # fmt: skip


def psi_leaving(psi: PsiClassifier) -> Callable[[Tensor], Tensor]:
    """``psi``'s one-window leave probability of each lump, ``G x d`` inputs -> ``G x 2``
    float64: ``psi_0`` and ``1 - psi_1``."""

    def leaving(points: Tensor) -> Tensor:
        z = points.float()
        rows = points.shape[0]
        p0 = psi.evaluate(torch.zeros(rows, dtype=torch.int64), z).double().cpu()
        p1 = psi.evaluate(torch.ones(rows, dtype=torch.int64), z).double().cpu()
        return torch.stack([p0, 1.0 - p1], dim=-1)

    return leaving


def fit_phase_chain(
    settings: FitSettings,
    domain: Mapping[str, tuple[float, float]],
    psi: PsiClassifier | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The hidden-phase chain of the train settings ``settings``: ``gp.phases.n_cells``
    unperturbed full-model cells where collect starts them, every window for
    ``gp.phases.t_end`` s, their phi sequences fitted (:func:`select_phases`) over ``domain``;
    with ``gp.phases.means=psi``, its table's means matched to ``psi``'s at every node (the
    sample's cells live where an unperturbed population from collect's start lives, few of them
    at some inputs; psi is fitted from collect's perturbed cells over its whole domain). Its
    state (``table``, ``law``: the sequences' own) and metrics.

    Raises:
        ConfigError: ``gp.phases.means=psi`` without ``psi``.
    """
    phases = PhaseSettings.from_config(settings.gp_config.get("phases"))
    if phases.means == "psi" and psi is None:
        raise ConfigError("gp.phases.means=psi matches the chain's means to psi's: train fits "
                          "psi first and passes it; gp.phases.means=sequences needs none")  # fmt: skip
    setup, job = settings.setup, settings.job
    model = setup.model
    seed_everything(settings.seed + SEQUENCE_SEED_OFFSET)
    t0 = time.perf_counter()
    simulator = Simulator(model, FullDecision(model.internal), setup.field, setup.dt, job.device)
    perturbation = model.body.perturbation(setup.field, model.perturbation_options)
    start = perturbation.start(phases.n_cells, job.device)
    log.info("hidden phases: %d full-model cells for %g s, every window", phases.n_cells,
             phases.t_end)  # fmt: skip
    rows = record_occupancy(simulator, phases.n_cells, phases.t_end, start, record_every=1)
    inputs, phi = phi_sequences(rows, settings.inputs)
    sampled = time.perf_counter() - t0
    bounds = [domain[n] for n in settings.inputs]
    selection = PhaseSelection(phases.max_per_lump, phases.structure, phases.held_out,
                               phases.per_lump)  # fmt: skip
    law, report = select_phases(inputs, phi, bounds, selection, phases.fit, settings.seed)
    leaving = psi_leaving(psi) if phases.means == "psi" and psi is not None else None
    table = phase_table(law, settings.inputs, model.internal.lump_names, setup.dt,
                        phases.fit.nodes, leaving)  # fmt: skip
    if leaving is not None:
        # how far the sequences' own mean sojourns were from psi's (1: equal), per lump: the
        # range over the table's nodes
        points = grid_points(input_grid(law.basis.bounds, phases.fit.nodes))
        with torch.no_grad():
            ratio = leaving(points) / stationary_leaving(law.moves(points), law.layout.lumps())
        report["sequence_means_over_psi"] = {
            name: [float(ratio[:, j].min()), float(ratio[:, j].max())]
            for j, name in enumerate(model.internal.lump_names)
        }
        log.info("hidden phases: the sequences' mean sojourns over psi's %s (min, max), matched "
                 "to psi's", report["sequence_means_over_psi"])  # fmt: skip
    log.info("hidden phases per lump %s (held-out cells %d)", report["per_lump"],
             report["held_out_cells"])  # fmt: skip
    metrics = {**report, "cells": int(phi.shape[0]), "windows": int(phi.shape[1] - 1),
               "sample_seconds": sampled, "seconds": time.perf_counter() - t0}  # fmt: skip
    return {"phase_chain": table.to_state(), "phase_law": law.to_state()}, metrics


def _read(directory: str | os.PathLike) -> dict[str, Any]:
    path = Path(directory) / PHASE_CHAIN
    obj = load_tensors(path, made_by="python scripts/train.py gp=phases")
    if not isinstance(obj, dict) or not {"phase_chain", "phase_law"} <= obj.keys():
        raise ArtefactError(f"{path} is not a saved hidden-phase chain (no 'phase_chain' and "
                            f"'phase_law' entries)")  # fmt: skip
    return obj


def load_phase_chain(
    directory: str | os.PathLike, device: str | torch.device = "cpu"
) -> ClassTable:
    """The hidden-phase chain's table of a fit or train directory (``gp.lumps=phases``)."""
    return ClassTable.from_state(_read(directory)["phase_chain"]).to(device)

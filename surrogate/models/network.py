"""One network-backed internal model: any reaction network, run window by window.

This is how a user brings their own internal network: a mass-action
:class:`~surrogate.ctmc.ReactionNetwork` with a function from the inputs to its rate
constants, or an :class:`~surrogate.sbml.SbmlModel` (general kinetics read from SBML, whose
input parameters are read by name from the agent's inputs and features), plus the property
that defines the two lumps: a predicate on the species counts, given as a function or as a
formula (``"N >= 2 and S == 0"``, parsed by :mod:`surrogate.sbml.formula`). Windows are exact:
the compiled per-cell SSA (numba, CPU) or the batched event-round SSA (torch, any device).
Where the reachable state space is small the stationary law and the exact lumped psi come from
the generator (:mod:`surrogate.ctmc.lumped`).

Species assignment rules and state-triggered events (:mod:`surrogate.ctmc.events`) run in
every window, each cell carrying its triggers' values from window to window (a trigger on an
input fires where the input changes, at a window's start). Time-triggered events are refused
here: the abstraction learns psi as a function of the inputs alone (a time-homogeneous chain),
and the network's own clock would not be the simulation's (burn-in and collection run their
own time); the SSAs and the DSMTS runner simulate them exactly.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch
from torch import Tensor

from surrogate.ctmc import ReactionNetwork, gillespie, mass_action_kinetics
from surrogate.ctmc.events import EventProgram, EventState, start_events
from surrogate.ctmc.kinetics import Expr, species_ref, torch_function
from surrogate.ctmc.lumped import (
    MAX_STATES,
    StateSpace,
    lumped_age_psi,
    lumped_class_step,
    lumped_psi,
    stationary_distribution,
)
from surrogate.errors import ConfigError, EventCapError, RunawayError
from surrogate.models.base import InternalState, Randoms, burn_in_seconds
from surrogate.models.capabilities import ClassCount
from surrogate.models.count_classes import CountClasses, CountClassifier
from surrogate.sbml import SbmlModel
from surrogate.sbml.formula import parse_formula

if TYPE_CHECKING:  # numba: imported on first use
    from surrogate.ctmc import CompiledSSA
    from surrogate.ctmc.cuda_ssa import CudaSSA


def _cuda_ssa_available() -> bool:
    """Whether the CUDA SSA can run (numba-cuda imported only when a GPU run asks)."""
    try:
        from surrogate.ctmc.cuda_ssa import cuda_ssa_available
    except ImportError:  # numba-cuda not installed
        return False
    return cuda_ssa_available()


def _cuda_simulated() -> bool:
    """Whether numba's CUDA simulator runs CUDA kernels on the CPU (tests without a GPU)."""
    from numba import config

    return bool(getattr(config, "ENABLE_CUDASIM", False))


Feature = Callable[[Tensor], Tensor]
Lump = Callable[[Tensor], Tensor] | str

SSA_BACKENDS = ("auto", "compiled", "batched", "cuda")
#: seconds per SSA event, measured on the phospho network (docs/sbml.md, one thread): the
#: compiled SSA 1.33e7 events/s, the batched torch SSA 5.3e5 events/s
COMPILED_EVENT_SECONDS = 1 / 1.33e7
BATCHED_EVENT_SECONDS = 1 / 5.3e5
#: seconds per SSA event on the CUDA SSA (one thread per cell): the phospho network through
#: the simulate stage on one H200, 10,000 cells, 2.7e9 events/s (2.73e5 cell-steps/s at ~1e4
#: events a window; the kernel alone 3.7e9 at 1e4 cells, 1.2e10 at 1e5: docs/performance.md).
#: The smallest population measured, so larger ones are priced high, as a guard should be; a
#: population too small to fill the GPU waits on its slowest thread, which the stage's measured
#: fixed cost per step (:func:`surrogate.diagnosis.cost.step_seconds`) holds
CUDA_EVENT_SECONDS = 1 / 2.7e9
#: seconds per cell and step around the window's events (the SSA call's per-cell work, the
#: step's other per-cell tensor work, collect's records), measured as the slope of the wall
#: time per step between 200 and 4,000 cells (the loop's fixed part cancels; best of 3-5
#: repeats, one torch thread, a 2-core machine loaded by two other jobs) on the gene switch in
#: a walker in the Gaussian field, less its events (0.70 per window at the cells' states) at
#: COMPILED_EVENT_SECONDS: collect's loop (torch step, records every 2 steps, jumps) 0.47 us of
#: 0.53 us per cell-step, the torch step alone 0.25 of 0.30, the numba kernel 0.09 of 0.15.
#: The largest, rounded: the stages' estimates are guards, not forecasts. (It was 3 us, read
#: from a collection's whole wall time at 2,000 cells, the fixed part per step included.)
STEP_OVERHEAD_SECONDS = 5e-7
#: the most SSA events any cell makes in one window unless a model says otherwise (its
#: ``max_events``): ~1 s of the compiled SSA for that cell, 1,000x the phospho network's
#: 10,241 per window; past it the network runs away (a RunawayError names the counts)
RUNAWAY_EVENTS = 10**7
#: a burn-in is one window of many seconds: its default cap is RUNAWAY_EVENTS per this many
#: seconds of it (the auto-regulatory network's 4,000-s burn-in makes ~7e6 events at its median
#: input, and a stationary sample's cell at a high input passed 1e7 in one call: no runaway)
RUNAWAY_SPAN_SECONDS = 100.0
#: ... and at least this many times the events the file's counts imply over the burn-in: a
#: network busy from its start is no runaway (StochSS's Brusselator, ~215,000 events a second
#: from its counts, 1.1e7 in its 50-s burn-in, was refused as one; a runaway's rate grows past
#: any multiple of its start's)
RUNAWAY_RATE_FACTOR = 10.0
#: seconds per cell-step of the exact chain computed directly, per K^3 of a K-state generator
#: (exp(Q dt) at each cell's inputs, decision.mode=direct): 5.7 ms per cell-step at K = 151
#: (the textbook's dimerisation, the 2-core box under load), ~1.65e-9 x 151^3
DIRECT_EXACT_SECONDS_PER_K3 = 1.65e-9
#: the exact functions' (lumped psi, age psi, class step) memory per call: rows go in chunks
#: whose generators and exponentials (~EXACT_COPIES float64 K x K matrices each) fit it
EXACT_CHUNK_BYTES = 2**28
EXACT_COPIES = 6


class SpeciesCondition:
    """``counts (n x S) -> bool (n,)``: a condition on species counts (e.g. the lump), from
    its validated expression; compiled on first use, picklable (the expression, not the code).

    Example:
        >>> run = SpeciesCondition(call("geq", species_ref(0, "N"), const(2.0)))
        >>> run(torch.tensor([[3], [1]]))
        tensor([ True, False])
    """

    def __init__(self, expr: Expr) -> None:
        self.expr = expr
        self._function: Callable[[Tensor, Tensor], Tensor] | None = None

    def __call__(self, counts: Tensor) -> Tensor:
        if self._function is None:
            self._function = torch_function([self.expr])
        return self._function(counts, counts.new_zeros((counts.shape[0], 0)))[:, 0]

    def __getstate__(self) -> dict:
        return {"expr": self.expr, "_function": None}


class NetworkInternalModel:
    """An internal model over a reaction network.

    Args:
        network: a mass-action :class:`ReactionNetwork` (with ``rate_constants``) or an
            :class:`SbmlModel` (general kinetics; each of its input parameters is the internal
            model's input or feature of that name).
        input_names: names of the columns of ``x`` the body hands in.
        lump: the property phi, ``counts (n x S) int64 -> bool (n,)``, or a formula over the
            species ids (``"N >= 2 and S == 0"``); an unknown species is refused by name.
        rate_constants: mass action only: ``signal (n x k) -> (n x R)`` rate constants of the
            window, a function of the signal features alone.
        initial_counts: ``(S,)`` a state of the network (default: the SBML file's); the states
            reachable from it form the state space (its conserved totals).
        lump_names: names of phi = 0 and phi = 1.
        features: derived inputs by name, each ``x (n x d) -> (n,)`` in the dtype of ``x``.
        signal_names: the inputs or features the rates depend on (default: the SBML model's
            input parameters, or ``input_names``).
        ssa: ``compiled`` (numba, one random stream per cell, CPU), ``cuda`` (the same kernel,
            one CUDA thread per cell, numba-cuda; :mod:`surrogate.ctmc.cuda_ssa`), ``batched``
            (torch, any device) or ``auto``: compiled on the CPU and cuda on a GPU for SBML
            kinetics (batched on a GPU where numba-cuda is missing), batched for a mass-action
            network with a rate function (whose windows have few events).
        burn_in: seconds of SSA from ``initial_counts`` at the cell's inputs that stand in for
            the stationary law when the state space is too large to enumerate.
        max_states: bound on the enumerated state space (exact stationary law and lumped psi).
        max_rounds: passed to the batched SSA (guards against unexpectedly stiff rates).
        signal_bounds: ``{signal name: (lo, hi)}`` where the signal lives (lets the exact psi
            be tabulated); optional.
        classes: classes finer than phi for the K-lumps chain (``gp=classes``): each lump split
            into bins of a count (:class:`~surrogate.models.count_classes.CountClasses`);
            optional. With them the model declares ``class_names``, ``class_lumps`` and
            ``classes(state)``, and, where the state space is enumerable, the exact
            class-to-class law of adapted cells (``exact_class_step``).
        input_labels: ``{kinetic input: label}``, how an error names where an input of the
            kinetics comes from (the yaml model: ``model.inputs.<param>``); default ``input
            parameter '<name>'`` (SBML) or ``rate constant '<name>'`` (mass action).

    Rates are checked where they are used, as the compiled SSA checks them: a kinetic input
    that is not finite, or a propensity that is negative or not finite in a reachable state,
    is refused with a :class:`ConfigError` naming the input (its label and value) and the
    reaction, when the generator is built (exact stationary law, exact psi: one host sync per
    generator) and when a window's SSA fails (the SSA's own check, no extra sync per window).

    State: ``(counts,)`` (``n x S`` int64) on the batched SSA with a mass-action network,
    else ``(counts, streams)`` with the compiled SSA's per-cell xoshiro256** states (``n x 4``
    int64), seeded from torch's generator, so from the run's seed (:meth:`reseed_streams`
    draws them afresh for a copied state); with events also each cell's network time
    (``(n,)`` float64) and trigger values (``n x E`` bool).

    Example:
        >>> net = ReactionNetwork.from_reactions(
        ...     ["off", "on"], [("up", {"off": 1}, {"on": 1}), ("down", {"on": 1}, {"off": 1})])
        >>> gene = NetworkInternalModel(net, ["s"], "on >= 1", rate_constants=lambda s: torch.cat(
        ...     [s, torch.ones_like(s)], 1).double(), initial_counts=[1, 0])
        >>> gene.phi(gene.advance(gene.initial_state(torch.ones(3, 1)), torch.ones(3, 1), 0.1))
        tensor([...])
    """

    fusable = False
    randoms = Randoms()
    #: a cap on any cell's events in one window (None: the SSA's own), set on a
    #: :meth:`bounded` copy; a class default, so models pickled before it existed load
    max_events: int | None = None

    def __init__(  # noqa: PLR0913  # the public model constructor: options keyword-only
        self,
        network: ReactionNetwork | SbmlModel,
        input_names: Sequence[str],
        lump: Lump,
        *,
        rate_constants: Callable[[Tensor], Tensor] | None = None,
        initial_counts: Sequence[int] | Tensor | None = None,
        lump_names: tuple[str, str] = ("off", "on"),
        features: Mapping[str, Feature] | None = None,
        signal_names: Sequence[str] | None = None,
        ssa: str = "auto",
        burn_in: float = 50.0,
        max_states: int = MAX_STATES,
        max_rounds: int | None = None,
        signal_bounds: Mapping[str, tuple[float, float]] | None = None,
        classes: CountClasses | None = None,
        input_labels: Mapping[str, str] | None = None,
    ) -> None:
        self.network = network
        self.input_names = tuple(input_names)
        self._features = dict(features or {})
        self.feature_names = tuple(self._features)
        known = (*self.input_names, *self.feature_names)
        if isinstance(network, SbmlModel):
            if rate_constants is not None:
                raise ValueError("rate_constants is for mass-action networks; SBML kinetics "
                                 "read their input parameters by name")  # fmt: skip
            self.kinetics = network.kinetics
            self.mass_action = False
            missing = [n for n in network.input_names if n not in known]
            if missing:
                raise ConfigError(
                    f"the SBML model's input parameter(s) {missing} are neither inputs nor "
                    f"features of the internal model ({list(known)})"
                )
            default_signal: tuple[str, ...] = network.input_names
            initial = network.initial_state if initial_counts is None else initial_counts
            timed = [event.name for event in network.kinetics.events if event.uses_time]
            if timed:
                raise ConfigError(
                    f"the SBML model's event(s) {timed} are triggered by the time: an agent's "
                    "internal network may have state-triggered events only (psi is learned as "
                    "a function of the inputs alone, and the network's clock would not be the "
                    "simulation's); simulate it with the SSAs directly (CompiledSSA, gillespie, "
                    "or scripts/dsmts.py), or trigger the event on a species or an input"
                )
        else:
            if rate_constants is None:
                raise ValueError("a mass-action ReactionNetwork needs rate_constants")
            if initial_counts is None:
                raise ValueError("a ReactionNetwork needs initial_counts")
            self.kinetics = mass_action_kinetics(network)
            self.mass_action = True
            default_signal, initial = self.input_names, initial_counts
        self._rates = rate_constants
        self.reactions: ReactionNetwork = self.kinetics.network
        self.species = self.reactions.species
        self.signal_names = tuple(signal_names) if signal_names else default_signal
        unknown = [n for n in self.signal_names if n not in known]
        if unknown:
            raise ConfigError(f"signal(s) {unknown} are neither inputs nor features {list(known)}")
        self._lump = self._lump_function(lump)
        self.initial_counts = torch.as_tensor(initial, dtype=torch.int64).reshape(-1)
        self.lump_names = (str(lump_names[0]), str(lump_names[1]))
        if ssa not in SSA_BACKENDS:
            raise ConfigError(f"model.ssa must be one of {list(SSA_BACKENDS)}, got {ssa!r}")
        self.ssa = ssa
        self.burn_in = burn_in_seconds(burn_in, "burn_in")
        self.max_states = int(max_states)
        self.max_rounds = max_rounds
        self.signal_bounds = dict(signal_bounds) if signal_bounds else None
        what = "rate constant" if self.mass_action else "input parameter"
        labels = dict(input_labels or {})
        self.input_labels = {n: labels.get(n, f"{what} {n!r}") for n in self.kinetics.input_names}
        self._space: StateSpace | Literal[False] | None = None  # False: too large to enumerate
        self._compiled: CompiledSSA | None = None
        self._cuda: CudaSSA | None = None
        self.set_classes(classes)

    def set_classes(self, classes: CountClasses | None) -> None:
        """Declare (or drop, with None) the K-lumps classes of this network."""
        self.count_classes = classes
        self._classify = (None if classes is None
                          else CountClassifier(classes, self.species, "model.classes"))  # fmt: skip

    # properties, not instance attributes, so a subclass may declare its own as class attributes
    @property
    def class_names(self) -> tuple[str, ...] | None:
        """The K-lumps classes' names (None: none declared)."""
        return None if self.count_classes is None else self.count_classes.names

    @property
    def class_lumps(self) -> tuple[int, ...] | None:
        """Each class's lump, phi (None: none declared)."""
        return None if self.count_classes is None else self.count_classes.lumps

    @property
    def class_bins(self) -> tuple[int, ...] | None:
        """Each class's bin of the count where both lumps share its edges (None: no classes,
        or each lump its own edges)."""
        return None if self.count_classes is None else self.count_classes.bins

    @property
    def class_count(self) -> ClassCount | None:
        """The count the classes bin, apart from the bins (None: no classes): a collection
        stores it, so its classes are applied when it is read."""
        classify = self._classify
        if self.count_classes is None or classify is None:
            return None
        return ClassCount(self.count_classes.variable, self.count_classes.digest(),
                          lambda state: classify.values(state[0]), classify.bin)  # fmt: skip

    def _lump_function(self, lump: Lump) -> Callable[[Tensor], Tensor]:
        #: the lump's parsed condition over the species (None for a Python function)
        self.lump_expr: Expr | None = None
        if callable(lump):
            return lump
        symbols = {name: species_ref(s, name) for s, name in enumerate(self.species)}
        self.lump_formula = lump
        self.lump_expr = parse_formula(lump, symbols, "model.lump", "bool", what="species")
        return SpeciesCondition(self.lump_expr)

    def __getstate__(self) -> dict:
        """Picklable (a model may be sent to another process): without the compiled SSA, which
        is rebuilt (from numba's cache) on first use."""
        return {**self.__dict__, "_compiled": None, "_cuda": None}

    # -- inputs and features -----------------------------------------------------------------
    def features(self, x: Tensor, names: Sequence[str]) -> Tensor:
        """Columns ``names`` (inputs or declared features) at inputs ``x`` (``n x d``)."""
        cols = []
        for name in names:
            if name in self.input_names:
                cols.append(x[:, self.input_names.index(name)])
            elif name in self._features:
                cols.append(self._features[name](x))
            else:
                known = [*self.input_names, *self.feature_names]
                raise KeyError(f"unknown feature {name!r}; known: {known}")
        return torch.stack(cols, -1)

    def kinetic_inputs(self, x: Tensor) -> Tensor:
        """``n x P`` float64: the kinetics' per-cell inputs at inputs ``x`` (the SBML model's
        input parameters, or the mass-action rate constants)."""
        return self._kinetic_inputs(self.features(x, self.signal_names))

    def _kinetic_inputs(self, signal: Tensor) -> Tensor:
        if self.mass_action:
            return self._rates(signal).to(torch.float64)  # type: ignore[misc]
        columns = [self.signal_names.index(n) for n in self.kinetics.input_names]
        return signal[:, columns].to(torch.float64)

    def rate_constants(self, x: Tensor) -> Tensor:
        """``n x R`` mass-action rate constants at inputs ``x`` (mass-action networks)."""
        if not self.mass_action:
            raise TypeError("SBML kinetics have no rate constants; see kinetic_inputs")
        return self.kinetic_inputs(x)

    @property
    def state_space(self) -> StateSpace | None:
        """The enumerated state space, or None when more than ``max_states`` are reachable
        (or the network has rules or events, which its generator does not hold)."""
        if self._space is None and self.kinetics.has_rules_or_events:
            self._space = False
        if self._space is None:
            try:
                self._space = StateSpace.enumerate(
                    self.reactions, self.initial_counts, self.max_states
                )
            except ValueError:
                self._space = False
        return self._space or None

    # -- the window ----------------------------------------------------------------------------
    def backend(self, device: torch.device) -> str:
        """The SSA that runs windows on ``device``: ``compiled`` or ``batched``."""
        if self.ssa == "auto":
            if self.mass_action:
                return "batched"
            if device.type == "cpu":
                return "compiled"
            return "cuda" if _cuda_ssa_available() else "batched"
        if self.ssa == "compiled" and device.type != "cpu":
            raise ConfigError(
                "model.ssa=compiled runs on the CPU; use model.ssa=cuda (or batched) on CUDA"
            )
        if self.ssa == "cuda" and device.type != "cuda" and not _cuda_simulated():
            raise ConfigError(
                "model.ssa=cuda runs on a CUDA GPU; use model.ssa=compiled on the CPU"
            )
        if self.ssa == "cuda" and not _cuda_ssa_available():
            raise ConfigError(
                "model.ssa=cuda needs numba-cuda (pip install numba-cuda) and a CUDA driver; "
                "model.ssa=batched runs the torch SSA on CUDA"
            )
        return self.ssa

    def _streams(self, device: torch.device) -> bool:
        return not (self.mass_action and self.backend(device) == "batched")

    def _compiled_ssa(self) -> CompiledSSA:  # lazily built: numba compiles once per process
        if self._compiled is None:
            from surrogate.ctmc import CompiledSSA  # numba: imported on demand

            self._compiled = CompiledSSA(self.kinetics)
        return self._compiled

    def _cuda_ssa(self) -> CudaSSA:  # lazily built: compiled for the GPU on its first window
        if self._cuda is None:
            from surrogate.ctmc.cuda_ssa import CudaSSA  # numba-cuda: imported on demand

            self._cuda = CudaSSA(self.kinetics)
        return self._cuda

    def initial_state(self, x: Tensor) -> InternalState:
        """Counts from the exact stationary law at each cell's inputs (small state spaces),
        else ``initial_counts`` then ``burn_in`` seconds at each cell's inputs; with the
        compiled SSA's random streams seeded from torch's generator (so from the run's seed)."""
        n = x.shape[0]
        space = self.state_space
        if space is not None:
            pi = stationary_distribution(self._generator(x))
            idx = torch.multinomial(pi, 1).squeeze(1)
            counts = space.states.to(x.device)[idx]
            return (counts, *self._new_streams(n, x.device))
        return self.burn_in_at(self.kinetic_inputs(x), x)

    def burn_in_at(self, inputs: Tensor, x: Tensor | None = None) -> InternalState:
        """:meth:`start_state` then ``burn_in`` seconds at the kinetic inputs ``inputs``
        (``n x P``, e.g. :meth:`kinetic_inputs`; ``x``: the inputs they came from, named in an
        error)."""
        state = self.start_state(inputs.shape[0], inputs.device, inputs)
        if self.burn_in <= 0:
            return state
        return self.advance_at(state, inputs, self.burn_in, x,
                               max_events=self.burn_in_cap(self.burn_in))  # fmt: skip

    def burn_in_cap(self, seconds: float) -> int:
        """The events a cell may make in a burn-in of ``seconds``, one window: the model's
        :attr:`max_events` where set (a probe's copy), else :data:`RUNAWAY_EVENTS` per
        :data:`RUNAWAY_SPAN_SECONDS` of it (at least one window's: 4e8 for a 4,000-s burn-in),
        or :data:`RUNAWAY_RATE_FACTOR` times the events the file's counts imply over it, the
        larger."""
        if self.max_events is not None:
            return int(self.max_events)
        expected = self.events_per_window(seconds)  # NaN where the inputs have no values
        busy = RUNAWAY_RATE_FACTOR * expected if math.isfinite(expected) else 0.0
        return int(max(RUNAWAY_EVENTS * max(1.0, seconds / RUNAWAY_SPAN_SECONDS), busy))

    def start_state(
        self, n: int, device: torch.device, inputs: Tensor | None = None
    ) -> InternalState:
        """``n`` cells at ``initial_counts`` (no burn-in; rules applied and events at t = 0
        fired at the kinetic inputs ``inputs``, ``n x P``, where the network has any), with
        fresh random streams (from torch's generator): where a network's own settling is
        measured from."""
        counts = self.initial_counts.to(device).expand(n, -1).clone()
        clock: tuple[Tensor, ...] = ()
        if self.kinetics.has_rules_or_events:  # rules applied, events at t = 0 fired
            if inputs is None:
                raise ValueError("a network with rules or events starts from its inputs")
            counts, start = start_events(self.kinetics, counts, inputs)
            clock = (start.time, start.triggers) if self.kinetics.events else ()
        return (counts, *self._new_streams(n, device), *clock)

    def reseed_streams(self, state: InternalState) -> InternalState:
        """``state`` with fresh random streams from torch's generator (so from the run's seed),
        its counts (and event clock) kept: a run that starts from a copy of another run's
        state (:mod:`surrogate.simulate.paired`) would otherwise replay that run's random
        numbers."""
        counts = state[0]
        if not self._streams(counts.device):
            return state
        return (counts, *self._new_streams(counts.shape[0], counts.device), *state[2:])

    def _new_streams(self, n: int, device: torch.device) -> tuple[Tensor, ...]:
        if not self._streams(device):
            return ()
        from surrogate.ctmc import CellStreams  # numba: imported on demand

        seed = int(torch.randint(0, 2**62, (1,)).item())
        return (torch.from_numpy(CellStreams.from_seed(seed, n).state.view(np.int64)).to(device),)

    def advance(self, state: InternalState, x: Tensor, dt: float) -> InternalState:
        """One exact window (every reaction event) with the inputs held fixed."""
        return self.advance_at(state, self.kinetic_inputs(x), dt, x)

    def advance_at(
        self,
        state: InternalState,
        inputs: Tensor,
        dt: float,
        x: Tensor | None = None,
        max_events: int | None = None,
    ) -> InternalState:
        """One exact window at the kinetic inputs ``inputs`` (``n x P`` float64; ``x``: the
        inputs they came from, named in an error). ``max_events`` (default
        :attr:`max_events`, else :data:`RUNAWAY_EVENTS`): a :class:`RunawayError` (a
        ``RuntimeError``) where a cell would make more events than this in the window (the
        compiled SSA's ``max_events``, naming the cell; the batched SSA's ``max_rounds``, one
        event per cell and round, at most :attr:`max_rounds`)."""
        cap = (self.max_events or RUNAWAY_EVENTS) if max_events is None else int(max_events)
        counts = state[0]
        # each window moves the clock of a copy: the state handed in stays as it was
        clock = EventState(state[2].clone(), state[3].clone()) if self.kinetics.events else None
        after = () if clock is None else (clock.time, clock.triggers)
        try:
            if self.backend(inputs.device) == "compiled":
                from surrogate.ctmc import CellStreams  # numba: imported on demand

                streams = CellStreams(state[1].numpy().view(np.uint64))  # shares memory
                capped = {} if cap is None else {"max_events": cap}
                counts, _ = self._compiled_ssa().advance(counts, inputs, dt, streams,
                                                         clock=clock, **capped)  # fmt: skip
                return (counts, state[1], *after)
            if self.backend(inputs.device) == "cuda":  # the same kernel, a thread per cell
                counts, _ = self._cuda_ssa().advance(counts, inputs, dt, state[1], clock=clock,
                                                     max_events=cap)  # fmt: skip
                return (counts, state[1], *after)
            propensity = None if self.mass_action else self.kinetics.torch_propensity
            events = EventProgram.of(self.kinetics) if self.kinetics.has_rules_or_events else None
            rounds = self.max_rounds if cap is None else \
                min(cap, self.max_rounds) if self.max_rounds is not None else cap  # fmt: skip
            counts = gillespie(self.reactions, counts, inputs, dt, max_rounds=rounds,
                               propensity=propensity, events=events, clock=clock)  # fmt: skip
        except EventCapError as error:  # raised where the SSA's cap was hit
            raise RunawayError(self._runaway(error, counts, cap, dt)) from error
        except ValueError as error:
            # The SSA refused the window: name the input or rate at fault where the window
            # started (its own check costs nothing when all is well; this runs only on failure).
            a = self.kinetics.torch_propensity(counts, inputs).unsqueeze(1)  # (n, 1, R)
            if bool((~torch.isfinite(inputs)).any() | ~((a >= 0) & (a < math.inf)).all()):
                where, names = (x, self.input_names) if x is not None else (
                    inputs, self.kinetics.input_names)  # fmt: skip
                message = self._bad_rates(where, names, inputs, counts[:, None], a)
                raise ConfigError(message) from error
            raise
        return (counts, *state[1 : len(state) - len(after)], *after)

    def _runaway(self, error: Exception, counts: Tensor, cap: int, dt: float) -> str:
        """Why a window stopped at ``cap`` events in a cell, with the largest counts where the
        window started."""
        top = counts.max(0).values.tolist()
        largest = ", ".join(f"{s} = {v:,}" for s, v in zip(self.species, top, strict=True))
        return (f"{error}: a cell made more than {cap:,} SSA events in one window of {dt:g} s "
                f"(max_events): the network runs away there, a count growing without bound "
                f"(e.g. a prey whose predators died out); the largest counts at the window's "
                f"start: {largest}. Bound the network (a source that saturates, a "
                f"degradation), or choose inputs or a run where it stays bounded")  # fmt: skip

    def fused_advance(
        self, state: InternalState, x: Tensor, dt: float, u: Tensor, u64: Tensor | None
    ) -> tuple[InternalState, tuple[Tensor, ...]]:
        """Not available: an SSA window has a data-dependent number of events."""
        raise RuntimeError(f"{type(self).__name__} has no fused window (fusable = False)")

    def phi(self, state: InternalState) -> Tensor:
        """The property as float 0/1 ``(n,)``."""
        return self._lump(state[0]).to(torch.float32)

    def concat_states(self, states: Sequence[InternalState]) -> InternalState:
        """Counts (and streams) joined along cells."""
        return tuple(torch.cat(parts) for parts in zip(*states, strict=True))

    def classes(self, state: InternalState) -> Tensor:
        """Each cell's K-lumps class ``(n,)`` int64 (index into :attr:`class_names`).

        Raises:
            TypeError: the model declares no classes.
        """
        if self._classify is None:
            raise TypeError(f"{type(self).__name__} declares no classes")
        counts = state[0]
        return self._classify(counts, self._lump(counts).long())

    # -- optional capabilities -----------------------------------------------------------------
    @property
    def exact_psi(self) -> Callable[[Tensor, float], Tensor] | None:
        """``exact_psi(signal (n x k), dt) -> n x 2``: the exact lumped ``P(phi' = 1 | phi)``
        from the enumerated generator; None when the state space is too large to enumerate."""
        return self._exact_psi if self.state_space is not None else None

    def _by_chunks(self, signal: Tensor, law: Callable[[Tensor], Tensor]) -> Tensor:
        """``law`` of the generators at the rows of ``signal``, in chunks whose ``K x K``
        generators and their exponentials fit :data:`EXACT_CHUNK_BYTES` (200,000 rows of a
        151-state network would ask for 36 GB at once)."""
        space = self.state_space
        assert space is not None
        rows = max(1, EXACT_CHUNK_BYTES // (EXACT_COPIES * 8 * space.n_states**2))
        parts = [law(self._generator(part, is_signal=True)) for part in signal.split(rows)]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def _state_lumps(self, device: torch.device) -> tuple[Tensor, Tensor]:
        """The enumerated states on ``device`` and each one's lump (bool)."""
        space = self.state_space
        assert space is not None
        states = space.states.to(device)
        return states, self._lump(states)

    def _exact_psi(self, signal: Tensor, dt: float) -> Tensor:
        _, lump = self._state_lumps(signal.device)
        return self._by_chunks(signal, lambda q: lumped_psi(q, lump, dt))

    @property
    def exact_age_psi(self) -> Callable[[Tensor, float, int], Tensor] | None:
        """``exact_age_psi(signal (n x k), dt, max_steps) -> n x 2 x (max_steps + 1)``: the exact
        ``P(phi' = 1 | phi, k windows since phi last changed)`` of adapted cells (the switch
        clock's limit, :func:`surrogate.ctmc.lumped.lumped_age_psi`); None when the state space
        is too large to enumerate."""
        return self._exact_age_psi if self.state_space is not None else None

    def _exact_age_psi(self, signal: Tensor, dt: float, max_steps: int) -> Tensor:
        _, lump = self._state_lumps(signal.device)
        return self._by_chunks(signal, lambda q: lumped_age_psi(q, lump, dt, max_steps))

    @property
    def exact_class_step(self) -> Callable[[Tensor, float], Tensor] | None:
        """``exact_class_step(signal (n x k), dt) -> n x C x C``: the exact class-to-class law
        of adapted cells (:func:`surrogate.ctmc.lumped.lumped_class_step`); None without
        classes or when the state space is too large to enumerate."""
        if self._classify is None or self.state_space is None:
            return None
        return self._exact_class_step

    def _exact_class_step(self, signal: Tensor, dt: float) -> Tensor:
        assert self._classify is not None
        states, lump = self._state_lumps(signal.device)
        classes = self._classify(states, lump.long())
        n_classes = len(self.class_names or ())
        return self._by_chunks(signal, lambda q: lumped_class_step(q, classes, n_classes, dt))

    def generator(self, x: Tensor) -> Tensor:
        """Generators ``n x K x K`` (float64) of the enumerated state space at inputs ``x``
        (``n x d``); ValueError when the state space is too large to enumerate."""
        if self.state_space is None:
            raise ValueError(f"more than max_states={self.max_states} states are reachable")
        return self._generator(x)

    def _generator(self, x: Tensor, is_signal: bool = False) -> Tensor:
        """Generators ``n x K x K`` at inputs ``x`` (``n x d``; the signal features with
        ``is_signal``), refusing inputs and rates the SSA would refuse (one host sync)."""
        space = self.state_space
        assert space is not None
        inputs = self._kinetic_inputs(x) if is_signal else self.kinetic_inputs(x)
        a = space.propensities(inputs, None if self.mass_action else self.kinetics.torch_propensity)
        if bool((~torch.isfinite(inputs)).any() | ~((a >= 0) & (a < math.inf)).all()):
            names = self.signal_names if is_signal else self.input_names
            states = space.states.to(a.device).expand(a.shape[0], -1, -1)
            raise ConfigError(self._bad_rates(x, names, inputs, states, a))
        return space.generator_of(a)

    def _bad_rates(
        self, x: Tensor, names: Sequence[str], inputs: Tensor, states: Tensor, a: Tensor
    ) -> str:
        """The message for the first cell whose kinetic inputs are not finite or whose
        propensities ``a`` (``n x K x R``, in ``states`` ``n x K x S``) are negative or not
        finite.

        Args:
            x: ``n x d`` the cells' inputs (or signal features), named ``names``.
            inputs: ``n x P`` the kinetic inputs at ``x``.
        """
        bad_input = ~torch.isfinite(inputs)
        bad_rate = ~((a >= 0) & (a < math.inf))
        cell = int(torch.nonzero(bad_input.any(-1) | bad_rate.flatten(1).any(-1))[0])
        at = ", ".join(f"{n} = {float(v):g}" for n, v in zip(names, x[cell].tolist(), strict=True))
        params = self.kinetics.input_names
        if bool(bad_input[cell].any()):
            j = int(torch.nonzero(bad_input[cell])[0])
            return (f"{self.input_labels[params[j]]} is {float(inputs[cell, j])} where {at}: "
                    "the reaction rates need finite inputs wherever the cells go")  # fmt: skip
        k, r = (int(v) for v in torch.nonzero(bad_rate[cell])[0])
        state = dict(zip(self.species, states[cell, k].tolist(), strict=True))
        given = "; ".join(f"{self.input_labels[n]} = {float(v):g}"
                          for n, v in zip(params, inputs[cell].tolist(), strict=True))  # fmt: skip
        return (f"reaction {self.reactions.reaction_names[r]!r} has rate {float(a[cell, k, r]):g} "
                f"(negative or not finite) in state {state} where {at} ({given}): a rate must "
                "be finite and >= 0 wherever the cells go (the SSA refuses it too)")  # fmt: skip

    def file_inputs(self) -> Tensor | None:
        """``(P,)`` float64 the kinetic inputs at the SBML file's values (1 where unset), where
        :meth:`events_per_window` estimates the cost; None for a mass-action network (its
        rates are a function of the signal, with no value of its own)."""
        if self.mass_action:
            return None
        defaults = [self.network.input_defaults.get(n, 1.0)  # type: ignore[union-attr]
                    for n in self.kinetics.input_names]  # fmt: skip
        return torch.tensor([1.0 if v != v else v for v in defaults], dtype=torch.float64)

    def events_per_window(self, dt: float, inputs: Tensor | None = None) -> float:
        """Expected SSA events in a window ``dt`` from the initial counts at ``inputs`` (``(P,)``
        kinetic inputs; default: the SBML file's values, 1 where unset): a cost estimate."""
        if inputs is None:
            inputs = self.file_inputs()
            if inputs is None:
                return float("nan")
        state = self.initial_counts.unsqueeze(0)
        rates = self.kinetics.propensities(state, inputs.reshape(1, -1).to(torch.float64))
        return float(rates.clamp_min(0).sum()) * dt

    def cell_step_seconds(
        self, dt: float, events: float | None = None, device: torch.device | str = "cpu"
    ) -> float:
        """Estimated wall time of one cell and step of the full model (s), from the events of
        a window (``events``; default: :meth:`events_per_window` at the initial state) and the
        measured cost of an event on ``device``'s SSA (no accuracy guarantee: events far from
        the initial counts and default inputs differ)."""
        if events is None:
            events = self.events_per_window(dt)
        if events != events:  # no estimate of the inputs: one event per window
            events = 1.0
        return STEP_OVERHEAD_SECONDS + events * self.event_seconds(device)

    def event_seconds(self, device: torch.device | str = "cpu") -> float:
        """The measured cost of one SSA event on ``device``'s SSA
        (:data:`COMPILED_EVENT_SECONDS`, :data:`CUDA_EVENT_SECONDS` or
        :data:`BATCHED_EVENT_SECONDS`): what :meth:`cell_step_seconds` prices events at."""
        return {"compiled": COMPILED_EVENT_SECONDS, "cuda": CUDA_EVENT_SECONDS}.get(
            self.backend(torch.device(device)), BATCHED_EVENT_SECONDS)  # fmt: skip

    def prepare(self, device: torch.device | str = "cpu") -> None:
        """Compile (or load) the SSA that runs on ``device`` now, where it is compiled, so that
        a timed run does not pay it."""
        if self.backend(torch.device(device)) == "compiled":
            ssa = self._compiled_ssa()
            ssa.compile()  # the SSA's numba compile (not the builtin, which the audit forbids)

    def bounded(self, max_events: int | None, burn_in: float | None = None) -> NetworkInternalModel:
        """A shallow copy whose windows refuse more than ``max_events`` events per cell
        (:attr:`max_events`; a ``RuntimeError``), with ``burn_in`` seconds of burn-in (default
        this one's), sharing this one's compiled SSA: for timing a few windows without paying
        an unbounded burn-in or a runaway window (:func:`surrogate.diagnosis.cost.step_seconds`)."""
        if self.backend(torch.device("cpu")) == "compiled":
            self._compiled_ssa()  # built once, shared
        other = copy.copy(self)
        other._compiled = self._compiled
        other.max_events = max_events
        if burn_in is not None:
            other.burn_in = burn_in_seconds(burn_in, "burn_in")
        return other


def direct_exact_step_seconds(internal: Any) -> float:
    """Seconds per cell-step of ``internal``'s exact chain computed directly (0 for a model
    without an enumerated state space)."""
    space = getattr(internal, "state_space", None)
    return 0.0 if space is None else DIRECT_EXACT_SECONDS_PER_K3 * float(space.n_states) ** 3

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
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from surrogate.ctmc import ReactionNetwork, gillespie, mass_action_kinetics
from surrogate.ctmc.kinetics import Expr, species_ref, torch_function
from surrogate.ctmc.lumped import (
    MAX_STATES,
    StateSpace,
    lumped_age_psi,
    lumped_psi,
    stationary_distribution,
)
from surrogate.errors import ConfigError
from surrogate.models.base import InternalState, Randoms, burn_in_seconds
from surrogate.sbml import SbmlModel
from surrogate.sbml.formula import parse_formula

Feature = Callable[[Tensor], Tensor]
Lump = Callable[[Tensor], Tensor] | str

SSA_BACKENDS = ("auto", "compiled", "batched")
#: seconds per SSA event, measured on the phospho network (docs/sbml.md, one thread): the
#: compiled SSA 1.33e7 events/s, the batched torch SSA 5.3e5 events/s
COMPILED_EVENT_SECONDS = 1 / 1.33e7
BATCHED_EVENT_SECONDS = 1 / 5.3e5
#: seconds per cell and step around the window's events (the SSA call's per-cell work, the
#: torch step, collect's records): the gene switch (1-2 events per window) collected at 7.1 us
#: per cell-step on a loaded 2-core machine (2,000 cells), so ~3 us on a quiet one
STEP_OVERHEAD_SECONDS = 3e-6


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
        ssa: ``compiled`` (numba, one random stream per cell, CPU), ``batched`` (torch, any
            device) or ``auto``: compiled on the CPU for SBML kinetics, batched on CUDA and for
            a mass-action network with a rate function (whose windows have few events).
        burn_in: seconds of SSA from ``initial_counts`` at the cell's inputs that stand in for
            the stationary law when the state space is too large to enumerate.
        max_states: bound on the enumerated state space (exact stationary law and lumped psi).
        max_rounds: passed to the batched SSA (guards against unexpectedly stiff rates).
        signal_bounds: ``{signal name: (lo, hi)}`` where the signal lives (lets the exact psi
            be tabulated); optional.

    State: ``(counts,)`` (``n x S`` int64) on the batched SSA with a mass-action network,
    else ``(counts, streams)`` with the compiled SSA's per-cell xoshiro256** states (``n x 4``
    int64), seeded from torch's generator, so from the run's seed.

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

    def __init__(
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
        self._space: StateSpace | bool | None = None  # False: too large to enumerate
        self._compiled = None

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
        return {**self.__dict__, "_compiled": None}

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
        """The enumerated state space, or None when more than ``max_states`` are reachable."""
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
            return "compiled" if device.type == "cpu" and not self.mass_action else "batched"
        if self.ssa == "compiled" and device.type != "cpu":
            raise ConfigError("model.ssa=compiled runs on the CPU; use model.ssa=batched on CUDA")
        return self.ssa

    def _streams(self, device: torch.device) -> bool:
        return not (self.mass_action and self.backend(device) == "batched")

    def _compiled_ssa(self):  # lazily built: numba compiles once per process
        if self._compiled is None:
            from surrogate.ctmc import CompiledSSA

            self._compiled = CompiledSSA(self.kinetics)
        return self._compiled

    def initial_state(self, x: Tensor) -> InternalState:
        """Counts from the exact stationary law at each cell's inputs (small state spaces),
        else ``initial_counts`` then ``burn_in`` seconds at each cell's inputs; with the
        compiled SSA's random streams seeded from torch's generator (so from the run's seed)."""
        n = x.shape[0]
        space = self.state_space
        if space is not None:
            pi = stationary_distribution(self.generator(x))
            idx = torch.multinomial(pi, 1).squeeze(1)
            counts = space.states.to(x.device)[idx]
            return (counts, *self._new_streams(n, x.device))
        state = self.start_state(n, x.device)
        return self.advance(state, x, self.burn_in) if self.burn_in > 0 else state

    def start_state(self, n: int, device: torch.device) -> InternalState:
        """``n`` cells at ``initial_counts`` (no burn-in), with fresh random streams (from
        torch's generator): where a network's own settling is measured from."""
        counts = self.initial_counts.to(device).expand(n, -1).clone()
        return (counts, *self._new_streams(n, device))

    def _new_streams(self, n: int, device: torch.device) -> tuple[Tensor, ...]:
        if not self._streams(device):
            return ()
        from surrogate.ctmc import CellStreams

        seed = int(torch.randint(0, 2**62, (1,)).item())
        return (torch.from_numpy(CellStreams.from_seed(seed, n).state.view(np.int64)).to(device),)

    def advance(self, state: InternalState, x: Tensor, dt: float) -> InternalState:
        """One exact window (every reaction event) with the inputs held fixed."""
        counts = state[0]
        inputs = self.kinetic_inputs(x)
        if self.backend(x.device) == "compiled":
            from surrogate.ctmc import CellStreams

            streams = CellStreams(state[1].numpy().view(np.uint64))  # shares memory
            counts, _ = self._compiled_ssa().advance(counts, inputs, dt, streams)
            return (counts, state[1])
        propensity = None if self.mass_action else self.kinetics.torch_propensity
        counts = gillespie(self.reactions, counts, inputs, dt, max_rounds=self.max_rounds,
                           propensity=propensity)  # fmt: skip
        return (counts, *state[1:])

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

    # -- optional capabilities -----------------------------------------------------------------
    @property
    def exact_psi(self) -> Callable[[Tensor, float], Tensor] | None:
        """``exact_psi(signal (n x k), dt) -> n x 2``: the exact lumped ``P(phi' = 1 | phi)``
        from the enumerated generator; None when the state space is too large to enumerate."""
        return self._exact_psi if self.state_space is not None else None

    def _exact_psi(self, signal: Tensor, dt: float) -> Tensor:
        space = self.state_space
        assert space is not None
        q = space.generator(*self._generator_args(signal, is_signal=True))
        return lumped_psi(q, self._lump(space.states.to(q.device)), dt)

    @property
    def exact_age_psi(self) -> Callable[[Tensor, float, int], Tensor] | None:
        """``exact_age_psi(signal (n x k), dt, max_steps) -> n x 2 x (max_steps + 1)``: the exact
        ``P(phi' = 1 | phi, k windows since phi last changed)`` of adapted cells (the switch
        clock's limit, :func:`surrogate.ctmc.lumped.lumped_age_psi`); None when the state space
        is too large to enumerate."""
        return self._exact_age_psi if self.state_space is not None else None

    def _exact_age_psi(self, signal: Tensor, dt: float, max_steps: int) -> Tensor:
        space = self.state_space
        assert space is not None
        q = space.generator(*self._generator_args(signal, is_signal=True))
        return lumped_age_psi(q, self._lump(space.states.to(q.device)), dt, max_steps)

    def generator(self, x: Tensor) -> Tensor:
        """Generators ``n x K x K`` (float64) of the enumerated state space at inputs ``x``
        (``n x d``); ValueError when the state space is too large to enumerate."""
        space = self.state_space
        if space is None:
            raise ValueError(f"more than max_states={self.max_states} states are reachable")
        return space.generator(*self._generator_args(x))

    def _generator_args(self, x: Tensor, is_signal: bool = False) -> tuple:
        inputs = self._kinetic_inputs(x) if is_signal else self.kinetic_inputs(x)
        return (inputs, None if self.mass_action else self.kinetics.torch_propensity)

    def events_per_window(self, dt: float, inputs: Tensor | None = None) -> float:
        """Expected SSA events in a window ``dt`` from the initial counts at ``inputs`` (``(P,)``
        kinetic inputs; default: the SBML file's values, 1 where unset): a cost estimate."""
        if inputs is None:
            if self.mass_action:
                return float("nan")
            defaults = [self.network.input_defaults.get(n, 1.0)  # type: ignore[union-attr]
                        for n in self.kinetics.input_names]  # fmt: skip
            inputs = torch.tensor([1.0 if v != v else v for v in defaults], dtype=torch.float64)
        state = self.initial_counts.unsqueeze(0)
        rates = self.kinetics.propensities(state, inputs.reshape(1, -1).to(torch.float64))
        return float(rates.clamp_min(0).sum()) * dt

    def cell_step_seconds(self, dt: float, events: float | None = None) -> float:
        """Estimated wall time of one cell and step of the full model (s), from the events of
        a window (``events``; default: :meth:`events_per_window` at the initial state) and the
        measured cost of an event on this SSA."""
        if events is None:
            events = self.events_per_window(dt)
        if events != events:  # no estimate of the inputs: one event per window
            events = 1.0
        per_event = COMPILED_EVENT_SECONDS if self.backend(torch.device("cpu")) == "compiled" \
            else BATCHED_EVENT_SECONDS  # fmt: skip
        return STEP_OVERHEAD_SECONDS + events * per_event

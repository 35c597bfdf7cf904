"""A generic internal model: any reaction network whose rates are functions of the agent's inputs.

This is how a user brings their own internal network: a :class:`~surrogate.ctmc.ReactionNetwork`
(or one read from SBML), a function from the inputs to the rate constants, and the property that
defines the two lumps. Windows are simulated exactly by the batched Gillespie SSA; where the
reachable state space is small the stationary law and the exact lumped psi come from the
generator (:mod:`surrogate.ctmc.lumped`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import torch
from torch import Tensor

from surrogate.ctmc import ReactionNetwork, gillespie
from surrogate.ctmc.lumped import MAX_STATES, StateSpace, lumped_psi, stationary_distribution
from surrogate.models.base import InternalState, Randoms, burn_in_seconds

Feature = Callable[[Tensor], Tensor]


class NetworkInternalModel:
    """An internal model over a mass-action reaction network.

    Args:
        network: the reaction network (species = state columns).
        input_names: names of the columns of ``x`` the body hands in.
        rate_constants: ``signal (n x k) -> (n x R)`` rate constants of the window, a function of
            the signal features alone (by default the inputs themselves).
        lump: ``counts (n x S) int64 -> bool (n,)``, the property phi.
        initial_counts: ``(S,)`` a state of the network; states reachable from it form the state
            space (its conserved totals, e.g. the number of motors or genes).
        lump_names: names of phi = 0 and phi = 1.
        features: derived inputs by name, each ``x (n x d) -> (n,)``.
        signal_names: the features (or inputs) the rates depend on; default ``input_names``.
        burn_in: seconds of SSA from ``initial_counts`` at the cell's inputs that stand in for
            the stationary law when the state space is too large to enumerate.
        max_states: bound on the enumerated state space (exact stationary law and lumped psi).
        max_rounds: passed to the SSA (guards against unexpectedly stiff rates).
    """

    fusable = False
    randoms = Randoms()

    def __init__(
        self,
        network: ReactionNetwork,
        input_names: Sequence[str],
        rate_constants: Callable[[Tensor], Tensor],
        lump: Callable[[Tensor], Tensor],
        initial_counts: Sequence[int] | Tensor,
        lump_names: tuple[str, str] = ("off", "on"),
        features: Mapping[str, Feature] | None = None,
        signal_names: Sequence[str] | None = None,
        burn_in: float = 50.0,
        max_states: int = MAX_STATES,
        max_rounds: int | None = None,
    ) -> None:
        self.network = network
        self.input_names = tuple(input_names)
        self._rates = rate_constants
        self._lump = lump
        self.initial_counts = torch.as_tensor(initial_counts, dtype=torch.int64).reshape(-1)
        self.lump_names = (str(lump_names[0]), str(lump_names[1]))
        self._features = dict(features or {})
        self.feature_names = tuple(self._features)
        self.signal_names = tuple(signal_names) if signal_names else self.input_names
        self.burn_in = burn_in_seconds(burn_in, "burn_in")
        self.max_states = int(max_states)
        self.max_rounds = max_rounds
        self._space: StateSpace | bool | None = None  # False: too large to enumerate

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

    def rate_constants(self, x: Tensor) -> Tensor:
        """``n x R`` rate constants at inputs ``x``."""
        return self._rates(self.features(x, self.signal_names)).to(torch.float64)

    @property
    def state_space(self) -> StateSpace | None:
        """The enumerated state space, or None when more than ``max_states`` are reachable."""
        if self._space is None:
            try:
                self._space = StateSpace.enumerate(
                    self.network, self.initial_counts, self.max_states
                )
            except ValueError:
                self._space = False
        return self._space or None

    # -- the window ----------------------------------------------------------------------------
    def initial_state(self, x: Tensor) -> InternalState:
        """Counts from the exact stationary law at each cell's inputs (small state spaces), else
        after ``burn_in`` seconds of SSA from ``initial_counts``."""
        n = x.shape[0]
        space = self.state_space
        if space is not None:
            pi = stationary_distribution(space.generator(self.rate_constants(x)))
            idx = torch.multinomial(pi, 1).squeeze(1)
            return (space.states.to(x.device)[idx],)
        counts = self.initial_counts.to(x.device).expand(n, -1).clone()
        return self.advance((counts,), x, self.burn_in)

    def advance(self, state: InternalState, x: Tensor, dt: float) -> InternalState:
        """One exact window by the batched Gillespie SSA."""
        rates = self.rate_constants(x)
        return (gillespie(self.network, state[0], rates, dt, max_rounds=self.max_rounds),)

    def fused_advance(
        self, state: InternalState, x: Tensor, dt: float, u: Tensor, u64: Tensor | None
    ) -> tuple[InternalState, tuple[Tensor, ...]]:
        """Not available: an SSA window has a data-dependent number of events."""
        raise RuntimeError(f"{type(self).__name__} has no fused window (fusable = False)")

    def phi(self, state: InternalState) -> Tensor:
        """The property as float 0/1 ``(n,)``."""
        return self._lump(state[0]).to(torch.float32)

    def concat_states(self, states: Sequence[InternalState]) -> InternalState:
        """Counts ``(n, S)`` joined along cells."""
        return (torch.cat([s[0] for s in states]),)

    def exact_psi(self, signal: Tensor, dt: float) -> Tensor:
        """Exact lumped ``P(phi' = 1 | phi)`` ``n x 2`` from the enumerated generator."""
        space = self.state_space
        if space is None:
            raise NotImplementedError(
                f"more than {self.max_states} states are reachable from "
                f"{self.initial_counts.tolist()}: no exact lumped psi"
            )
        q = space.generator(self._rates(signal).to(torch.float64))
        return lumped_psi(q, self._lump(space.states.to(q.device)), dt)

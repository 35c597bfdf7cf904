"""Decision layers: a cell's next property phi (e.g. RUN) given phi now and its inputs x.

The outer loop is shared; only this layer differs between

* :class:`FullDecision`: the internal model itself, one exact window per step (Algorithm 1);
* :class:`AbstractDecision`: the two-state chain phi' ~ Bernoulli(psi_phi(z)), z the
  abstraction's inputs computed from x, psi a learned classifier or its lookup table
  (Algorithm 2);
* :class:`ExactDecision`: the same chain driven by the internal model's exact lumped psi (where
  the state space is small enough to compute it): the psi of cells adapted to their current
  inputs, not a bound on what a two-state chain can do (moving cells are not adapted);
* :class:`~surrogate.simulate.memory.MemoryDecision` (its own module): the chain with a switch
  clock.

Besides the eager protocol (``initialize`` / ``step``) each layer has a *pure* form the
simulator fuses into its one-function step (and can ``torch.compile``): ``fused_step`` takes its
random numbers as inputs, never synchronises with the host and returns the next layer state
instead of mutating it. Flags travel as float 0/1 inside it (see :mod:`surrogate.models.base`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import torch
from torch import Tensor

from surrogate.models.base import FeatureMap, InternalModel, InternalState, Randoms
from surrogate.models.capabilities import exact_psi_of, randoms_of
from surrogate.models.capabilities import is_fusable as internal_fusable

#: ``psi(phi (n,), z (n x k)) -> p(phi' = 1)`` float32 ``(n,)``; a learned classifier, its
#: lookup table or the exact psi. An object may also offer ``evaluate(phi, z)``: the same
#: without input checks (no host sync), which the decision layers prefer.
RunProbability = Callable[[Tensor, Tensor], Tensor]


class DecisionLayer(Protocol):
    """What the simulator needs of a decision layer."""

    # read-only for the simulator: a plain attribute or a property satisfies each
    @property
    def name(self) -> str: ...
    @property
    def fusable(self) -> bool: ...
    @property
    def randoms(self) -> Randoms: ...

    def initialize(self, x: Tensor) -> Tensor:
        """Initial phi (bool ``(n,)``) of cells adapted to inputs ``x`` (``n x d``)."""
        ...

    def step(self, phi: Tensor, x: Tensor, dt: float) -> Tensor:
        """Eagerly advance one window with inputs fixed; return the next phi (bool)."""
        ...

    def fused_state(self) -> InternalState:
        """Per-cell tensors the pure step carries (e.g. motor states)."""
        ...

    def set_fused_state(self, state: InternalState) -> None:
        """Store what :meth:`fused_step` returned."""
        ...

    def fused_step(
        self,
        phi: Tensor,
        x: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: InternalState,
    ) -> tuple[Tensor, InternalState, tuple[Tensor, ...]]:
        """Pure: (phi after the window as float 0/1, next state, aux tensors)."""
        ...


class FullDecision:
    """The internal model itself: one exact window per step, then its property (Algorithm 1).

    Args:
        internal: the internal model (e.g. the E. coli motors).
    """

    name = "full"

    def __init__(self, internal: InternalModel) -> None:
        self.internal = internal
        self.state: InternalState | None = None

    @property
    def fusable(self) -> bool:
        """Whether the internal model has a pure window (the simulator then fuses it)."""
        return internal_fusable(self.internal)

    @property
    def randoms(self) -> Randoms:
        """What the internal model's pure window needs."""
        return randoms_of(self.internal)

    def initialize(self, x: Tensor) -> Tensor:
        """Internal states drawn from their stationary law at each cell's inputs."""
        self.state = self.internal.initial_state(x)
        return self.internal.phi(self.state) > 0

    def step(self, phi: Tensor, x: Tensor, dt: float) -> Tensor:
        """One exact window, then phi."""
        if self.state is None:
            raise RuntimeError("FullDecision.step called before initialize()")
        self.state = self.internal.advance(self.state, x, dt)
        return self.internal.phi(self.state) > 0

    def fused_state(self) -> InternalState:
        """The internal model's state."""
        if self.state is None:
            raise RuntimeError("FullDecision: not initialised")
        return self.state

    def set_fused_state(self, state: InternalState) -> None:
        """Store the internal state returned by :meth:`fused_step`."""
        self.state = state

    def fused_step(
        self,
        phi: Tensor,
        x: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: InternalState,
    ) -> tuple[Tensor, InternalState, tuple[Tensor, ...]]:
        """Pure: one exact window of the internal model, then phi."""
        state, aux = self.internal.fused_advance(state, x, dt, u, u64)
        return self.internal.phi(state), state, aux


class AbstractDecision:
    """The two-state chain phi' ~ Bernoulli(psi_phi(z)) with z = ``featurize(x)`` (Algorithm 2).

    Args:
        run_probability: ``psi(phi, z)`` (see :data:`RunProbability`).
        internal: the internal model, used only for the initial phi (the same stationary law as
            the full model, for a fair start).
        featurize: ``x (n x d) -> z (n x k)``, the abstraction's inputs; identity by default.
        name: the layer's name in logs and manifests.

    The caller's ``run_probability`` is never modified: the layer calls its unchecked
    ``evaluate`` when it has one (the simulator checks its state at record times instead).
    """

    fusable = True
    randoms = Randoms(uniform=1)

    def __init__(
        self,
        run_probability: RunProbability,
        internal: InternalModel,
        featurize: Callable[[Tensor], Tensor] | None = None,
        name: str = "abstract",
    ) -> None:
        self.run_probability = run_probability
        self.internal = internal
        self.featurize = featurize
        self.name = name
        self._psi = getattr(run_probability, "evaluate", run_probability)

    def restacked(self, run_probability: RunProbability, name: str) -> AbstractDecision:
        """The same chain over another psi (e.g. several chains' tables stacked into one)."""
        return AbstractDecision(run_probability, self.internal, self.featurize, name)

    def probability(self, phi: Tensor, x: Tensor) -> Tensor:
        """p(phi' = 1) ``(n,)`` for current phi and inputs x (pure, unchecked)."""
        z = x if self.featurize is None else self.featurize(x)
        return self._psi(phi, z)

    def initialize(self, x: Tensor) -> Tensor:
        """phi of an internal state drawn from its stationary law at each cell's inputs."""
        return self.internal.phi(self.internal.initial_state(x)) > 0

    def start_at(self, x: Tensor, phi: Tensor) -> None:
        """Start cells whose first phi (``(n,)``) is given, at inputs ``x`` (``n x d``), as
        :meth:`initialize` would but without drawing phi: no internal state is made (a full
        model's burn-in can cost minutes: the auto-regulatory network's is 4,000 s a cell).
        The chain carries nothing of its own."""

    def step(self, phi: Tensor, x: Tensor, dt: float) -> Tensor:
        """One Bernoulli draw per cell."""
        p = self.probability(phi, x)
        return torch.rand_like(p) < p

    def fused_state(self) -> InternalState:
        """No per-cell state."""
        return ()

    def set_fused_state(self, state: InternalState) -> None:
        """Nothing to store."""

    def fused_step(
        self,
        phi: Tensor,
        x: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: InternalState,
    ) -> tuple[Tensor, InternalState, tuple[Tensor, ...]]:
        """Pure: phi' = [u < psi_phi(z)] with the uniform ``u[0]``."""
        p = self.probability(phi, x)
        return (u[0] < p).to(torch.float32), (), ()


class ExactPsi:
    """The internal model's exact lumped psi as a run probability over its signal features.

    ``psi(phi, s)`` with ``s`` (``n x k``) in the order of ``internal.signal_names``; computes
    the generator's exp(Q dt) per row (exact; costs a small matrix exponential per cell).
    """

    check_finite = False

    def __init__(self, internal: InternalModel, dt: float) -> None:
        self.internal = internal
        self.dt = float(dt)
        self.input_names = tuple(internal.signal_names)
        psi = exact_psi_of(internal)
        if psi is None:
            raise ValueError(f"{type(internal).__name__} has no exact lumped psi")
        self._exact = psi

    def evaluate(self, phi: Tensor, signal: Tensor) -> Tensor:
        """p(phi' = 1) ``(n,)`` float32."""
        psi = self._exact(signal, self.dt)  # (n, 2)
        index = (phi.reshape(-1, 1) > 0).long()
        return psi.gather(1, index).squeeze(1).to(torch.float32)

    __call__ = evaluate


class ExactDecision(AbstractDecision):
    """The two-state chain driven by the exact lumped psi (``decision=exact``).

    Args:
        internal: an internal model with an exact psi (a small state space).
        dt: the window length the psi is computed for.
        run_probability: a tabulated exact psi over the signal (e.g. a
            :class:`~surrogate.gp.PsiLookupTable`) instead of the direct :class:`ExactPsi`.
    """

    def __init__(
        self, internal: InternalModel, dt: float, run_probability: RunProbability | None = None
    ) -> None:
        psi = run_probability if run_probability is not None else ExactPsi(internal, dt)
        super().__init__(psi, internal, FeatureMap(internal, internal.signal_names), name="exact")


def is_fusable(decision: object) -> bool:
    """Whether ``decision`` implements the fused protocol and allows it now."""
    return bool(getattr(decision, "fusable", False)) and hasattr(decision, "fused_step")


__all__ = [
    "AbstractDecision",
    "DecisionLayer",
    "ExactDecision",
    "ExactPsi",
    "FullDecision",
    "RunProbability",
    "is_fusable",
]

"""Decision layers that carry a per-cell tensor of their own between windows.

The two-state chain (:class:`~surrogate.simulate.decision.AbstractDecision`) keeps nothing but
phi. A switch clock (:class:`~surrogate.simulate.memory.MemoryDecision`) and the K-lumps chain
(:class:`~surrogate.simulate.classes.ClassDecision`) each keep one ``(n,)`` tensor per cell
(the clock in steps, the class): the layer's fused state, which the simulator carries through
its pure step, a batch joins across runs and the engine packs for a model's compiled kernel
(:class:`~surrogate.models.packed.LayerState`). :class:`StatefulDecision` holds that tensor and
does the bookkeeping once; a layer gives only its window's rule, eager and pure.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor

from surrogate.models.base import InternalState
from surrogate.models.capabilities import concat_states


class StatefulDecision(ABC):
    """A decision layer with one per-cell tensor, :attr:`carried`, as its fused state.

    A subclass sets :attr:`carried` in its ``initialize`` and gives one window's rule twice:
    :meth:`_eager_step` (draws its own random numbers) and :meth:`_pure_step` (the uniforms it
    is handed; no host sync, nothing mutated). This base checks the layer was initialised,
    stores the eager step's tensor, and gives the fused protocol (``fused_state``,
    ``set_fused_state``, ``fused_step``, ``concat_states``). Mixed with another layer class,
    list it first so its protocol methods win.

    Attributes:
        carried: ``(n,)`` the per-cell tensor; None before ``initialize``.
    """

    fusable = True
    carried: Tensor | None = None

    #: several populations' tensors as one, cells in order: the default join, never the
    #: internal model's own (its concat_states joins its states, not this layer's tensor)
    concat_states = staticmethod(concat_states)

    @abstractmethod
    def _eager_step(
        self, phi: Tensor, x: Tensor, dt: float, carried: Tensor
    ) -> tuple[Tensor, Tensor]:
        """One window with the layer's own random numbers.

        Args:
            phi: ``(n,)`` phi now (bool).
            x: ``n x d`` inputs.
            dt: the window (s).
            carried: ``(n,)`` the per-cell tensor now.

        Returns:
            phi after the window (bool ``(n,)``) and the tensor after it.
        """

    @abstractmethod
    def _pure_step(
        self, phi: Tensor, x: Tensor, dt: float, u: Tensor, carried: Tensor
    ) -> tuple[Tensor, Tensor]:
        """One window from the uniforms ``u`` (``randoms.uniform x n``), pure.

        Args:
            phi: ``(n,)`` phi now (float 0/1).
            x: ``n x d`` inputs.
            dt: the window (s).
            u: ``randoms.uniform x n`` uniforms in [0, 1).
            carried: ``(n,)`` the per-cell tensor now.

        Returns:
            phi after the window (float 0/1 ``(n,)``) and the tensor after it.
        """

    def _current(self, what: str) -> Tensor:
        """:attr:`carried`, or a RuntimeError ``<class><what>`` before ``initialize``."""
        if self.carried is None:
            raise RuntimeError(f"{type(self).__name__}{what}")
        return self.carried

    def step(self, phi: Tensor, x: Tensor, dt: float) -> Tensor:
        """One window, eagerly: the next phi (bool ``(n,)``); the tensor is stored."""
        carried = self._current(".step called before initialize()")
        nxt, self.carried = self._eager_step(phi, x, dt, carried)
        return nxt

    def fused_state(self) -> InternalState:
        """The per-cell tensor, alone in a tuple."""
        return (self._current(": not initialised"),)

    def set_fused_state(self, state: InternalState) -> None:
        """Store the tensor :meth:`fused_step` returned."""
        (self.carried,) = state

    def fused_step(
        self,
        phi: Tensor,
        x: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: InternalState,
    ) -> tuple[Tensor, InternalState, tuple[Tensor, ...]]:
        """Pure: :meth:`_pure_step` on the tensor in ``state``; no aux tensors."""
        (carried,) = state
        nxt, carried = self._pure_step(phi, x, dt, u, carried)
        return nxt, (carried,), ()


def carried_alias(doc: str) -> property:
    """:attr:`StatefulDecision.carried` under a layer's own name (e.g. ``age``, ``cls``).

    Args:
        doc: the name's docstring (what the tensor is, with its shape and dtype).
    """

    def get(self: StatefulDecision) -> Tensor | None:
        return self.carried

    def set(self: StatefulDecision, value: Tensor | None) -> None:
        self.carried = value

    return property(get, set, doc=doc)


__all__ = ["StatefulDecision", "carried_alias"]

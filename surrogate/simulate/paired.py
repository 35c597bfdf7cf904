"""Paired starts: every run of a comparison starts its cells from the same internal states.

A slow network's full model draws each cell's internal state by a long burn-in (minutes of a
slowly degraded protein), so two runs from independent burn-ins differ by their starts as much
as by their dynamics: at 1,000 cells the auto-regulatory network's mean durations differed by
2.9-3.8 % between two full runs (docs/fidelity.md). Within :func:`paired_starts`, the internal
model draws its initial state once per distinct set of inputs and hands every later call with
the same inputs a copy of it (cells at one start point in one field see the same inputs).

Only the state is shared, never the randomness: where the state carries the model's own random
streams (a network on the compiled SSA: each cell's xoshiro state), every copy gets fresh
streams from torch's generator, seeded with that run's seed (the model's ``reseed_streams``,
:func:`~surrogate.models.capabilities.reseed_streams_of`); a model whose windows draw from
torch's generator needs nothing. The first run to draw keeps its own streams, so it is the run
it would be alone. The full run, its repeat (the noise floor) and every abstraction then start
from the same counts and differ by their dynamics alone, each driven by its own seed. (Copied
streams, as shipped until 2026-11-28, made the runs replay one another's random numbers: two
full runs at one input agreed far more than their dynamics allow, see docs/fidelity.md.)
"""

from __future__ import annotations

import contextlib
import hashlib
from collections.abc import Callable, Iterator
from typing import Any

from torch import Tensor

from surrogate.models.capabilities import reseed_streams_of

__all__ = ["PairedStarts", "paired_starts"]


def _copy(state: Any) -> Any:
    """A copy of an internal state: a tensor, or tuples, lists and dicts of them."""
    if isinstance(state, Tensor):
        return state.clone()
    if isinstance(state, tuple | list):
        return type(state)(_copy(s) for s in state)
    if isinstance(state, dict):
        return {k: _copy(v) for k, v in state.items()}
    return state


class PairedStarts:
    """``initial_state(x)`` drawn once per distinct ``x`` (its shape, dtype and bytes), then
    copied, each copy with fresh random streams where the model's state carries any.

    Args:
        draw: the internal model's own ``initial_state``.
        reseed: ``state -> state`` with fresh random streams from torch's generator (the
            model's ``reseed_streams``), or None where the state holds no random streams.
    """

    def __init__(
        self, draw: Callable[[Tensor], Any], reseed: Callable[[Any], Any] | None = None
    ) -> None:
        self.draw = draw
        self.reseed = reseed
        self._made: dict[tuple[Any, ...], Any] = {}
        #: calls answered with a copy of an earlier draw
        self.reused = 0

    @property
    def drawn(self) -> int:
        """The distinct initial states drawn (one per field and start point)."""
        return len(self._made)

    def __call__(self, x: Tensor) -> Any:
        """The internal states of cells at inputs ``x`` (``n x d``)."""
        data = x.detach().cpu().contiguous()
        key = (tuple(x.shape), str(x.dtype), str(x.device),
               hashlib.sha256(data.numpy().tobytes()).hexdigest())  # fmt: skip
        if key not in self._made:
            # the first run keeps the streams its draw advanced: it is the run it would be alone
            self._made[key] = self.draw(x)
            return _copy(self._made[key])
        self.reused += 1
        state = _copy(self._made[key])
        return state if self.reseed is None else self.reseed(state)


@contextlib.contextmanager
def paired_starts(internal: Any) -> Iterator[PairedStarts]:
    """Within the block, ``internal.initial_state`` is a :class:`PairedStarts` over its own
    (copies reseeded by ``internal.reseed_streams`` where it has one); restored after, whatever
    happens.

    Example:
        >>> import torch
        >>> class Noisy:
        ...     def initial_state(self, x):
        ...         return torch.rand(x.shape[0])
        >>> net, x = Noisy(), torch.zeros(3, 1)
        >>> with paired_starts(net) as starts:
        ...     same = torch.equal(net.initial_state(x), net.initial_state(x))
        >>> same, starts.drawn, starts.reused
        (True, 1, 1)
    """
    own = internal.__dict__.get("initial_state")  # an instance attribute to put back, if any
    memo = PairedStarts(internal.initial_state, reseed_streams_of(internal))
    internal.initial_state = memo
    try:
        yield memo
    finally:
        if own is None:
            del internal.initial_state
        else:
            internal.initial_state = own

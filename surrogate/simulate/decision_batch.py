"""Decision layers side by side, one per block of cells (a batch of runs, or stacked chains).

Kept apart from :mod:`surrogate.simulate.batch` (which builds it) so that the kernel packer
(:mod:`surrogate.simulate.kernel_pack`) can read it without importing the simulator's loop:
the loop imports the packer.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor

from surrogate.models.base import InternalState, Randoms
from surrogate.simulate.decision import DecisionLayer, is_fusable


def global_state(device: torch.device) -> Tensor:
    """The global generator's state on ``device``'s type (CPU or CUDA)."""
    if device.type == "cuda":
        return torch.cuda.get_rng_state(device)
    return torch.random.get_rng_state()


def set_global_state(device: torch.device, state: Tensor) -> None:
    """Set the global generator's state on ``device``'s type."""
    if device.type == "cuda":
        torch.cuda.set_rng_state(state, device)
    else:
        torch.random.set_rng_state(state)


@contextlib.contextmanager
def own_stream(gen: torch.Generator, device: torch.device) -> Iterator[None]:
    """Code that draws from the global generator draws from ``gen`` instead (its state
    swapped in, and back out with what was drawn)."""
    saved = global_state(device)
    set_global_state(device, gen.get_state())
    try:
        yield
        gen.set_state(global_state(device))
    finally:
        set_global_state(device, saved)


class DecisionBatch:
    """Decision layers side by side: block i of ``sizes[i]`` cells is decided by ``members[i]``.

    Fusable when every member is; the fused step runs each member on its block, with its own
    rows of the random numbers (right-aligned in the decision block, see
    :class:`~surrogate.simulate.batch.BatchSimulator`) and its own state, and concatenates the
    results.
    """

    def __init__(self, members: Sequence[DecisionLayer], sizes: Sequence[int]) -> None:
        if len(members) != len(sizes) or not members:
            raise ValueError("DecisionBatch needs one size per decision layer")
        self.members = list(members)
        self.sizes = [int(n) for n in sizes]
        self.name = "+".join(dict.fromkeys(m.name for m in self.members))
        self.fusable = all(is_fusable(m) for m in self.members)
        rs = [m.randoms for m in self.members] if self.fusable else [Randoms()]
        self.randoms = Randoms(
            max(r.uniform for r in rs), max(r.uniform64 for r in rs), max(r.normal for r in rs)
        )
        self._state_lengths: list[int] = []
        #: one generator per member where each member decides one replicate's cells and the
        #: batch is not fusable (set by the batch simulator): its eager step draws from its
        #: replicate's own stream, so a replicate's draws do not depend on the batch
        self.generators: list[torch.Generator] | None = None

    @property
    def internal(self):
        """The internal model of the first member (all members share one model)."""
        return self.members[0].internal  # type: ignore[attr-defined]

    def _split(self, tensor: Tensor) -> list[Tensor]:
        return list(torch.split(tensor, self.sizes, dim=0))

    def initialize(self, x: Tensor) -> Tensor:
        """Each member's initial phi on its block."""
        return torch.cat(
            [m.initialize(b) for m, b in zip(self.members, self._split(x), strict=True)]
        )

    def step(self, phi: Tensor, x: Tensor, dt: float) -> Tensor:
        """Each member's eager window on its block (on its replicate's generator, where
        :attr:`generators` is set)."""
        blocks = zip(self.members, self._split(phi), self._split(x), strict=True)
        if self.generators is None:
            return torch.cat([m.step(p, b, dt) for m, p, b in blocks])
        out = []
        for (m, p, b), gen in zip(blocks, self.generators, strict=True):
            with own_stream(gen, p.device):
                out.append(m.step(p, b, dt))
        return torch.cat(out)

    def fused_state(self) -> InternalState:
        """The members' states, one after the other."""
        states = [m.fused_state() for m in self.members]
        self._state_lengths = [len(s) for s in states]
        return tuple(t for s in states for t in s)

    def set_fused_state(self, state: InternalState) -> None:
        """Give every member its part of ``state``."""
        k = 0
        for m, n in zip(self.members, self._state_lengths, strict=True):
            m.set_fused_state(tuple(state[k : k + n]))
            k += n

    def fused_step(
        self,
        phi: Tensor,
        x: Tensor,
        dt: float,
        u: Tensor,
        u64: Tensor | None,
        state: InternalState,
    ) -> tuple[Tensor, InternalState, tuple[Tensor, ...]]:
        """Pure: every member's fused step on its block."""
        outs, states, auxes = [], [], []
        k, col = 0, 0
        r = self.randoms
        for m, n, length in zip(self.members, self.sizes, self._state_lengths, strict=True):
            mr = m.randoms
            cols = slice(col, col + n)
            mu = u[r.uniform - mr.uniform : r.uniform, cols]
            mu64 = None if u64 is None else u64[r.uniform64 - mr.uniform64 : r.uniform64, cols]
            out, s, aux = m.fused_step(
                phi[cols], x[cols], dt, mu, mu64, tuple(state[k : k + length])
            )
            outs.append(out.to(torch.float32))
            states += list(s)
            auxes += list(aux)
            k, col = k + length, col + n
        return torch.cat(outs), tuple(states), tuple(auxes)


__all__ = ["DecisionBatch"]

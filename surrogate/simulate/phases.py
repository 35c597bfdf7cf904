"""The hidden-phase chain as a decision layer (``gp.lumps=phases``).

Each cell carries its hidden state (its lump and the lump's phase, :mod:`surrogate.gp.phases`)
as one int64 in the batch dimension; each window it draws the next state from the learned law
tabulated over the abstraction's inputs (a :class:`~surrogate.simulate.classes.ClassTable` over
the ``S`` hidden states: one row lookup per cell), and phi is the state's lump. The model
declares no classes: the states are the chain's own.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from surrogate.models.base import InternalModel
from surrogate.simulate.classes import ClassTable, TableDecision
from surrogate.simulate.stateful import carried_alias


class PhaseDecision(TableDecision):
    """The hidden-phase chain: state' drawn from the table's law at each cell's inputs; phi is
    the state's lump.

    Args:
        table: the chain's law over its hidden states (``class_names``: ``<lump>.<phase>``,
            ``class_lumps``: each state's phi).
        internal: the internal model (for ``start="internal"``: phi of a state from its initial
            law at the cells' inputs).
        featurize: ``x (n x d) -> z (n x k)``, the table's inputs; identity by default.
        name: the layer's name in logs and manifests.
        start: ``internal``: phi as the full model's cells start, the phase from the chain's
            stationary law at the cells' inputs given that phi; ``stationary``: the state
            from the chain's stationary law.
    """

    state = carried_alias("(n,) int64: each cell's hidden state; None before initialize.")

    what = "hidden-phase chain"

    def __init__(
        self,
        table: ClassTable,
        internal: InternalModel,
        featurize: Callable[[Tensor], Tensor] | None = None,
        name: str = "abstract",
        start: str = "internal",
    ) -> None:
        super().__init__(table, internal, featurize, name, start)
        self._within: Tensor | None = None  # per lump, node: the stationary law's cdf in it

    def _start_within(self) -> Tensor:
        """``2 x nodes x S`` the cumulative stationary law of each lump's states at each node."""
        if self._within is None or self._within.device != self.table.device:
            pi = self.table.stationary().reshape(-1, self.table.n_classes)
            lumps = torch.tensor(self.table.class_lumps)
            laws = torch.stack([pi * (lumps == lump) for lump in (0, 1)])
            laws = laws / laws.sum(-1, keepdim=True).clamp_min(1e-300)
            cdf = laws.cumsum(-1)
            cdf[..., -1] = 1.0
            self._within = cdf.to(torch.float32).to(self.table.device)
        return self._within

    def start_law(self, x: Tensor, phi: Tensor) -> Tensor:
        """The law ``n x S`` (float64) a cell's first hidden state is drawn from given its phi
        ``(n,)`` (0/1) at its inputs ``x`` (``n x d``): the stationary law within phi's lump,
        at the grid nodes as ``start="internal"`` draws them (multilinear weights: what the
        stochastic rounding to a node averages to)."""
        cdf = self._start_within().to(torch.float64)  # 2 x nodes x S
        pmf = torch.diff(cdf, dim=-1, prepend=torch.zeros_like(cdf[..., :1]))
        z = self._inputs(x)
        law = torch.where(phi.bool()[:, None], self.table.read(pmf[1], z),
                          self.table.read(pmf[0], z))  # fmt: skip
        # the cdf's last entry is set to 1: no mass outside the lump from its rounding
        law = law * (self.table.lumps.to(law.device)[None, :] == phi.bool()[:, None])
        return law / law.sum(-1, keepdim=True).clamp_min(1e-300)

    def initialize(self, x: Tensor) -> Tensor:
        """Each cell's first hidden state (see ``start``) at its inputs ``x`` (``n x d``)."""
        z = self._inputs(x)
        u = torch.rand(len(self.table.input_names) + 1, z.shape[0], device=z.device)
        if self.start == "stationary":
            self.state = self.table.draw_start(z, u)
        else:
            phi = (self.internal.phi(self.internal.initial_state(x)) > 0).long().to(z.device)
            cdf = self._start_within()[phi, self.table.node_index(z, u)]
            # a state past the lump's last has cdf 1: the draw stays within the lump
            self.state = (u[-1][:, None] >= cdf[:, :-1]).sum(-1)
        return self.table.lumps[self.state] > 0


__all__ = ["PhaseDecision"]

"""The paper's two-state chain (``gp.lumps=phi``, ``gp.history=none``) as a kind module: psi of
the inputs alone is the whole chain, so it is :class:`~surrogate.kinds.base.ChainKind` as it
is (the base gives the chain over phi's fit, artefact and layers)."""

from __future__ import annotations

from dataclasses import dataclass

from surrogate.kinds.base import ChainKind, register_chain_kind


@register_chain_kind
@dataclass(frozen=True)
class TwoStateChain(ChainKind):
    """The paper's chain over phi: psi of the inputs alone (``gp.lumps=phi``,
    ``gp.history=none``)."""

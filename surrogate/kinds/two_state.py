"""The paper's two-state chain (``gp.lumps=phi``, ``gp.history=none``) as a kind module: psi of
the inputs alone is the whole chain, so it is :class:`~surrogate.kinds.base.ChainKind` as it
is (the base gives the chain over phi's fit, artefact and layers), with its likelihood of phi
sequences (:meth:`TwoStateChain.window_log_likelihoods`)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from surrogate.kinds.base import ChainKind, bernoulli_log_likelihood, register_chain_kind
from surrogate.simulate.decision import AbstractDecision, DecisionLayer


@register_chain_kind
@dataclass(frozen=True)
class TwoStateChain(ChainKind):
    """The paper's chain over phi: psi of the inputs alone (``gp.lumps=phi``,
    ``gp.history=none``)."""

    candidate = True

    def window_log_likelihoods(
        self, layer: DecisionLayer, inputs: Tensor, phi: Tensor, dt: float
    ) -> Tensor:
        """log Bernoulli(phi_{t+1}; psi_{phi_t}(x_t)), every window in one call."""
        if not isinstance(layer, AbstractDecision):
            raise TypeError(f"the two-state chain scores an AbstractDecision, got {layer!r}")
        n, steps, d = inputs.shape
        p = layer.probability(phi[:, :-1].reshape(-1).float(), inputs.reshape(n * steps, d))
        return bernoulli_log_likelihood(p, phi[:, 1:].reshape(-1)).reshape(n, steps)

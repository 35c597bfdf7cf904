"""Exact window sampling for populations of independent first-order units.

When every reaction moves one unit from one state to another (``A -> B`` with coefficient 1 on
both sides), the population is a set of independent single-unit chains over ``K`` states (the
species) with generator ``Q``. Over a window of length ``dt`` with fixed rates each unit in state
``i`` ends in state ``j`` with probability ``P[i, j] = exp(Q dt)[i, j]``, independently, so the
new counts are a sum of multinomials. Sampling that costs one uniform per unit, however many
events the chain would make in the window, which is what makes it the method of choice when
rates are far above ``1/dt``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from surrogate.ctmc.network import ReactionNetwork

__all__ = ["sample_counts", "unit_generator", "unit_transition_matrix"]


def _unit_reactions(network: ReactionNetwork) -> tuple[Tensor, Tensor]:
    """Source and target state of each reaction; ``ValueError`` unless all are unit switches."""
    for name, consumed, produced in zip(
        network.reaction_names, network.reactants, network.products, strict=True
    ):
        for side, coeffs in (("reactant", consumed), ("product", produced)):
            if int(coeffs.sum()) != 1:
                raise ValueError(
                    f"reaction {name!r} must have exactly one {side} with coefficient 1 for a "
                    f"network of independent first-order units, got {side} coefficients "
                    f"{dict(zip(network.species, coeffs.tolist(), strict=True))}"
                )
    return network.reactants.argmax(dim=1), network.products.argmax(dim=1)


def unit_generator(network: ReactionNetwork, rate_constants: Tensor) -> Tensor:
    """Per-unit generator matrices ``Q`` of a network of independent first-order units.

    Args:
        network: Network whose reactions each move one unit from one species (state) to another.
        rate_constants: ``(n, R)`` non-negative rate constants per cell.

    Returns:
        ``(n, K, K)`` float64 with ``Q[c, i, j]`` the rate of ``i -> j`` (summed over reactions
        with the same source and target) and rows summing to zero; ``K`` = number of species.
    """
    source, target = _unit_reactions(network)
    if not isinstance(rate_constants, Tensor) or rate_constants.dim() != 2:
        raise ValueError("rate_constants must be a tensor of shape (n, R)")
    n, n_reactions = rate_constants.shape
    if n_reactions != network.n_reactions:
        raise ValueError(
            f"rate_constants must have shape (n, R) with R = {network.n_reactions}, "
            f"got {tuple(rate_constants.shape)}"
        )
    if not rate_constants.dtype.is_floating_point:
        raise ValueError(f"rate_constants must be floating point, got {rate_constants.dtype}")
    if not bool(((rate_constants >= 0) & torch.isfinite(rate_constants)).all()):
        raise ValueError("rate_constants must be finite and non-negative")
    k = network.n_species
    device = rate_constants.device
    flat = (source * k + target).to(device)
    q = torch.zeros((n, k * k), dtype=torch.float64, device=device)
    q.index_add_(1, flat, rate_constants.to(torch.float64))
    q = q.view(n, k, k)
    # Self-loops (i -> i) cancel here: they add c to Q[i, i] and to the row sum alike.
    return q - torch.diag_embed(q.sum(dim=-1))


def unit_transition_matrix(q: Tensor, dt: float | Tensor) -> Tensor:
    """Transition matrices ``P = exp(Q dt)`` of a batch of generators, in float64.

    Args:
        q: ``(..., K, K)`` generator matrices.
        dt: Window length (> 0), a float or a tensor broadcastable to the batch shape of ``q``.

    Returns:
        ``(..., K, K)`` float64 row-stochastic matrices: round-off negatives are clamped to 0 and
        rows renormalised to sum to 1.
    """
    if not isinstance(q, Tensor) or q.dim() < 2 or q.shape[-1] != q.shape[-2]:
        raise ValueError("q must be a tensor of shape (..., K, K)")
    step: Tensor | float
    if isinstance(dt, Tensor):
        step = dt.to(device=q.device, dtype=torch.float64)
        if not bool(((step > 0) & torch.isfinite(step)).all()):
            raise ValueError("dt must be finite and > 0")
        step = step[..., None, None]
    else:
        if isinstance(dt, bool) or not isinstance(dt, (int, float)):
            raise ValueError(f"dt must be a float or a tensor, got {type(dt).__name__}")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and > 0, got {dt}")
        step = float(dt)
    p = torch.linalg.matrix_exp(q.to(torch.float64) * step).clamp_min(0.0)
    return p / p.sum(dim=-1, keepdim=True)


def sample_counts(counts: Tensor, p: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Sample new counts when every unit moves independently according to ``p``.

    Each of the ``counts[c, i]`` units of cell ``c`` in state ``i`` moves to state ``j`` with
    probability ``p[c, i, j]``, independently; the result is the exact sum of multinomials.

    Args:
        counts: ``(n, K)`` non-negative integer counts.
        p: ``(n, K, K)`` row-stochastic matrices (``(K, K)`` is shared by all cells).
        generator: Random generator on the device of ``counts``.

    Returns:
        ``(n, K)`` int64 counts with the same per-cell totals. Memory is ``O(n M K)`` with ``M``
        the largest per-cell total, so this suits small unit numbers (motors, receptors).
    """
    if not isinstance(counts, Tensor) or counts.dim() != 2:
        raise ValueError("counts must be a tensor of shape (n, K)")
    if counts.dtype.is_floating_point or counts.dtype.is_complex or counts.dtype == torch.bool:
        raise ValueError(f"counts must hold integers, got dtype {counts.dtype}")
    n, k = counts.shape
    if not isinstance(p, Tensor) or not p.dtype.is_floating_point:
        raise ValueError("p must be a floating-point tensor")
    if p.dim() == 2:
        p = p.unsqueeze(0).expand(n, k, k)
    if tuple(p.shape) != (n, k, k):
        raise ValueError(f"p must have shape (n, K, K) = ({n}, {k}, {k}), got {tuple(p.shape)}")
    if p.device != counts.device:
        raise ValueError(f"counts is on {counts.device} but p on {p.device}")
    device = counts.device
    if generator is not None and generator.device.type != device.type:
        raise ValueError(f"generator is on {generator.device} but counts on {device}")
    counts = counts.to(torch.int64)
    if n == 0:
        return counts.clone()
    # One sync for the check and the unit count together.
    min_count, max_total = torch.stack([counts.min(), counts.sum(dim=1).max()]).tolist()
    if min_count < 0:
        raise ValueError("counts must be non-negative")
    if max_total == 0:
        return counts.clone()

    # Unit u of a cell is in state i when cum[i - 1] <= u < cum[i]; units at or beyond the
    # cell's total get state k and are masked out.
    cum = counts.cumsum(dim=1)
    units = torch.arange(max_total, device=device)
    state = (units[None, :, None] >= cum[:, None, :]).sum(dim=-1)  # (n, M)
    valid = state < k
    # Row of cumulative probabilities for each unit's current state.
    rows = p.to(torch.float64).cumsum(dim=-1)
    rows = rows.gather(1, state.clamp_max(k - 1).unsqueeze(-1).expand(-1, -1, k))  # (n, M, K)
    # Threshold in (0, row total]: the first j whose cumulative probability reaches it has
    # probability p[i, j], and a j with p[i, j] == 0 never wins (its cum equals its left one).
    u = torch.rand(state.shape, generator=generator, device=device, dtype=torch.float64)
    threshold = (1.0 - u) * rows[..., -1]
    new_state = (rows < threshold.unsqueeze(-1)).sum(dim=-1).clamp_max(k - 1)
    out = torch.zeros((n, k), dtype=torch.int64, device=device)
    return out.scatter_add_(1, new_state, valid.to(torch.int64))

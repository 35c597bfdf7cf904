"""Sequential design of collect's perturbations: where the learned psi is least certain, weighted
by where an unperturbed population lives.

After a round of collection the learned psi's posterior says how well each input is known; an
occupancy run says which inputs matter. :class:`Acquisition` tabulates their product,
``occupancy density x posterior sd of psi``, on a histogram grid over the occupied band, per
origin state; :class:`GuidedJump` then draws each perturbation's destination by rejection against
it, so later rounds add data where it lowers the error where cells live the most.

Both are generic over models: the body's own perturbation proposes destinations, the body's
``inputs`` and the internal model's ``features`` say where a destination puts a cell's inputs.
The design needs a jump perturbation (each destination drawn afresh whatever the cell's current
position, like the bodies' jumps to random points of a disc), since a rejected destination is
redrawn by applying the perturbation again.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from surrogate.models.base import AgentBody, BodyState, Perturbation

#: grid cells of an acquisition table in all (per dimension: this ** (1 / d))
GRID_CELLS = 4096


class Acquisition:
    """``w_phi(z)``: how much a transition at inputs ``z`` from origin ``phi`` is worth, tabulated.

    Args:
        edges: per input dimension, the ``b_i + 1`` bin edges of the grid (ascending).
        weights: ``2 x b_1 x ... x b_d`` non-negative weights per origin and grid cell; inputs
            outside the grid weigh 0.

    Example:
        >>> w = Acquisition([torch.linspace(0, 1, 3)], torch.tensor([[1.0, 0.0], [0.0, 2.0]]))
        >>> w(torch.tensor([0, 1]), torch.tensor([[0.25], [0.75]]))
        tensor([1., 2.])
    """

    def __init__(self, edges: Sequence[Tensor], weights: Tensor) -> None:
        self.edges = [e.double() for e in edges]
        self.weights = weights.double()
        if self.weights.dim() != len(self.edges) + 1 or self.weights.shape[0] != 2:
            raise ValueError(
                f"weights must be 2 x b_1 x ... x b_d for {len(self.edges)} input(s), got "
                f"{tuple(self.weights.shape)}"
            )
        if bool((self.weights < 0).any()) or not bool(torch.isfinite(self.weights).all()):
            raise ValueError("acquisition weights must be finite and non-negative")
        #: per origin, the largest weight (the rejection sampler's bound)
        self.peak = self.weights.reshape(2, -1).amax(1)

    @classmethod
    def from_posterior(
        cls,
        spread: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]],
        phi: Tensor,
        z: Tensor,
        margin: float = 0.1,
    ) -> Acquisition:
        """Occupancy density x posterior sd of psi, on a grid over the occupied band.

        Args:
            spread: ``(phi (m,), z (m x d)) -> (psi, sd)``, the learned psi and its posterior sd
                (e.g. :meth:`surrogate.gp.fast.CachedPsi.spread`).
            phi: ``(n,)`` origin states of an occupancy run's rows.
            z: ``n x d`` their abstraction inputs.
            margin: the grid extends the occupied range by this share on each side, so the band's
                edges are learned as well as its middle.
        """
        z = z.double().reshape(z.shape[0], -1)
        d = z.shape[1]
        bins = max(2, int(GRID_CELLS ** (1.0 / d)))
        lo, hi = z.min(0).values, z.max(0).values
        pad = (hi - lo).clamp_min(1e-12) * margin
        edges = [torch.linspace(float(lo[i] - pad[i]), float(hi[i] + pad[i]), bins + 1,
                                dtype=torch.float64) for i in range(d)]  # fmt: skip
        centres = torch.stack(
            torch.meshgrid(*[(e[1:] + e[:-1]) / 2 for e in edges], indexing="ij"), -1
        ).reshape(-1, d)
        weights = torch.zeros(2, bins**d, dtype=torch.float64)
        index = _cell_index(edges, z)
        for p in (0, 1):
            rows = (phi.reshape(-1) == p) & (index >= 0)
            density = torch.bincount(index[rows], minlength=bins**d).double()
            _, sd = spread(torch.full((centres.shape[0],), p), centres.float())
            weights[p] = density * sd.double().cpu()
        return cls(edges, weights.reshape(2, *([bins] * d)))

    def __call__(self, phi: Tensor, z: Tensor) -> Tensor:
        """Weights ``(n,)`` of rows with origins ``phi (n,)`` at inputs ``z (n x d)``."""
        z = z.double().reshape(z.shape[0], -1).cpu()
        index = _cell_index(self.edges, z)
        flat = self.weights.reshape(2, -1)
        w = flat[phi.reshape(-1).long().cpu(), index.clamp_min(0)]
        return torch.where(index >= 0, w, torch.zeros_like(w))


def _cell_index(edges: Sequence[Tensor], z: Tensor) -> Tensor:
    """Flat grid-cell index of each row of ``z`` (``n x d``); -1 outside the grid."""
    index = torch.zeros(z.shape[0], dtype=torch.long)
    inside = torch.ones(z.shape[0], dtype=torch.bool)
    for i, e in enumerate(edges):
        b = e.numel() - 1
        k = torch.bucketize(z[:, i].contiguous(), e, right=True) - 1
        k = torch.where(z[:, i] == e[-1], b - 1, k)  # the top edge belongs to the last cell
        inside &= (k >= 0) & (k < b)
        index = index * b + k.clamp(0, b - 1)
    return torch.where(inside, index, torch.full_like(index, -1))


class GuidedJump:
    """A body's jump perturbation whose destinations follow an :class:`Acquisition`.

    Each jumping cell keeps, with probability ``explore``, its first destination as drawn (the
    fixed design's coverage, a margin for fields not trained on); otherwise destinations are
    drawn up to ``candidates`` times and accepted with probability ``w / max w`` at the inputs
    they put the cell at (rejection sampling: accepted destinations follow the perturbation's own
    distribution reweighted by ``w``); a cell with none accepted keeps its last draw.

    Args:
        perturbation: the body's perturbation (proposes destinations).
        body: the body (its ``inputs`` at a destination).
        field: the field the cells move in.
        features: ``x (n x k) -> z (n x d)``, the abstraction's inputs from the body's inputs.
        acquisition: the weights.
        candidates: destinations drawn at most per jump.
        explore: share of jumps kept as first drawn.
    """

    def __init__(
        self,
        perturbation: Perturbation,
        body: AgentBody,
        field: Any,
        features: Callable[[Tensor], Tensor],
        acquisition: Acquisition,
        candidates: int = 16,
        explore: float = 0.25,
    ) -> None:
        if candidates < 1:
            raise ValueError(f"candidates must be >= 1, got {candidates}")
        if not 0.0 <= explore <= 1.0:
            raise ValueError(f"explore must lie in [0, 1], got {explore}")
        self.perturbation = perturbation
        self.body = body
        self.field = field
        self.features = features
        self.acquisition = acquisition
        self.candidates = int(candidates)
        self.explore = float(explore)

    def start(self, n_cells: int, device: torch.device) -> Tensor:
        """Start positions: the perturbation's."""
        return self.perturbation.start(n_cells, device)

    def apply(self, state: BodyState, mask: Tensor, phi: Tensor, t: float) -> BodyState:
        """Jump the cells where ``mask`` (bool ``(n,)``) is true, destinations guided by the
        acquisition of each cell's origin ``phi`` (bool ``(n,)``) at time ``t``."""
        state = self.perturbation.apply(state, mask)
        pending = mask & (torch.rand(mask.shape, device=mask.device) >= self.explore)
        bound = self.acquisition.peak.to(mask.device)[phi.long()]
        for k in range(self.candidates):
            if not bool(pending.any()):
                break
            if k:
                state = self.perturbation.apply(state, pending)
            z = self.features(self.body.inputs(state, self.field, t))
            w = self.acquisition(phi, z).to(mask.device)
            accept = torch.rand(w.shape, device=mask.device, dtype=w.dtype) * bound < w
            pending = pending & ~accept
        return state


__all__ = ["GRID_CELLS", "Acquisition", "GuidedJump"]

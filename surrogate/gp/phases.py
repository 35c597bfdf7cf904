"""A chain over hidden phases of each lump, learned from phi sequences (``gp.lumps=phases``).

The two-state chain keeps only phi, so each lump's sojourn is geometric. Here each lump ``l``
has ``K_l`` hidden phases; the chain's state is (phi, phase), phi a function of the state, and
one window's law is a row-stochastic ``S x S`` matrix ``P(z)`` (``S = K_0 + K_1``) whose
logits are smooth functions of the abstraction's inputs ``z``: a linear map of an additive basis
(:class:`InputBasis`: a constant, each input scaled to [-1, 1] and Gaussian bumps along it).
A lump's sojourn is then phase-type: peaked (phases in series) or heavy-tailed (an early exit
or a slow phase), nothing the user names.

The fit maximises the exact likelihood of observed phi sequences (the forward algorithm over the
hidden states, batched over cells, float64, scaled per step) by L-BFGS, with a ridge penalty on
the basis weights; ``K_l`` is given, or chosen by the held-out likelihood of held-out cells
(:func:`select_phases`; that sum over every window can miss a slow lump's tail, docs/kinds.md).
With ``K = (1, 1)`` the chain is the two-state chain with psi's logit in the basis.

Moves (:class:`PhaseLayout`): ``series`` (a Coxian chain per lump: a phase stays, moves to the
next phase of its lump, or leaves to the other lump's first phase; every acyclic phase-type law
has such a form, and its parameters are identifiable up to the order of equal phases) or
``full`` (any state to any other: also memory carried across a switch, more parameters).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from surrogate.errors import NumericalError
from surrogate.threads import one_thread

log = logging.getLogger(__name__)

#: the moves a layout allows (:class:`PhaseLayout`): phases in a row per lump, or any move
SERIES, FULL = "series", "full"
STRUCTURES = (SERIES, FULL)
#: the fit's log-likelihood counts in float64 (sequences of thousands of windows)
DTYPE = torch.float64


@dataclass(frozen=True)
class PhaseLayout:
    """The hidden states: ``per_lump[l]`` phases of lump ``l`` (states ``0..K_0-1`` are lump 0's
    phases in order, then lump 1's), and the moves between them (``structure``, one of
    :data:`STRUCTURES`).

    Example:
        >>> PhaseLayout((1, 2)).moves().int().tolist()
        [[1, 1, 0], [1, 1, 1], [1, 0, 1]]
    """

    per_lump: tuple[int, int]
    structure: str = SERIES

    def __post_init__(self) -> None:
        if len(self.per_lump) != 2 or any(k < 1 for k in self.per_lump):
            raise ValueError(f"per_lump must be two phase counts >= 1, got {self.per_lump}")
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}, got {self.structure!r}")

    @property
    def n_states(self) -> int:
        """``S = K_0 + K_1``."""
        return sum(self.per_lump)

    def lumps(self) -> Tensor:
        """Each state's phi ``(S,)`` int64."""
        k0, k1 = self.per_lump
        return torch.tensor([0] * k0 + [1] * k1, dtype=torch.int64)

    def first(self, lump: int) -> int:
        """The state of lump ``lump``'s first phase."""
        return 0 if lump == 0 else self.per_lump[0]

    def moves(self) -> Tensor:
        """The allowed moves ``S x S`` bool (the diagonal, staying, always)."""
        s = self.n_states
        if self.structure == FULL:
            return torch.ones(s, s, dtype=torch.bool)
        lumps = self.lumps().tolist()
        allowed = torch.eye(s, dtype=torch.bool)
        for a in range(s):
            if a + 1 < s and lumps[a + 1] == lumps[a]:
                allowed[a, a + 1] = True  # to the next phase of the lump
            allowed[a, self.first(1 - lumps[a])] = True  # leave to the other lump
        return allowed

    def names(self, lump_names: Sequence[str]) -> tuple[str, ...]:
        """The states' names: ``<lump name>.<phase>``."""
        return tuple(f"{lump_names[l]}.{k}" for l in (0, 1) for k in range(self.per_lump[l]))


@dataclass(frozen=True)
class InputBasis:
    """Additive features of the inputs: a constant, then per input its value scaled to [-1, 1]
    over ``bounds`` (clamped) and ``bumps`` Gaussians evenly spaced along it (width their
    spacing). ``n_features = 1 + d (1 + bumps)``."""

    bounds: tuple[tuple[float, float], ...]
    bumps: int = 4

    @property
    def n_features(self) -> int:
        """Features per input point."""
        return 1 + len(self.bounds) * (1 + self.bumps)

    def features(self, z: Tensor) -> Tensor:
        """``(..., d)`` inputs -> ``(..., n_features)`` float64 features."""
        z = z.to(DTYPE)
        out = [torch.ones_like(z[..., :1])]
        for j, (lo, hi) in enumerate(self.bounds):
            u = ((2.0 * (z[..., j] - lo) / (hi - lo) - 1.0) if hi > lo
                 else torch.zeros_like(z[..., j])).clamp(-1.0, 1.0)  # fmt: skip
            out.append(u.unsqueeze(-1))
            if self.bumps:
                centres = torch.linspace(-1.0, 1.0, self.bumps, dtype=DTYPE, device=z.device)
                width = 2.0 / max(self.bumps - 1, 1)
                out.append(torch.exp(-0.5 * ((u.unsqueeze(-1) - centres) / width) ** 2))
        return torch.cat(out, dim=-1)


class PhaseLaw:
    """One window's law over the hidden states as a function of the inputs.

    Args:
        layout: the hidden states and their moves.
        basis: the inputs' features.
        weights: ``n_features x S x S`` float64: move ``a -> b``'s logit is ``features(z) @
            weights[:, a, b]``; staying's logit is 0 and moves the layout forbids have none
            (their weights are ignored).
    """

    def __init__(self, layout: PhaseLayout, basis: InputBasis, weights: Tensor) -> None:
        s = layout.n_states
        if tuple(weights.shape) != (basis.n_features, s, s):
            raise ValueError(f"weights must be {basis.n_features} x {s} x {s}, got "
                             f"{tuple(weights.shape)}")  # fmt: skip
        self.layout = layout
        self.basis = basis
        self.weights = weights
        moves = layout.moves()
        self._free = moves & ~torch.eye(s, dtype=torch.bool)
        self._blocked = ~moves

    def log_moves(self, z: Tensor) -> Tensor:
        """``(..., d)`` inputs -> log P ``(..., S, S)`` float64 (rows sum to 1)."""
        feats = self.basis.features(z)
        w = self.weights * self._free.to(self.weights.device)
        logits = torch.einsum("...f,fab->...ab", feats, w)
        logits = logits.masked_fill(self._blocked.to(logits.device), -math.inf)
        return torch.log_softmax(logits, dim=-1)

    def moves(self, z: Tensor) -> Tensor:
        """P ``(..., S, S)`` at inputs ``z`` ``(..., d)``."""
        return self.log_moves(z).exp()

    def to_state(self) -> dict[str, Any]:
        """Plain tensors and lists (loads with ``weights_only=True``)."""
        return {"per_lump": list(self.layout.per_lump), "structure": self.layout.structure,
                "bounds": [list(b) for b in self.basis.bounds], "bumps": self.basis.bumps,
                "weights": self.weights.detach().cpu()}  # fmt: skip

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> PhaseLaw:
        """The law :meth:`to_state` wrote."""
        layout = PhaseLayout((int(state["per_lump"][0]), int(state["per_lump"][1])),
                             state["structure"])  # fmt: skip
        basis = InputBasis(tuple((float(a), float(b)) for a, b in state["bounds"]),
                           int(state["bumps"]))  # fmt: skip
        return cls(layout, basis, state["weights"].to(DTYPE))


def stationary(moves: Tensor) -> Tensor:
    """The stationary law ``(..., S)`` of row-stochastic ``moves`` ``(..., S, S)`` (irreducible;
    differentiable: one linear solve)."""
    s = moves.shape[-1]
    a = moves.transpose(-1, -2) - torch.eye(s, dtype=moves.dtype, device=moves.device)
    a = torch.cat([a[..., :-1, :], torch.ones_like(a[..., -1:, :])], dim=-2)
    b = torch.zeros(*moves.shape[:-1], dtype=moves.dtype, device=moves.device)
    b[..., -1] = 1.0
    return torch.linalg.solve(a, b).clamp_min(0.0)


def _start_law(moves: Tensor, node: Tensor, first: Tensor) -> Tensor:
    """Each cell's first hidden state's law ``n x S``: the chain's stationary law at its first
    window's node given phi_0 (``first``: ``n x S`` 0/1, the states of phi_0's lump)."""
    alpha = stationary(moves)[node[:, 0]] * first
    return alpha / alpha.sum(-1, keepdim=True).clamp_min(1e-300)


def sequence_log_likelihood(
    log_moves: Tensor, lumps: Tensor, node: Tensor, phi: Tensor, start: Tensor | None = None
) -> Tensor:
    """Each cell's log P(phi_1..phi_T | phi_0, its inputs) under a hidden-phase chain (the forward
    algorithm, scaled per window), its first hidden state drawn from the chain's stationary law
    at its first window's inputs given phi_0.

    Args:
        log_moves: ``G x S x S`` log P at ``G`` input nodes.
        lumps: ``(S,)`` each state's phi.
        node: ``n x T`` int64: the node of each cell's inputs during each window.
        phi: ``n x (T + 1)`` int64 phi at the windows' edges.
        start: ``n x S`` each cell's first hidden state's law given phi_0 (zero outside
            phi_0's lump); None: the stationary law at the first window's node.

    Returns:
        ``(n,)`` float64 log-likelihoods.
    """
    return expected_moves(log_moves.detach().exp(), lumps, node, phi, start)[0]


@torch.no_grad()
def expected_moves(
    moves: Tensor,
    lumps: Tensor,
    node: Tensor,
    phi: Tensor,
    start: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The forward-backward pass: each cell's log-likelihood (as
    :func:`sequence_log_likelihood`), the expected number of each move at each node given the
    sequences ``G x S x S``, and the first hidden state's posterior law ``n x S``. By Fisher's
    identity the likelihood's gradient is that of ``sum(counts * log P) + sum(first * log
    start law)`` with the expectations held fixed (what :func:`fit_phase_law` differentiates:
    no autograd graph through the windows; the windows run in compiled code, one cell after
    another: a Python loop over windows of batched torch ops with autograd cost 9-17x more per
    evaluation at 300 cells x 300 windows, docs/kinds.md; cells over numba's threads lost on a
    busy 2-core box, 6x slower than one thread, docs/kinds.md).

    Args: as :func:`sequence_log_likelihood`, with ``moves`` (P, not log P) ``G x S x S``.
    """
    if start is None:
        start = _start_law(moves.to(DTYPE), node, (phi[:, :1] == lumps).to(DTYPE))
    # C-contiguous arrays of fixed dtypes: one compiled signature, cached on disk
    args = [np.ascontiguousarray(t.detach().cpu().numpy(), dtype=d) for t, d in (
        (moves, np.float64), (lumps, np.int64), (node, np.int64), (phi, np.int64),
        (start, np.float64))]  # fmt: skip
    ll, counts, first = _forward_backward(*args)
    return torch.from_numpy(ll), torch.from_numpy(counts), torch.from_numpy(first)


@torch.no_grad()
def window_log_likelihoods(
    moves: Tensor, lumps: Tensor, node: Tensor, phi: Tensor, start: Tensor | None = None
) -> Tensor:
    """Each cell's log P(phi_t+1 | phi_0..phi_t, its inputs) at every window ``t`` (``n x T``
    float64; summed over the windows, :func:`sequence_log_likelihood`'s): the forward pass's
    log scale per window. Args as :func:`expected_moves`."""
    if start is None:
        start = _start_law(moves.to(DTYPE), node, (phi[:, :1] == lumps).to(DTYPE))
    args = [np.ascontiguousarray(t.detach().cpu().numpy(), dtype=d) for t, d in (
        (moves, np.float64), (lumps, np.int64), (node, np.int64), (phi, np.int64),
        (start, np.float64))]  # fmt: skip
    return torch.from_numpy(_forward_windows(*args))


@numba.njit(cache=True)
def _lump_members(
    lumps: np.ndarray, s: int
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Each lump's states in order (``members[l, :sizes[l]]``) and their counts."""
    members = np.zeros((2, s), dtype=np.int64)
    sizes = np.zeros(2, dtype=np.int64)
    for a in range(s):
        members[lumps[a], sizes[lumps[a]]] = a
        sizes[lumps[a]] += 1
    return members, sizes


@numba.njit(cache=True)
def _forward_step(
    before: np.ndarray,
    after: np.ndarray,
    moves: np.ndarray,
    g: int,
    members: np.ndarray,
    sizes: np.ndarray,
    was: int,
    seen: int,
) -> float:  # pragma: no cover - compiled
    """One window of the scaled forward pass: ``after`` (zero outside the lump ``seen``) from
    ``before`` through the moves at node ``g``, scaled to sum to one; returns the scale ``c``
    (this window's likelihood given the past). From every state at the first window
    (``was`` < 0: the start law as given), then only from the lump ``was`` seen at the
    window's start."""
    s, first = moves.shape[1], was < 0
    na, nb = (s if first else sizes[was]), sizes[seen]
    after[:] = 0.0
    c = 0.0
    for jb in range(nb):
        b = members[seen, jb]
        v = 0.0
        for ja in range(na):
            a = ja if first else members[was, ja]
            v += before[a] * moves[g, a, b]
        after[b] = v
        c += v
    c = max(c, 1e-300)
    inverse = 1.0 / c
    for jb in range(nb):
        after[members[seen, jb]] *= inverse
    return c


@numba.njit(cache=True)
def _forward_windows(
    moves: np.ndarray, lumps: np.ndarray, node: np.ndarray, phi: np.ndarray, start: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """The scaled forward pass of :func:`_forward_backward` alone, each window's log scale
    kept."""
    n, s, steps = node.shape[0], moves.shape[1], node.shape[1]
    members, sizes = _lump_members(lumps, s)
    out = np.zeros((n, steps))
    alpha, ahead = np.zeros(s), np.zeros(s)
    for i in range(n):
        alpha[:] = start[i, :]
        for t in range(steps):
            was = -1 if t == 0 else phi[i, t]  # the first window: from every state
            c = _forward_step(alpha, ahead, moves, node[i, t], members, sizes, was, phi[i, t + 1])
            alpha[:] = ahead
            out[i, t] = math.log(c)
    return out


@numba.njit(cache=True)
def _forward_backward(
    moves: np.ndarray, lumps: np.ndarray, node: np.ndarray, phi: np.ndarray, start: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Per cell the scaled forward pass (alpha, its scales) then the backward one (beta),
    adding each window's expected moves to its node's counts.

    After the first window alpha is zero outside the lump seen, so only the moves between the
    lumps seen at a window's edges are summed (``members[l, :sizes[l]]``: lump ``l``'s states
    in order): the terms left out are exact zeros. The scales' logarithm is taken of their
    running product (one log per ~1e250 of it, not one per window)."""
    n, nodes, s = node.shape[0], moves.shape[0], moves.shape[1]
    members, sizes = _lump_members(lumps, s)
    ll = np.zeros(n)
    first = np.zeros((n, s))
    counts = np.zeros((nodes, s, s))
    steps = node.shape[1]
    alphas = np.zeros((steps + 1, s))
    scales = np.empty(steps)
    beta, ahead, back = np.empty(s), np.zeros(s), np.empty(s)
    for i in range(n):
        alphas[0, :] = start[i, :]
        total, product = 0.0, 1.0
        for t in range(steps):
            was = -1 if t == 0 else phi[i, t]  # the first window: from every state
            c = _forward_step(alphas[t], alphas[t + 1], moves, node[i, t], members, sizes, was,
                              phi[i, t + 1])  # fmt: skip
            scales[t] = 1.0 / c
            product *= c
            if product < 1e-250:
                total += math.log(product)
                product = 1.0
        ll[i] = total + math.log(product)
        beta[:] = 1.0
        for t in range(steps - 1, -1, -1):
            g, was, seen = node[i, t], phi[i, t], phi[i, t + 1]
            na, nb = (s if t == 0 else sizes[was]), sizes[seen]
            for jb in range(nb):
                b = members[seen, jb]
                ahead[b] = beta[b] * scales[t]
            # beta at the window's start is read only in the lump seen there (all at the first)
            for ja in range(na):
                a = ja if t == 0 else members[was, ja]
                alpha = alphas[t, a]
                v = 0.0
                for jb in range(nb):
                    b = members[seen, jb]
                    w = moves[g, a, b] * ahead[b]
                    counts[g, a, b] += alpha * w
                    v += w
                back[a] = v
            for ja in range(na):
                a = ja if t == 0 else members[was, ja]
                beta[a] = back[a]
        first[i, :] = alphas[0, :] * beta
    return ll, counts, first


def input_grid(bounds: Sequence[tuple[float, float]], nodes: int) -> list[Tensor]:
    """Each input's ``nodes`` evenly spaced values over its bounds (one where the bounds are one
    point)."""
    return [torch.linspace(lo, hi, nodes if hi > lo else 1, dtype=DTYPE) for lo, hi in bounds]


def grid_points(axes: Sequence[Tensor]) -> Tensor:
    """The grid's nodes ``G x d`` in C order (the last input fastest, as a
    :class:`~surrogate.simulate.classes.ClassTable`'s strides)."""
    return torch.cartesian_prod(*axes).reshape(-1, len(axes))


def nearest_node(z: Tensor, axes: Sequence[Tensor]) -> Tensor:
    """Each point's nearest grid node: ``(..., d)`` inputs -> ``(...)`` int64 flat index."""
    index = torch.zeros(z.shape[:-1], dtype=torch.int64)
    for j, axis in enumerate(axes):
        n = len(axis)
        if n == 1:
            continue
        lo, hi = float(axis[0]), float(axis[-1])
        pos = ((z[..., j] - lo) * ((n - 1) / (hi - lo))).round().clamp(0, n - 1).long()
        index = index * n + pos
    return index


@dataclass(frozen=True)
class PhaseFitSettings:
    """How a hidden-phase law is fitted: ``bumps`` per input (:class:`InputBasis`), the ridge
    ``penalty`` on the basis weights (a Gaussian prior's precision), ``nodes`` per input of the
    grid the inputs are read on, L-BFGS's ``max_iterations`` and ``tolerance`` (it stops when
    an iteration changes the objective, the penalised log-likelihood per window, or any weight
    by less)."""

    bumps: int = 4
    penalty: float = 1.0
    nodes: int = 64
    max_iterations: int = 200
    #: 1e-9 per window (3e-4 nats over E. coli's 300,000): below it the fits only wandered
    #: along flat directions, their held-out likelihood within ~1e-8 per window (docs/kinds.md)
    tolerance: float = 1e-9


def _initial_weights(layout: PhaseLayout, basis: InputBasis, phi: Tensor, seed: int) -> Tensor:
    """Logits near the two-state chain: each lump's sojourn spread over its phases in series,
    plus a little seeded noise (phases that start equal stay equal)."""
    s = layout.n_states
    lumps = layout.lumps().tolist()
    before, after = phi[:, :-1], phi[:, 1:]
    weights = torch.zeros(basis.n_features, s, s, dtype=DTYPE)
    for a in range(s):
        lump, k = lumps[a], layout.per_lump[lumps[a]]
        mine = before == lump
        switch = float((after[mine] != lump).double().mean()) if bool(mine.any()) else 0.1
        rate = min(max(k * switch, 1e-4), 0.5)  # leaving a phase, per window
        for b in range(s):
            if a != b:
                last = a + 1 == s or lumps[a + 1] != lump
                leaves = lumps[b] != lump
                weights[0, a, b] = math.log(rate if (not leaves or last) else 0.3 * rate)
    generator = torch.Generator().manual_seed(seed)
    return weights + 0.1 * torch.randn(weights.shape, generator=generator, dtype=DTYPE)


def log_likelihood_with_gradient(
    law: PhaseLaw, points: Tensor, node: Tensor, phi: Tensor
) -> Tensor:
    """The sequences' log-likelihood (a float64 scalar) under ``law`` read at the grid
    ``points`` (``G x d``; ``node`` ``n x T``: each window's, ``phi`` ``n x (T + 1)``), its
    gradient added to ``law.weights.grad`` (the weights must require it). By Fisher's identity
    the gradient is that of ``sum(counts * log P) + sum(first * log start law)`` with the
    expectations of :func:`expected_moves` held fixed: no autograd graph through the windows.
    """
    log_moves = law.log_moves(points)
    lumps = law.layout.lumps()
    start = _start_law(log_moves.exp(), node, (phi[:, :1] == lumps).to(DTYPE))
    ll, counts, first = expected_moves(log_moves.detach().exp(), lumps, node, phi,
                                       start.detach())  # fmt: skip
    surrogate = ((counts * log_moves.clamp_min(-1e300)).sum()
                 + (first * start.clamp_min(1e-300).log()).sum())  # fmt: skip
    surrogate.backward()
    return ll.sum()


def fit_phase_law(
    inputs: Tensor,
    phi: Tensor,
    layout: PhaseLayout,
    bounds: Sequence[tuple[float, float]],
    settings: PhaseFitSettings = PhaseFitSettings(),
    seed: int = 0,
) -> tuple[PhaseLaw, dict[str, Any]]:
    """The hidden-phase law of ``layout`` that maximises the likelihood of the sequences.

    Args:
        inputs: ``n x T x d`` each cell's inputs during each window.
        phi: ``n x (T + 1)`` int64 phi at the windows' edges.
        layout: the hidden states and their moves.
        bounds: ``d`` pairs (lo, hi): the basis's span (inputs outside are clamped).
        settings: the basis, penalty, grid and optimiser's budget.
        seed: the initial logits' noise.

    Returns:
        The law and its fit's facts (``log_likelihood`` per window, ``iterations``,
        ``seconds``).

    Raises:
        NumericalError: the likelihood is not finite.
    """
    t0 = time.perf_counter()
    basis = InputBasis(tuple((float(a), float(b)) for a, b in bounds), settings.bumps)
    axes = input_grid(basis.bounds, settings.nodes)
    points = grid_points(axes)
    node = nearest_node(inputs.to(DTYPE), axes)
    phi = phi.long()
    weights = _initial_weights(layout, basis, phi, seed).requires_grad_(True)
    law = PhaseLaw(layout, basis, weights)
    lumps = layout.lumps()
    windows = phi.shape[0] * (phi.shape[1] - 1)
    optimiser = torch.optim.LBFGS([weights], lr=1.0, max_iter=settings.max_iterations,
                                  history_size=20, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-9, tolerance_change=settings.tolerance)  # fmt: skip
    evaluations = 0

    def closure() -> Tensor:
        nonlocal evaluations
        evaluations += 1
        optimiser.zero_grad()
        # weights.grad: d ll / dw
        ll = log_likelihood_with_gradient(law, points, node, phi)
        assert weights.grad is not None
        with torch.no_grad():
            ridge = torch.cat([torch.zeros_like(weights[:1]), weights[1:]])  # no intercepts
            penalty = 0.5 * settings.penalty * (ridge**2).sum()
            weights.grad.copy_((settings.penalty * ridge - weights.grad) / windows)
        value = (-ll + penalty) / windows
        if not torch.isfinite(value):
            raise NumericalError(f"hidden-phase fit {layout.per_lump}: the likelihood is not "
                                 f"finite")  # fmt: skip
        return value

    with one_thread(True):  # small tensors: a second torch thread only waits (same results)
        optimiser.step(closure)
    weights.requires_grad_(False)
    with torch.no_grad():
        ll = float(sequence_log_likelihood(law.log_moves(points), lumps, node, phi).sum())
    return law, {"per_lump": list(layout.per_lump), "log_likelihood": ll / windows,
                 "evaluations": evaluations, "seconds": time.perf_counter() - t0}  # fmt: skip


def score(law: PhaseLaw, inputs: Tensor, phi: Tensor, nodes: int) -> Tensor:
    """Each cell's log-likelihood ``(n,)`` under ``law`` (its inputs read on the grid of
    ``nodes`` per input the fit used)."""
    axes = input_grid(law.basis.bounds, nodes)
    with torch.no_grad():
        log_moves = law.log_moves(grid_points(axes))
        return sequence_log_likelihood(log_moves, law.layout.lumps(), nearest_node(
            inputs.to(DTYPE), axes), phi.long())  # fmt: skip


def held_out_split(n_cells: int, held_out: float) -> tuple[int, int]:
    """The held-out and the fitted cells of ``n_cells`` for the share ``held_out``
    (:func:`select_phases`' split: at least one each way)."""
    m = min(max(1, round(held_out * n_cells)), n_cells - 1)
    return m, n_cells - m


@dataclass(frozen=True)
class PhaseSelection:
    """Which phase counts :func:`select_phases` tries, and how it scores them.

    Attributes:
        max_per_lump: the most phases a lump may get.
        structure: the moves (:class:`PhaseLayout`).
        held_out: the share of cells held out (at least one cell each way).
        per_lump: fixed phase counts (no selection; the held-out score is still reported).
    """

    max_per_lump: int
    structure: str = SERIES
    held_out: float = 0.25
    per_lump: tuple[int, int] | None = None


def select_phases(
    inputs: Tensor,
    phi: Tensor,
    bounds: Sequence[tuple[float, float]],
    selection: PhaseSelection,
    settings: PhaseFitSettings = PhaseFitSettings(),
    seed: int = 0,
) -> tuple[PhaseLaw, dict[str, Any]]:
    """The phase counts chosen by held-out likelihood, and their law.

    From ``(1, 1)`` (the two-state chain), each round fits one more phase in either lump and
    keeps the better one while its held-out gain (summed over held-out cells) exceeds twice its
    standard error (from the cells' paired differences): a phase is added only where held-out
    cells tell it apart from noise. Fits are on the other cells.

    Args:
        inputs: ``n x T x d`` each cell's inputs during each window.
        phi: ``n x (T + 1)`` phi at the windows' edges.
        bounds: the inputs' span.
        selection: the counts tried, the moves and the held-out share
            (:class:`PhaseSelection`).
        settings: the fit's settings.
        seed: the split's and the fits' seed.

    Returns:
        The chosen law (fitted on the training cells) and a report: ``per_lump``, ``candidates``
        (each fit's phase counts, train and held-out log-likelihood per window, seconds),
        ``held_out_cells``.
    """
    structure, per_lump = selection.structure, selection.per_lump
    n = phi.shape[0]
    m = held_out_split(n, selection.held_out)[0]
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    test, train = order[:m], order[m:]
    windows = m * (phi.shape[1] - 1)
    candidates: list[dict[str, Any]] = []

    def fitted(counts: tuple[int, int]) -> tuple[PhaseLaw, Tensor]:
        law, info = fit_phase_law(inputs[train], phi[train], PhaseLayout(counts, structure),
                                  bounds, settings, seed)  # fmt: skip
        cells = score(law, inputs[test], phi[test], settings.nodes)
        info["held_out_log_likelihood"] = float(cells.sum()) / windows
        candidates.append(info)
        log.info("hidden phases %s: held-out log-likelihood %.6f per window (%.1f s)", counts,
                 info["held_out_log_likelihood"], info["seconds"])  # fmt: skip
        return law, cells

    counts = per_lump or (1, 1)
    best, best_cells = fitted(counts)
    while per_lump is None:
        trials = [(counts[0] + 1, counts[1]), (counts[0], counts[1] + 1)]
        scored = [(c, *fitted(c)) for c in trials if max(c) <= selection.max_per_lump]
        if not scored:
            break
        c, law, cells = max(scored, key=lambda item: float(item[2].sum()))
        diff = cells - best_cells
        gain, error = float(diff.sum()), float(diff.std()) * math.sqrt(m) if m > 1 else 0.0
        if not gain > 2.0 * error:
            break
        counts, best, best_cells = c, law, cells
    return best, {"per_lump": list(counts), "structure": structure, "candidates": candidates,
                  "held_out_cells": m}  # fmt: skip


def sojourn_law(moves: Tensor, lumps: Tensor, lump: int, windows: int) -> Tensor:
    """P(a sojourn in ``lump`` lasts k windows), k = 1..``windows``, at stationarity: entered
    by the stationary flow from the other lump, then the chain's moves within it.

    Args:
        moves: ``S x S`` one window's law (a hidden-phase chain's, or an exact ``exp(Q dt)``).
        lumps: ``(S,)`` each state's phi.
        lump: 0 or 1.
        windows: the longest sojourn counted.

    Returns:
        ``(windows,)`` float64 probabilities (their sum falls short of 1 by the tail's mass).
    """
    moves = moves.to(DTYPE)
    inside, outside = lumps == lump, lumps != lump
    flow = stationary(moves)[outside] @ moves[outside][:, inside]
    entry = flow / flow.sum()
    stay = moves[inside][:, inside]
    leave = 1.0 - stay.sum(-1)
    out = torch.empty(windows, dtype=DTYPE)
    for k in range(windows):
        out[k] = entry @ leave
        entry = entry @ stay
    return out


def stationary_leaving(moves: Tensor, lumps: Tensor) -> Tensor:
    """Each lump's one-window leave probability at stationarity: P(phi' != l | phi = l) with
    the hidden state from the stationary law within lump ``l`` (its mean sojourn's inverse, in
    windows; the two-state chain's psi_0 and 1 - psi_1).

    Args:
        moves: ``(..., S, S)`` one window's law.
        lumps: ``(S,)`` each state's phi.

    Returns:
        ``(..., 2)`` float64: lump 0's, then lump 1's.
    """
    moves = moves.to(DTYPE)
    pi = stationary(moves)
    out = []
    for lump in (0, 1):
        inside = lumps == lump
        leave = moves[..., inside, :][..., :, ~inside].sum(-1)  # (..., K_l)
        weight = pi[..., inside]
        out.append((weight * leave).sum(-1) / weight.sum(-1).clamp_min(1e-300))
    return torch.stack(out, dim=-1)


def match_leaving(
    moves: Tensor, lumps: Tensor, target: Tensor, tolerance: float = 1e-4, rounds: int = 500
) -> tuple[Tensor, Tensor]:
    """``moves`` with each lump's moves out of it scaled (their odds against the row's other
    moves, one factor per lump and point) so that its one-window leave probability at
    stationarity (:func:`stationary_leaving`) is ``target``: the means of the sojourns set,
    their shape (the phases' relative exits and moves within the lump) kept.

    Args:
        moves: ``(..., S, S)`` one window's law (rows sum to 1).
        lumps: ``(S,)`` each state's phi.
        target: ``(..., 2)`` each lump's leave probability wanted, in (0, 1).
        tolerance: the largest relative error of the matched leave probabilities (1e-4: psi
            itself is known to ~1 %; on E. coli's tables the ratio step stalled at 2e-8 to
            4e-5 after 200 rounds, short of the 1e-10 first asked).
        rounds: the most rounds of the root search in the log factor per lump and point: a
            secant step on the log leave probability (the ratio step, slope 1, first),
            bisecting the bracket where a step would leave it.

    Returns:
        The matched moves ``(..., S, S)`` float64 and the factors ``(..., 2)`` on the leaving
        odds (1: the sequences' means were psi's already).

    Raises:
        NumericalError: the leave probabilities are not matched within ``tolerance``.
    """
    moves, target = moves.to(DTYPE), target.to(DTYPE).clamp(1e-12, 1 - 1e-12)
    lumps = lumps.to(moves.device)
    outside = (lumps.unsqueeze(-1) != lumps).to(DTYPE)  # (S, S): the move leaves a's lump
    log_target = target.log()
    x = torch.zeros(target.shape, dtype=DTYPE, device=moves.device)  # log factor per lump
    # a bracket on x per lump and point (f < 0 at lo, f > 0 at hi), once seen
    lo = torch.full_like(x, -math.inf)
    hi = torch.full_like(x, math.inf)
    slope = torch.ones_like(x)  # d log(leave) / d log(factor): 1 while leaving is rare
    last_x = last_f = None
    matched, error = moves, math.inf
    for _ in range(rounds):
        # each row's factor is its own lump's: c on the leaving moves, then renormalised
        row = x[..., lumps].exp().unsqueeze(-1)  # (..., S, 1)
        scaled = moves * (1.0 + (row - 1.0) * outside)
        matched = scaled / scaled.sum(-1, keepdim=True)
        leave = stationary_leaving(matched, lumps)
        error = float((leave / target - 1.0).abs().max())
        if error <= tolerance:
            return matched, x.exp()
        f = leave.clamp_min(1e-300).log() - log_target
        lo = torch.where(f < 0, torch.maximum(lo, x), lo)
        hi = torch.where(f > 0, torch.minimum(hi, x), hi)
        # with moves across lumps (structure full) a lump's root moves with the other's
        # factor: a bracket that closed without a match is stale, and is dropped
        stale = (hi - lo) < 1e-9
        lo, hi = lo.masked_fill(stale, -math.inf), hi.masked_fill(stale, math.inf)
        if last_x is not None and last_f is not None:
            # the secant's slope: leave grows faster than the factor where a slow phase
            # holds most of the lump (fewer cells reach it, and it empties sooner), and the
            # plain ratio step (slope 1) then overshoots and oscillates
            dx = x - last_x
            moved = dx.abs() > 1e-12
            secant = torch.where(moved, (f - last_f) / torch.where(moved, dx, 1.0), slope)
            slope = torch.where(secant > 0, secant.clamp(0.1, 10.0), slope)
        step = x - f / slope
        # a step out of the bracket bisects it (the leave probability rises with the factor)
        bracketed = lo.isfinite() & hi.isfinite()
        outside_bracket = (step <= lo) | (step >= hi)
        step = torch.where(bracketed & outside_bracket, 0.5 * (lo + hi), step)
        last_x, last_f, x = x, f, step
    raise NumericalError(f"the hidden-phase chain's leave probabilities match psi's only to "
                         f"{error:.2g} (relative) after {rounds} rounds")  # fmt: skip


def mean_sojourn(moves: Tensor, lumps: Tensor, lump: int) -> float:
    """The mean sojourn in ``lump`` (windows) of the chain ``moves`` (``S x S``) at
    stationarity: ``entry (I - P_ll)^-1 1``."""
    moves = moves.to(DTYPE)
    inside, outside = lumps == lump, lumps != lump
    flow = stationary(moves)[outside] @ moves[outside][:, inside]
    stay = moves[inside][:, inside]
    eye = torch.eye(stay.shape[0], dtype=DTYPE)
    ones = torch.ones(stay.shape[0], 1, dtype=DTYPE)
    return float((flow / flow.sum()) @ torch.linalg.solve(eye - stay, ones))


__all__ = [
    "STRUCTURES",
    "InputBasis",
    "PhaseFitSettings",
    "PhaseLaw",
    "PhaseLayout",
    "PhaseSelection",
    "fit_phase_law",
    "held_out_split",
    "input_grid",
    "match_leaving",
    "mean_sojourn",
    "nearest_node",
    "score",
    "select_phases",
    "sequence_log_likelihood",
    "sojourn_law",
    "stationary",
    "stationary_leaving",
    "window_log_likelihoods",
]

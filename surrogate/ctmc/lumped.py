"""Exact lumped switching probabilities of a small reaction network, for cells adapted to their inputs.

A two-state abstraction replaces an internal network by a Markov chain over one boolean property
phi of its state (e.g. RUN). For a network whose reachable state space is small (the four motors
of an E. coli cell: 15 states; anything up to a few thousand states), the abstraction's transition
probabilities can be computed exactly from the generator Q of the window's rates:

    psi_phi = sum_{s in lump phi} pi(s | phi) * sum_{s' in lump 1} exp(Q dt)[s, s'],

where pi is the stationary law of Q (the network adapted to the current inputs) and pi(. | phi)
its restriction to lump phi, renormalised. ``psi_phi`` is P(phi' = 1 | phi) after one window dt.
This is the psi of cells adapted to their current inputs (the internal state at its stationary
law there), the reference a learned psi is scored against where the population lives. It is not
the best a two-state chain can do: a moving cell's internal state lags its inputs, and psis
learned from the full model's own transitions pass fidelity checks the chain driven by this one
fails (the fidelity table of docs/fidelity.md).

Everything is batched over cells: ``(n, R)`` rate constants give ``(n, K, K)`` generators.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from surrogate.ctmc.network import ReactionNetwork, make_propensity_fn
from surrogate.threads import one_thread

__all__ = [
    "StateSpace",
    "lumped_age_psi",
    "lumped_class_step",
    "lumped_psi",
    "relaxation_time",
    "stationary_distribution",
]

#: default bound on the number of enumerated states (a generator of K^2 float64 per cell)
MAX_STATES = 5000


@dataclass(frozen=True, eq=False)
class StateSpace:
    """The states a network reaches from ``initial`` counts, and its transitions between them.

    Attributes:
        network: the reaction network.
        states: ``K x S`` int64 reachable states, ``states[0]`` = the initial state.
        source, target, reaction: int64 ``(T,)``: firing ``reaction[t]`` in ``source[t]`` leads to
            ``target[t]`` (only reactions that can fire there, i.e. non-zero mass-action factor).

    Example:
        >>> net = ReactionNetwork.from_reactions(["A", "B"], [("a->b", {"A": 1}, {"B": 1})])
        >>> StateSpace.enumerate(net, torch.tensor([2, 0])).states.tolist()
        [[2, 0], [1, 1], [0, 2]]
    """

    network: ReactionNetwork
    states: Tensor
    source: Tensor
    target: Tensor
    reaction: Tensor

    @classmethod
    def enumerate(
        cls, network: ReactionNetwork, initial: Tensor, max_states: int = MAX_STATES
    ) -> StateSpace:
        """Breadth-first enumeration of the states reachable from ``initial`` (``S`` counts).

        Raises ``ValueError`` when more than ``max_states`` states are reachable (an open or large
        network has no exact lumped psi this way).
        """
        start = tuple(int(v) for v in torch.as_tensor(initial).reshape(-1).tolist())
        if len(start) != network.n_species or min(start) < 0:
            raise ValueError(
                f"initial state must be {network.n_species} non-negative counts, got {start}"
            )
        reactants = network.reactants.tolist()
        stoich = network.stoichiometry.tolist()
        index = {start: 0}
        order = [start]
        src, tgt, rxn = [], [], []
        head = 0
        while head < len(order):
            state = order[head]
            for r, (need, change) in enumerate(zip(reactants, stoich, strict=True)):
                if any(x < k for x, k in zip(state, need, strict=True)):
                    continue  # mass-action factor prod binom(x, k) is zero
                nxt = tuple(x + d for x, d in zip(state, change, strict=True))
                if nxt == state:
                    continue  # a reaction that changes nothing is no transition
                j = index.get(nxt)
                if j is None:
                    if len(order) >= max_states:
                        raise ValueError(
                            f"more than max_states={max_states} states are reachable from "
                            f"{start}; the exact lumped psi needs a small state space"
                        )
                    j = index[nxt] = len(order)
                    order.append(nxt)
                src.append(head)
                tgt.append(j)
                rxn.append(r)
            head += 1
        as_long = lambda v: torch.tensor(v, dtype=torch.int64)  # noqa: E731
        return cls(network, as_long(order), as_long(src), as_long(tgt), as_long(rxn))

    @property
    def n_states(self) -> int:
        """Number of states ``K``."""
        return int(self.states.shape[0])

    def mass_action(self, rate_constants: Tensor) -> Tensor:
        """Propensities ``n x K x R`` of every reaction in every state (float64).

        Args:
            rate_constants: ``n x R`` mass-action rate constants per cell.
        """
        fn = make_propensity_fn(self.network.reactants, rate_constants.device)
        k, r = self.n_states, self.network.n_reactions
        n = rate_constants.shape[0]
        states = self.states.to(rate_constants.device).repeat(n, 1)  # (n K, S)
        rates = rate_constants.to(torch.float64).repeat_interleave(k, dim=0)  # (n K, R)
        return fn(states, rates).reshape(n, k, r)

    def propensities(
        self, rate_constants: Tensor, propensity: Callable[[Tensor, Tensor], Tensor] | None = None
    ) -> Tensor:
        """Propensities ``n x K x R`` of every reaction in every state (float64).

        Args:
            rate_constants: ``n x R`` mass-action rate constants, or ``n x P`` parameters of
                ``propensity``.
            propensity: optional ``f(states (m x S) float64, params (m x P)) -> (m x R)`` for
                non-mass-action kinetics; ``None`` means mass action.
        """
        if propensity is None:
            return self.mass_action(rate_constants)
        n, k = rate_constants.shape[0], self.n_states
        states = self.states.to(rate_constants.device, torch.float64).repeat(n, 1)
        params = rate_constants.to(torch.float64).repeat_interleave(k, dim=0)
        return propensity(states, params).reshape(n, k, -1).to(torch.float64)

    def generator(
        self, rate_constants: Tensor, propensity: Callable[[Tensor, Tensor], Tensor] | None = None
    ) -> Tensor:
        """Generators ``n x K x K`` (float64, rows summing to 0) at each cell's parameters.

        Args:
            rate_constants: ``n x R`` mass-action rate constants, or ``n x P`` parameters of
                ``propensity``.
            propensity: optional ``f(states (m x S) float64, params (m x P)) -> (m x R)`` for
                non-mass-action kinetics; ``None`` means mass action.
        """
        return self.generator_of(self.propensities(rate_constants, propensity))

    def generator_of(self, a: Tensor) -> Tensor:
        """Generators ``n x K x K`` (float64, rows summing to 0) from propensities.

        Args:
            a: ``n x K x R`` propensities of every reaction in every state
                (:meth:`propensities`); not checked (negative or non-finite ones give a
                generator that is not one).
        """
        n, k = a.shape[0], self.n_states
        device = a.device
        src, tgt, rxn = (t.to(device) for t in (self.source, self.target, self.reaction))
        rates = a[:, src, rxn]  # (n, T)
        q = torch.zeros((n, k * k), dtype=torch.float64, device=device)
        q.index_add_(1, src * k + tgt, rates)
        q = q.view(n, k, k)
        return q - torch.diag_embed(q.sum(-1))


def stationary_distribution(q: Tensor) -> Tensor:
    """Stationary law ``n x K`` of generators ``q`` (``n x K x K``, irreducible), in float64.

    Solves pi Q = 0 with sum(pi) = 1 after scaling each generator by its largest exit rate (the
    uniformised chain has the same stationary law and entries of order one); round-off negatives
    are clamped to 0 and the result renormalised.
    """
    q = q.to(torch.float64)
    scale = (-torch.diagonal(q, dim1=-2, dim2=-1)).amax(-1).clamp_min(1e-300)
    a = (q / scale[:, None, None]).mT.clone()
    a[:, -1, :] = 1.0  # replace one balance equation by the normalisation
    b = torch.zeros(q.shape[:-1], dtype=torch.float64, device=q.device)
    b[:, -1] = 1.0
    with _lu_threads(a):
        pi = torch.linalg.solve(a, b).clamp_min(0.0)
    return pi / pi.sum(-1, keepdim=True)


#: the largest matrix side whose batched LU (torch.linalg.solve) keeps the process's threads:
#: with torch's threads set explicitly to 2 or more (a job's ``threads=2``), torch 2.13's CPU
#: build (oneMKL 2024.2) reports "Parameter 6 was incorrect on entry to DLASWP" and hangs on a
#: batch of two or more 151 x 151 systems (measured: 150 solves, 151 and larger hang; a batch
#: of one, the default thread count or one thread solve). Larger ones run on one thread.
LU_MAX_THREADED_SIDE = 128


def _lu_threads(a: Tensor) -> contextlib.AbstractContextManager[None]:
    """One torch thread for a batched CPU LU of matrices larger than
    :data:`LU_MAX_THREADED_SIDE`."""
    return one_thread(a.device.type == "cpu" and a.shape[-1] > LU_MAX_THREADED_SIDE)


def relaxation_time(q: Tensor) -> Tensor:
    """``1 / spectral gap`` ``(n,)`` of generators ``q`` (``n x K x K``, irreducible), float64.

    The gap is the smallest decay rate ``-Re(lambda)`` over the non-zero eigenvalues of Q: the
    slowest mode of the chain, so the autocorrelation of any function of the state (e.g. the
    lump phi) decays at least as fast as ``exp(-lag / tau)`` at long lags (exactly so when that
    function has a component along the slowest mode). ``inf`` for a chain with one state.

    Example:
        >>> q = torch.tensor([[[-1.0, 1.0], [2.0, -2.0]]])  # a telegraph: gap = 1 + 2
        >>> relaxation_time(q)
        tensor([0.3333], dtype=torch.float64)
    """
    q = q.to(torch.float64)
    if q.shape[-1] < 2:
        return torch.full(q.shape[:1], torch.inf, dtype=torch.float64, device=q.device)
    rates = -torch.linalg.eigvals(q).real  # (n, K): one ~0 (the stationary law), the rest > 0
    slowest = rates.sort(-1).values[:, 1]
    return 1.0 / slowest.clamp_min(1e-300)


def lumped_psi(q: Tensor, lump: Tensor, dt: float) -> Tensor:
    """Exact ``P(phi' = 1 | phi)`` after a window ``dt``, ``n x 2`` (column 0: phi = 0, 1: phi = 1).

    Args:
        q: ``n x K x K`` generators (rates held fixed over the window).
        lump: ``K`` bool, the property phi of each state.
        dt: window length (s).

    The chain starts from the stationary law of ``q`` restricted to the current lump (see the
    module docstring). A lump with zero stationary mass gets NaN.
    """
    lump = lump.to(q.device)
    pi = stationary_distribution(q)  # (n, K)
    p = torch.linalg.matrix_exp(q.to(torch.float64) * dt).clamp_min(0.0)
    p = p / p.sum(-1, keepdim=True)
    to_one = p[:, :, lump].sum(-1)  # (n, K): P(phi' = 1 | s)
    out = []
    for phi in (False, True):
        w = pi * (lump == phi)
        out.append((w * to_one).sum(-1) / w.sum(-1))
    return torch.stack(out, -1).clamp(0.0, 1.0)


def lumped_age_psi(q: Tensor, lump: Tensor, dt: float, max_steps: int) -> Tensor:
    """Exact ``P(phi' = 1 | phi, age)`` of a chain observed every ``dt``, ``n x 2 x (A + 1)``.

    The two-state chain's memory limit: ``age`` = k windows since phi last changed (k = 0: it
    changed in the window just ended), ``A = max_steps``. Cells adapted to their inputs enter
    lump ``phi`` with the stationary flux ``pi P[other lump -> s]`` (P = exp(Q dt)); k windows
    later, having stayed, their state is that entrance law times ``P_phi,phi^k`` (P restricted to
    the lump), renormalised; psi is that law's chance of ending the next window in lump 1. As k
    grows the law tends to the lump's quasi-stationary law (not :func:`lumped_psi`'s
    stationary restriction, which mixes all ages), so the last column stands for ages >= A.

    Args:
        q: ``n x K x K`` generators (rates held fixed).
        lump: ``K`` bool, the property phi of each state.
        dt: window length (s).
        max_steps: the largest age ``A`` in windows.

    Returns:
        ``n x 2 x (A + 1)`` float64: ``[:, phi, k]`` = P(phi' = 1 | phi, age k).

    Example:
        >>> q = torch.tensor([[[-1.0, 1.0], [2.0, -2.0]]])  # one memoryless state per lump
        >>> psi = lumped_age_psi(q, torch.tensor([False, True]), 0.1, 3)
        >>> bool(torch.allclose(psi[0, 0], psi[0, 0, :1].expand(4)))  # no memory: flat in age
        True
    """
    if max_steps < 0:
        raise ValueError(f"max_steps must be >= 0, got {max_steps}")
    lump = lump.to(q.device)
    pi = stationary_distribution(q)
    p = torch.linalg.matrix_exp(q.to(torch.float64) * dt).clamp_min(0.0)
    p = p / p.sum(-1, keepdim=True)
    to_one = p[:, :, lump].sum(-1)  # (n, K)
    out = []
    for phi in (False, True):
        inside = (lump == phi).to(p.dtype)  # (K,)
        # entrance law: from the other lump into each state of this one, in one window
        law = torch.einsum("nk,nkj->nj", pi * (1.0 - inside), p) * inside
        stay = p * inside[None, :, None] * inside[None, None, :]  # P restricted to the lump
        ages = []
        for _ in range(max_steps + 1):
            law = law / law.sum(-1, keepdim=True)
            ages.append((law * to_one).sum(-1))
            law = torch.einsum("nk,nkj->nj", law, stay)
        out.append(torch.stack(ages, -1))
    return torch.stack(out, 1).clamp(0.0, 1.0)


def lumped_class_step(q: Tensor, classes: Tensor, n_classes: int, dt: float) -> Tensor:
    """Exact one-window class-to-class law of adapted cells, ``n x C x C`` float64.

    The K-lumps route's limit: the states are grouped into ``C`` classes (finer than phi, e.g.
    E. coli's (phi, number of CCW motors)); a cell adapted to its inputs sits in state s with
    the stationary law pi, so ``P(class' = b | class = a) = sum_{s in a, t in b} pi_s P_st /
    sum_{s in a} pi_s`` with ``P = exp(Q dt)``. Rows of classes with no stationary mass are
    uniform (never read by a chain started from the stationary law).

    Args:
        q: ``n x K x K`` generators (rates held fixed over the window).
        classes: ``K`` int64, the class of each state, in ``[0, n_classes)``.
        n_classes: ``C``.
        dt: window length (s).

    Example:
        >>> q = torch.tensor([[[-1.0, 1.0], [2.0, -2.0]]])  # two states, one class each
        >>> step = lumped_class_step(q, torch.tensor([0, 1]), 2, 0.1)
        >>> bool(torch.allclose(step[0], torch.linalg.matrix_exp(q[0].double() * 0.1)))
        True
    """
    member = torch.nn.functional.one_hot(classes.to(q.device).long(), n_classes).to(torch.float64)
    pi = stationary_distribution(q)  # (n, K)
    p = torch.linalg.matrix_exp(q.to(torch.float64) * dt).clamp_min(0.0)
    p = p / p.sum(-1, keepdim=True)
    flow = torch.einsum("sa,ns,nst,tb->nab", member, pi, p, member)
    mass = flow.sum(-1, keepdim=True)
    uniform = torch.full_like(flow, 1.0 / n_classes)
    return torch.where(mass > 0, flow / mass.clamp_min(1e-300), uniform)

"""The hidden-phase law (:mod:`surrogate.gp.phases`): the fit recovers a known phase chain, the
held-out choice of phase counts finds an Erlang on time and refuses phases a memoryless
telegraph does not have, the simulated sojourns follow the truth only with the right phases,
and on an enumerable network the fitted chain's mean sojourns match the exact lumped ones."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from surrogate.ctmc.lumped import StateSpace
from surrogate.ctmc.network import ReactionNetwork
from surrogate.errors import NumericalError
from surrogate.gp.phases import (
    InputBasis,
    PhaseFitSettings,
    PhaseLaw,
    PhaseLayout,
    PhaseSelection,
    expected_moves,
    fit_phase_law,
    grid_points,
    input_grid,
    log_likelihood_with_gradient,
    match_leaving,
    mean_sojourn,
    nearest_node,
    score,
    select_phases,
    sequence_log_likelihood,
    sojourn_law,
    stationary,
    stationary_leaving,
)
from surrogate.kinds.phases import phase_table
from surrogate.simulate.phases import PhaseDecision

#: a constant law over one input: the linear term only (no bumps)
FLAT = PhaseFitSettings(bumps=0, nodes=8, max_iterations=100)


def simulate_chain(moves: torch.Tensor, lumps: torch.Tensor, n: int, steps: int, seed: int):
    """``n`` cells of the hidden chain ``moves`` (``S x S``) from its stationary law for
    ``steps`` windows: phi ``n x (steps + 1)`` and one input per cell (uniform, unused)."""
    g = torch.Generator().manual_seed(seed)
    moves = moves.double()
    state = torch.multinomial(stationary(moves).expand(n, -1), 1, generator=g).squeeze(1)
    cdf = moves.cumsum(-1)
    out = [lumps[state]]
    for _ in range(steps):
        u = torch.rand(n, 1, generator=g, dtype=torch.float64)
        state = (u > cdf[state]).sum(-1).clamp(max=moves.shape[0] - 1)
        out.append(lumps[state])
    z = torch.rand(n, 1, 1, generator=g, dtype=torch.float64).expand(n, steps, 1)
    return z, torch.stack(out, 1)


def sojourns(phi: np.ndarray, lump: int) -> np.ndarray:
    """The complete sojourns (windows) in ``lump`` of each row of ``phi`` (``n x T``): those
    that start and end inside the record."""
    out = []
    for row in phi:
        edges = np.flatnonzero(np.diff(row)) + 1  # where phi changes
        for a, b in itertools.pairwise(edges):
            if row[a] == lump:
                out.append(b - a)
    return np.asarray(out)


def erlang_telegraph(on_phases: int, leave_on: float, leave_off: float):
    """Off: one phase left with ``leave_off`` per window; on: ``on_phases`` phases in series,
    each left with ``leave_on`` (an Erlang on time)."""
    s = 1 + on_phases
    p = torch.zeros(s, s, dtype=torch.float64)
    p[0, 0], p[0, 1] = 1 - leave_off, leave_off
    for a in range(1, s):
        p[a, a] = 1 - leave_on
        p[a, a + 1 if a + 1 < s else 0] = leave_on
    return p, torch.tensor([0] + [1] * on_phases)


def test_layout_and_basis_refuse_what_they_cannot_hold() -> None:
    with pytest.raises(ValueError, match="per_lump must be two phase counts >= 1"):
        PhaseLayout((0, 2))
    with pytest.raises(ValueError, match="structure must be one of"):
        PhaseLayout((1, 1), "cyclic")
    # series: stay, next phase, or the other lump's first phase; full: any move
    assert PhaseLayout((2, 2)).moves().sum() == 4 + 2 + 4
    assert PhaseLayout((2, 2), "full").moves().all()
    assert InputBasis(((0.0, 1.0), (0.0, 2.0)), 3).n_features == 1 + 2 * 4
    with pytest.raises(ValueError, match="weights must be 4 x 2 x 2"):
        PhaseLaw(PhaseLayout((1, 1)), InputBasis(((0.0, 1.0),), 2), torch.zeros(3, 2, 2))


def test_the_gradient_by_fishers_identity_is_the_likelihoods() -> None:
    """The fit differentiates expected counts (no graph through the windows): its gradient must
    be the log-likelihood's, checked against central differences."""
    p, lumps = erlang_telegraph(2, 0.3, 0.2)
    _z, phi = simulate_chain(p, lumps, 20, 40, seed=1)
    layout, basis = PhaseLayout((1, 2)), InputBasis(((0.0, 1.0),), 2)
    g = torch.Generator().manual_seed(0)
    weights = 0.3 * torch.randn(basis.n_features, 3, 3, generator=g, dtype=torch.float64)
    weights[0] -= 1.0
    node = torch.zeros(20, 40, dtype=torch.int64)
    point = torch.tensor([[0.3]], dtype=torch.float64)

    def loglik(w: torch.Tensor) -> float:
        return float(sequence_log_likelihood(PhaseLaw(layout, basis, w).log_moves(point), lumps,
                                             node, phi).sum())  # fmt: skip

    w = weights.clone().requires_grad_(True)
    log_likelihood_with_gradient(PhaseLaw(layout, basis, w), point, node, phi)
    free = layout.moves() & ~torch.eye(3, dtype=torch.bool)
    for f in range(basis.n_features):
        for a, b in free.nonzero().tolist():
            step = torch.zeros_like(weights)
            step[f, a, b] = 1e-5
            numeric = (loglik(weights + step) - loglik(weights - step)) / 2e-5
            assert w.grad[f, a, b].item() == pytest.approx(numeric, rel=1e-4, abs=1e-6)


def test_one_phase_per_lump_is_the_two_state_chain() -> None:
    """K = (1, 1) is the two-state chain: on a constant law its fit is the switch shares (the
    two-state chain's maximum likelihood), up to the prior's pull (penalty / windows)."""
    p = torch.tensor([[0.9, 0.1], [0.25, 0.75]], dtype=torch.float64)
    z, phi = simulate_chain(p, torch.tensor([0, 1]), 200, 200, seed=2)
    law, _ = fit_phase_law(z, phi, PhaseLayout((1, 1)), [(0.0, 1.0)], FLAT)
    before, after = phi[:, :-1], phi[:, 1:]
    share = [float((after[before == k] != k).double().mean()) for k in (0, 1)]
    fitted = law.moves(torch.tensor([[0.5]], dtype=torch.float64))[0]
    assert fitted[0, 1].item() == pytest.approx(share[0], abs=2e-3)
    assert fitted[1, 0].item() == pytest.approx(share[1], abs=2e-3)


def _standard_errors(law: PhaseLaw, z: torch.Tensor, phi: torch.Tensor, at: torch.Tensor):
    """The standard error of each move probability at inputs ``at`` from the observed
    information (the log-likelihood's Hessian in the free weights, by central differences of
    its gradient) by the delta method."""
    axes = input_grid(law.basis.bounds, FLAT.nodes)
    points, node = grid_points(axes), nearest_node(z, axes)
    free = law.layout.moves() & ~torch.eye(law.layout.n_states, dtype=torch.bool)
    index = [(f, a, b) for f in range(law.basis.n_features) for a, b in free.nonzero().tolist()]

    def gradient(w: torch.Tensor) -> torch.Tensor:
        w = w.clone().requires_grad_(True)
        log_likelihood_with_gradient(PhaseLaw(law.layout, law.basis, w), points, node, phi)
        return torch.stack([w.grad[i] for i in index])

    hessian = torch.zeros(len(index), len(index), dtype=torch.float64)
    for k, i in enumerate(index):
        step = torch.zeros_like(law.weights)
        step[i] = 1e-4
        hessian[k] = (gradient(law.weights + step) - gradient(law.weights - step)) / 2e-4
    covariance = torch.linalg.inv(-(hessian + hessian.T) / 2)
    w = law.weights.clone().requires_grad_(True)
    moves = PhaseLaw(law.layout, law.basis, w).moves(at)[0]
    errors = torch.zeros_like(moves)
    for a, b in free.nonzero().tolist():
        (grad,) = torch.autograd.grad(moves[a, b], w, retain_graph=True)
        jac = torch.stack([grad[i] for i in index])
        errors[a, b] = (jac @ covariance @ jac).sqrt()
    return moves.detach(), errors


def test_the_fit_recovers_a_known_two_phase_chain() -> None:
    """Off: one phase; on: two in series (a Coxian: the first may leave early). Each fitted
    move probability within 4 standard errors of the truth, the errors from the observed
    information (a share over the windows spent in its origin would be ~10x too small: the
    phases are hidden)."""
    p = torch.tensor([[0.9, 0.1, 0.0], [0.05, 0.7, 0.25], [0.12, 0.0, 0.88]], dtype=torch.float64)
    lumps = torch.tensor([0, 1, 1])
    z, phi = simulate_chain(p, lumps, 300, 300, seed=3)
    law, _ = fit_phase_law(z, phi, PhaseLayout((1, 2)), [(0.0, 1.0)], FLAT)
    fitted, errors = _standard_errors(law, z, phi, torch.tensor([[0.5]], dtype=torch.float64))
    free = PhaseLayout((1, 2)).moves() & ~torch.eye(3, dtype=torch.bool)
    assert (errors[free] > 0).all() and (errors[free] < 0.05).all()
    assert ((fitted - p).abs()[free] < 4 * errors[free]).all(), (fitted, errors)


def _held_out_gain(more: PhaseLaw, fewer: PhaseLaw, z, phi) -> tuple[float, float]:
    """The held-out log-likelihood gain of ``more`` over ``fewer`` and its standard error (the
    cells' paired differences)."""
    diff = score(more, z, phi, FLAT.nodes) - score(fewer, z, phi, FLAT.nodes)
    return float(diff.sum()), float(diff.std()) * math.sqrt(len(diff))


def _simulated_on_times(law: PhaseLaw, cells: int, steps: int) -> np.ndarray:
    """On sojourns of the law's table stepped by its decision layer (the population step)."""
    table = phase_table(law, ("z",), ("off", "on"), 0.1, FLAT.nodes)
    layer = PhaseDecision(table, None, start="stationary")  # type: ignore[arg-type]
    torch.manual_seed(4)
    x = torch.full((cells, 1), 0.5)
    phi = [layer.initialize(x)]
    for _ in range(steps):
        phi.append(layer.step(phi[-1], x, 0.1))
    return sojourns(torch.stack(phi, 1).numpy().astype(np.int64), 1)


def _ks(sample: np.ndarray, law: torch.Tensor) -> float:
    """One-sample KS distance of integer ``sample`` against the pmf ``law`` over 1..len(law):
    the largest gap between the two step functions, read at the atoms."""
    cdf = law.cumsum(0).numpy()
    atoms = np.arange(1, len(cdf) + 1)
    ecdf = np.searchsorted(np.sort(sample), atoms, side="right") / len(sample)
    return float(np.abs(ecdf - cdf).max())


def test_an_erlang_on_time_needs_three_phases() -> None:
    """On time Erlang(3), off time geometric: three on phases beat one on held-out cells by far
    more than the gain's standard error, the held-out choice finds them, and only with them do
    the simulated on times pass the KS test against the truth (5 % critical value)."""
    p, lumps = erlang_telegraph(3, 0.3, 0.1)
    z, phi = simulate_chain(p, lumps, 400, 300, seed=5)
    train, test = slice(0, 300), slice(300, 400)
    one, _ = fit_phase_law(z[train], phi[train], PhaseLayout((1, 1)), [(0.0, 1.0)], FLAT)
    three, _ = fit_phase_law(z[train], phi[train], PhaseLayout((1, 3)), [(0.0, 1.0)], FLAT)
    gain, error = _held_out_gain(three, one, z[test], phi[test])
    assert gain > 10 * error > 0
    _chosen, report = select_phases(z, phi, [(0.0, 1.0)], PhaseSelection(3), settings=FLAT)
    assert report["per_lump"] == [1, 3]
    truth = sojourn_law(p, lumps, 1, 400)
    critical = {}
    for name, law in (("one", one), ("three", three)):
        times = _simulated_on_times(law, 400, 300)
        critical[name] = (_ks(times, truth), 1.36 / math.sqrt(len(times)))
    assert critical["three"][0] < critical["three"][1], critical
    assert critical["one"][0] > critical["one"][1], critical


def test_a_memoryless_telegraph_keeps_one_phase_per_lump() -> None:
    """Both sojourns geometric: no added phase gains beyond twice its standard error."""
    p, lumps = erlang_telegraph(1, 0.15, 0.1)
    z, phi = simulate_chain(p, lumps, 300, 300, seed=6)
    _, report = select_phases(z, phi, [(0.0, 1.0)], PhaseSelection(3), settings=FLAT)
    assert report["per_lump"] == [1, 1]
    assert len(report["candidates"]) == 3  # (1, 1), then (2, 1) and (1, 2) tried and refused


def test_the_fitted_sojourns_match_an_enumerable_networks_exact_ones() -> None:
    """A gene cycling A -> B -> C -> D -> A, on in C and D: its phi every window is a hidden
    chain over the 4 states (exp(Q dt)). The fitted chain's mean sojourns in each lump match
    the exact lumped ones within 4 standard errors of the sample's mean sojourn."""
    net = ReactionNetwork.from_reactions(["A", "B", "C", "D"], [
        ("ab", {"A": 1}, {"B": 1}), ("bc", {"B": 1}, {"C": 1}),
        ("cd", {"C": 1}, {"D": 1}), ("da", {"D": 1}, {"A": 1})])  # fmt: skip
    space = StateSpace.enumerate(net, torch.tensor([1, 0, 0, 0]))
    rates = torch.tensor([[1.0, 4.0, 2.0, 3.0]], dtype=torch.float64)
    exact = torch.linalg.matrix_exp(space.generator(rates)[0] * 0.1)
    lumps = (space.states[:, 2] + space.states[:, 3]).long()
    z, phi = simulate_chain(exact, lumps, 300, 400, seed=7)
    law, report = select_phases(z, phi, [(0.0, 1.0)], PhaseSelection(3), settings=FLAT)
    assert min(report["per_lump"]) >= 2  # each lump's sojourn is two exponential steps
    fitted = law.moves(torch.tensor([[0.5]], dtype=torch.float64))[0]
    observed = phi.numpy()
    for lump in (0, 1):
        times = sojourns(observed, lump)
        error = times.std() / math.sqrt(len(times))
        truth = mean_sojourn(exact, lumps, lump)
        assert abs(mean_sojourn(fitted, law.layout.lumps(), lump) - truth) < 4 * error
        assert abs(times.mean() - truth) < 4 * error  # the sample itself is the network's


def _telegraph_over_z(z: torch.Tensor) -> torch.Tensor:
    """Off left with 0.02 + 0.2 z^2 per window, on two phases in series each left with 0.3
    (an Erlang(2) on time): ``(..., 1)`` inputs -> ``(..., 3, 3)``."""
    leave_off = 0.02 + 0.2 * z[..., 0].double() ** 2
    p = torch.zeros(*z.shape[:-1], 3, 3, dtype=torch.float64)
    p[..., 0, 0], p[..., 0, 1] = 1 - leave_off, leave_off
    p[..., 1, 1], p[..., 1, 2] = 0.7, 0.3
    p[..., 2, 2], p[..., 2, 0] = 0.7, 0.3
    return p


def test_the_table_takes_psis_means_where_the_sample_never_went() -> None:
    """Cells that each stay at one input in [0, 0.3] of the domain [0, 1] (an unperturbed
    sample): the fitted law's off sojourn at the unseen end is the basis's extrapolation, far
    from the truth; matched to the true leave probabilities (what psi, fitted over the whole
    domain, gives) the table's stationary leave probabilities are the truth's at every node, and
    the moves within a lump keep the fit's odds (the sojourn's shape)."""
    lumps = torch.tensor([0, 1, 1])
    n, steps = 300, 300
    g = torch.Generator().manual_seed(8)
    z = 0.3 * torch.rand(n, 1, generator=g, dtype=torch.float64)
    moves = _telegraph_over_z(z)  # n x 3 x 3: each cell's own law
    state = torch.multinomial(stationary(moves), 1, generator=g).squeeze(1)
    cdf, rows = moves.cumsum(-1), torch.arange(n)
    phi = [lumps[state]]
    for _ in range(steps):
        u = torch.rand(n, 1, generator=g, dtype=torch.float64)
        state = (u > cdf[rows, state]).sum(-1).clamp(max=2)
        phi.append(lumps[state])
    settings = PhaseFitSettings(bumps=2, nodes=8, max_iterations=100)
    law, _ = fit_phase_law(z.unsqueeze(1).expand(n, steps, 1), torch.stack(phi, 1),
                           PhaseLayout((1, 2)), [(0.0, 1.0)], settings)  # fmt: skip
    points = grid_points(input_grid(law.basis.bounds, settings.nodes))
    truth = stationary_leaving(_telegraph_over_z(points), lumps)  # G x 2
    fitted = law.moves(points).detach()
    # the case is real: at the unseen end the sequences' own off sojourn misses by far
    assert abs(float(stationary_leaving(fitted, lumps)[-1, 0] / truth[-1, 0]) - 1) > 0.3
    matched = match_leaving(fitted, lumps, truth)[0]
    torch.testing.assert_close(stationary_leaving(matched, lumps), truth, rtol=1e-4, atol=0.0)
    # the on lump's move to its next phase against staying: the fit's odds, unscaled
    torch.testing.assert_close(matched[:, 1, 2] / matched[:, 1, 1],
                               fitted[:, 1, 2] / fitted[:, 1, 1], rtol=1e-8, atol=0.0)  # fmt: skip
    # the table the layer reads holds the matched moves (its cumulative rows, float32)
    leaving = lambda x: stationary_leaving(_telegraph_over_z(x), lumps)  # noqa: E731
    table = phase_table(law, ("z",), ("off", "on"), 0.1, settings.nodes, leaving)
    rows = table.cdf.double().reshape(3, -1, 3).movedim(0, 1)  # G x a x b
    torch.testing.assert_close(rows, matched.cumsum(-1), rtol=0.0, atol=1e-6)
    with pytest.raises(NumericalError, match="match psi's only to"):
        match_leaving(fitted, lumps, truth, rounds=1)


def test_match_leaving_with_a_slow_last_phase() -> None:
    """A lump whose slow last phase holds most of its cells: its leave probability grows
    faster than the factor on its leaving odds (fewer cells reach that phase, and it empties
    sooner), so the ratio step (slope 1) overshoots and oscillates: the law of CERENA's
    gene-expression network at its lowest input, rounded, where it ended 4.8 (relative) off
    after 500 rounds. The search matches both lumps and keeps each lump's moves within it."""
    moves = torch.tensor([[0.24, 0.52, 0.0, 0.24, 0.0],
                          [0.0, 0.89, 0.075, 0.035, 0.0],
                          [0.0, 0.0, 0.9992, 0.0008, 0.0],
                          [0.38, 0.0, 0.0, 0.44, 0.18],
                          [0.1, 0.0, 0.0, 0.0, 0.9]], dtype=torch.float64)  # fmt: skip
    moves = moves / moves.sum(-1, keepdim=True)
    lumps = torch.tensor([0, 0, 0, 1, 1])
    target = torch.tensor([0.0107, 0.0999], dtype=torch.float64)  # 6.3x and 0.5x the law's
    matched, factor = match_leaving(moves, lumps, target)
    torch.testing.assert_close(stationary_leaving(matched, lumps), target, rtol=1e-4, atol=0.0)
    assert float(factor[0]) > 1.0 > float(factor[1])
    # the moves within each lump keep the fit's odds
    torch.testing.assert_close(matched[0, 1] / matched[0, 0], moves[0, 1] / moves[0, 0])
    torch.testing.assert_close(matched[3, 4] / matched[3, 3], moves[3, 4] / moves[3, 3])


def _dense_forward_backward(moves: np.ndarray, lumps: np.ndarray, node: np.ndarray,
                            phi: np.ndarray, start: np.ndarray):  # fmt: skip
    """The forward-backward pass written plainly (every state, every move, one cell at a time,
    unscaled products of the window's masked matrices): the reference for the compiled one."""
    n, steps = node.shape
    counts = np.zeros(moves.shape)
    ll, first = np.zeros(n), np.zeros(start.shape)
    for i in range(n):
        mats = [moves[node[i, t]] * (lumps == phi[i, t + 1]) for t in range(steps)]
        alphas = [start[i]]
        for m in mats:
            alphas.append(alphas[-1] @ m)
        betas = [np.ones(len(lumps))]
        for m in reversed(mats):
            betas.insert(0, m @ betas[0])
        total = alphas[-1].sum()
        ll[i] = np.log(total)
        for t, m in enumerate(mats):
            counts[node[i, t]] += np.outer(alphas[t], betas[t + 1]) * m / total
        first[i] = alphas[0] * betas[0] / total
    return ll, counts, first


@pytest.mark.parametrize("structure", ["series", "full"])
def test_the_compiled_forward_backward_is_the_plain_one(structure) -> None:
    """The compiled pass sums only the moves between the lumps seen: its likelihoods, expected
    moves and first-state posteriors must be the plain dense pass's (to 1e-12)."""
    layout = PhaseLayout((2, 3), structure)
    g = torch.Generator().manual_seed(5)
    logits = torch.randn(4, 5, 5, generator=g, dtype=torch.float64)
    moves = torch.softmax(logits.masked_fill(~layout.moves(), -math.inf), -1)
    lumps = layout.lumps()
    n, steps = 37, 30
    node = torch.randint(0, 4, (n, steps), generator=g)
    phi = (torch.rand(n, steps + 1, generator=g) < 0.4).long()
    start = torch.rand(n, 5, generator=g, dtype=torch.float64) * (phi[:, :1] == lumps)
    start = start / start.sum(-1, keepdim=True)
    want = _dense_forward_backward(moves.numpy(), lumps.numpy(), node.numpy(), phi.numpy(),
                                   start.numpy())  # fmt: skip
    for got, ref in zip(expected_moves(moves, lumps, node, phi, start), want, strict=True):
        np.testing.assert_allclose(got.numpy(), ref, rtol=1e-12, atol=1e-12)


def test_the_fits_tolerance_stops_early_at_the_same_likelihood() -> None:
    """L-BFGS stops at a change of ``tolerance`` per window: on an Erlang(2) on time the fit at
    the default 1e-9 takes fewer evaluations than at 1e-12 and reaches its log-likelihood per
    window within 1e-7 (the objective's change below 1e-9 per iteration)."""
    p, lumps = erlang_telegraph(2, 0.3, 0.1)
    z, phi = simulate_chain(p, lumps, 150, 200, seed=4)
    loose = PhaseFitSettings(bumps=0, nodes=8)
    tight = PhaseFitSettings(bumps=0, nodes=8, tolerance=1e-12)
    _, fast = fit_phase_law(z, phi, PhaseLayout((1, 2)), [(0.0, 1.0)], loose)
    _, slow = fit_phase_law(z, phi, PhaseLayout((1, 2)), [(0.0, 1.0)], tight)
    assert fast["evaluations"] < slow["evaluations"]
    assert fast["log_likelihood"] == pytest.approx(slow["log_likelihood"], abs=1e-7)


def test_the_window_terms_sum_to_the_forward_backward_likelihood() -> None:
    """The forward pass window by window (the choice's scoring) and the forward-backward pass
    (the fit's) share one step: the windows' log scales sum to each sequence's likelihood."""
    from surrogate.gp.phases import expected_moves, window_log_likelihoods

    gen = torch.Generator().manual_seed(0)
    moves = torch.rand(5, 4, 4, generator=gen, dtype=torch.float64)
    moves = moves / moves.sum(-1, keepdim=True)
    lumps = torch.tensor([0, 0, 1, 1])
    node = torch.randint(0, 5, (30, 200), generator=gen)
    phi = torch.randint(0, 2, (30, 201), generator=gen)
    terms = window_log_likelihoods(moves, lumps, node, phi)
    assert terms.shape == (30, 200) and bool((terms <= 0).all())
    torch.testing.assert_close(terms.sum(1), expected_moves(moves, lumps, node, phi)[0],
                               rtol=0, atol=1e-10)  # fmt: skip

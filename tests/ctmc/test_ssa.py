"""Exactness of the batched Gillespie SSA against the matrix exponential of the full generator.

Statistical checks (fixed seeds, so every run is the same deterministic check):

* Chi-square goodness of fit after merging bins with expected count < 5; we require p > 1e-3, so
  had the seed been drawn at random a correct sampler would fail with probability 1e-3.
* Total variation between the empirical and exact distributions, against a bound derived from the
  sample size (see ``tv_bound``) that a correct sampler exceeds with probability <= 1e-6.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
import torch

from surrogate.ctmc import ReactionNetwork, gillespie
from surrogate.errors import EventCapError

P_MIN = 1e-3  # chi-square false-alarm rate
TV_DELTA = 1e-6  # false-alarm probability of the total-variation bound
N_CHAINS = 20_000

# ----------------------------------------------------------------------------------------------
# reference: full population generator over the enumerated reachable state space


def population_generator(
    network: ReactionNetwork, start: Sequence[int], rates: Sequence[float]
) -> tuple[list[tuple[int, ...]], np.ndarray]:
    """States reachable from ``start`` (``start`` first) and the generator matrix over them.

    Propensities are recomputed here with ``math.comb``, independently of the code under test.
    """
    reactants = network.reactants.tolist()
    stoich = network.stoichiometry.tolist()
    states = [tuple(start)]
    index = {states[0]: 0}
    edges: list[tuple[int, int, float]] = []
    queue = deque([states[0]])
    while queue:
        x = queue.popleft()
        for r, (coeffs, change) in enumerate(zip(reactants, stoich, strict=True)):
            a = rates[r] * math.prod(math.comb(xs, rs) for xs, rs in zip(x, coeffs, strict=True))
            if a <= 0:
                continue
            y = tuple(xs + d for xs, d in zip(x, change, strict=True))
            if y not in index:
                assert len(states) < 5_000, "reference state space unexpectedly large"
                index[y] = len(states)
                states.append(y)
                queue.append(y)
            edges.append((index[x], index[y], a))
    q = np.zeros((len(states), len(states)))
    for i, j, a in edges:
        q[i, j] += a
        q[i, i] -= a
    return states, q


def exact_distribution(
    network: ReactionNetwork, start: Sequence[int], rates: Sequence[float], dt: float
) -> tuple[list[tuple[int, ...]], np.ndarray]:
    """Reachable states and the exact law of the state after ``dt``: row ``start`` of exp(Q dt)."""
    states, q = population_generator(network, start, rates)
    p = scipy.linalg.expm(q * dt)[0].clip(min=0.0)
    return states, p / p.sum()


# ----------------------------------------------------------------------------------------------
# statistics


def state_counts(final: torch.Tensor, states: list[tuple[int, ...]]) -> np.ndarray:
    """Histogram of the rows of ``final`` over ``states``; fails on an unreachable state."""
    rows, counts = np.unique(final.cpu().numpy(), axis=0, return_counts=True)
    index = {s: i for i, s in enumerate(states)}
    observed = np.zeros(len(states), dtype=np.int64)
    for row, count in zip(rows.tolist(), counts.tolist(), strict=True):
        assert tuple(row) in index, f"sampled state {tuple(row)} is not reachable"
        observed[index[tuple(row)]] = count
    return observed


def merge_small_bins(observed: np.ndarray, expected: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pool all bins with expected count < 5 into one; if the pool is still < 5, fold it into the
    smallest remaining bin (so the chi-square approximation holds for every bin)."""
    small = expected < 5
    obs, exp = list(observed[~small]), list(expected[~small])
    pool_obs, pool_exp = observed[small].sum(), expected[small].sum()
    if small.any():
        if pool_exp >= 5 or not exp:
            obs.append(pool_obs)
            exp.append(pool_exp)
        else:
            k = int(np.argmin(exp))
            obs[k] += pool_obs
            exp[k] += pool_exp
    return np.asarray(obs, dtype=float), np.asarray(exp, dtype=float)


def tv_bound(p: np.ndarray, n: int, delta: float = TV_DELTA) -> float:
    """Upper bound on TV(empirical, p) for ``n`` iid draws from ``p``, exceeded w.p. <= delta.

    E|p^_k - p_k| <= sqrt(Var p^_k) = sqrt(p_k (1 - p_k) / n) (Jensen), so
    E TV <= 1/2 sum_k sqrt(p_k (1 - p_k) / n). Changing one draw changes TV by at most 1/n, so by
    McDiarmid's inequality P(TV >= E TV + eps) <= exp(-2 n eps^2); eps = sqrt(ln(1/delta) / 2n).
    """
    mean_bound = 0.5 * np.sqrt(p * (1 - p) / n).sum()
    return float(mean_bound + math.sqrt(math.log(1 / delta) / (2 * n)))


def assert_matches_distribution(
    final: torch.Tensor, states: list[tuple[int, ...]], p: np.ndarray
) -> None:
    """Chi-square goodness of fit and total-variation check of samples ``final`` against ``p``."""
    n = final.shape[0]
    observed = state_counts(final, states)
    tv = 0.5 * np.abs(observed / n - p).sum()
    bound = tv_bound(p, n)
    assert tv <= bound, f"total variation {tv:.4g} exceeds the bound {bound:.4g}"
    obs, exp = merge_small_bins(observed, n * p)
    if len(obs) >= 2:  # with one bin (a near-deterministic law) only the TV check applies
        result = scipy.stats.chisquare(obs, exp)
        assert result.pvalue > P_MIN, (
            f"chi-square p = {result.pvalue:.3g} (stat {result.statistic:.3g}, {len(obs)} bins)"
        )


# ----------------------------------------------------------------------------------------------
# networks


def flagella_network() -> ReactionNetwork:
    """E. coli flagellum: N(ormal, CCW motor), S(emi-coiled) and C(urly) (CW).

    S -> C at mu, S/C -> N at k+ (CW -> CCW), N -> S at k- (CCW -> CW), with k+ k- = omega^2.
    """
    return ReactionNetwork.from_reactions(
        ["S", "C", "N"],
        [
            ("S->C", {"S": 1}, {"C": 1}),
            ("C->N", {"C": 1}, {"N": 1}),
            ("S->N", {"S": 1}, {"N": 1}),
            ("N->S", {"N": 1}, {"S": 1}),
        ],
    )


def flagella_rates(k_plus: float, k_minus: float, mu: float = 5.0) -> list[float]:
    """Rate constants in the reaction order of ``flagella_network``."""
    return [mu, k_plus, k_plus, k_minus]


def three_state_unit() -> ReactionNetwork:
    """One unit cycling through three states, with a back reaction."""
    return ReactionNetwork.from_reactions(
        ["X0", "X1", "X2"],
        [
            ("01", {"X0": 1}, {"X1": 1}),
            ("12", {"X1": 1}, {"X2": 1}),
            ("20", {"X2": 1}, {"X0": 1}),
            ("10", {"X1": 1}, {"X0": 1}),
        ],
    )


def isomerisation() -> ReactionNetwork:
    """A <-> B, A -> C (population version, first order)."""
    return ReactionNetwork.from_reactions(
        ["A", "B", "C"],
        [("AB", {"A": 1}, {"B": 1}), ("BA", {"B": 1}, {"A": 1}), ("AC", {"A": 1}, {"C": 1})],
    )


def dimerisation() -> ReactionNetwork:
    """Second-order homo- and heteromeric reactions; A + 2B + 3C is conserved."""
    return ReactionNetwork.from_reactions(
        ["A", "B", "C"],
        [
            ("2A->B", {"A": 2}, {"B": 1}),
            ("B->2A", {"B": 1}, {"A": 2}),
            ("A+B->C", {"A": 1, "B": 1}, {"C": 1}),
            ("C->A+B", {"C": 1}, {"A": 1, "B": 1}),
        ],
    )


K_FAST = 3e4
EXACTNESS_CASES = {
    "unit-3-state": (three_state_unit(), (1, 0, 0), [2.0, 1.0, 0.5, 3.0], 0.7),
    "isomerise-3-molecules": (isomerisation(), (3, 0, 0), [4.0, 2.0, 1.5], 0.3),
    "second-order": (dimerisation(), (5, 0, 0), [0.8, 1.0, 0.5, 0.7], 0.4),
    "flagella-adapted": (flagella_network(), (1, 1, 2), flagella_rates(3.5, 0.48), 0.05),
    "flagella-slow-long": (flagella_network(), (1, 1, 2), flagella_rates(3.5, 0.48), 0.5),
    # rates >> 1/dt (k+ at CheY-P = 0, k- = omega^2 / k+): every motor is driven into N
    # within ~1e-4 s and stays there.
    "flagella-fast": (
        flagella_network(),
        (1, 1, 2),
        flagella_rates(K_FAST, 1.3**2 / K_FAST),
        0.05,
    ),
    # rates * dt ~ 10-15 both ways: ~100 events per chain, a non-degenerate final law.
    "flagella-many-events": (flagella_network(), (1, 1, 2), flagella_rates(300.0, 200.0), 0.05),
}


@pytest.mark.parametrize("case", list(EXACTNESS_CASES))
def test_gillespie_matches_matrix_exponential(case: str) -> None:
    network, start, rates, dt = EXACTNESS_CASES[case]
    states, p = exact_distribution(network, start, rates, dt)
    assert len(states) > 1
    generator = torch.Generator().manual_seed(1234)
    x0 = torch.tensor(start).expand(N_CHAINS, -1)
    c = torch.tensor(rates, dtype=torch.float64).expand(N_CHAINS, -1)
    final = gillespie(network, x0, c, dt, generator)
    assert final.shape == (N_CHAINS, network.n_species)
    assert final.dtype == torch.int64
    assert_matches_distribution(final, states, p)


def test_statistical_check_rejects_a_wrong_window() -> None:
    """The checks above have power: dt off by 20 % is detected for the adapted motor."""
    network, start, rates, dt = EXACTNESS_CASES["flagella-slow-long"]
    states, p = exact_distribution(network, start, rates, dt)
    x0 = torch.tensor(start).expand(N_CHAINS, -1)
    c = torch.tensor(rates, dtype=torch.float64)
    final = gillespie(network, x0, c, 1.2 * dt, torch.Generator().manual_seed(1234))
    with pytest.raises(AssertionError):
        assert_matches_distribution(final, states, p)


def test_groups_with_different_rates_and_windows_in_one_batch() -> None:
    """Interleaved groups (few vs many events, per-cell dt) each follow their own exact law."""
    network = flagella_network()
    start = (1, 1, 2)
    groups = [
        (flagella_rates(3.5, 0.48), 0.05),
        (flagella_rates(300.0, 200.0), 0.05),
        (flagella_rates(3.5, 0.48), 0.5),
        (flagella_rates(0.5, 8.0), 0.2),
    ]
    per_group = 8_000
    label = torch.arange(len(groups)).repeat_interleave(per_group)
    label = label[torch.randperm(label.shape[0], generator=torch.Generator().manual_seed(0))]
    all_rates = torch.tensor([g[0] for g in groups], dtype=torch.float64)[label]
    all_dt = torch.tensor([g[1] for g in groups], dtype=torch.float64)[label]
    x0 = torch.tensor(start).expand(label.shape[0], -1)
    final = gillespie(network, x0, all_rates, all_dt, torch.Generator().manual_seed(7))
    for g, (rates, dt) in enumerate(groups):
        states, p = exact_distribution(network, start, rates, dt)
        assert_matches_distribution(final[label == g], states, p)


def test_absorbing_states_stay_put() -> None:
    network = ReactionNetwork.from_reactions(["A", "B"], [("AB", {"A": 1}, {"B": 1})])
    x0 = torch.tensor([[0, 3], [3, 0], [2, 1], [5, 0]])
    # Row 0 starts absorbed; row 1 has zero rate; rows 2-3 are absorbed after a few events
    # (k dt = 200, so P(some A survives) <= 5 exp(-200)), and must then stop, not loop.
    c = torch.tensor([[1.0], [0.0], [4e3], [4e3]], dtype=torch.float64)
    final = gillespie(network, x0, c, 0.05, torch.Generator().manual_seed(0), max_rounds=10)
    assert final.tolist() == [[0, 3], [3, 0], [0, 3], [0, 5]]


def test_reproducible_with_the_same_seed() -> None:
    network, start, rates, dt = EXACTNESS_CASES["flagella-many-events"]
    x0 = torch.tensor(start).expand(2_000, -1)
    c = torch.tensor(rates, dtype=torch.float64)

    def run(seed: int) -> torch.Tensor:
        return gillespie(network, x0, c, dt, torch.Generator().manual_seed(seed))

    torch.testing.assert_close(run(3), run(3), rtol=0, atol=0)
    assert not torch.equal(run(3), run(4))


def test_tensor_dt_equals_float_dt() -> None:
    network, start, rates, dt = EXACTNESS_CASES["flagella-adapted"]
    x0 = torch.tensor(start).expand(500, -1)
    c = torch.tensor(rates, dtype=torch.float64)
    a = gillespie(network, x0, c, dt, torch.Generator().manual_seed(5))
    b = gillespie(network, x0, c, torch.full((500,), dt), torch.Generator().manual_seed(5))
    assert torch.equal(a, b)


def test_max_rounds_guard() -> None:
    network, start, rates, dt = EXACTNESS_CASES["flagella-many-events"]
    x0 = torch.tensor(start).expand(100, -1)
    c = torch.tensor(rates, dtype=torch.float64)
    with pytest.raises(EventCapError, match="max_rounds=5"):  # a RuntimeError
        gillespie(network, x0, c, dt, max_rounds=5)


def test_empty_batch() -> None:
    network = flagella_network()
    out = gillespie(network, torch.zeros((0, 3), dtype=torch.int64), torch.ones(0, 4), 0.05)
    assert out.shape == (0, 3)


@pytest.mark.parametrize("dt", [0.0, -0.1, float("nan"), float("inf"), True])
def test_invalid_dt(dt: float) -> None:
    with pytest.raises(ValueError, match="dt"):
        gillespie(flagella_network(), torch.tensor([[1, 1, 2]]), torch.ones(1, 4), dt)


def test_invalid_inputs() -> None:
    network = flagella_network()
    with pytest.raises(ValueError, match="state must have shape"):
        gillespie(network, torch.tensor([[1, 1]]), torch.ones(1, 4), 0.05)
    with pytest.raises(ValueError, match="rate_constants must have shape"):
        gillespie(network, torch.tensor([[1, 1, 2]]), torch.ones(1, 3), 0.05)
    with pytest.raises(ValueError, match="dt must be a scalar or have shape"):
        gillespie(network, torch.tensor([[1, 1, 2]]), torch.ones(1, 4), torch.ones(2))
    with pytest.raises(ValueError, match="max_rounds"):
        gillespie(network, torch.tensor([[1, 1, 2]]), torch.ones(1, 4), 0.05, max_rounds=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_runs_on_cuda() -> None:
    network, start, rates, dt = EXACTNESS_CASES["flagella-many-events"]
    device = torch.device("cuda")
    x0 = torch.tensor(start, device=device).expand(N_CHAINS, -1)
    c = torch.tensor(rates, dtype=torch.float64, device=device)
    final = gillespie(network, x0, c, dt, torch.Generator(device=device).manual_seed(0))
    assert final.device.type == "cuda"
    states, p = exact_distribution(network, start, rates, dt)
    assert_matches_distribution(final, states, p)

"""Exact window sampling for independent first-order units, and agreement with the SSA.

The statistical checks reuse the helpers of ``test_ssa`` (chi-square p > 1e-3 after merging
bins with expected count < 5, so with the fixed seeds these are deterministic checks whose
false-alarm rate under a random seed would be 1e-3; total variation against a sample-size bound
with false-alarm probability 1e-6).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
import torch

from surrogate.ctmc import (
    ReactionNetwork,
    gillespie,
    sample_counts,
    unit_generator,
    unit_transition_matrix,
)

from .test_ssa import (
    K_FAST,
    N_CHAINS,
    P_MIN,
    assert_matches_distribution,
    exact_distribution,
    flagella_network,
    flagella_rates,
    state_counts,
)

DT = 0.05
RATE_CASES = {
    "adapted": (3.5, 0.48),
    "ccw-biased": (0.5, 8.0),
    "many-events": (300.0, 200.0),
    "fast": (K_FAST, 1.3**2 / K_FAST),
}


def rate_tensor(k_plus: float, k_minus: float, n: int = 1) -> torch.Tensor:
    """``(n, 4)`` float64 flagella rate constants."""
    return torch.tensor(flagella_rates(k_plus, k_minus), dtype=torch.float64).expand(n, -1)


def multinomial_sum_distribution(
    start: tuple[int, ...], p: np.ndarray
) -> tuple[list[tuple[int, ...]], np.ndarray]:
    """Law of the new counts when each unit in state i moves to j w.p. p[i, j], independently.

    Convolution over source states of Multinomial(start[i], p[i]), via scipy.stats.multinomial.
    """
    k = len(start)
    law: dict[tuple[int, ...], float] = {(0,) * k: 1.0}
    for i, n_i in enumerate(start):
        if n_i == 0:
            continue
        moves = [m for m in itertools.product(range(n_i + 1), repeat=k) if sum(m) == n_i]
        pmf = scipy.stats.multinomial.pmf(moves, n_i, p[i])
        new: dict[tuple[int, ...], float] = {}
        for x, px in law.items():
            for m, pm in zip(moves, pmf, strict=True):
                y = tuple(a + b for a, b in zip(x, m, strict=True))
                new[y] = new.get(y, 0.0) + px * pm
        law = new
    states = sorted(law)
    return states, np.array([law[s] for s in states])


# ----------------------------------------------------------------------------------------------
# generator and transition matrix


def test_unit_generator_of_the_flagella_network() -> None:
    mu, kp, km = 5.0, 3.5, 0.48
    q = unit_generator(flagella_network(), rate_tensor(kp, km, 2))
    expected = torch.tensor(
        [[-(mu + kp), mu, kp], [0.0, -kp, kp], [km, 0.0, -km]], dtype=torch.float64
    )
    assert q.shape == (2, 3, 3)
    assert q.dtype == torch.float64
    torch.testing.assert_close(q[0], expected, rtol=1e-15, atol=0.0)
    torch.testing.assert_close(q[1], expected, rtol=1e-15, atol=0.0)


def test_unit_generator_sums_parallel_reactions_and_ignores_self_loops() -> None:
    network = ReactionNetwork.from_reactions(
        ["A", "B"],
        [
            ("ab1", {"A": 1}, {"B": 1}),
            ("ab2", {"A": 1}, {"B": 1}),
            ("aa", {"A": 1}, {"A": 1}),
            ("ba", {"B": 1}, {"A": 1}),
        ],
    )
    q = unit_generator(network, torch.tensor([[1.0, 2.0, 10.0, 4.0]]))
    torch.testing.assert_close(
        q[0], torch.tensor([[-3.0, 3.0], [4.0, -4.0]], dtype=torch.float64), rtol=0, atol=0
    )


@pytest.mark.parametrize(
    "reaction",
    [
        ("dimerise", {"A": 2}, {"B": 1}),
        ("split", {"A": 1}, {"B": 2}),
        ("bind", {"A": 1, "B": 1}, {"B": 1}),
        ("decay", {"A": 1}, {}),
        ("influx", {}, {"A": 1}),
    ],
)
def test_unit_generator_rejects_non_unit_networks(reaction: tuple) -> None:
    network = ReactionNetwork.from_reactions(["A", "B"], [("ab", {"A": 1}, {"B": 1}), reaction])
    with pytest.raises(ValueError, match="exactly one"):
        unit_generator(network, torch.ones(1, 2))


def test_unit_generator_rejects_bad_rates() -> None:
    network = flagella_network()
    with pytest.raises(ValueError, match="shape"):
        unit_generator(network, torch.ones(4))
    with pytest.raises(ValueError, match="shape"):
        unit_generator(network, torch.ones(2, 3))
    with pytest.raises(ValueError, match="non-negative"):
        unit_generator(network, -torch.ones(2, 4))
    with pytest.raises(ValueError, match="floating"):
        unit_generator(network, torch.ones(2, 4, dtype=torch.int64))


def test_transition_matrix_matches_scipy_expm() -> None:
    cases = [*RATE_CASES.values(), (K_FAST, K_FAST)]
    rates = torch.cat([rate_tensor(kp, km) for kp, km in cases])
    q = unit_generator(flagella_network(), rates)
    p = unit_transition_matrix(q, DT)
    assert p.shape == (len(cases), 3, 3)
    assert p.dtype == torch.float64
    assert (p >= 0).all()
    torch.testing.assert_close(p.sum(-1), torch.ones((len(cases), 3), dtype=torch.float64))
    for c in range(len(cases)):
        reference = scipy.linalg.expm(q[c].numpy() * DT)
        # Both are accurate to ~1e-15 relative to ||exp(Q dt)|| = 1; 1e-10 leaves room for
        # the round-off of the up to ~12 squarings the stiff cases need.
        np.testing.assert_allclose(p[c].numpy(), reference, rtol=0, atol=1e-10)


def test_transition_matrix_accepts_per_cell_dt() -> None:
    q = unit_generator(flagella_network(), rate_tensor(3.5, 0.48, 3))
    dt = torch.tensor([0.01, 0.1, 1.0], dtype=torch.float64)
    p = unit_transition_matrix(q, dt)
    for c in range(3):
        reference = scipy.linalg.expm(q[c].numpy() * dt[c].item())
        np.testing.assert_allclose(p[c].numpy(), reference, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dt", [0.0, -1.0, float("nan"), float("inf")])
def test_transition_matrix_rejects_bad_dt(dt: float) -> None:
    q = unit_generator(flagella_network(), rate_tensor(3.5, 0.48))
    with pytest.raises(ValueError, match="dt"):
        unit_transition_matrix(q, dt)


# ----------------------------------------------------------------------------------------------
# sample_counts


def test_reference_multinomial_sum_equals_population_expm() -> None:
    """Independent units: the population law is the convolution of unit multinomials."""
    network = flagella_network()
    for kp, km in RATE_CASES.values():
        rates = flagella_rates(kp, km)
        p_unit = unit_transition_matrix(unit_generator(network, rate_tensor(kp, km)), DT)[0]
        states, law = multinomial_sum_distribution((1, 1, 2), p_unit.numpy())
        ref_states, ref_law = exact_distribution(network, (1, 1, 2), rates, DT)
        lookup = dict(zip(ref_states, ref_law, strict=True))
        np.testing.assert_allclose(law, [lookup.get(s, 0.0) for s in states], atol=1e-10)
        assert set(ref_states) <= set(states)


@pytest.mark.parametrize("case", list(RATE_CASES))
def test_sample_counts_matches_exact_multinomial_sum(case: str) -> None:
    kp, km = RATE_CASES[case]
    start = (1, 1, 2)
    p_unit = unit_transition_matrix(unit_generator(flagella_network(), rate_tensor(kp, km)), DT)
    states, law = multinomial_sum_distribution(start, p_unit[0].numpy())
    counts = torch.tensor(start).expand(N_CHAINS, -1)
    new = sample_counts(counts, p_unit.expand(N_CHAINS, -1, -1), torch.Generator().manual_seed(11))
    assert new.dtype == torch.int64
    assert_matches_distribution(new, states, law)


def test_sample_counts_with_mixed_totals_in_one_batch() -> None:
    """Cells with different totals (incl. 0) and per-cell matrices: each group is exact."""
    starts = [(1, 1, 2), (0, 3, 0), (0, 0, 0), (2, 0, 5)]
    rates = [(3.5, 0.48), (0.5, 8.0), (3.5, 0.48), (300.0, 200.0)]
    per_group = 6_000
    label = torch.arange(len(starts)).repeat_interleave(per_group)
    label = label[torch.randperm(label.shape[0], generator=torch.Generator().manual_seed(1))]
    counts = torch.tensor(starts)[label]
    q = unit_generator(flagella_network(), torch.cat([rate_tensor(*r) for r in rates])[label])
    p = unit_transition_matrix(q, DT)
    new = sample_counts(counts, p, torch.Generator().manual_seed(2))
    assert torch.equal(new.sum(1), counts.sum(1))
    for g, start in enumerate(starts):
        states, law = multinomial_sum_distribution(start, p[label == g][0].numpy())
        assert_matches_distribution(new[label == g], states, law)


def test_sample_counts_deterministic_matrices() -> None:
    counts = torch.tensor([[3, 0, 1], [0, 0, 0], [2, 5, 7], [0, 4, 0]])
    identity = torch.eye(3, dtype=torch.float64)
    assert torch.equal(sample_counts(counts, identity), counts)
    # Permutation 0 -> 1 -> 2 -> 0, including an exact zero in every row.
    perm = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.equal(sample_counts(counts, perm.expand(4, -1, -1)), counts[:, [2, 0, 1]])


def test_sample_counts_reproducible_and_validated() -> None:
    counts = torch.tensor([[1, 1, 2]]).expand(100, -1)
    p = unit_transition_matrix(unit_generator(flagella_network(), rate_tensor(3.5, 0.48)), 1.0)
    a = sample_counts(counts, p[0], torch.Generator().manual_seed(9))
    b = sample_counts(counts, p[0], torch.Generator().manual_seed(9))
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="shape"):
        sample_counts(counts, p.expand(3, -1, -1))
    with pytest.raises(ValueError, match="integers"):
        sample_counts(counts.double(), p[0])
    with pytest.raises(ValueError, match="non-negative"):
        sample_counts(-counts, p[0])
    assert sample_counts(torch.zeros((0, 3), dtype=torch.int64), p[0]).shape == (0, 3)


# ----------------------------------------------------------------------------------------------
# the two exact samplers agree


def merged_contingency_pvalue(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """Two-sample chi-square (2 x bins contingency table) of two histograms over the same bins.

    Bins whose smallest expected cell count is < 5 are pooled (and the pool folded into the
    smallest regular bin if it is still < 5), as for the goodness-of-fit test. Returns the
    p-value (NaN when a single bin is left) and the number of bins used.
    """
    table = np.vstack([a, b]).astype(float)
    min_expected = table.sum(0) * table.sum(1).min() / table.sum()
    small = min_expected < 5
    regular = [table[:, k] for k in np.flatnonzero(~small)]
    if small.any():
        pool = table[:, small].sum(1)
        if min_expected[small].sum() >= 5 or not regular:
            regular.append(pool)
        else:
            k = int(np.argmin([col.sum() for col in regular]))
            regular[k] = regular[k] + pool
    if len(regular) < 2:
        return math.nan, len(regular)
    merged = np.stack(regular, axis=1)
    return float(scipy.stats.chi2_contingency(merged, correction=False).pvalue), len(regular)


@pytest.mark.parametrize("case", list(RATE_CASES))
def test_gillespie_and_sample_counts_agree(case: str) -> None:
    kp, km = RATE_CASES[case]
    network = flagella_network()
    start = (1, 1, 2)
    rates = rate_tensor(kp, km, N_CHAINS)
    counts = torch.tensor(start).expand(N_CHAINS, -1)
    by_ssa = gillespie(network, counts, rates, DT, torch.Generator().manual_seed(21))
    p = unit_transition_matrix(unit_generator(network, rates), DT)
    by_matrix = sample_counts(counts, p, torch.Generator().manual_seed(22))
    states = [s for s in itertools.product(range(5), repeat=3) if sum(s) == sum(start)]
    pvalue, bins = merged_contingency_pvalue(
        state_counts(by_ssa, states), state_counts(by_matrix, states)
    )
    if case == "fast":
        # Exactly, P(not all motors in N) ~ 1e-5: ~0.2 of 20,000 chains expected, so a single
        # bin; > 20 chains elsewhere (Poisson(0.2) tail < 1e-30) means a wrong sampler.
        assert bins == 1
        all_n = torch.tensor([0, 0, 4])
        assert (by_ssa != all_n).any(1).sum() <= 20
        assert (by_matrix != all_n).any(1).sum() <= 20
    else:
        assert bins >= 3
        assert pvalue > P_MIN, f"two-sample chi-square p = {pvalue:.3g} over {bins} bins"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_sample_counts_on_cuda() -> None:
    device = torch.device("cuda")
    q = unit_generator(flagella_network(), rate_tensor(3.5, 0.48, N_CHAINS).to(device))
    p = unit_transition_matrix(q, DT)
    counts = torch.tensor((1, 1, 2), device=device).expand(N_CHAINS, -1)
    new = sample_counts(counts, p, torch.Generator(device=device).manual_seed(0))
    assert new.device.type == "cuda"
    states, law = multinomial_sum_distribution((1, 1, 2), p[0].cpu().numpy())
    assert_matches_distribution(new, states, law)

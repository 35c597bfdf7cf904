"""Compiled per-cell direct method: RNG, reproducibility across thread counts, exactness against
the matrix exponential of the generator (same statistics as test_ssa), and its errors."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
import torch

from surrogate.ctmc import CellStreams, CompiledSSA, ReactionNetwork, mass_action_kinetics
from surrogate.ctmc._xoshiro import next_double, next_u64, seed_streams
from surrogate.errors import EventCapError
from tests.ctmc.test_ssa import EXACTNESS_CASES, assert_matches_distribution, exact_distribution

N_CHAINS = 20_000


def test_xoshiro_reference_sequence():
    """xoshiro256** from state (1, 2, 3, 4): the first outputs of the reference C code,
    recomputed here with Python integers."""
    mask = (1 << 64) - 1

    def rotl(x, k):
        return ((x << k) | (x >> (64 - k))) & mask

    s = [1, 2, 3, 4]
    expected = []
    for _ in range(8):
        expected.append((rotl((s[1] * 5) & mask, 7) * 9) & mask)
        t = (s[1] << 17) & mask
        s[2] ^= s[0]
        s[3] ^= s[1]
        s[1] ^= s[2]
        s[0] ^= s[3]
        s[2] ^= t
        s[3] = rotl(s[3], 45)
    assert expected[:4] == [11520, 0, 1509978240, 1215971899390074240]
    state = np.array([1, 2, 3, 4], dtype=np.uint64)
    assert [int(next_u64(state)) for _ in range(8)] == expected


def test_uniform_doubles():
    state = seed_streams(7, 1)[0]
    u = np.array([next_double(state) for _ in range(100_000)])
    assert u.min() >= 0.0 and u.max() < 1.0
    # mean of 1e5 uniforms: sd 1 / sqrt(12e5) = 2.9e-4; 5 sd
    assert abs(u.mean() - 0.5) < 5 * math.sqrt(1 / 12 / u.size)


def test_streams_are_distinct_and_seeded():
    a, b = seed_streams(1, 100), seed_streams(1, 100)
    assert np.array_equal(a, b)
    assert len({tuple(row) for row in a.tolist()}) == 100
    assert not np.array_equal(a, seed_streams(2, 100))
    with pytest.raises(ValueError, match="seed"):
        seed_streams(-1, 3)


def _isomerisation_ssa(parallel: bool = True) -> tuple[CompiledSSA, torch.Tensor, torch.Tensor]:
    network, start, rates, _ = EXACTNESS_CASES["isomerise-3-molecules"]
    ssa = CompiledSSA(mass_action_kinetics(network), parallel=parallel)
    n = 2000
    state = torch.tensor(start).repeat(n, 1)
    return ssa, state, torch.tensor(rates, dtype=torch.float64)


def test_same_result_whatever_the_thread_count_and_parallel_flag():
    ssa, state, rates = _isomerisation_ssa()
    before = numba.get_num_threads()
    results = []
    try:
        for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(threads)
            streams = CellStreams.from_seed(5, state.shape[0])
            x, events = ssa.advance(state, rates, 0.3, streams)
            results.append((x, events, streams.state.copy()))
    finally:
        numba.set_num_threads(before)
    serial, _, _ = _isomerisation_ssa(parallel=False)
    streams = CellStreams.from_seed(5, state.shape[0])
    results.append((*serial.advance(state, rates, 0.3, streams), streams.state.copy()))
    for x, events, streams_after in results[1:]:
        assert torch.equal(x, results[0][0])
        assert torch.equal(events, results[0][1])
        assert np.array_equal(streams_after, results[0][2])
    assert not torch.equal(results[0][0], state), "nothing happened"


@pytest.mark.parametrize("case", ["unit-3-state", "second-order", "flagella-adapted"])
def test_exact_distribution(case):
    network, start, rates, dt = EXACTNESS_CASES[case]
    states, p = exact_distribution(network, start, rates, dt)
    ssa = CompiledSSA(mass_action_kinetics(network))
    state = torch.tensor(start).repeat(N_CHAINS, 1)
    final, events = ssa.advance(
        state, torch.tensor(rates, dtype=torch.float64), dt, CellStreams.from_seed(17, N_CHAINS)
    )
    assert_matches_distribution(final, states, p)
    assert (events >= 0).all()


def test_per_cell_windows_and_numpy_io():
    """dt per cell: cells with a window 1e-12 stay put (no event can happen in practice)."""
    network = ReactionNetwork.from_reactions(["X"], [("decay", {"X": 1}, {})])
    ssa = CompiledSSA(mass_action_kinetics(network))
    state = np.full((4, 1), 1000, dtype=np.int64)
    dt = np.array([1e-12, 5.0, 1e-12, 5.0])
    x, events = ssa.advance(state, np.array([1.0]), dt, CellStreams.from_seed(0, 4))
    assert isinstance(x, np.ndarray)
    assert x[[0, 2], 0].tolist() == [1000, 1000] and events[[0, 2]].tolist() == [0, 0]
    assert (x[[1, 3], 0] < 50).all()  # mean 1000 e^-5 = 6.7
    assert (events == 1000 - x[:, 0]).all()
    assert state[0, 0] == 1000, "the input state must not be modified"


def test_errors_name_the_reaction_and_the_argument():
    network = ReactionNetwork.from_reactions(["X"], [("decay", {"X": 1}, {})])
    ssa = CompiledSSA(mass_action_kinetics(network))
    state = torch.tensor([[5]])
    streams = CellStreams.from_seed(0, 1)
    with pytest.raises(ValueError, match="propensity of reaction 'decay'"):
        ssa.advance(state, torch.tensor([-1.0]), 1.0, streams)
    with pytest.raises(EventCapError, match="max_events"):  # a RuntimeError
        ssa.advance(torch.tensor([[10**6]]), torch.tensor([1.0]), 1.0, streams, max_events=10)
    with pytest.raises(ValueError, match="inputs must have shape"):
        ssa.advance(state, torch.tensor([1.0, 2.0]), 1.0, streams)
    with pytest.raises(ValueError, match="streams must hold"):
        ssa.advance(state, torch.tensor([1.0]), 1.0, CellStreams.from_seed(0, 2))
    with pytest.raises(ValueError, match="dt must be finite and > 0"):
        ssa.advance(state, torch.tensor([1.0]), 0.0, streams)
    with pytest.raises(ValueError, match="integer counts"):
        ssa.advance(state.double(), torch.tensor([1.0]), 1.0, streams)


def test_negative_count_is_refused():
    from surrogate.ctmc.kinetics import Kinetics, const

    network = ReactionNetwork.from_reactions(["X"], [("leak", {"X": 1}, {})])
    kinetics = Kinetics(network=network, input_names=(), propensity_exprs=(const(100.0),))
    ssa = CompiledSSA(kinetics)
    with pytest.raises(ValueError, match="reaction 'leak' drove a count negative"):
        ssa.advance(torch.tensor([[2]]), torch.zeros(0), 1.0, CellStreams.from_seed(0, 1))

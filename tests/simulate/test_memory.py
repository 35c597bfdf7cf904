"""The switch clock (gp.history=age): a model whose switch depends on how long it has been in a
state fails with the two-state chain and passes with the clock, exact and learned, at the
two-sample KS critical value of its dwell times; plus the clock's rules and its inputs' checks.

The model: one molecule cycling A0 -> A1 -> B -> A0 (rates 2, 2, 1 /s), phi = [B >= 1]. A stay
in phi = 0 is Erlang(2, 2) (hazard rising with age), so a memoryless chain over phi, which gives
it a geometric law of the same mean, misses it by KS D ~ 0.1 on ~10^4 dwells.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.ctmc import ReactionNetwork
from surrogate.ctmc.lumped import lumped_age_psi, lumped_psi
from surrogate.errors import ConfigError
from surrogate.gp import GPSettings, fit_psi
from surrogate.models import NetworkInternalModel
from surrogate.simulate.decision import AbstractDecision, FullDecision
from surrogate.simulate.memory import (
    AGE,
    CENSORED,
    SETTLED,
    MemoryDecision,
    can_age,
    clock_rows,
    exact_age_table,
    has_history,
    history_setting,
    tick,
    with_age,
)

DT = 0.1
RATES = (2.0, 2.0, 1.0)  # A0 -> A1, A1 -> B, B -> A0 (/s)
MAX_AGE = 5.0  # s: an Erlang(2, 2) stay outlasts it with probability 11 e^-10 = 5e-4
N_CELLS, STEPS = 1000, 300
ALPHA_CRITICAL = 1.358  # two-sample KS: D_crit = 1.358 sqrt((n + m) / (n m)) at alpha = 0.05


def erlang_model(cls: type[NetworkInternalModel] = NetworkInternalModel) -> NetworkInternalModel:
    """The cycle A0 -> A1 -> B -> A0 with phi = [B >= 1] (``cls``: a subclass adding
    capabilities, e.g. K-lumps classes)."""
    net = ReactionNetwork.from_reactions(
        ["A0", "A1", "B"],
        [
            ("mature", {"A0": 1}, {"A1": 1}),
            ("fire", {"A1": 1}, {"B": 1}),
            ("reset", {"B": 1}, {"A0": 1}),
        ],
    )
    rates = torch.tensor(RATES, dtype=torch.float64)
    return cls(
        net,
        ["s"],
        "B >= 1",
        rate_constants=lambda s: rates.expand(s.shape[0], 3),
        initial_counts=[1, 0, 0],
        signal_bounds={"s": (0.0, 1.0)},
    )


def run(layer, seed: int) -> np.ndarray:
    """phi of every cell at every window boundary, ``(STEPS + 1) x N_CELLS`` bool."""
    torch.manual_seed(seed)
    x = torch.full((N_CELLS, 1), 0.5)
    phi = layer.initialize(x)
    out = [phi]
    for _ in range(STEPS):
        phi = layer.step(phi, x, DT)
        out.append(phi)
    return torch.stack(out).bool().numpy()


def dwells(phis: np.ndarray, value: int) -> np.ndarray:
    """Lengths (windows) of the complete stays in ``value`` (both ends seen) of every cell."""
    padded = np.full((phis.shape[0] + 2, phis.shape[1]), -1)
    padded[1:-1] = phis.astype(int)
    flat = padded.T.ravel()
    starts = np.r_[0, np.flatnonzero(np.diff(flat)) + 1]
    ends = np.r_[starts[1:], flat.size]
    inner = (starts > 0) & (ends < flat.size)
    starts, ends = starts[inner], ends[inner]
    complete = (flat[starts] == value) & (flat[starts - 1] != -1) & (flat[ends] != -1)
    return (ends - starts)[complete]


def ks(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Two-sample KS distance and its 5 % critical value."""
    from scipy.stats import ks_2samp

    d = float(ks_2samp(a, b).statistic)
    return d, ALPHA_CRITICAL * math.sqrt((a.size + b.size) / (a.size * b.size))


def transitions(phis: np.ndarray) -> pd.DataFrame:
    """A transitions table with the switch clocks, as collect records them (the same rule)."""
    age = torch.zeros(phis.shape[1])
    censored = torch.ones(phis.shape[1], dtype=torch.bool)
    chunks = []
    for k in range(phis.shape[0] - 1):
        before, after = torch.from_numpy(phis[k]), torch.from_numpy(phis[k + 1])
        chunks.append(
            pd.DataFrame(
                {
                    "phi": phis[k].astype(np.int64),
                    "phi_next": phis[k + 1].astype(np.int64),
                    AGE: (age * DT).numpy(),
                    CENSORED: censored.numpy(),
                }
            )
        )
        age, censored = tick(age, before, after), censored & (after == before)
    return pd.concat(chunks, ignore_index=True)


@pytest.fixture(scope="module")
def full_dwells():
    internal = erlang_model()
    phis = run(FullDecision(internal), seed=0)
    return internal, phis, dwells(phis, 0), dwells(phis, 1)


def test_the_two_state_chain_misses_an_age_dependent_switch(full_dwells):
    internal, _, off, _ = full_dwells
    psi = internal.exact_psi
    assert psi is not None
    chain = AbstractDecision(lambda phi, z: _lumped(psi, phi, z), internal)
    d, critical = ks(off, dwells(run(chain, seed=1), 0))
    assert off.size > 5000
    assert d > 3 * critical, (d, critical)


def _lumped(psi, phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    p = psi(z.double(), DT)
    return p.gather(1, phi.long().unsqueeze(1)).squeeze(1).float()


def test_the_exact_clock_reproduces_the_dwell_laws(full_dwells):
    internal, _, off, on = full_dwells
    assert can_age(internal)
    table = exact_age_table(internal, DT, MAX_AGE, size=8)
    chain = MemoryDecision(table, internal, max_age=MAX_AGE)
    phis = run(chain, seed=1)
    for full, chained in ((off, dwells(phis, 0)), (on, dwells(phis, 1))):
        d, critical = ks(full, chained)
        assert d < critical, (d, critical)


def test_a_learned_clock_reproduces_the_dwell_laws(full_dwells):
    internal, phis, off, _ = full_dwells
    table = clock_rows(transitions(phis), MAX_AGE)
    # natural gradients: converged in 200 full-batch steps (Adam needs ~1000 for the rise at age 0)
    gp = GPSettings(n_inducing=32, epochs=200, bins=200, natural_gradient=True)
    psi = fit_psi(table, [AGE], gp, progress=False)
    chain = MemoryDecision(psi, internal, featurize=lambda x: x[:, :0], max_age=MAX_AGE)
    d, critical = ks(off, dwells(run(chain, seed=2), 0))
    assert d < critical, (d, critical)


def test_the_clock_limit_is_flat_without_memory_and_averages_to_the_lumped_psi():
    # one state per lump: no memory, every age gives the lumped psi
    q = torch.tensor([[[-1.0, 1.0], [2.0, -2.0]]], dtype=torch.float64)
    lump = torch.tensor([False, True])
    by_age = lumped_age_psi(q, lump, DT, 10)
    assert torch.allclose(by_age, lumped_psi(q, lump, DT).unsqueeze(-1).expand_as(by_age))
    # the Erlang model: the hazard of leaving phi = 0 rises with age, and the stationary mixture
    # of ages (weights: the chance to be still in the lump k windows after entering) gives back
    # the memoryless lumped psi
    internal = erlang_model()
    s = torch.zeros(1, 1, dtype=torch.float64)
    by_age = internal.exact_age_psi(s, DT, 400)[0]  # (2, 401)
    leave_off = by_age[0]
    assert bool((leave_off[1:40] > leave_off[:39]).all())
    stay = torch.cumprod(torch.cat([torch.ones(1, dtype=torch.float64), 1 - leave_off[:-1]]), 0)
    mixture = float((stay * leave_off).sum() / stay.sum())
    assert mixture == pytest.approx(float(internal.exact_psi(s, DT)[0, 0]), rel=1e-9)


def test_tick_and_with_age():
    age = torch.tensor([0.0, 3.0, SETTLED])
    phi = torch.tensor([True, False, True])
    assert tick(age, phi, torch.tensor([True, True, True])).tolist() == [
        1.0,
        0.0,
        SETTLED,
    ]  # settled stays put
    z = with_age(torch.zeros(3, 1), age, 0.5, 1.0)
    assert z[:, 1].tolist() == [0.0, 1.0, 1.0]


def test_fused_step_is_the_eager_rule():
    internal = erlang_model()
    table = exact_age_table(internal, DT, MAX_AGE, size=8)
    layer = MemoryDecision(table, internal, max_age=MAX_AGE)
    x = torch.full((6, 1), 0.5)
    phi = torch.tensor([0, 0, 1, 1, 0, 1], dtype=torch.float32)
    age = torch.tensor([0.0, 7.0, 2.0, SETTLED, 1.0, 0.0])
    u = torch.rand(1, 6)
    nxt, (age_next,), _ = layer.fused_step(phi, x, DT, u, None, (age,))
    p = layer.probability_at(phi, x, age, DT)
    assert torch.equal(nxt, (u[0] < p).float())
    assert torch.equal(age_next, tick(age, phi, nxt))


def test_clock_rows_drop_censored_clocks_below_the_cap():
    table = pd.DataFrame({AGE: [0.5, 2.0, 7.0, 1.0], CENSORED: [True, True, True, False]})
    out = clock_rows(table, 2.0)
    assert out[AGE].tolist() == [2.0, 2.0, 1.0]
    with pytest.raises(KeyError):
        clock_rows(table.drop(columns=[CENSORED]), 2.0)


@pytest.mark.parametrize(
    "history, max_age", [("clock", 5.0), ("age", 0.0), ("age", -1.0), ("age", "5"), ("age", True)]
)
def test_bad_history_settings_are_refused_by_name(history, max_age):
    with pytest.raises(ConfigError, match="gp\\."):
        history_setting(history, max_age, "gp")


def test_history_setting_and_inputs():
    assert history_setting(None, 5, "gp") == ("none", 5.0)
    assert has_history(("dG", AGE)) and not has_history(("dG",)) and not has_history(())


def test_a_table_with_a_clock_node_per_step_is_read_at_the_node():
    """tabulate_with_clock puts a node at every step: the chain reads each cell's node (one
    lerp less) and gets the interpolated value at that clock, alone or in stacked tables."""
    from surrogate.gp.lookup import StackedPsiLookup
    from surrogate.simulate.memory import tabulate_with_clock

    internal = erlang_model()

    def psi(phi, z):
        return torch.sigmoid(z[:, 0] - z[:, 1]) * (0.5 + 0.5 * phi)

    table = tabulate_with_clock(psi, [(0.0, 1.0)], ("s", AGE), DT, 2.0, (33,))
    assert table.shape == (33, 21)
    by_node = MemoryDecision(table, internal, max_age=2.0, dt=DT)
    by_time = MemoryDecision(table, internal, max_age=2.0)
    assert by_node.clock_nodes == 20 and by_time.clock_nodes is None
    g = torch.Generator().manual_seed(0)
    x = torch.rand(500, 1, generator=g)
    phi = (torch.rand(500, generator=g) < 0.5).float()
    age = torch.randint(0, 40, (500,), generator=g).float()
    age[:3] = torch.tensor([0.0, 20.0, SETTLED])
    node = by_node.probability_at(phi, x, age, DT)
    torch.testing.assert_close(node, by_time.probability_at(phi, x, age, DT), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="dt"):
        by_node.probability_at(phi, x, age, 2 * DT)
    other = tabulate_with_clock(lambda p, z: 0.3 + 0 * z[:, 0], [(0.0, 1.0)], ("s", AGE), DT,
                                2.0, (33,))  # fmt: skip
    stacked = StackedPsiLookup([table, other], [300, 200])
    both = MemoryDecision(stacked, internal, max_age=2.0, dt=DT)
    out = both.probability_at(phi, x, age, DT)
    assert torch.equal(out[:300], node[:300]) and torch.allclose(out[300:], torch.tensor(0.3))


def test_a_clock_tables_deviation_is_read_at_the_clocks_it_takes():
    """A psi whose law of the age jumps between two steps (a regular oscillator's hazard) is
    exact at every clock a cell can have: the table's deviation reads its clock axis at the
    nodes (0 here), where midway between them it would read half the jump."""
    from surrogate.simulate.memory import tabulate_with_clock

    def psi(phi, z):  # a step in the age midway between the 5th and 6th step
        return 0.1 + 0.8 * (z[:, 1] > 5.5 * DT).float() + 0.0 * phi

    table = tabulate_with_clock(psi, [(0.0, 1.0)], ("s", AGE), DT, 2.0, (33,))
    assert table.node_axes == (1,)
    assert table.max_deviation(psi, n_check=None) < 1e-6
    table.node_axes = ()  # midway between the clock's nodes: half the step
    assert table.max_deviation(psi, n_check=None) == pytest.approx(0.4, abs=1e-6)

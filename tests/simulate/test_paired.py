"""Paired starts: one internal draw per distinct inputs, copied to every later run; the copies
share the state, never the random streams."""

from __future__ import annotations

import pytest
import torch

from surrogate.ctmc import ReactionNetwork
from surrogate.models.network import NetworkInternalModel
from surrogate.simulate.paired import paired_starts


class _Network:
    """An internal model whose initial state is a fresh random draw (a burn-in's stand-in)."""

    def __init__(self) -> None:
        self.calls = 0

    def initial_state(self, x: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        self.calls += 1
        return torch.rand(x.shape[0]), {"count": torch.randint(0, 100, (x.shape[0],))}


def test_same_inputs_share_one_draw_as_copies_and_others_draw_their_own() -> None:
    net = _Network()
    x, other = torch.zeros(5, 2), torch.ones(5, 2)
    with paired_starts(net) as starts:
        a, b, c = net.initial_state(x), net.initial_state(x.clone()), net.initial_state(other)
    assert net.calls == 2 and (starts.drawn, starts.reused) == (2, 1)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1]["count"], b[1]["count"])
    assert not torch.equal(a[0], c[0])
    a[0].add_(1.0)  # a run that changes its state in place leaves the others' alone
    assert not torch.equal(a[0], b[0])
    # outside the block the model draws afresh again
    assert not torch.equal(net.initial_state(x)[0], b[0]) and net.calls == 3


def test_the_model_is_restored_when_the_block_fails() -> None:
    net = _Network()
    with pytest.raises(RuntimeError, match="stop"), paired_starts(net):
        raise RuntimeError("stop")
    assert "initial_state" not in net.__dict__
    net.initial_state(torch.zeros(2, 1))
    assert net.calls == 1


def _gene() -> NetworkInternalModel:
    """A telegraph gene on the compiled SSA, so its state carries each cell's random stream:
    on at rate s, off at rate 1 (phi = on, P(on) = s / (s + 1), relaxation rate s + 1)."""
    net = ReactionNetwork.from_reactions(
        ["off", "on"], [("up", {"off": 1}, {"on": 1}), ("down", {"on": 1}, {"off": 1})]
    )
    return NetworkInternalModel(
        net, ["s"], "on >= 1", initial_counts=[1, 0], ssa="compiled",
        rate_constants=lambda s: torch.cat([s, torch.ones_like(s)], 1).double(),
    )  # fmt: skip


def test_paired_runs_share_the_counts_but_each_draws_its_own_streams() -> None:
    """The full run, its repeat (another seed) and a run at inputs 1 % apart start from the same
    counts; with the streams copied too, the repeat replayed the full run window for window and
    the 1 % run agreed with it in (nearly) every window."""
    gene, n, windows, dt = _gene(), 100, 200, 0.5
    x = torch.ones(n, 1)  # s = 1: P(on) = 1/2
    torch.manual_seed(0)
    alone = gene.initial_state(x)
    with paired_starts(gene) as starts:
        runs = []
        for seed, s in ((0, 1.0), (1, 1.0), (2, 1.01)):
            torch.manual_seed(seed)
            runs.append((gene.initial_state(x), s))
    assert (starts.drawn, starts.reused) == (1, 2)
    (full, _), (repeat, _), (near, _) = runs
    # the first run is the run it would be alone; the others its counts with their own streams
    assert torch.equal(full[0], alone[0]) and torch.equal(full[1], alone[1])
    for other in (repeat, near):
        assert torch.equal(other[0], full[0])
        assert not torch.equal(other[1], full[1])
    phis = []
    for state, s in runs:
        phi = torch.empty(windows, n)
        for w in range(windows):
            state = gene.advance(state, x * s, dt)
            phi[w] = gene.phi(state)
        phis.append(phi)
    # Independent runs agree in a window with probability p^2 + (1 - p)^2 ~ 1/2 (p ~ 1/2); a
    # window's agreement and the next one's are correlated by exp(-(s + 1) dt)^2 ~ 0.14, so over
    # 100 cells x 200 windows its standard error is ~0.004: 0.05 is > 10 of them. Copied
    # streams agreed in (nearly) every window.
    for other in phis[1:]:
        agreement = (other == phis[0]).float().mean().item()
        assert abs(agreement - 0.5) < 0.05, agreement

"""Paired starts: one internal draw per distinct inputs, copied to every later run."""

from __future__ import annotations

import pytest
import torch

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

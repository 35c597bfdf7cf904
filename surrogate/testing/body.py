"""The body contract (:class:`BodyContract`): what the simulator and collect rely on of every
:class:`~surrogate.models.base.AgentBody`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from surrogate.fields import Field, GaussianField
from surrogate.models.base import BodyState, Randoms
from surrogate.models.capabilities import start_size_of


def clone(state: BodyState) -> BodyState:
    """A copy of each tensor of ``state`` (to see that a pure function left it alone)."""
    return {k: v.clone() for k, v in state.items()}


def assert_same(a: BodyState, b: BodyState) -> None:
    """Two body states are equal, key by key."""
    assert a.keys() == b.keys(), (a.keys(), b.keys())
    for key in a:
        assert torch.equal(a[key], b[key]), key


def rows(state: BodyState, part: slice) -> BodyState:
    """The cells ``part`` of ``state``."""
    return {k: v[part] for k, v in state.items()}


class BodyContract:
    """What every body guarantees, as tests a body's test class inherits.

    A subclass (named ``Test...``) fills :meth:`make_body`, and :meth:`make_field`,
    :meth:`make_start` and :meth:`perturbation_options` where the defaults (a Gaussian field,
    the origin, no options) do not suit it; :attr:`dt` is its step (s).

    Example:
        >>> from surrogate.models.bodies.walker import Walker
        >>> class TestWalker(BodyContract):
        ...     def make_body(self):
        ...         return Walker()
    """

    #: the step (s)
    dt: float = 0.05
    #: the cells
    n: int = 8

    def make_body(self) -> Any:
        """The body under test."""
        raise NotImplementedError(f"{type(self).__name__} must define make_body()")

    def make_field(self) -> Field:
        """The field the body lives in."""
        return GaussianField()

    def make_start(self) -> Tensor:
        """One start position (``start_size`` coordinates; two where it declares none)."""
        return torch.full((start_size_of(self.make_body()) or 2,), 0.5)

    def perturbation_options(self) -> Mapping[str, Any]:
        """The model's ``perturbation`` options collect builds the body's perturbation from."""
        return {}

    def _draws(self, randoms: Randoms, seed: int) -> tuple[Tensor, Tensor]:
        """``u`` (``uniform x n``) and ``z`` (``normal x n``) as the simulator draws them."""
        g = torch.Generator().manual_seed(seed)
        return (torch.rand(randoms.uniform, self.n, generator=g),
                torch.randn(randoms.normal, self.n, generator=g))  # fmt: skip

    def _state(self) -> tuple[Any, Field, BodyState]:
        body, field = self.make_body(), self.make_field()
        torch.manual_seed(5)
        return body, field, body.initial_state(self.n, self.make_start(), field, self.dt)

    def test_declares_its_observables_and_randoms(self) -> None:
        body = self.make_body()
        names = tuple(body.observable_names)
        assert names and all(isinstance(n, str) for n in names)
        assert isinstance(body.randoms, Randoms) and isinstance(body.adapt_randoms, Randoms)

    def test_state_inputs_and_observables_are_per_cell(self) -> None:
        body, field, state = self._state()
        assert state and all(v.shape[0] == self.n for v in state.values()), state
        before = clone(state)
        x = body.inputs(state, field, 0.0)
        assert x.ndim == 2 and x.shape[0] == self.n and torch.isfinite(x).all()
        assert body.check_inputs(x) is None  # its own inputs are valid
        observed = body.observables(state, field)
        assert set(observed) == set(body.observable_names)
        assert all(v.shape == (self.n,) for v in observed.values())
        assert_same(state, before)  # reading a state leaves it alone

    def test_move_is_pure_per_cell_and_repeatable(self) -> None:
        body, field, state = self._state()
        x = body.inputs(state, field, 0.0)
        u, z = self._draws(body.randoms, seed=1)
        extra = body.sample_extra(self.n, x.device)
        phi0 = (torch.arange(self.n) % 2).float()
        phi1 = 1.0 - phi0
        before = clone(state)
        moved = body.move(state, phi0, phi1, x, self.dt, u, z, extra)
        assert_same(state, before)  # pure: its input is left alone
        assert moved.keys() == state.keys()
        assert all(moved[k].shape == state[k].shape for k in state)
        assert_same(moved, body.move(clone(before), phi0, phi1, x, self.dt, u, z, extra))
        if extra is None or extra.shape == (self.n,):  # each cell reads its own column
            part = slice(2, 5)
            sub = body.move(rows(before, part), phi0[part], phi1[part], x[part], self.dt,
                            u[:, part], z[:, part], None if extra is None else extra[part])  # fmt: skip
            for key in moved:
                assert torch.allclose(sub[key], moved[key][part], rtol=1e-6, atol=1e-7), key

    def test_adapt_is_pure_and_keeps_the_state_per_cell(self) -> None:
        body, field, state = self._state()
        x = body.inputs(state, field, 0.0)
        u, z = self._draws(body.adapt_randoms, seed=2)
        before = clone(state)
        adapted = body.adapt(state, x, self.dt, u, z)
        assert_same(state, before)
        assert adapted.keys() == state.keys()
        assert all(adapted[k].shape == state[k].shape for k in state)
        assert_same(adapted, body.adapt(clone(before), x, self.dt, u, z))

    def test_perturbation_moves_only_the_cells_it_is_asked_to(self) -> None:
        body, field = self.make_body(), self.make_field()
        perturbation = body.perturbation(field, self.perturbation_options())
        torch.manual_seed(6)
        start = perturbation.start(self.n, torch.device("cpu"))
        assert start.shape[0] == self.n
        state = body.initial_state(self.n, start, field, self.dt)
        mask = torch.arange(self.n) % 2 == 0
        before = clone(state)
        after = perturbation.apply(state, mask)
        assert after.keys() == before.keys()
        for key in before:
            assert torch.equal(after[key][~mask], before[key][~mask]), key
        assert any(not torch.equal(after[k][mask], before[k][mask]) for k in before)

"""The internal-model contract (:class:`InternalModelContract`): what the engine relies on of
every :class:`~surrogate.models.base.InternalModel`, its required protocol and the optional
capabilities it declares (:mod:`surrogate.models.capabilities`)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from surrogate.config import seed_everything
from surrogate.models.base import InternalState
from surrogate.models.capabilities import (
    check_members,
    concat_states_of,
    exact_psi_of,
    expected_phi_next_of,
    feature_names_of,
    features_of,
    is_fusable,
    randoms_of,
)


def assert_phi(phi: Tensor, n: int) -> None:
    """``phi`` is float 0/1 per cell, ``(n,)``."""
    assert phi.shape == (n,) and phi.is_floating_point(), (phi.shape, phi.dtype)
    assert ((phi == 0) | (phi == 1)).all(), phi


def clone_state(state: InternalState) -> InternalState:
    """A copy of each tensor of ``state`` (to see that a pure function left it alone)."""
    return tuple(s.clone() for s in state)


class InternalModelContract:
    """What every internal model guarantees, as tests a model's test class inherits.

    A subclass (named ``Test...``) fills :meth:`make_internal` and :meth:`make_inputs`;
    :attr:`dt` is the window (s) it is advanced by. The optional capabilities are checked where
    the model declares them (a pure window, concatenated states, the exact psi, expected
    labels).

    Example:
        >>> import torch
        >>> from examples.python_model.minimal import TelegraphInternal
        >>> class TestTelegraph(InternalModelContract):
        ...     def make_internal(self):
        ...         return TelegraphInternal(50.0, 2.0)
        ...     def make_inputs(self, n):
        ...         return torch.linspace(0.0, 0.1, n)[:, None]
    """

    #: the window (s)
    dt: float = 0.05
    #: the cells
    n: int = 8

    def make_internal(self) -> Any:
        """The internal model under test."""
        raise NotImplementedError(f"{type(self).__name__} must define make_internal()")

    def make_inputs(self, n: int) -> Tensor:
        """Inputs ``x`` (``n x d``, float32, in the order of ``input_names``) where the model
        lives, different between cells."""
        raise NotImplementedError(f"{type(self).__name__} must define make_inputs()")

    def test_declares_its_names(self) -> None:
        internal = self.make_internal()
        names = tuple(internal.input_names)
        assert names and all(isinstance(n, str) for n in names)
        assert len(tuple(internal.lump_names)) == 2
        known = (*names, *feature_names_of(internal))
        assert set(internal.signal_names) <= set(known), (internal.signal_names, known)
        check_members(internal, type(internal).__name__)  # no misspelt optional member
        assert self.make_inputs(self.n).shape == (self.n, len(names))

    def test_states_are_per_cell_and_phi_is_0_or_1(self) -> None:
        internal, x = self.make_internal(), self.make_inputs(self.n)
        state = internal.initial_state(x)  # opaque per-cell tensors (cells in any dimension)
        assert isinstance(state, tuple) and all(isinstance(s, Tensor) for s in state)
        assert_phi(internal.phi(state), self.n)
        after = internal.advance(state, x, self.dt)
        assert len(after) == len(state)
        for a, s in zip(after, state, strict=True):
            assert a.shape == s.shape and a.dtype == s.dtype, (a.shape, s.shape)
        assert_phi(internal.phi(after), self.n)

    def test_one_seed_gives_one_run(self) -> None:
        internal, x = self.make_internal(), self.make_inputs(self.n)
        runs = []
        for _ in range(2):
            seed_everything(11)
            state = internal.initial_state(x)
            seen = [*state]
            for _ in range(3):
                state = internal.advance(state, x, self.dt)
                seen += state
            runs.append(torch.cat([s.double().flatten() for s in seen]))
        assert torch.equal(runs[0], runs[1])  # the whole state, not only phi

    def test_states_join_cells_in_order(self) -> None:
        internal, x = self.make_internal(), self.make_inputs(self.n)
        a, b = internal.initial_state(x[:3]), internal.initial_state(x[3:])
        joined = concat_states_of(internal)([a, b])
        assert torch.equal(internal.phi(joined), torch.cat([internal.phi(a), internal.phi(b)]))

    def test_signal_is_a_column_per_name(self) -> None:
        internal, x = self.make_internal(), self.make_inputs(self.n)
        signal = features_of(internal, x, list(internal.signal_names))
        assert signal.shape == (self.n, len(internal.signal_names))
        assert torch.isfinite(signal).all()

    def test_pure_window_is_per_cell_and_repeatable(self) -> None:
        """A fused window (where declared) is pure: the same random numbers give the same
        state, its input is left alone, and each cell reads only its own column (two
        populations stepped apart give the states of the two stepped together)."""
        internal, x = self.make_internal(), self.make_inputs(self.n)
        if not is_fusable(internal):
            return  # the simulator runs the eager advance
        state = internal.initial_state(x)
        randoms = randoms_of(internal)
        g = torch.Generator().manual_seed(3)
        u = torch.rand(randoms.uniform, self.n, generator=g)
        u64 = (torch.rand(randoms.uniform64, self.n, generator=g, dtype=torch.float64)
               if randoms.uniform64 else None)  # fmt: skip
        before = clone_state(state)
        after, _ = internal.fused_advance(state, x, self.dt, u, u64)
        assert all(torch.equal(s, b) for s, b in zip(state, before, strict=True))
        again, _ = internal.fused_advance(clone_state(before), x, self.dt, u, u64)
        assert all(torch.equal(a, b) for a, b in zip(after, again, strict=True))
        assert_phi(internal.phi(after), self.n)
        join, k = concat_states_of(internal), 3
        a, b = internal.initial_state(x[:k]), internal.initial_state(x[k:])
        both, _ = internal.fused_advance(join([a, b]), x, self.dt, u, u64)
        first, _ = internal.fused_advance(a, x[:k], self.dt, u[:, :k],
                                          None if u64 is None else u64[:, :k])  # fmt: skip
        second, _ = internal.fused_advance(b, x[k:], self.dt, u[:, k:],
                                           None if u64 is None else u64[:, k:])  # fmt: skip
        apart = join([first, second])
        assert all(torch.equal(s, t) for s, t in zip(both, apart, strict=True))

    def test_exact_laws_are_probabilities_per_cell(self) -> None:
        """The exact psi (``n x 2``) and the expected label (``(n,)``), where declared."""
        internal, x = self.make_internal(), self.make_inputs(self.n)
        exact = exact_psi_of(internal)
        if exact is not None:
            signal = features_of(internal, x, list(internal.signal_names))
            p = exact(signal, self.dt)
            assert p.shape == (self.n, 2) and torch.isfinite(p).all()
            assert ((p >= 0) & (p <= 1)).all(), p
        expected = expected_phi_next_of(internal)
        if expected is not None:
            q = expected(internal.initial_state(x), x, self.dt)
            assert q.shape == (self.n,) and ((q >= 0) & (q <= 1)).all(), q

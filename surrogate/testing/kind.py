"""The chain-kind contract (:class:`ChainKindContract`): what the settings, train, simulate and
the measured choice rely on of every :class:`~surrogate.kinds.base.ChainKind`."""

from __future__ import annotations

import json
import math
import tempfile
import unittest
from collections.abc import Mapping
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from surrogate.gp.training import GPSettings
from surrogate.kinds.base import (
    CHAIN_KINDS,
    FIT_GP_KEYS,
    ChainKind,
    kind_gp_keys,
    register_chain_kind,
)
from surrogate.kinds.chains import chain_kind
from surrogate.kinds.files import PSI
from surrogate.simulate.classes import STARTS
from surrogate.simulate.decision import DecisionLayer
from surrogate.simulate.memory import AGE, CENSORED

#: what a kind's fit is given: the train settings (or a stand-in with the members it reads),
#: the transitions table and psi's domain
FitInputs = tuple[Any, pd.DataFrame, Mapping[str, tuple[float, float]]]


def telegraph_sequences(n: int, steps: int, seed: int) -> tuple[Tensor, Tensor]:
    """Synthetic phi sequences over one input ``x`` in [0, 1] (constant per cell): OFF -> ON
    with probability 0.1 + 0.3 x per window, ON -> OFF with 0.2.

    Returns:
        ``inputs`` ``n x steps x 1`` float32 and ``phi`` ``n x (steps + 1)`` float32 0/1.
    """
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, generator=g)
    phi = torch.zeros(n, steps + 1)
    phi[:, 0] = (torch.rand(n, generator=g) < 0.5).float()
    for t in range(steps):  # over windows: cells in the batch
        switch = torch.where(phi[:, t] > 0, torch.full_like(x, 0.2), 0.1 + 0.3 * x)
        moved = torch.rand(n, generator=g) < switch
        phi[:, t + 1] = torch.where(moved, 1.0 - phi[:, t], phi[:, t])
    return x[:, None, None].expand(n, steps, 1).contiguous(), phi


def transitions_table(n: int = 400, seed: int = 0) -> pd.DataFrame:
    """A tiny synthetic collection as collect writes it: ``cell``, ``t``, the input ``x``,
    ``phi``, ``phi_next`` and the switch clock (``phi_age``, ``phi_age_censored``)."""
    rng = np.random.default_rng(seed)
    phi = rng.integers(0, 2, n)
    return pd.DataFrame({
        "cell": np.arange(n) % 20, "t": 0.1 * (np.arange(n) // 20), "x": rng.random(n),
        "phi": phi, "phi_next": np.where(rng.random(n) < 0.8, phi, 1 - phi),
        AGE: rng.random(n) * 8.0, CENSORED: rng.random(n) < 0.2,
    })  # fmt: skip


def same(a: Any, b: Any) -> bool:
    """Whether two artefact states are equal: tensors and arrays elementwise, mappings and
    sequences member by member, numbers exactly."""
    if isinstance(a, Tensor) or isinstance(b, Tensor):
        return isinstance(a, Tensor) and isinstance(b, Tensor) and torch.equal(a.cpu(), b.cpu())
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(same(u, v) for u, v in zip(a, b, strict=True))
    return bool(a == b)


class ChainKindContract:
    """What every chain kind guarantees, as tests a kind's test class inherits.

    A subclass (named ``Test...``) fills :meth:`make_kind` and :meth:`make_layer`, and
    :meth:`make_fitted` and :meth:`fit_inputs` where the kind fits an artefact of its own;
    :meth:`loaded_state` says how the kind's loaded artefact compares with what it wrote.

    Example:
        >>> from surrogate.kinds import chain_kind
        >>> from surrogate.simulate.decision import AbstractDecision
        >>> class TestTwoState(ChainKindContract):
        ...     def make_kind(self):
        ...         return chain_kind()
        ...     def make_layer(self, internal):
        ...         return AbstractDecision(lambda phi, z: 0.2 + 0.6 * z[:, 0], internal)
    """

    #: the window (s) of the synthetic sequences
    dt: float = 0.1

    # ---- what a kind's test class fills ------------------------------------------------------

    def make_kind(self) -> ChainKind:
        """The kind under test (an instance, as :func:`~surrogate.kinds.chain_kind` gives)."""
        raise NotImplementedError(f"{type(self).__name__} must define make_kind()")

    def make_layer(self, internal: Any) -> DecisionLayer:
        """A layer of the kind (as its :meth:`~ChainKind.decision_layer` gives) over the
        synthetic sequences' one input ``x`` in [0, 1] (:func:`telegraph_sequences`), for the
        least ``internal`` model (:class:`PhiInternal`: input ``x``, a state that is phi),
        switching phi with probability at most 0.4 per window."""
        raise NotImplementedError(f"{type(self).__name__} must define make_layer()")

    def make_fitted(self) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """What the kind's :meth:`~ChainKind.fit` gives on a tiny collection (its artefact's
        state and metrics), or None for a kind with no artefact of its own."""
        return None

    def fit_inputs(self) -> FitInputs | None:
        """The settings, table and domain the kind's fit is run on (None: its fit is not run
        here, e.g. it simulates the full model)."""
        return None

    def loaded_state(self, kind: ChainKind, directory: Path) -> Any:
        """The artefact ``kind`` wrote in ``directory``, read back (its :meth:`~ChainKind.load`)
        as the state :meth:`make_fitted` gives, to compare them."""
        return kind.load(directory)

    # ---- the contract ------------------------------------------------------------------------

    def test_is_registered_and_selected_by_its_strings(self) -> None:
        kind = self.make_kind()
        cls = type(kind)
        was = cls in CHAIN_KINDS
        register_chain_kind(cls)  # refuses strings or gp keys another kind has
        try:
            assert chain_kind(kind.lumps, kind.history, kind.class_moves) == kind
        finally:
            if not was:
                CHAIN_KINDS.remove(cls)

    def test_declares_its_strings_flags_and_files(self) -> None:
        kind = self.make_kind()
        assert isinstance(kind.lumps, str) and isinstance(kind.history, str)
        assert kind.class_moves in kind.class_moves_choices
        assert isinstance(kind.title, str) and kind.title
        assert isinstance(kind.recipe, str) and kind.recipe
        assert isinstance(kind.complexity, int) and kind.complexity >= 0
        # its files are its own artefact's: psi's file is every kind's, written by train
        assert all(isinstance(f, str) for f in kind.files) and PSI not in kind.files
        assert kind.starts and set(kind.starts) <= set(STARTS)
        kind.check_start(kind.starts[0], "decision.initial")

    def test_gp_keys_are_its_own_and_its_identity_is_its_own(self) -> None:
        kind = self.make_kind()
        shared = {f.name for f in fields(GPSettings)} | set(FIT_GP_KEYS)
        assert not set(kind.gp_keys) & shared, kind.gp_keys
        was = type(kind) in CHAIN_KINDS
        register_chain_kind(type(kind))
        try:
            others = kind_gp_keys() - set(kind.gp_keys)
            identity = kind.fit_identity(self._gp(kind, others))
            # the keys every fit reads are kept; the other kinds' keys are not (its own it may
            # resolve or drop: learned class moves keep the identity they had before)
            assert identity.get("bins") == 10, identity
            selected = {
                a for a in ("lumps", "history") if getattr(kind, a) != getattr(ChainKind, a)
            }
            assert not (others - selected) & set(identity), identity
            # two kinds' fits never share an identity (it names their directories)
            for other_cls in CHAIN_KINDS:
                for moves in other_cls.class_moves_choices:
                    other = other_cls.make(moves)
                    if other != kind:
                        mine = other.fit_identity(self._gp(other, kind_gp_keys()))
                        assert mine != kind.fit_identity(self._gp(kind, kind_gp_keys())), other
        finally:
            if not was:
                CHAIN_KINDS.remove(type(kind))

    @staticmethod
    def _gp(kind: ChainKind, keys: set[str]) -> dict[str, Any]:
        """A gp group selecting ``kind``, with every key in ``keys`` (and its own) set."""
        own = {k: 1 for k in (*keys, *kind.gp_keys)}
        return {**own, "bins": 10, "lumps": kind.lumps, "history": kind.history,
                "class_moves": kind.class_moves}  # fmt: skip

    def test_training_rows_are_rows_of_the_table(self) -> None:
        kind = self.make_kind()
        table = transitions_table()
        before = table.copy()
        rows = kind.training_rows(table, 5.0, "the contract's table", None)
        assert isinstance(rows, pd.DataFrame) and 0 < len(rows) <= len(table)
        assert {"phi", "phi_next"} <= set(rows.columns)
        pd.testing.assert_frame_equal(table, before)  # the caller's table is not changed
        keys = set(zip(table["cell"], table["t"], strict=True))
        assert set(zip(rows["cell"], rows["t"], strict=True)) <= keys

    def test_fit_is_deterministic_and_gives_its_artefact(self) -> None:
        inputs = self.fit_inputs()
        if inputs is None:
            raise unittest.SkipTest("the kind's fit is not run by its contract test")
        kind = self.make_kind()
        first, second = kind.fit(*inputs), kind.fit(*inputs)
        assert same(first, second)
        # a kind with no file of its own fits nothing beyond psi
        assert (first is None) == (kind.files == ()), (first, kind.files)

    def test_its_artefact_round_trips(self) -> None:
        kind = self.make_kind()
        fitted = self.make_fitted()
        assert (fitted is None) == (kind.files == ()), kind.files
        with tempfile.TemporaryDirectory() as name:
            directory = Path(name)
            if fitted is None:
                assert kind.load(directory) is None
                return
            metrics = kind.write(directory, fitted, {"contract": 1})
            json.dumps(metrics)  # the fit metrics' entries are JSON
            assert {p.name for p in directory.iterdir()} == set(kind.files)
            assert kind.load(directory) is not None
            assert same(self.loaded_state(kind, directory), fitted[0])

    def _sequences(self) -> tuple[Tensor, Tensor]:
        return telegraph_sequences(6, 25, seed=1)

    def _scored(self) -> ChainKind:
        """The kind, where it scores phi sequences: one the measured choice may pick
        (:attr:`~ChainKind.candidate`) must."""
        kind = self.make_kind()
        if not kind.candidate:
            try:
                kind.window_log_likelihoods(self.make_layer(PhiInternal()),
                                            *self._sequences(), self.dt)  # fmt: skip
            except NotImplementedError:
                raise unittest.SkipTest(f"{kind.title} scores no phi sequences") from None
        return kind

    def test_sequence_log_likelihood_is_a_log_probability_per_sequence(self) -> None:
        kind = self._scored()
        inputs, phi = self._sequences()
        layer = self.make_layer(PhiInternal())
        terms = kind.window_log_likelihoods(layer, inputs, phi, self.dt)
        assert terms.shape == (6, 25) and terms.dtype == torch.float64
        # each window's term a log probability: a conditional one, whose sum is the sequence's
        assert torch.isfinite(terms).all() and (terms <= 1e-9).all(), terms
        ll = kind.sequence_log_likelihood(layer, inputs, phi, self.dt)
        assert ll.shape == (6,) and torch.allclose(ll, terms.sum(1))
        # each sequence's alone: a sub-batch gives the same values, and again the same
        again = kind.window_log_likelihoods(layer, inputs[2:5], phi[2:5], self.dt)
        assert torch.allclose(again, terms[2:5], rtol=1e-6, atol=1e-9), (again, terms[2:5])
        # each window's alone of those after it: the sequence cut short scores its windows so
        cut = kind.window_log_likelihoods(layer, inputs[:, :10], phi[:, :11], self.dt)
        assert torch.allclose(cut, terms[:, :10], rtol=1e-6, atol=1e-9), (cut, terms[:, :10])
        # a sequence the chain finds less likely scores lower: phi flipped every window is
        # unlikely under a chain whose switches have probability <= 0.4 each
        flips = torch.arange(phi.shape[1]).remainder(2).float().expand_as(phi)
        rare = kind.sequence_log_likelihood(layer, inputs, flips, self.dt)
        assert rare.sum() < ll.sum() - math.log(2.0), (rare, ll)

    def test_a_started_layer_draws_a_batch_reproducibly(self) -> None:
        kind = self.make_kind()
        inputs, phi = self._sequences()
        draws = []
        for _ in range(2):
            layer = self.make_layer(PhiInternal())
            torch.manual_seed(7)
            kind.start_sequences(layer, inputs[:, 0], phi[:, 0])
            step = phi[:, 0].bool()
            out = []
            for t in range(inputs.shape[1]):
                step = layer.step(step, inputs[:, t], self.dt)
                assert step.shape == (6,) and step.device == inputs.device
                step = step.bool()
                out.append(step)
            draws.append(torch.stack(out))
        assert torch.equal(draws[0], draws[1])  # one seed, one draw


class PhiInternal:
    """The least internal model a contract layer starts from: one input ``x``, a state that is
    phi, started OFF (the layers of a chain over classes read it as their class)."""

    input_names = ("x",)
    signal_names = ("x",)
    lump_names = ("off", "on")
    class_names = ("off", "on")
    class_lumps = (0, 1)

    def initial_state(self, x: Tensor) -> tuple[Tensor]:
        """Every cell OFF: ``(n,)`` zeros."""
        return (torch.zeros(x.shape[0], device=x.device),)

    def advance(self, state: tuple[Tensor], x: Tensor, dt: float) -> tuple[Tensor]:
        """The state as it is (a contract layer never runs the internal model)."""
        return state

    def phi(self, state: tuple[Tensor]) -> Tensor:
        """The state itself, float 0/1 ``(n,)``."""
        return state[0]

    def classes(self, state: tuple[Tensor]) -> Tensor:
        """The class of each cell: its phi."""
        return state[0].long()

"""The shipped chain kinds held to the chain-kind contract (:class:`ChainKindContract`), each
with a tiny layer over the contract's synthetic sequences; and the contract catching a broken
kind."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import torch
from torch import Tensor

from surrogate.gp.phases import InputBasis, PhaseLaw, PhaseLayout
from surrogate.kinds import chain_kind
from surrogate.kinds.base import ChainKind
from surrogate.kinds.phases import HiddenPhases, load_phase_chain, phase_table
from surrogate.kinds.two_state import TwoStateChain
from surrogate.simulate.classes import ClassDecision, ClassTable
from surrogate.simulate.decision import AbstractDecision, DecisionLayer
from surrogate.simulate.memory import MemoryDecision
from surrogate.simulate.phases import PhaseDecision
from surrogate.testing import ChainKindContract
from surrogate.testing.kind import transitions_table

DT = ChainKindContract.dt


def psi(phi: Tensor, z: Tensor) -> Tensor:
    """P(phi' = 1 | phi) at inputs ``z`` (its first column x in [0, 1]): the contract's
    telegraph's (switches at most 0.4 per window)."""
    return torch.where(phi > 0, torch.full_like(z[:, 0], 0.8), 0.1 + 0.3 * z[:, 0])


class TestTwoStateContract(ChainKindContract):
    def make_kind(self) -> ChainKind:
        return chain_kind()

    def make_layer(self, internal: Any) -> DecisionLayer:
        return AbstractDecision(psi, internal)

    def fit_inputs(self) -> Any:
        return SimpleNamespace(), transitions_table(), {"x": (0.0, 1.0)}


class TestSwitchClockContract(TestTwoStateContract):
    def make_kind(self) -> ChainKind:
        return chain_kind("phi", "age")

    def make_layer(self, internal: Any) -> DecisionLayer:
        def clock_psi(phi: Tensor, z: Tensor) -> Tensor:  # leaves ON sooner once settled
            return psi(phi, z) - 0.1 * phi * (z[:, 1] > 0.5).float()

        return MemoryDecision(clock_psi, internal, max_age=1.0, dt=DT)


def class_table() -> ClassTable:
    """A two-class table over x (two nodes), the classes the lumps."""
    law = torch.tensor([[[0.9, 0.1], [0.6, 0.4]], [[0.2, 0.8], [0.2, 0.8]]])  # from, node, to
    return ClassTable(law, [(0.0, 1.0)], ("x",), ("off", "on"), (0, 1), DT)


@pytest.mark.parametrize("moves", ["learned", "relaxation"])
class TestKLumpsContract(ChainKindContract):
    @pytest.fixture(autouse=True)
    def _moves(self, moves: str) -> None:
        self.moves = moves

    def make_kind(self) -> ChainKind:
        return chain_kind("classes", "none", self.moves)

    def make_layer(self, internal: Any) -> DecisionLayer:
        return ClassDecision(class_table(), internal)

    def make_fitted(self) -> tuple[dict[str, Any], dict[str, Any]]:
        return class_table().to_state(), {"classes": 2}

    def loaded_state(self, kind: ChainKind, directory: Path) -> Any:
        return kind.load(directory).to_state()


class TestHiddenPhasesContract(ChainKindContract):
    def law(self) -> PhaseLaw:
        """One OFF and two ON phases, every allowed move's logit -1.5 + 0.5 x (scaled)."""
        weights = torch.tensor([-1.5, 0.5], dtype=torch.float64)[:, None, None].expand(2, 3, 3)
        return PhaseLaw(PhaseLayout((1, 2)), InputBasis(((0.0, 1.0),), bumps=0), weights)

    def table(self) -> ClassTable:
        return phase_table(self.law(), ("x",), ("off", "on"), DT, 4)

    def make_kind(self) -> ChainKind:
        return HiddenPhases()

    def make_layer(self, internal: Any) -> DecisionLayer:
        return PhaseDecision(self.table(), internal)

    def make_fitted(self) -> tuple[dict[str, Any], dict[str, Any]]:
        return {"phase_chain": self.table().to_state(), "phase_law": self.law().to_state()}, {}

    def loaded_state(self, kind: ChainKind, directory: Path) -> Any:
        return {"phase_chain": load_phase_chain(directory).to_state(),
                "phase_law": kind.load(directory).to_state()}  # fmt: skip


class _Broken(TestTwoStateContract):
    """The two-state chain's contract run on a broken kind."""

    broken: type[ChainKind]

    def make_kind(self) -> ChainKind:
        return self.broken()


class PooledScore(TwoStateChain):
    """Scores the batch's sequences together: one sequence's likelihood reads the others'."""

    def window_log_likelihoods(
        self, layer: DecisionLayer, inputs: Tensor, phi: Tensor, dt: float
    ) -> Tensor:
        terms = super().window_log_likelihoods(layer, inputs, phi, dt)
        return terms.mean(0).expand_as(terms)


class DroppingRows(TwoStateChain):
    """Drops the rows it does not read from the caller's table."""

    def training_rows(self, table, max_age, where, source):  # type: ignore[no-untyped-def]
        table.drop(table.index[table["phi"] == 0], inplace=True)
        return table


class ClaimsEpochs(TwoStateChain):
    """Claims a GP hyperparameter as its own key."""

    gp_keys = ("epochs",)


@pytest.mark.parametrize(
    ("broken", "test"),
    [(PooledScore, "test_sequence_log_likelihood_is_a_log_probability_per_sequence"),
     (DroppingRows, "test_training_rows_are_rows_of_the_table"),
     (ClaimsEpochs, "test_gp_keys_are_its_own_and_its_identity_is_its_own")],
)  # fmt: skip
def test_a_broken_kind_fails_the_contract(broken: type[ChainKind], test: str) -> None:
    contract = type("Contract", (_Broken,), {"broken": broken})()
    with pytest.raises(AssertionError):
        getattr(contract, test)()

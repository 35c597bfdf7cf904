"""The shipped internal models and bodies held to their contracts
(:class:`InternalModelContract`, :class:`BodyContract`): E. coli's motors and its phospho
network, an SBML agent (the gene switch's yaml), and the library's bodies; and the contracts
catching a broken model and body."""

from __future__ import annotations

from functools import cache
from typing import Any

import pytest
import torch
from torch import Tensor

from surrogate.config import CONF_DIR, build_model, group_config
from surrogate.models import Model
from surrogate.models.bodies import build_body
from surrogate.models.ecoli import adapted_methylation
from surrogate.models.sbml_agent import SbmlAgentModel
from surrogate.testing import BodyContract, InternalModelContract

GENE_SWITCH = CONF_DIR.parent / "examples" / "gene_switch" / "model.yaml"


@cache
def model(name: str) -> Model:
    """A shipped model, built once (its build reads files)."""
    if name == "gene_switch":
        return SbmlAgentModel(str(GENE_SWITCH))
    return build_model(group_config("model", name))


def ecoli_inputs(n: int) -> Tensor:
    """Methylation adapted to ligand from 0 to 0.1 mM, and that ligand: ``n x 2`` (m, L)."""
    ligand = torch.linspace(0.0, 0.1, n)
    return torch.stack([adapted_methylation(ligand, model("ecoli").params), ligand], 1)


class TestEcoliMotorsContract(InternalModelContract):
    def make_internal(self) -> Any:
        return model("ecoli").internal

    def make_inputs(self, n: int) -> Tensor:
        return ecoli_inputs(n)


class TestEcoliPhosphoContract(TestEcoliMotorsContract):
    def make_internal(self) -> Any:
        return model("ecoli_phospho").internal


class TestSbmlGeneSwitchContract(InternalModelContract):
    def make_internal(self) -> Any:
        return model("gene_switch").internal

    def make_inputs(self, n: int) -> Tensor:
        return torch.linspace(0.001, 0.1, n)[:, None]


class TestEcoliBodyContract(BodyContract):
    def make_body(self) -> Any:
        return model("ecoli").body

    def perturbation_options(self) -> dict[str, Any]:
        return dict(model("ecoli").perturbation_options)


@pytest.mark.parametrize("kind", ["chemotaxis", "walker", "static"])
class TestLibraryBodyContract(BodyContract):
    @pytest.fixture(autouse=True)
    def _kind(self, kind: str) -> None:
        self.kind = kind

    def make_body(self) -> Any:
        return build_body({"kind": self.kind})

    def perturbation_options(self) -> dict[str, Any]:
        return dict(self.make_body().perturbation_options)


class _BrokenInternal:
    """The gene switch's internal model, broken as ``how`` says."""

    def __init__(self, how: str) -> None:
        self.inner, self.how = model("gene_switch").internal, how
        self.input_names, self.signal_names = self.inner.input_names, self.inner.signal_names
        self.lump_names = self.inner.lump_names

    def initial_state(self, x: Tensor) -> Any:
        return self.inner.initial_state(x)

    def advance(self, state: Any, x: Tensor, dt: float) -> Any:
        after = self.inner.advance(state, x, dt)
        if self.how == "unseeded":  # also draws from a generator of its own, seeded by nobody
            g = torch.Generator()
            g.seed()
            after = tuple(t + torch.randint(0, 2, t.shape, generator=g).to(t) for t in after)
        return after

    def phi(self, state: Any) -> Tensor:
        phi = self.inner.phi(state)
        return phi.bool() if self.how == "bool" else phi


@pytest.mark.parametrize(("how", "test"), [("bool", "test_states_are_per_cell_and_phi_is_0_or_1"),
                                           ("unseeded", "test_one_seed_gives_one_run")])  # fmt: skip
def test_a_broken_internal_model_fails_the_contract(how: str, test: str) -> None:
    contract = type("Contract", (TestSbmlGeneSwitchContract,),
                    {"make_internal": lambda self: _BrokenInternal(how)})()  # fmt: skip
    with pytest.raises(AssertionError):
        getattr(contract, test)()


def test_a_body_that_perturbs_every_cell_fails_the_contract() -> None:
    class EveryCell(TestLibraryBodyContract):
        def make_body(self) -> Any:
            body = build_body({"kind": "walker"})
            perturbation = body.perturbation

            def every(field: Any, options: Any) -> Any:
                inner = perturbation(field, options)
                apply = inner.apply
                inner.apply = lambda state, mask: apply(state, torch.ones_like(mask))
                return inner

            body.perturbation = every
            return body

    with pytest.raises(AssertionError):
        EveryCell().test_perturbation_moves_only_the_cells_it_is_asked_to()

"""The contract's one list of optional members, and the refusal of a misspelt one at load."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest
import torch
import yaml
from torch import Tensor

from examples.python_model.gene_switch import GeneSwitchModel
from examples.python_model.minimal import TelegraphInternal, TelegraphModel
from surrogate.config import build_model, group_config
from surrogate.errors import ConfigError
from surrogate.models import capabilities
from surrogate.models.capabilities import (
    OPTIONAL_MEMBERS,
    REQUIRED_MEMBERS,
    check_members,
    edit_distance,
    misspelt_members,
)

ROOT = Path(__file__).resolve().parents[2]


class MisspeltInternal(TelegraphInternal):
    """The minimal model with an exact psi under a misspelt name (and names far from any)."""

    def exact_psy(self, signal: Tensor, dt: float) -> Tensor:
        return torch.full((signal.shape[0], 2), 0.5)

    def rates(self) -> tuple[float, float]:  # the model's own, far from every optional name
        return self.k_on, self.k_off


class MisspeltModel(TelegraphModel):
    def __init__(self) -> None:
        super().__init__()
        self.internal = MisspeltInternal(50.0, 2.0)


def test_a_misspelt_optional_member_is_refused_when_the_model_is_built() -> None:
    target = f"{__name__}.MisspeltModel"
    with pytest.raises(ConfigError, match=r"MisspeltInternal\.exact_psy: did you mean 'exact_psi'"):
        build_model({"_target_": target})
    # the same model spelt right builds
    assert isinstance(build_model({"_target_": "examples.python_model.minimal.TelegraphModel"}),
                      TelegraphModel)  # fmt: skip


@pytest.mark.parametrize(
    ("name", "meant"),
    [("exact_psy", "exact_psi"), ("exact_pis", "exact_psi"), ("expected_phi_nxt",
     "expected_phi_next"), ("signal_bound", "signal_bounds"), ("fusible", "fusable"),
     ("feature_name", "feature_names"), ("cell_step_second", "cell_step_seconds"),
     ("burnin", "burn_in")],
)  # fmt: skip
def test_names_within_two_edits_of_an_optional_one_are_found(name: str, meant: str) -> None:
    internal = type("Internal", (TelegraphInternal,), {name: None})(1.0, 1.0)
    assert misspelt_members(internal) == {name: meant}
    with pytest.raises(ConfigError, match=rf"Internal\.{name}: did you mean '{meant}'"):
        check_members(internal, "model")


def test_private_far_and_contract_names_are_not_flagged() -> None:
    internal = TelegraphInternal(1.0, 1.0)
    internal._exact_psy = None  # the model's own (private)
    internal.network = internal.params = internal.kinetics = None  # far from every name
    assert misspelt_members(internal) == {}
    check_members(internal)


@pytest.mark.filterwarnings("ignore::surrogate.sbml.SbmlWarning")  # the toggle switch's
def test_the_shipped_models_have_no_misspelt_member() -> None:
    """The yaml-configured models, the SBML examples and the Python examples all pass (no
    false alarm on their own attributes)."""
    models = [build_model(group_config("model", name)) for name in ("ecoli", "ecoli_phospho")]
    for spec in sorted(ROOT.glob("examples/*/model.yaml")):
        # classes: auto would run the chooser (a minute of simulation); the members are the
        # same without classes (properties that return None)
        auto = "auto" in str((yaml.safe_load(spec.read_text()) or {}).get("classes", ""))
        classes = {"classes": None} if auto else {}
        models.append(build_model({"_target_": "surrogate.models.sbml_agent.SbmlAgentModel",
                                   "spec": str(spec), **classes}))  # fmt: skip
    models += [TelegraphModel(), GeneSwitchModel()]
    for model in models:
        assert misspelt_members(model.internal) == {}, type(model).__name__


def test_edit_distance_counts_a_swap_as_one_edit() -> None:
    assert edit_distance("exact_psi", "exact_psi") == 0
    assert edit_distance("exact_psy", "exact_psi") == 1
    assert edit_distance("exact_pis", "exact_psi") == 1  # neighbours swapped
    assert edit_distance("burnin", "burn_in") == 1
    assert edit_distance("", "abc") == 3 and edit_distance("abc", "") == 3
    assert edit_distance("classes", "count_classes") == 6


def _names_read(source: str) -> set[str]:
    """String names passed to ``_optional``/``_callable``/``getattr`` on an internal model."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id in ("_optional", "_callable", "getattr")
            and len(node.args) >= 2
            and isinstance(node.args[0], ast.Name)
            and node.args[0].id == "internal"
            and isinstance(node.args[1], ast.Constant)
        ):
            names.add(node.args[1].value)
    return names


def test_every_optional_member_read_is_in_the_one_list() -> None:
    read = _names_read(inspect.getsource(capabilities))
    assert read and read <= set(OPTIONAL_MEMBERS), read - set(OPTIONAL_MEMBERS)
    assert not set(OPTIONAL_MEMBERS) & set(REQUIRED_MEMBERS)
    with pytest.raises(KeyError, match="not in capabilities.OPTIONAL_MEMBERS"):
        capabilities._optional(object(), "exact_psy")

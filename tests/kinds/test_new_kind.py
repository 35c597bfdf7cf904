"""A new chain kind is one module and one yaml (issue 40): the toy kind of
:mod:`tests.kinds.toy_kind`, registered with :func:`register_chain_kind` from outside the
package and its recipe put on Hydra's search path, is selected by its config strings, keeps the
shipped kinds' fit identities as they were, and its own fit, artefact and layer are the ones the
stages' Python API uses. Unknown kind strings are refused with the registered values."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.io import write_manifest
from surrogate.kinds import CHAIN_KINDS, LayerRequest, chain_kind, register_chain_kind
from surrogate.kinds.base import ChainKind
from surrogate.kinds.chains import fit_chain
from surrogate.simulate.decision import DecisionLayer
from surrogate.stages.settings import SimulateSettings, TrainSettings
from surrogate.stages.simulate import learned_decision
from surrogate.testing import ChainKindContract
from surrogate.testing.kind import transitions_table
from tests.kinds.toy_kind import TOY_FILE, TOY_YAML, ToyChain
from tests.test_kinds import GP_IDENTITIES


@pytest.fixture
def toy(tmp_path: Path) -> Iterator[list[str]]:
    """The toy kind registered, its yaml on the search path (the overrides that put it there);
    both gone after the test."""
    register_chain_kind(ToyChain)
    ToyChain.calls.clear()
    conf = tmp_path / "conf"
    (conf / "gp").mkdir(parents=True)
    (conf / "gp" / "toy.yaml").write_text(TOY_YAML)
    try:
        yield [f"hydra.searchpath=[file://{conf}]", "gp=toy"]
    finally:
        CHAIN_KINDS.remove(ToyChain)


def test_a_new_kind_is_one_module_and_one_yaml(toy, compose_cfg, tmp_path) -> None:
    kind = chain_kind("toy")
    assert isinstance(kind, ToyChain) and chain_kind("toy") is kind
    settings = TrainSettings.from_config(compose_cfg("train", toy))
    assert settings.kind is kind and settings.lumps == "toy" and "configure" in ToyChain.calls
    gp = settings.fit_identity()["gp"]
    assert gp["lumps"] == "toy" and gp["toy_floor"] == 0.01
    assert "lumps=toy" in settings.fit_directory.name
    # the shipped kinds keep their identities (the toy's key is dropped from theirs)
    for recipe, identity in GP_IDENTITIES.items():
        shipped = TrainSettings.from_config(compose_cfg("train", [f"gp={recipe}"]))
        assert shipped.fit_identity()["gp"] == identity
    # its own fit and artefact, as train asks for them
    rng = np.random.default_rng(0)
    phi = rng.integers(0, 2, 2000)
    table = pd.DataFrame({"phi": phi, "phi_next": np.where(rng.random(2000) < 0.9, phi, 1 - phi),
                          "dG": rng.random(2000)})  # fmt: skip
    rows = settings.kind.training_rows(table, settings.max_age, "toy table", None)
    fitted = settings.kind.fit(settings, rows, {"dG": (0.0, 1.0)})
    directory = tmp_path / "fit"
    directory.mkdir()
    metrics = settings.kind.write(directory, fitted, settings.fit_identity())
    assert metrics == {"toy": {"rows": 2000}} and (directory / TOY_FILE).exists()
    assert settings.kind.files == (TOY_FILE,)
    write_manifest(directory, stage="train", config={}, seed=0)
    # its own layer, as simulate asks for it (stages/simulate.py:learned_decision)
    request = LayerRequest.of_fit(settings.setup.model, settings, "lookup", None,
                                  torch.device("cpu"))  # fmt: skip
    layer, info = learned_decision(request, settings, directory)
    assert info["lumps"] == "toy" and layer.name == "toy"  # type: ignore[attr-defined]
    p = layer.probability(torch.tensor([0, 1]), torch.zeros(2, 1))  # type: ignore[attr-defined]
    assert p[0] == pytest.approx(0.1, abs=0.03) and p[1] == pytest.approx(0.9, abs=0.03)
    assert ToyChain.calls[-4:] == ["fit", "write", "decision_layer", "load"]


def test_a_new_kinds_values_join_the_messages(toy, compose_cfg) -> None:
    with pytest.raises(
        ConfigError, match=r"gp.lumps must be one of \['phi', 'classes', 'phases', 'toy'\]"
    ):
        TrainSettings.from_config(compose_cfg("train", [*toy, "gp.lumps=motors"]))
    with pytest.raises(ConfigError, match="gp.toy_floor must be in"):
        TrainSettings.from_config(compose_cfg("train", [*toy, "gp.toy_floor=0.7"]))
    # a combination of registered strings that no kind has names the kinds
    with pytest.raises(ConfigError, match=r"no chain kind has gp.lumps=toy, gp.history=age .*"
                                          r"ToyChain \(gp.lumps=toy, gp.history=none"):  # fmt: skip
        TrainSettings.from_config(compose_cfg("train", [*toy, "gp.history=age"]))


def test_the_shipped_kinds_are_their_modules() -> None:
    """Each module of KIND_MODULES registers one kind, and nothing else is registered."""
    from surrogate.kinds import KIND_MODULES
    from surrogate.kinds.base import ChainKind

    registered = [
        v for m in KIND_MODULES for v in vars(m).values()
        if isinstance(v, type) and issubclass(v, ChainKind) and v.__module__ == m.__name__
    ]  # fmt: skip
    assert set(registered) == set(CHAIN_KINDS) and len(registered) == len(KIND_MODULES)


def test_unknown_kind_strings_list_the_registered_values(compose_cfg) -> None:
    assert ToyChain not in CHAIN_KINDS
    cases = [
        ("train", ["gp.lumps=motors"], r"gp.lumps must be one of \['phi', 'classes', 'phases'\], got 'motors'"),
        ("train", ["gp.history=clock"], r"gp.history must be one of \['none', 'age'\], got 'clock'"),
        ("train", ["gp=classes", "gp.class_moves=drift"],
         r"gp.class_moves must be one of \['learned', 'relaxation'\], got 'drift'"),
        ("simulate", ["decision=exact", "decision.lumps=x"],
         r"decision.lumps must be one of \['phi', 'classes', 'phases'\], got 'x'"),
        ("simulate", ["decision=exact", "decision.history=x"],
         r"decision.history must be one of \['none', 'age'\], got 'x'"),
    ]  # fmt: skip
    for stage, overrides, message in cases:
        settings = TrainSettings if stage == "train" else SimulateSettings
        with pytest.raises(ConfigError, match=message):
            settings.from_config(compose_cfg(stage, overrides))
    with pytest.raises(ValueError, match="no chain kind"):
        chain_kind("motors")


def test_a_kind_selected_by_anothers_strings_is_refused() -> None:
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Clash(ToyChain):
        lumps = "classes"

    with pytest.raises(ValueError, match="KLumps and Clash are both selected"):
        register_chain_kind(Clash)
    assert Clash not in CHAIN_KINDS


@pytest.mark.parametrize(("key", "whose"), [("n_inducing", "read by every fit"),
                                            ("labels", "read by every fit"),
                                            ("min_events", "KLumps's"),
                                            ("clock_bins", "SwitchClock's")])  # fmt: skip
def test_a_kind_claiming_a_key_it_does_not_own_is_refused(key: str, whose: str) -> None:
    """A kind's gp keys are dropped from the other kinds' fits: one claiming gp.n_inducing made
    every two-state fit train with the default 100, in one directory whatever the value."""
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Claims(ToyChain):
        gp_keys = ("toy_floor", key)

    try:
        with pytest.raises(ValueError, match=rf"Claims: gp_keys names gp.{key}, which is {whose}"):
            register_chain_kind(Claims)
    finally:
        if Claims in CHAIN_KINDS:
            CHAIN_KINDS.remove(Claims)


def test_fit_chain_asks_the_kinds_not_their_names() -> None:
    """The clock adds its axis and K lumps its refusals through their hooks."""
    from surrogate.gp.training import GPSettings

    class NoClasses:
        signal_names = ("s",)

    gp = GPSettings(bins=100)
    clock = fit_chain({"history": "age", "clock_bins": 20}, gp, ("dG",), NoClasses(), "m")
    assert clock.inputs == ("dG", "phi_age") and clock.gp.bins == (100, 20)
    with pytest.raises(ConfigError, match="declares no classes"):
        fit_chain({"lumps": "classes"}, gp, ("dG",), NoClasses(), "m")
    with pytest.raises(ConfigError, match="K-lumps option: use gp=classes"):
        fit_chain({"class_moves": "relaxation"}, gp, ("dG",), NoClasses(), "m")


class TestToyKindContract(ChainKindContract):
    """The toy kind held to the chain-kind contract, as a user's kind is: its fit on a tiny
    collection, its artefact and its layer (it scores no phi sequences: not a candidate)."""

    def make_kind(self) -> ChainKind:
        return ToyChain()

    def fit_inputs(self) -> Any:
        return SimpleNamespace(gp_config={"toy_floor": 0.01}), transitions_table(), {}

    def make_fitted(self) -> Any:
        return ToyChain().fit(*self.fit_inputs())

    def loaded_state(self, kind: ChainKind, directory: Path) -> Any:
        return {k: v for k, v in kind.load(directory).items() if k != "settings"}

    def make_layer(self, internal: Any) -> DecisionLayer:
        kind = ToyChain()
        with tempfile.TemporaryDirectory() as name:
            kind.write(Path(name), self.make_fitted(), {})
            request = LayerRequest(SimpleNamespace(internal=internal), 0.1)  # type: ignore[arg-type]
            layer, _ = kind.decision_layer(request, Path(name))
        return layer

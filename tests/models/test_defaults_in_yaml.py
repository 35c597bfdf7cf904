"""The Python defaults of the models' constants equal the shipped yaml, key by key: the yaml is
where a user reads and overrides them, the dataclass defaults serve where no config is read
(``EcoliParameters()``, a yaml model's chemotaxis body, ``PhosphoConstants()``)."""

from __future__ import annotations

import dataclasses

import pytest

from surrogate.config import group_config
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.ecoli_phospho import PhosphoConstants
from surrogate.models.ecoli_phospho.model import PHOSPHO_KEYS


@pytest.mark.parametrize("model", ["ecoli", "ecoli_phospho"])
def test_ecoli_parameters_defaults_are_the_yaml(model: str) -> None:
    """Every constant of ``EcoliParameters`` is in the model's composed yaml with the default's
    value (ecoli_phospho has no ``motor_sampler``: its motors are species of the network)."""
    yaml = group_config("model", model)
    defaults = EcoliParameters()
    names = [f.name for f in dataclasses.fields(EcoliParameters)]
    if model == "ecoli_phospho":
        names.remove("motor_sampler")
    missing = [n for n in names if n not in yaml]
    assert not missing, f"conf/model/{model}.yaml lacks {missing}"
    differ = {n: (yaml[n], getattr(defaults, n)) for n in names if yaml[n] != getattr(defaults, n)}
    assert not differ, f"yaml vs EcoliParameters() defaults: {differ}"


def test_phospho_constants_defaults_are_the_yaml() -> None:
    """``PhosphoConstants()``: the network's constants as in ``ecoli_phospho.yaml``, the
    cell's (motors, switching, the adapted state) as in the shared cell yaml."""
    yaml = group_config("model", "ecoli_phospho")
    c = PhosphoConstants()
    assert {k: getattr(c, k) for k in PHOSPHO_KEYS} == {k: yaml[k] for k in PHOSPHO_KEYS}
    shared = ("n_motors", "mu", "omega", "g0", "g1", "k_d")
    assert {k: getattr(c, k) for k in shared} == {k: yaml[k] for k in shared}
    assert c.adapted_cheyp == yaml["yp_adapted"]
    assert c.adapted_activity == pytest.approx(yaml["yp_adapted"] / yaml["alpha"])

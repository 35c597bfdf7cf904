"""gp=auto, the default: the best measured chain for the model (issue 40), resolved once where
the train settings are made, to the same fit (the same directory) as the recipe it picks."""

from __future__ import annotations

import shlex

import pytest

from surrogate.config import group_config
from surrogate.stages.settings.train import TrainSettings


def _settings(compose_cfg, overrides: list[str]) -> TrainSettings:
    return TrainSettings.from_config(compose_cfg("train", overrides))


def test_the_default_is_gp_classes_for_a_model_with_classes(compose_cfg) -> None:
    default = _settings(compose_cfg, [])
    classes = _settings(compose_cfg, ["gp=classes"])
    assert default.lumps == "classes"
    assert default.fit_directory == classes.fit_directory
    assert default.gp == classes.gp
    assert "gp=classes" in default.command()
    assert (default.auto_recipe, classes.auto_recipe) == ("classes", None)  # the log says which


def test_the_default_is_gp_svgp_for_a_model_without_classes(compose_cfg) -> None:
    default = _settings(compose_cfg, ["model=ecoli_phospho"])
    two_state = _settings(compose_cfg, ["model=ecoli_phospho", "gp=svgp"])
    assert default.lumps == "phi"
    assert default.fit_directory == two_state.fit_directory


@pytest.mark.parametrize(
    ("overrides", "lumps"),
    [
        (["gp.history=age"], "phi"),  # a switch clock is a two-state chain's
        (["experiment=paper"], "phi"),  # the paper's chain
        (["gp.lumps=phi"], "phi"),
        (["gp=clock"], "phi"),
    ],
)
def test_a_chain_asked_for_is_kept(compose_cfg, overrides: list[str], lumps: str) -> None:
    assert _settings(compose_cfg, overrides).lumps == lumps


def test_a_key_the_user_sets_is_kept_and_the_rest_follow_the_recipe(compose_cfg) -> None:
    settings = _settings(compose_cfg, ["gp.n_inducing=64"])
    recipe = group_config("gp", "classes")
    assert settings.lumps == "classes"
    assert settings.gp.n_inducing == 64
    assert settings.gp.bins == recipe["bins"] != group_config("gp", "svgp")["bins"]


@pytest.mark.parametrize("overrides", [[], ["gp=svgp"], ["gp.n_inducing=64"], ["gp=clock"]])
def test_the_command_makes_the_same_fit_under_the_default(compose_cfg, overrides) -> None:
    """A missing fit's command names its recipe: a two-state fit's says gp=svgp, which the
    default would not pick for E. coli."""
    settings = _settings(compose_cfg, overrides)
    again = _settings(compose_cfg, shlex.split(settings.command())[2:])
    assert again.fit_directory == settings.fit_directory
    if settings.lumps == "phi":
        assert "gp=svgp" in settings.command()

"""gp=auto, the default: the best measured chain for the model (issue 40), resolved once where
the train settings are made, to the same fit (the same directory) as the recipe it picks."""

from __future__ import annotations

import shlex

import pytest

from surrogate.config import group_config
from surrogate.kinds import AUTO_RECIPES
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


def test_a_value_the_user_gives_is_kept_where_it_equals_gp_svgps(compose_cfg) -> None:
    """gp=auto gp.n_inducing=200 gp.bins=500 on E. coli fitted 32 and 100 (gp=classes's), in
    plain gp=auto's directory: the composed group could not tell svgp's values from given ones."""
    svgp = group_config("gp", "svgp")
    given = [f"gp.n_inducing={svgp['n_inducing']}", f"gp.bins={svgp['bins']}"]
    settings = _settings(compose_cfg, given)
    assert settings.lumps == "classes"
    assert (settings.gp.n_inducing, settings.gp.bins) == (svgp["n_inducing"], svgp["bins"])
    assert settings.fit_directory != _settings(compose_cfg, []).fit_directory
    again = _settings(compose_cfg, shlex.split(settings.command())[2:])
    assert again.fit_directory == settings.fit_directory


def test_auto_leaves_every_key_the_recipes_set_apart_from_gp_svgps() -> None:
    """A key gp=auto inherits from gp=svgp with a recipe's value elsewhere could not be told
    from a value given on the command line: auto.yaml leaves each to the recipe (auto)."""
    auto, svgp = group_config("gp", "auto"), group_config("gp", "svgp")
    apart = {k for name in AUTO_RECIPES for k, v in group_config("gp", name).items()
             if k in svgp and v != svgp[k]}  # fmt: skip
    assert apart and {k for k in apart if auto[k] != "auto"} == set()
    assert auto["labels"] == svgp["labels"] == "auto"  # gp.labels' own choice, not the recipe's


@pytest.mark.parametrize("overrides", [["gp.lumps=phi"], ["gp.lumps=classes"]])
def test_a_chain_named_under_auto_takes_gp_svgps_values(compose_cfg, overrides) -> None:
    """gp=auto with a chain named is gp=svgp's values, as it was before auto.yaml left them to
    the recipe: the same fits, the same directories."""
    settings = _settings(compose_cfg, overrides)
    svgp = group_config("gp", "svgp")
    assert (settings.gp.n_inducing, settings.gp.bins) == (svgp["n_inducing"], svgp["bins"])
    if overrides == ["gp.lumps=phi"]:
        assert settings.fit_directory == _settings(compose_cfg, ["gp=svgp"]).fit_directory


@pytest.mark.parametrize(
    "overrides",
    [[], ["gp=svgp"], ["gp.n_inducing=64"], ["gp.n_inducing=200"], ["gp=clock"]],
)
def test_the_command_makes_the_same_fit_under_the_default(compose_cfg, overrides) -> None:
    """A missing fit's command names its recipe: a two-state fit's says gp=svgp, which the
    default would not pick for E. coli."""
    settings = _settings(compose_cfg, overrides)
    again = _settings(compose_cfg, shlex.split(settings.command())[2:])
    assert again.fit_directory == settings.fit_directory
    if settings.lumps == "phi":
        assert "gp=svgp" in settings.command()

"""gp.mean: the default keeps every fit's identity; a linear mean is another fit, named so."""

from __future__ import annotations

import pytest

from surrogate.errors import ConfigError
from surrogate.stages.settings import TrainSettings


@pytest.mark.parametrize("recipe", ["gp=svgp", "gp=classes"])
def test_the_default_mean_keeps_the_identity_and_linear_makes_another_fit(
    compose_cfg, recipe
) -> None:
    plain = TrainSettings.from_config(compose_cfg("train", [recipe]))
    named = TrainSettings.from_config(compose_cfg("train", [recipe, "gp.mean=constant"]))
    linear = TrainSettings.from_config(compose_cfg("train", [recipe, "gp.mean=linear"]))
    assert "mean" not in plain.fit_identity()["gp"]  # identities from before the key exist
    assert named.fit_directory == plain.fit_directory
    assert linear.fit_identity()["gp"]["mean"] == "linear"
    assert linear.fit_directory != plain.fit_directory
    assert "_mean=linear_" in linear.fit_directory.name and "mean=" not in plain.fit_directory.name
    assert "gp.mean=linear" in linear.command()


def test_an_unknown_mean_is_refused_by_name(compose_cfg) -> None:
    with pytest.raises(ConfigError, match=r"gp.mean: unknown mean 'cubic'; allowed values"):
        TrainSettings.from_config(compose_cfg("train", ["gp.mean=cubic"]))

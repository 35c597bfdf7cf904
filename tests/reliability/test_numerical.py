"""NaN and inf are stopped with a NumericalError where they enter, never propagated silently."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch
from omegaconf import open_dict

from surrogate.errors import NumericalError
from surrogate.fields import Field
from surrogate.gp import FittedClassifier, GPSettings, PsiLookupTable, fit_classifier
from surrogate.io import MANIFEST, write_parquet
from surrogate.stages import collect, train
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.collect import TRANSITIONS

from .conftest import collect_dir, fit_dir, simulate_dir, train_dir


class BadField(Field):
    """A user field that returns ``value`` (NaN or inf) at every position from time ``after``."""

    name = "bad"

    def __init__(self, value: float = math.nan, after: float = 0.0, peak=(0.0, 0.0)) -> None:
        super().__init__(peak)
        self.value = float(value)
        self.after = float(after)

    def __call__(self, position: torch.Tensor, t: float) -> torch.Tensor:
        out = 0.05 * torch.exp(-0.1 * position.square().sum(-1))
        return out.fill_(self.value) if t >= self.after else out


def _with_bad_field(cfg, value: float, after: float):
    with open_dict(cfg):
        cfg.field = {"_target_": f"{__name__}.BadField", "value": value, "after": after}
    return cfg


@pytest.mark.parametrize("after", [0.0, 1.0], ids=["from-start", "mid-run"])
@pytest.mark.parametrize("value", [math.nan, math.inf], ids=["nan", "inf"])
def test_a_field_returning_nan_stops_the_simulation(tiny, value: float, after: float) -> None:
    cfg = _with_bad_field(tiny("simulate"), value, after)
    with pytest.raises(NumericalError, match=r"NaN") as info:
        simulate_stage.run(cfg)
    assert "field" in str(info.value)
    out = simulate_dir(cfg)
    assert not (out / MANIFEST).exists() and not (out / "observables.parquet").exists()


def test_a_field_returning_nan_stops_collect(tiny) -> None:
    cfg = _with_bad_field(tiny("collect"), math.nan, 0.5)
    with pytest.raises(NumericalError, match="NaN"):
        collect.run(cfg)
    assert not (collect_dir(cfg) / TRANSITIONS).exists()


def test_nan_in_the_transitions_is_refused_by_name(tiny, copy_data) -> None:
    cfg = tiny("train")
    path = collect_dir(cfg) / TRANSITIONS
    table = pd.read_parquet(path)
    table.loc[3, "dG"] = np.nan
    write_parquet(path, table)
    with pytest.raises(NumericalError, match=r"contains NaN or infinite values in \['dG'\]"):
        train.run(cfg, force=True)


def test_fit_classifier_refuses_non_finite_inputs() -> None:
    x = torch.rand(50, 2)
    x[7, 1] = math.inf
    with pytest.raises(NumericalError, match=r"NaN or inf in 1 row"):
        fit_classifier(x, torch.randint(0, 2, (50,)).float(), GPSettings(n_inducing=5, epochs=1))
    with pytest.raises(NumericalError, match="labels must be 0/1 outcomes or probabilities"):
        fit_classifier(torch.rand(50, 2), torch.full((50,), math.nan), GPSettings(n_inducing=5))


def test_diverging_gp_training_stops_and_keeps_the_last_good_model(tiny, copy_data) -> None:
    """lr = 1e6 diverges in epoch 2 (measured): the train stage stops with a message naming the
    setting, writes nothing, and the error carries the model restored to the end of epoch 1.
    Adam's loop (K lumps' recipe fits by Newton, whose failure tests/gp/test_newton.py checks)."""
    cfg = tiny("train", ["gp.lr=1e6", "gp.epochs=3", "gp.batch_size=1000", "gp.optimizer=adam"])
    with pytest.raises(NumericalError) as info:
        train.run(cfg)
    text = str(info.value)
    assert "GP training diverged in epoch 2/3" in text and "gp.lr" in text
    assert f"Nothing was written to {fit_dir(cfg)}" in text
    for directory in (fit_dir(cfg), train_dir(cfg)):
        assert not (directory / "psi.pt").exists() and not (directory / MANIFEST).exists()
    partial = info.value.partial
    assert isinstance(partial, FittedClassifier) and len(partial.history) == 1
    assert all(math.isfinite(v) for v in partial.history)


def test_the_restored_model_predicts_finite_values() -> None:
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(200, 2, generator=gen)
    y = (x[:, 0] > 0.5).float()
    settings = GPSettings(n_inducing=10, epochs=3, lr=1e6, batch_size=1000)
    with pytest.raises(NumericalError) as info:
        fit_classifier(x, y, settings, progress=False)
    p = info.value.partial.predict_proba(torch.tensor([[0.2, 0.3], [0.7, 0.1]]))
    assert bool(torch.isfinite(p).all())


def test_a_lookup_table_of_a_nan_classifier_yields_nan_not_a_bad_index() -> None:
    """The table never indexes out of bounds on NaN; the NaN stays visible in its output."""
    table = PsiLookupTable(torch.rand(2, 4, 4), [(0.0, 1.0), (0.0, 1.0)])
    # evaluate: unchecked, as in the simulation loop, which checks at record times
    out = table.evaluate(torch.tensor([0, 1]), torch.tensor([[math.nan, 0.5], [0.5, math.nan]]))
    assert bool(torch.isnan(out).all())
    assert table.check_finite  # the direct call still checks


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_classifier_inputs_are_checked(tiny, copy_data, bad: float) -> None:
    psi = train.load_abstraction(train_dir(tiny("train")))
    with pytest.raises(NumericalError, match="NaN"):
        psi(torch.tensor([0, 1]), torch.tensor([[bad], [0.5]]))
    table = PsiLookupTable.from_function(psi, [(0.0, 1.0)], psi.input_names, size=(8,))
    with pytest.raises(NumericalError, match="NaN"):
        table(torch.tensor([0, 1]), torch.tensor([[0.5], [bad]]))

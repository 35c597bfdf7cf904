"""model=ecoli_phospho: the SBML network as a plug-in internal model, through the pipeline."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir

from surrogate.config import CONF_DIR, build_model, group_config
from surrogate.errors import ConfigError
from surrogate.evaluate.statistics import load_run
from surrogate.fields import ConstantField
from surrogate.models.ecoli import adapted_methylation
from surrogate.models.ecoli_phospho import NETWORK_PATH, EcoliPhosphoModel
from surrogate.simulate import FullDecision, Simulator
from surrogate.stages import collect, evaluate, simulate, train


def test_the_config_builds_the_shipped_network() -> None:
    model = build_model(group_config("model", "ecoli_phospho"))
    assert isinstance(model, EcoliPhosphoModel)
    assert model.internal.network.source == NETWORK_PATH
    assert model.internal.signal_names == ("activity",)
    assert model.constants.k_a == pytest.approx(34.84, rel=1e-3)  # calibrated
    # other constants: the network is generated anew from them
    other = EcoliPhosphoModel(k_y=50.0)
    assert other.internal.network.source is None
    assert other.internal.network.constants["kY"] == 50.0
    with pytest.raises(ConfigError, match="no such SBML file"):
        EcoliPhosphoModel(network="/nonexistent.xml")
    with pytest.raises(ConfigError, match="model.ssa"):
        EcoliPhosphoModel(ssa="foo")


def test_adapted_cells_have_the_first_models_cw_bias() -> None:
    """At the adapted point (L = 0, m = m0, methylation noise off) the motors' CW fraction is
    the first model's adapted bias 0.2227 (the network is calibrated to it), within 4.5
    standard errors of the per-cell time averages."""
    model = EcoliPhosphoModel(cv=1e-9, ssa="compiled", burn_in=1.0)
    torch.manual_seed(3)
    sim = Simulator(model, FullDecision(model.internal), ConstantField(0.0), dt=0.05)
    n = 200
    state = sim.initial_state(n, (0.0, 0.0))
    m0 = float(adapted_methylation(torch.tensor(0.0), model.params))
    assert state.body["m"].sub(m0).abs().max() < 1e-6
    species = model.internal.network.species
    cw = [species.index("S"), species.index("C")]
    fractions = []
    for _ in range(40):
        sim.step(state)
        counts = sim.decision.state[0]
        fractions.append(counts[:, cw].sum(1).double() / model.params.n_motors)
    per_cell = torch.stack(fractions).mean(0).numpy()
    se = per_cell.std(ddof=1) / math.sqrt(n)
    assert abs(per_cell.mean() - model.params.cw_bias_adapted) < 4.5 * se, (per_cell.mean(), se)


def test_batched_and_compiled_windows_agree() -> None:
    """The batched torch SSA (the CUDA path) and the compiled one sample the same window: from
    one state, CheY-P after 0.02 s (~4,000 events per cell) agrees between 150 cells of each
    (two-sample KS at alpha = 0.001)."""
    from scipy import stats

    compiled = EcoliPhosphoModel(ssa="compiled", burn_in=0.0).internal
    batched = EcoliPhosphoModel(ssa="batched", burn_in=0.0).internal
    x = torch.tensor([[2.25, 0.0]]).expand(150, 2).contiguous()
    torch.manual_seed(4)
    state = compiled.initial_state(x)
    yp = compiled.network.species.index("CheYp")
    a = compiled.advance(state, x, 0.02)[0][:, yp].numpy()
    b = batched.advance(state, x, 0.02)[0][:, yp].numpy()
    assert a.std() > 0 and b.std() > 0
    assert stats.ks_2samp(a, b).statistic < 1.949 * math.sqrt(2 / 150)


@pytest.mark.slow
def test_the_pipeline_runs_on_the_phospho_model(tmp_path) -> None:
    """collect -> train -> simulate (full, abstract) -> evaluate on model=ecoli_phospho, with
    the binned full-model frequencies as the diagnostic's reference (no exact psi). The
    pipeline's full run behaves as the first model's, whose adapted CheY-P its network is
    calibrated to: 60 cells for 8 s from the same start, the same field and seed give mean run
    and tumble durations within 4 standard errors of each other (measured: 1.3 and 0.4). The CW
    bias is steep in CheY-P: with the network's adapted CheY-P 7 % off (2.9 uM) the mean tumble
    moves by 26 %, 3.3 standard errors, so errors of ~10 % and more fail here."""
    run = ["n_cells=60", "t_end=8.0", "equilibration_time=0.5"]
    overrides = [
        f"data_dir={tmp_path / 'data'}", "progress=false", "model=ecoli_phospho",
        "model.burn_in=0.5", "collect.n_per_state=200", "collect.n_cells=50",
        "collect.equilibration_time=0.5", "gp.n_inducing=10", "gp.epochs=3",
        "gp.batch_size=100", "gp.diagnostic.n_cells=40", "gp.diagnostic.t_end=2.0",
        "gp.diagnostic.equilibration_time=0.5", "gp.diagnostic.max_cells=0", *run, "evaluate.subsample=100",
        "evaluate.run_missing=true", "evaluate.noise_floor=false",
    ]  # fmt: skip
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=overrides)
        first = compose(config_name="simulate", overrides=[
            f"data_dir={tmp_path / 'data'}", "progress=false", "model=ecoli", "decision=full",
            *run])  # fmt: skip
    table = pd.read_parquet(collect.run(cfg) / "transitions.parquet")
    assert {"m", "L", "F", "activity", "phi", "phi_next"} <= set(table.columns)
    assert np.isfinite(table["activity"]).all() and table["activity"].between(0, 1).all()
    train_dir = train.run(cfg)
    metrics = train.read_metrics(train_dir)
    assert metrics["inputs"] == ["activity"]
    assert metrics["diagnostic"]["reference"] == "empirical"
    out = evaluate.run(cfg)
    comparison = pd.read_csv(out / "comparison.csv")
    assert comparison["quantity"].tolist()[-2:] == ["run", "tumble"]
    assert comparison["ks"].between(0, 1).all()
    manifest = json.loads((out / "manifest.json").read_text())
    phospho = load_run(manifest["runs"]["full"])
    reference = load_run(simulate.run(first))
    for kind in ("run", "tumble"):
        a, b = phospho.durations_of(kind), reference.durations_of(kind)
        assert len(a) > 300 and len(b) > 300
        se = math.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
        assert abs(a.mean() - b.mean()) < 4 * se, (kind, a.mean(), b.mean(), se)


def test_the_motor_generator_is_the_first_models_at_the_current_cheyp() -> None:
    """The expected labels' motor generator is the network's own kinetics per motor at the
    cell's current CheY-P count: mu, omega exp(+-dG(CheY-P / n_per_um)) (the SBML rate laws,
    read back through the network's propensities), as the first model's motor chain."""
    from surrogate.models.ecoli.motors import FLAGELLA_NETWORK, rate_constants
    from surrogate.models.ecoli.signalling import delta_g, rates_from_delta_g

    model = EcoliPhosphoModel(ssa="compiled", burn_in=0.2)
    internal, p = model.internal, model.params
    gen = torch.Generator().manual_seed(5)
    n = 64
    x = torch.stack([2.2 + 0.3 * torch.randn(n, generator=gen), torch.zeros(n)], 1)
    torch.manual_seed(5)
    counts = internal.initial_state(x)[0]
    cheyp = counts[:, internal.network.species.index("CheYp")].double()
    k_plus, k_minus = rates_from_delta_g(delta_g(cheyp / model.constants.n_per_um, p), p)
    rates = rate_constants(k_plus, k_minus, p)  # S->C, C->N, S->N, N->S
    want = torch.zeros(n, 3, 3, dtype=torch.float64)
    for r, (reactant, product) in enumerate([(0, 1), (1, 2), (0, 2), (2, 0)]):
        assert FLAGELLA_NETWORK.reactants[r, reactant] == 1
        want[:, reactant, product] += rates[:, r]
    want -= torch.diag_embed(want.sum(-1))
    activity = internal.features(x, ("activity",)).double()
    got = internal._motor_generator(counts, activity)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)


def test_expected_labels_average_to_the_outcomes() -> None:
    """From one set of states, 12 sampled windows per cell: per origin, the RUN frequency
    agrees with the mean expected label (ghost CheY-P path, motors integrated out) within 4
    standard errors of the per-cell differences; the state and its random streams are left as
    they were (the real window draws the same numbers)."""
    model = EcoliPhosphoModel(ssa="compiled", burn_in=0.5)
    internal = model.internal
    gen = torch.Generator().manual_seed(8)
    n = 750  # ~20 s: the phospho SSA costs ~25 ms per cell-second here
    x = torch.stack([2.2 + 0.25 * torch.randn(n, generator=gen), torch.zeros(n)], 1)
    torch.manual_seed(8)
    state = internal.initial_state(x)
    before = tuple(t.clone() for t in state)
    expected = internal.expected_phi_next(state, x, 0.05)
    assert all(torch.equal(a, b) for a, b in zip(state, before, strict=True))
    windows = []
    for _ in range(12):
        copy = (state[0].clone(), state[1])  # the streams move on: independent windows
        windows.append(internal.phi(internal.advance(copy, x, 0.05)))
    frequency = torch.stack(windows).double().mean(0)
    phi = internal.phi(state)
    for origin in (0, 1):
        rows = phi == origin
        diff = (frequency - expected)[rows]
        se = float(diff.std()) / math.sqrt(int(rows.sum()))
        assert abs(float(diff.mean())) < 4 * se, (origin, float(diff.mean()), se)

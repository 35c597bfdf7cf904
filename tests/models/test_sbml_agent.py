"""model=sbml: models written as a yaml beside an SBML file, with no Python.

* examples/ecoli_phospho/model.yaml (the phospho network in the chemotaxis body) gives, from
  one seed, the same trajectories, transitions and learned abstraction as the hand-written
  plug-in ``model=ecoli_phospho``;
* examples/gene_switch/model.yaml (a gene switch in a walker, nothing of E. coli) runs through
  collect, train, simulate (full, learned, exact) and evaluate, and its exact psi is that of
  examples/python_model (the same network written in Python);
* a malformed yaml is refused before any simulation, naming the setting.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch
import yaml

from examples.python_model.gene_switch import GeneSwitchModel
from surrogate.config import CONF_DIR, build_model
from surrogate.errors import ConfigError
from surrogate.fields import ConstantField, GaussianField
from surrogate.gp import PsiLookupTable
from surrogate.models.ecoli_phospho import EcoliPhosphoModel
from surrogate.models.sbml_agent import SbmlAgentModel
from surrogate.sbml import SbmlError, SbmlWarning
from surrogate.simulate import AbstractDecision, FullDecision, Simulator
from surrogate.simulate.decision import ExactPsi
from surrogate.stages import collect, evaluate, simulate, train
from tests.conftest import composer

REPO = CONF_DIR.parent
PHOSPHO = REPO / "examples" / "ecoli_phospho" / "model.yaml"
GENE_SWITCH = REPO / "examples" / "gene_switch" / "model.yaml"
TOGGLE = REPO / "examples" / "toggle_switch" / "model.yaml"
AUTOREGULATION = REPO / "examples" / "autoregulation" / "model.yaml"
TYSON = REPO / "examples" / "tyson_oscillator" / "model.yaml"
DIMERISATION = REPO / "examples" / "dimerisation" / "model.yaml"
DROP = object()  # a key to remove from the spec


def compose_config(data_dir: Path, overrides: list[str]):
    return composer(data_dir)("evaluate", overrides)


def run_full(model, n_cells: int, steps: int, seed: int = 7):
    """Body state, phi per step and the network's counts after ``steps`` full-model steps."""
    torch.manual_seed(seed)
    sim = Simulator(model, FullDecision(model.internal), GaussianField(), dt=0.05, backend="auto")
    state = sim.initial_state(n_cells, (2.0, 0.0), equilibration_time=0.2)
    phis = []
    for _ in range(steps):
        sim.step(state)
        phis.append(state.phi.clone())
    return state.body, torch.stack(phis), sim.decision.state[0]


def test_the_phospho_yaml_is_the_plugins_full_model_from_one_seed() -> None:
    """Same body trajectories, phi at every step and network counts, bit for bit."""
    plugin = EcoliPhosphoModel(burn_in=0.2)
    config = SbmlAgentModel(str(PHOSPHO), burn_in=0.2)
    assert config.internal.input_names == plugin.internal.input_names == ("m", "L")
    assert config.internal.feature_names == plugin.internal.feature_names == ("F", "activity")
    assert config.internal.signal_names == plugin.internal.signal_names == ("activity",)
    a, b = run_full(plugin, 30, 15), run_full(config, 30, 15)
    for key in ("position", "heading", "m"):
        assert torch.equal(a[0][key], b[0][key]), key
    assert torch.equal(a[1], b[1]) and 0.2 < float(a[1].float().mean()) < 0.95  # both lumps occur
    assert torch.equal(a[2], b[2])
    assert config.internal.exact_psi is None and plugin.internal.exact_psi is None


def test_the_phospho_yaml_abstraction_runs_on_the_ecoli_kernel() -> None:
    """A lookup table over the activity runs on the E. coli body's compiled kernel for the
    yaml model as for the plug-in, with the same trajectories."""
    table = PsiLookupTable.from_function(
        lambda phi, z: 0.2 + 0.6 * z[:, 0] * (phi > 0) + 0.1 * (phi == 0),
        [(0.0, 1.0)], ["activity"], (64,),
    )  # fmt: skip
    out = []
    for model in (EcoliPhosphoModel(burn_in=0.1), SbmlAgentModel(str(PHOSPHO), burn_in=0.1)):
        torch.manual_seed(3)
        decision = AbstractDecision(table, model.internal, model.featurizer(["activity"]))
        sim = Simulator(model, decision, GaussianField(), dt=0.05, backend="auto")
        assert sim.backend == "numba", sim.backend_note
        state = sim.initial_state(50, (2.0, 0.0), equilibration_time=0.1)
        sim.advance(state, 40)
        out.append(state.body["position"].clone())
    assert torch.equal(out[0], out[1])


@pytest.mark.slow
def test_the_phospho_yaml_collects_and_learns_what_the_plugin_does(tmp_path) -> None:
    """Through the stages from one seed: the same transitions (the plug-in adds its expected
    labels, a motor-specific column) and, trained on the outcomes, the same psi."""
    common = [
        "collect.n_per_state=60", "collect.n_cells=30",
        "collect.record_every=1", "collect.equilibration_time=0.2", "gp.n_inducing=8",
        "gp.epochs=3", "gp.labels=outcome", "gp.diagnostic.n_cells=20", "gp.diagnostic.t_end=1.0",
        "gp.diagnostic.equilibration_time=0.2", "gp.diagnostic.max_cells=0",
    ]  # fmt: skip
    plugin = compose_config(tmp_path / "a", ["model=ecoli_phospho", "model.burn_in=0.2", *common])
    config = compose_config(tmp_path / "b", ["model=sbml", f"model.spec={PHOSPHO}",
                                             "+model.burn_in=0.2", *common])  # fmt: skip
    tables, grids = [], []
    for cfg in (plugin, config):
        tables.append(pd.read_parquet(collect.run(cfg) / "transitions.parquet"))
        grids.append(pd.read_csv(train.run(cfg) / "psi_grid.csv"))
    assert "phi_next_expected" in tables[0] and "phi_next_expected" not in tables[1]
    pd.testing.assert_frame_equal(tables[0][tables[1].columns], tables[1])
    pd.testing.assert_frame_equal(grids[0], grids[1])


def test_the_gene_switch_yaml_is_the_toy_network() -> None:
    """The SBML gene switch read with its yaml has the Python model's (examples/python_model) exact psi and
    state space: the same network, written once in SBML."""
    config, toy = SbmlAgentModel(str(GENE_SWITCH)), GeneSwitchModel()
    assert config.internal.state_space.n_states == toy.internal.state_space.n_states == 25
    signal = torch.tensor([[0.001], [0.02], [0.05], [0.1]])
    torch.testing.assert_close(config.internal.exact_psi(signal, 0.05),
                               toy.internal.exact_psi(signal, 0.05), rtol=1e-9, atol=1e-12)  # fmt: skip
    assert config.describe().startswith("gene_switch: SBML network gene_switch.xml")


def test_the_exact_functions_go_in_chunks_that_fit_memory(monkeypatch) -> None:
    """Rows of the exact psi, age psi and class step go in chunks of a memory budget (200,000
    diagnostic rows of a 151-state network asked for 36 GB at once): the same values as one
    call (to rounding: batched exponentials), the budget here a few rows' worth."""
    from surrogate.models import network
    from surrogate.stages.train import rows_table

    config = SbmlAgentModel(str(GENE_SWITCH))
    internal = config.internal
    signal = torch.linspace(0.001, 0.1, 23).reshape(-1, 1).double()
    whole = internal.exact_psi(signal, 0.05)
    ages = internal.exact_age_psi(signal, 0.05, 4)
    k = internal.state_space.n_states
    monkeypatch.setattr(network, "EXACT_CHUNK_BYTES", 5 * network.EXACT_COPIES * 8 * k * k)
    calls = []
    generator = internal._generator
    monkeypatch.setattr(internal, "_generator",
                        lambda x, **kw: calls.append(len(x)) or generator(x, **kw))  # fmt: skip
    torch.testing.assert_close(internal.exact_psi(signal, 0.05), whole, rtol=1e-12, atol=1e-12)
    assert calls == [5, 5, 5, 5, 3]
    torch.testing.assert_close(
        internal.exact_age_psi(signal, 0.05, 4), ages, rtol=1e-12, atol=1e-12
    )
    # the diagnostic tabulates an exact psi that is no table over its rows' range
    exact = ExactPsi(internal, 0.05)
    rows = torch.linspace(0.02, 0.08, 1000).reshape(-1, 1)
    table = rows_table(exact, rows, ["inducer"])
    assert table is not exact and rows_table(table, rows, ["inducer"]) is table
    for phi in (0, 1):
        at = torch.full((1000,), phi)
        torch.testing.assert_close(table(at, rows), exact(at, rows), rtol=0, atol=1e-4)


SMALL = [
    "collect.n_per_state=400", "collect.n_cells=100", "collect.equilibration_time=1.0",
    "gp.n_inducing=10", "gp.epochs=5", "gp.diagnostic.n_cells=100", "gp.diagnostic.t_end=5.0",
    "gp.diagnostic.equilibration_time=1.0", "n_cells=100", "t_end=10.0",
    "equilibration_time=1.0", "start=[1.0,0.0]", "evaluate.subsample=200",
    "evaluate.run_missing=true",
]  # fmt: skip


def test_the_gene_switch_yaml_runs_through_every_stage(tmp_path) -> None:
    """collect -> train -> simulate (full, learned, exact) -> evaluate with nothing but the
    yaml and the SBML file (the README's route)."""
    overrides = ["model=sbml", f"model.spec={GENE_SWITCH}", *SMALL]
    cfg = compose_config(tmp_path / "data", overrides)
    table = pd.read_parquet(collect.run(cfg) / "transitions.parquet")
    assert {"L", "inducer", "phi", "phi_next"} <= set(table.columns)
    assert (table["inducer"] == table["L"]).all() and table["inducer"].between(0, 0.1).all()
    metrics = train.read_metrics(train.run(cfg))
    assert metrics["inputs"] == ["inducer"] and metrics["diagnostic"]["reference"] == "exact"
    out = evaluate.run(cfg)
    comparison = pd.read_csv(out / "comparison.csv")
    assert comparison["quantity"].tolist()[-2:] == ["on", "off"]
    assert comparison["ks"].between(0, 1).all()
    exact = simulate.run(compose_config(tmp_path / "data", [*overrides, "decision=exact"]))
    assert pd.read_parquet(exact / "observables.parquet")["cell"].nunique() == 100


def test_a_static_agent_with_an_input_formula(tmp_path) -> None:
    """The static body and an input given as a formula over the body's variables: the
    network sees 2 L, the observable is the share of time ON."""
    spec = yaml.safe_load(GENE_SWITCH.read_text())
    spec.update(network=str(GENE_SWITCH.parent / "gene_switch.xml"), body={"kind": "static"},
                inputs={"inducer": "2 * L"}, signal_bounds=None)  # fmt: skip
    model = build_model({"_target_": "surrogate.models.sbml_agent.SbmlAgentModel", **spec})
    x = torch.tensor([[0.01], [0.04]])
    assert model.internal.feature_names == ("inducer",)
    torch.testing.assert_close(model.internal.features(x, ["inducer"])[:, 0], 2 * x[:, 0])
    torch.manual_seed(0)
    sim = Simulator(model, FullDecision(model.internal), ConstantField(0.05), dt=0.05)
    state = sim.initial_state(200, (0.0, 0.0), equilibration_time=0.5)
    on = []
    for _ in range(40):
        sim.step(state)
        on.append(state.phi.float())
    fraction = model.body.observables(state.body, sim.field)["on_fraction"]
    torch.testing.assert_close(fraction, torch.stack(on).mean(0))
    assert torch.equal(state.body["position"], torch.zeros(200, 2))


def _spec(**changes) -> dict:
    spec = yaml.safe_load(GENE_SWITCH.read_text())
    spec["network"] = str(GENE_SWITCH.parent / "gene_switch.xml")
    for key, value in changes.items():
        if value is DROP:
            spec.pop(key)
        elif isinstance(value, dict) and isinstance(spec.get(key), dict):
            spec[key] = {**spec[key], **value}
        else:
            spec[key] = value
    return spec


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"lump": "Q >= 2"}, "model.lump: unknown species 'Q'"),
        ({"lump": "D + 2"}, "model.lump: 'D + 2' must be a condition"),
        ({"lump": "D >= "}, "model.lump: cannot parse 'D >= '"),
        ({"inputs": {"inducr": "L"}}, "input 'inducr' is not a global parameter of the model"),
        ({"inputs": {"inducer": "M"}}, "model.inputs.inducer: unknown body variable 'M'"),
        ({"inputs": {"inducer": ["L"]}}, "model.inputs.inducer must be a body variable"),
        ({"body": {"speed_on": "fast"}}, "model.body.speed_on must be a finite number, got 'fast'"),
        ({"body": {"speed_off": -1.0}}, "model.body.speed_off must be >= 0"),
        ({"body": {"wings": 2}}, "unknown model.body setting(s) ['wings']"),
        ({"body": {"kind": "flyer"}}, "model.body.kind must be one of"),
        ({"body": {"perturbation": {"radius": 0}}}, "perturbation.radius must be a finite number"),
        ({"body": {"perturbation": {"radius": float("inf")}}}, "> 0 mm, got inf"),
        ({"body": {"perturbation": {"radius": "1e308"}}}, "as a string: write 1.0e+308"),
        ({"body": {"perturbation": 3}}, "perturbation must be a mapping of settings ['radius', "),
        ({"body": {"speed_on": "1e-3"}}, "got '1e-3' (YAML reads 1e-3 as a"),
        ({"network": "/nonexistent.xml"}, "model.network=/nonexistent.xml: no such SBML file"),
        ({"lump_names": [False, True]}, "write them in quotes"),
        ({"ssa": "gpu"}, "model.ssa must be one of"),
        ({"signal_bounds": {"inducer": [1.0, 0.0]}}, "model.signal_bounds must give finite [lo"),
        ({"signal_bounds": {"inducer": [0.0, float("inf")]}}, "signal_bounds must give finite"),
        ({"signal_bounds": {"inducer": [0.0, "1e308"]}}, "as a string: write 1.0e+308"),
        ({"max_states": 2.5}, "model.max_states must be a non-negative integer"),
        ({"max_states": "5e3"}, "got '5e3' (YAML reads 5e3 as a string: write 5.0e+3)"),
        ({"burn_in": float("inf")}, "model.burn_in must be a finite number of seconds >= 0"),
        ({"collect": {"n_per_state": 0}}, "model.collect.n_per_state must be a positive integer"),
        (
            {"collect": {"blackout_time": -1.0}},
            "model.collect.blackout_time must be a non-negative",
        ),
        (
            {"collect": {"perturb_rate": "fast"}},
            "model.collect.perturb_rate must be a non-negative",
        ),
        ({"collect": {"jump": 1}}, "unknown model.collect setting(s) ['jump']"),
        ({"colour": "red"}, "unknown model setting(s) ['colour']"),
        # issue 37: required keys, types, local inputs, substance units
        ({"inputs": DROP}, "model.inputs is required (which SBML parameters are the agent's"),
        ({"lump": DROP}, "model.lump is required (the property phi"),
        ({"body": DROP}, "model.body is required (a body of the library"),
        ({"network": DROP}, "model.network is required (the SBML file"),
        ({"inputs": None}, "model.inputs is required"),
        ({"inputs": "L"}, "model.inputs must map at least one SBML parameter to its source"),
        ({"inputs": ["inducer"]}, "model.inputs must map at least one SBML parameter"),
        ({"lump": 5}, "model.lump must be a non-empty string"),
        ({"network": 3}, "model.network must be a non-empty string"),
        ({"name": ["a"]}, "model.name must be a non-empty string, got ['a']"),
        ({"burn_in": float("inf")}, "model.burn_in must be a finite number of seconds >= 0"),
        (
            {"max_states": 2.5},
            "model.max_states must be a non-negative integer (the most states enumerated for the exact law), got 2.5",
        ),
        ({"substance_units": "moles"}, "model.substance_units must be items"),
        ({"species_in_laws": "amounts"}, "model.species_in_laws must be counts"),
        ({"reactant_guard": "yes"}, "model.reactant_guard must be true"),
        ({"inputs": {"R1.k": "L"}}, "input 'R1.k' is not a global parameter of the model nor a"),
        ({"inputs": {"inducer": {"k": "L"}}}, "a reaction's local parameter is one key"),
    ],
)
def test_a_malformed_yaml_is_refused_by_name(tmp_path, changes, message) -> None:
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump(_spec(**changes)))
    with pytest.raises(ConfigError) as info:
        SbmlAgentModel(str(path))
    assert message in str(info.value)
    assert f"model.spec={path}" in str(info.value)  # the message names the yaml


@pytest.mark.parametrize("kind", ["walker", "static", "chemotaxis"])
def test_every_body_refuses_a_perturbation_that_is_not_a_mapping_or_infinite(kind) -> None:
    """A number where the perturbation's settings go, or an infinite radius (jumps to inf),
    is refused naming the setting in every body, as in the E. coli models."""
    from surrogate.models.bodies import build_body
    from surrogate.models.ecoli import EcoliModel

    with pytest.raises(ConfigError, match=r"model\.body\.perturbation must be a mapping of "
                                          r"settings \['radius', 'sampling'\], got 3"):  # fmt: skip
        build_body({"kind": kind, "perturbation": 3})
    with pytest.raises(ConfigError, match=r"model\.body\.perturbation\.radius must be a finite"):
        build_body({"kind": kind, "perturbation": {"radius": float("inf")}})
    with pytest.raises(ConfigError, match=r"model\.perturbation must be a mapping"):
        EcoliModel(perturbation=3)
    with pytest.raises(ConfigError, match=r"model\.perturbation must be a mapping"):
        EcoliPhosphoModel(perturbation=3)


def test_the_chemotaxis_body_names_its_constants_under_the_body(tmp_path) -> None:
    spec = yaml.safe_load(PHOSPHO.read_text())
    spec["network"] = str((PHOSPHO.parent / spec["network"]).resolve())
    spec["body"] = {"kind": "chemotaxis", "tau": "slow"}
    with pytest.raises(ConfigError, match=r"model\.body\.tau must be a finite number, got 'slow'"):
        SbmlAgentModel(**spec)
    spec["body"] = {"kind": "chemotaxis", "tau": "2e1"}
    with pytest.raises(ConfigError, match=r"model\.body\.tau must be a finite number, got '2e1' "
                                          r"\(YAML reads 2e1 as a string: write 2\.0e\+1\)"):  # fmt: skip
        SbmlAgentModel(**spec)
    spec["body"] = {"kind": "chemotaxis", "tau": 0.04}
    with pytest.raises(ConfigError, match=r"dt=0.05 s must be smaller than model\.body\.tau"):
        SbmlAgentModel(**spec).validate(0.05)


def test_an_edited_file_changes_the_artefacts_identity(tmp_path) -> None:
    """The artefacts of a yaml model depend on its files' content, not only on their paths."""
    from surrogate.stages.settings import ModelSetup

    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "gene_switch.xml").write_text((GENE_SWITCH.parent / "gene_switch.xml").read_text())
    (folder / "model.yaml").write_text(GENE_SWITCH.read_text())
    cfg = compose_config(tmp_path / "data", ["model=sbml", f"model.spec={folder / 'model.yaml'}"])
    before = ModelSetup.from_config(cfg).identity()
    xml = (folder / "gene_switch.xml").read_text().replace('value="2"', 'value="3"')
    (folder / "gene_switch.xml").write_text(xml)
    after = ModelSetup.from_config(cfg).identity()
    assert before["model"] == after["model"]
    assert before["model_sources"]["network"] != after["model_sources"]["network"]


def test_a_comment_in_the_yaml_keeps_the_artefacts_identity(tmp_path) -> None:
    """The spec's digest is of its settings as read: a comment or layout edit keeps every
    artefact (collections cost minutes to hours), a changed setting does not."""
    from surrogate.stages.settings import ModelSetup

    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "gene_switch.xml").write_text((GENE_SWITCH.parent / "gene_switch.xml").read_text())
    spec = folder / "model.yaml"
    spec.write_text(GENE_SWITCH.read_text())
    cfg = compose_config(tmp_path / "data", ["model=sbml", f"model.spec={spec}"])
    before = ModelSetup.from_config(cfg).identity()["model_sources"]
    spec.write_text("# a note the user added\n" + GENE_SWITCH.read_text() + "\n# and another\n")
    assert ModelSetup.from_config(cfg).identity()["model_sources"] == before
    edited = yaml.safe_load(GENE_SWITCH.read_text())
    edited["burn_in"] = float(edited.get("burn_in", 50.0)) + 1.0
    spec.write_text(yaml.safe_dump(edited))
    assert ModelSetup.from_config(cfg).identity()["model_sources"]["spec"] != before["spec"]


def test_an_input_computed_by_sbml_math(tmp_path) -> None:
    """An input's formula may live in the SBML file: ``inducer`` assigned by a rule over the
    input parameter ``signal``, which the yaml maps to the field's value."""
    import libsbml

    document = libsbml.readSBMLFromFile(str(GENE_SWITCH.parent / "gene_switch.xml"))
    model = document.getModel()
    signal = model.createParameter()
    signal.setId("signal")
    signal.setValue(0.0)
    signal.setConstant(True)
    model.getParameter("inducer").setConstant(False)
    rule = model.createAssignmentRule()
    rule.setVariable("inducer")
    rule.setMath(libsbml.parseL3Formula("2 * signal"))
    path = tmp_path / "switch.xml"
    path.write_text(libsbml.writeSBMLToString(document))
    spec = {**_spec(network=str(path), signal_bounds=None), "inputs": {"signal": "L"}}
    agent = SbmlAgentModel(**spec)
    assert agent.internal.signal_names == ("signal",)
    x = torch.tensor([[0.01], [0.04]])
    counts = torch.tensor([[8, 0, 0], [8, 0, 0]])
    rates = agent.internal.kinetics.propensities(counts, agent.internal.kinetic_inputs(x))
    torch.testing.assert_close(rates[:, 0], 50.0 * 2 * x[:, 0].double() * 8)  # k_act 2 L I


@pytest.mark.parametrize("which", ["phospho_plugin", "phospho_yaml", "gene_switch_formula"])
def test_models_pickle_before_and_after_use(which) -> None:
    """Settings may travel to another process with their model: network models
    pickle (expressions, not generated code or the compiled SSA) before and after a window,
    and the copy computes the same features and phi."""
    import pickle

    model = {
        "phospho_plugin": lambda: EcoliPhosphoModel(burn_in=0.05),
        "phospho_yaml": lambda: SbmlAgentModel(str(PHOSPHO), burn_in=0.05),
        "gene_switch_formula": lambda: SbmlAgentModel(
            str(GENE_SWITCH), inputs={"inducer": "2 * L"}
        ),
    }[which]()
    pickle.dumps(model)
    torch.manual_seed(0)
    sim = Simulator(model, FullDecision(model.internal), GaussianField(), dt=0.05)
    state = sim.initial_state(5, (1.0, 0.0), 0.1)
    sim.step(state)
    copy = pickle.loads(pickle.dumps(model))
    names = model.internal.signal_names
    assert torch.equal(copy.internal.features(state.inputs, names),
                       model.internal.features(state.inputs, names))  # fmt: skip
    assert torch.equal(
        copy.internal.phi(sim.decision.state), model.internal.phi(sim.decision.state)
    )


# ----------------------------------------------------------------------------------------------
# issue 37: public files read as published


def test_the_published_examples_load_through_their_yamls() -> None:
    """The vendored StochSS toggle switch (substance units declared items, one-way reversible
    laws read as irreversible with one warning) and Wilkinson's auto-regulatory network (a
    local-parameter input) load as published, and their inputs reach the propensities."""
    with pytest.warns(SbmlWarning, match="'cu', 'cv', 'du', 'dv'"):
        toggle = SbmlAgentModel(str(TOGGLE))
    assert toggle.internal.signal_names == ("alpha1",) and toggle.internal.species == ("U", "V")
    x = torch.tensor([[0.02], [0.08]])  # L: alpha1 = 20 L = 0.4, 1.6
    counts = torch.tensor([[3, 2], [3, 2]])
    rates = toggle.internal.kinetics.propensities(counts, toggle.internal.kinetic_inputs(x))
    torch.testing.assert_close(rates[:, 0], 20 * x[:, 0].double() / (1 + 2**2))

    ar = SbmlAgentModel(str(AUTOREGULATION), classes=None)  # no classes: auto (a long run)
    assert ar.internal.signal_names == ("Transcription.k2",)
    counts = torch.tensor([[7, 3, 4, 25, 30], [7, 3, 4, 25, 30]])
    rates = ar.internal.kinetics.propensities(counts, ar.internal.kinetic_inputs(x))
    r = ar.internal.kinetics.network.reaction_names.index("Transcription")
    torch.testing.assert_close(rates[:, r], 0.4 * x[:, 0].double() * 7)  # k2 = 0.4 L, 7 genes
    lows = counts.clone()
    lows[:, 3] = torch.tensor([35, 34])
    assert ar.internal.phi((lows,)).tolist() == [1.0, 0.0]  # P = 35 >= 35, P = 34 < 35


def test_the_docs_other_public_networks_load_through_their_yamls() -> None:
    """StochSS's Tyson oscillator (counts in laws over a volume of 300, kt = 400 L, lump
    Y >= 300) and the textbook's dimerisation (a local input c1 = 0.0332 L, lump P2 >= 87,
    151 states) load through their yamls as the docs ran them, and a few full-model steps of
    each keep their laws (the dimerisation conserves P + 2 P2 = 301)."""
    with pytest.warns(SbmlWarning, match="'rxn1', 'rxn2', 'rxn3', 'rxn4', 'rxn5'"):
        tyson = SbmlAgentModel(str(TYSON))
    assert tyson.internal.signal_names == ("kt",) and tyson.internal.species == ("X", "Y")
    x = torch.tensor([[0.04], [0.07]])  # L: kt = 400 L = 16, 28
    counts = torch.tensor([[150, 300], [150, 299]])
    rates = tyson.internal.kinetics.propensities(counts, tyson.internal.kinetic_inputs(x))
    names = tyson.internal.kinetics.network.reaction_names
    torch.testing.assert_close(rates[:, names.index("rxn3")], 400 * x[:, 0].double() * 150)
    # counts, not concentrations: X's production is vol / (1 + (Y / vol)^2) = 300 / 2 at Y = 300
    assert rates[0, names.index("rxn1")].item() == pytest.approx(150.0)
    assert tyson.internal.phi((counts,)).tolist() == [1.0, 0.0]  # Y = 300 >= 300, Y = 299
    assert tyson.internal.burn_in == 130.0

    with pytest.warns(SbmlWarning, match="read with SBML Level 2's defaults"):
        dimer = SbmlAgentModel(str(DIMERISATION), classes=None)  # no classes: auto (a run)
    assert dimer.internal.signal_names == ("Dimerisation.c1",)
    assert dimer.internal.species == ("P", "P2")
    counts = torch.tensor([[127, 87], [129, 86]])
    rates = dimer.internal.kinetics.propensities(counts, dimer.internal.kinetic_inputs(x))
    torch.testing.assert_close(rates[:, 0], 0.0332 * x[:, 0].double() * counts[:, 0] *
                               (counts[:, 0] - 1) / 2)  # fmt: skip
    assert dimer.internal.phi((counts,)).tolist() == [1.0, 0.0]  # P2 = 87 >= 87, P2 = 86
    space = dimer.internal.state_space
    assert space is not None and space.n_states == 151  # enumerable: exact chain and law

    for model, n in ((tyson, 4), (dimer, 16)):
        _, phis, state = run_full(model, n_cells=n, steps=10)
        assert phis.shape == (10, n) and set(phis.unique().tolist()) <= {0.0, 1.0}
        assert (state >= 0).all()
    assert (state[:, 0] + 2 * state[:, 1] == 301).all()


def test_a_stochss_export_without_substance_units_is_refused_with_the_fix(tmp_path) -> None:
    spec = yaml.safe_load(TOGGLE.read_text())
    spec.pop("substance_units")
    spec["network"] = str(TOGGLE.parent / spec["network"])
    with pytest.raises(SbmlError, match=r"species 'U' \(mole\), 'V' \(mole\) have substance "
                       r"units other than items.*`substance_units: items` in the model yaml"):  # fmt: skip
        SbmlAgentModel(**spec)


def test_a_global_input_in_a_file_with_only_local_constants_lists_them(tmp_path) -> None:
    spec = yaml.safe_load(AUTOREGULATION.read_text())
    spec["network"] = str(AUTOREGULATION.parent / spec["network"])
    spec["inputs"] = {"k2": "L"}
    with pytest.raises(SbmlError) as info:
        SbmlAgentModel(**spec)
    assert "input 'k2' is not a global parameter of the model nor a local one" in str(info.value)
    assert "'Transcription.k2'" in str(info.value) and "global parameters: []" in str(info.value)


def test_a_shadowed_global_input_in_a_yaml_is_refused(tmp_path) -> None:
    from tests.sbml.builder import Reaction, Species, build

    (tmp_path / "net.xml").write_text(build("shadow", [Species("X", amount=5)], {"k": 1.0}, [
        Reaction("Make", "k", {}, {"X": 1}),
        Reaction("Decay", "k * X", {"X": 1}, local={"k": 0.1}),
    ]))  # fmt: skip
    spec = {**_spec(network=str(tmp_path / "net.xml"), signal_bounds=None), "lump": "X >= 3"}
    with pytest.raises(SbmlError, match=r"input 'k' is a global parameter, but reaction 'Decay' "
                       r"declares a local parameter 'k'.*\(Decay\.k\)"):  # fmt: skip
        SbmlAgentModel(**{**spec, "inputs": {"k": "L"}})
    agent = SbmlAgentModel(**{**spec, "inputs": {"Decay.k": "L"}})
    rates = agent.internal.kinetics.propensities(
        torch.tensor([[5]]), agent.internal.kinetic_inputs(torch.tensor([[0.3]]))
    )
    torch.testing.assert_close(rates, torch.tensor([[1.0, 0.3 * 5]], dtype=torch.float64))


def test_a_yaml_without_inputs_is_refused_before_collect_runs(tmp_path) -> None:
    """The issue's case: the yaml passed validation, then collect died with ``stack expects a
    non-empty TensorList``; now collect's validation names the key and writes nothing."""
    spec = _spec(inputs=DROP)
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump(spec))
    cfg = compose_config(tmp_path / "data", ["model=sbml", f"model.spec={path}"])
    with pytest.raises(ConfigError, match=r"model\.inputs is required"):
        collect.validate(cfg)
    assert not (tmp_path / "data").exists()
    with pytest.raises(ConfigError, match=r"model\.inputs must map at least one SBML parameter"):
        SbmlAgentModel(**{**spec, "inputs": {}})


def _agent(**changes) -> SbmlAgentModel:
    return SbmlAgentModel(**{**_spec(**changes), "signal_bounds": None})


def test_an_infinite_constant_in_the_lump_gives_the_exact_law() -> None:
    """``D < INF`` (always true) is code, not the name ``inf``: the exact stationary law and
    psi are computed, every state ON (the OFF lump has no mass: NaN, as documented)."""
    agent = _agent(lump="D < INF")
    x = torch.tensor([[0.01], [0.05]])
    assert agent.internal.phi(agent.internal.initial_state(x)).tolist() == [1.0, 1.0]
    psi = agent.internal.exact_psi(x.double(), 0.05)
    assert psi[:, 0].isnan().all() and torch.equal(psi[:, 1], torch.ones(2, dtype=psi.dtype))


@pytest.mark.parametrize(
    ("formula", "good", "at", "message"),
    [
        ("NaN", 0.02, 0.05, r"model\.inputs\.inducer \('NaN'\) is nan where (L|inducer) = "),
        ("1 / L", 0.02, 0.0, r"model\.inputs\.inducer \('1 / L'\) is inf where (L = 0|inducer = inf):"),
        ("-L", 0.0, 0.05, r"reaction 'activate' has rate -20 \(negative or not finite\) in "
                          r"state \{'I': 8, 'P': 0, 'D': 0\} where (L|inducer) = -?0\.05 "
                          r"\(model\.inputs\.inducer \('-L'\) = -0\.05\)"),
    ],
)  # fmt: skip
def test_bad_rates_from_an_input_formula_are_refused_by_name(formula, good, at, message) -> None:
    """A formula whose values are not finite, or give a negative rate, is refused where the
    exact law is built (stationary law, exact psi) and where a window runs (both SSAs), naming
    model.inputs.<param>; never a torch multinomial crash or a silent generator with negative
    off-diagonal rates."""
    x = torch.tensor([[good], [at]])  # the second cell's rates are bad
    agent = _agent(inputs={"inducer": formula})
    with pytest.raises(ConfigError, match=message):
        agent.internal.initial_state(x)
    signal = agent.internal.features(x, agent.internal.signal_names).double()
    with pytest.raises(ConfigError, match=message):
        agent.internal.exact_psi(signal, 0.05)
    with pytest.raises(ConfigError, match=message):
        agent.internal.exact_age_psi(signal, 0.05, 3)
    for ssa in ("compiled", "batched"):  # too many states for the exact law: burn-in windows
        windows = _agent(inputs={"inducer": formula}, max_states=2, ssa=ssa, burn_in=0.1)
        assert windows.internal.state_space is None
        with pytest.raises(ConfigError, match=message):
            windows.internal.initial_state(x)


def test_a_piecewise_rate_without_otherwise_is_refused_where_no_piece_holds(tmp_path) -> None:
    """SBML allows ``piecewise`` without ``otherwise`` (undefined where no condition holds): the
    rate is NaN there, and a NaN rate is refused naming the reaction, by the exact law as by
    the compiled SSA, while the inputs where a piece holds give the law of the piece."""
    import libsbml

    document = libsbml.readSBMLFromFile(str(GENE_SWITCH.parent / "gene_switch.xml"))
    law = document.getModel().getReaction("deactivate").getKineticLaw()
    law.setMath(libsbml.parseL3Formula("piecewise(k_deact * P, inducer < 0.08)"))
    path = tmp_path / "switch.xml"
    path.write_text(libsbml.writeSBMLToString(document))
    agent, plain = _agent(network=str(path)), _agent()
    inside = torch.tensor([[0.01], [0.05]], dtype=torch.float64)
    torch.testing.assert_close(agent.internal.exact_psi(inside, 0.05),
                               plain.internal.exact_psi(inside, 0.05), rtol=0, atol=0)  # fmt: skip
    message = r"reaction 'deactivate' has rate nan \(negative or not finite\) in state"
    with pytest.raises(ConfigError, match=message):
        agent.internal.exact_psi(torch.tensor([[0.09]], dtype=torch.float64), 0.05)
    windows = _agent(network=str(path), max_states=2, burn_in=0.1)
    with pytest.raises(ConfigError, match=message):
        windows.internal.initial_state(torch.tensor([[0.09]]))

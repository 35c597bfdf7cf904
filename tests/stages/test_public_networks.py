"""Networks written as public repositories export them (StochSS's L3V2: amounts in "mole",
every reaction flagged reversible, laws in counts), run as a new user runs them: a yaml with
no `signal_bounds`, the inspector, reproduce's settings. Each test reproduces one rough edge
such a file hit, in a few states written here (no public file is copied)."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch
import yaml

from surrogate.sbml import SbmlWarning

#: a StochSS-style export: a monomer dimerising reversibly, 12 monomers (7 states)
DIMERISATION = """<?xml version="1.0" encoding="UTF-8"?>
<sbml xmlns="http://www.sbml.org/sbml/level3/version2/core" level="3" version="2">
  <model name="Dimers">
    <listOfCompartments>
      <compartment id="vol" spatialDimensions="3" size="1" constant="true"/>
    </listOfCompartments>
    <listOfSpecies>
      <species id="M" compartment="vol" initialAmount="12" substanceUnits="mole"
               hasOnlySubstanceUnits="false" boundaryCondition="false" constant="false"/>
      <species id="D" compartment="vol" initialAmount="0" substanceUnits="mole"
               hasOnlySubstanceUnits="false" boundaryCondition="false" constant="false"/>
    </listOfSpecies>
    <listOfParameters>
      <parameter id="k_c" value="0.05" constant="true"/>
      <parameter id="k_d" value="0.5" constant="true"/>
    </listOfParameters>
    <listOfReactions>
      <reaction id="bind" reversible="true">
        <listOfReactants><speciesReference species="M" stoichiometry="2" constant="true"/>
        </listOfReactants>
        <listOfProducts><speciesReference species="D" stoichiometry="1" constant="true"/>
        </listOfProducts>
        <kineticLaw><math xmlns="http://www.w3.org/1998/Math/MathML">
          <apply><divide/><apply><times/><cn>0.5</cn><ci>k_c</ci><ci>M</ci>
            <apply><minus/><ci>M</ci><cn type="integer">1</cn></apply></apply><ci>vol</ci>
          </apply></math></kineticLaw>
      </reaction>
      <reaction id="unbind" reversible="true">
        <listOfReactants><speciesReference species="D" stoichiometry="1" constant="true"/>
        </listOfReactants>
        <listOfProducts><speciesReference species="M" stoichiometry="2" constant="true"/>
        </listOfProducts>
        <kineticLaw><math xmlns="http://www.w3.org/1998/Math/MathML">
          <apply><times/><ci>k_d</ci><ci>D</ci></apply></math></kineticLaw>
      </reaction>
    </listOfReactions>
  </model>
</sbml>
"""

WALKER = {"kind": "walker", "speed_on": 0.02, "speed_off": 0.005}


def write_model(tmp_path: Path, sbml: str, **spec: object) -> Path:
    """The SBML text beside a yaml naming it (``spec`` adds or overrides keys)."""
    (tmp_path / "net.sbml").write_text(sbml)
    keys = {"network": "net.sbml", "substance_units": "items", "body": WALKER, **spec}
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump(keys))
    return path


def test_reproduce_runs_the_exact_chain_directly_without_signal_bounds(
    compose_cfg, tmp_path
) -> None:
    """An enumerable network whose yaml declares no `signal_bounds` (none of the examples'
    keys a new user copies): reproduce's exact chain computes exp(Q dt) at each cell's inputs
    (decision.mode=direct) rather than refusing the whole run with advice that names the
    abstraction's decision; with bounds it keeps its table."""
    from surrogate.errors import ConfigError
    from surrogate.stages.settings import ReproduceSettings, SimulateSettings

    spec = write_model(tmp_path, DIMERISATION, inputs={"k_c": "L"}, lump="D >= 2")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        overrides = ["model=sbml", f"model.spec={spec}"]
        settings = ReproduceSettings.from_config(compose_cfg("reproduce", overrides))
        assert settings.exact, "the network is enumerable: its exact chain runs"
        assert {e.candidate.decision.mode for e in settings.exact.values()} == {"direct"}
        with pytest.raises(ConfigError, match="signal_bounds"):  # asked for by name
            SimulateSettings.from_config(compose_cfg("simulate", [*overrides, "decision=exact"]))
        bounded = write_model(tmp_path, DIMERISATION, inputs={"k_c": "L"}, lump="D >= 2",
                              signal_bounds={"k_c": [0.0, 0.1]})  # fmt: skip
        table = ReproduceSettings.from_config(
            compose_cfg("reproduce", ["model=sbml", f"model.spec={bounded}"])
        )
        assert {e.candidate.decision.mode for e in table.exact.values()} == {"lookup"}


def test_an_exact_chain_too_dear_to_compute_directly_is_skipped_with_the_fix(
    compose_cfg, tmp_path, monkeypatch, caplog
) -> None:
    """The textbook's dimerisation (151 states, ~5.7 ms per cell-step directly) made reproduce
    spend ~2 h on its exact chain, estimated at 1 s. The budget now prices the direct exact
    chain by its K^3, and reproduce skips it past DIRECT_EXACT_MAX_SECONDS, saying how to have
    it as a table; here the 7-state network is made dear by a small limit."""
    from surrogate.models import network
    from surrogate.stages import budget
    from surrogate.stages.settings import ReproduceSettings
    from surrogate.stages.settings import reproduce as reproduce_settings

    spec = write_model(tmp_path, DIMERISATION, inputs={"k_c": "L"}, lump="D >= 2")
    overrides = ["model=sbml", f"model.spec={spec}"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        settings = ReproduceSettings.from_config(compose_cfg("reproduce", overrides))
        internal = settings.train.setup.model.internal
        per_step = network.direct_exact_step_seconds(internal)
        assert per_step == pytest.approx(network.DIRECT_EXACT_SECONDS_PER_K3 * 7**3)
        run = next(iter(settings.exact.values())).candidate
        abstract = next(iter(settings.evaluations.values())).candidate
        dear = budget.run_work(run, reuse=False)[0].cell_step_seconds
        cheap = budget.run_work(abstract, reuse=False)[0].cell_step_seconds
        assert dear == pytest.approx(cheap + per_step)
        monkeypatch.setattr(reproduce_settings, "DIRECT_EXACT_MAX_SECONDS", 1e-3)
        caplog.clear()
        skipped = ReproduceSettings.from_config(compose_cfg("reproduce", overrides))
    assert not skipped.exact and skipped.evaluations
    assert "the exact-psi chain skipped" in caplog.text and "signal_bounds" in caplog.text


def decay_model(tmp_path: Path, **spec: object) -> Path:
    """StochSS's Degradation written small: X -> 0 at k X from 12 molecules (k = L), nothing
    makes X: every cell ends at X = 0, where no reaction can fire."""
    from tests.sbml.builder import Reaction, Species, build

    text = build("decay", [Species("X", amount=12)], {"k": 0.5},
                 [Reaction("decay", "k * X", {"X": 1}, {})])  # fmt: skip
    return write_model(tmp_path, text, inputs={"k": "20 * L"}, lump="X >= 6", **spec)


@pytest.mark.parametrize("max_states", [5000, 0], ids=["exact", "simulated"])
def test_a_network_that_runs_down_is_refused_as_such(compose_cfg, tmp_path, max_states) -> None:
    """StochSS's Degradation, Michaelis-Menten and Schlogl exports run down to a state where
    no reaction fires (the substrate used up): the inspector used to advise "choose a lump that
    holds part of the time" (none can) and flag the input `k` as having "no effect". Now it
    says the network stops, with the state it stops in, exactly (the generator) and by
    simulation; the input is flagged as unseen, not as without effect."""
    from surrogate.errors import ConfigError
    from surrogate.io import read_json
    from surrogate.stages import inspection

    spec = decay_model(tmp_path, max_states=max_states)
    small = ["model=sbml", f"model.spec={spec}", "fields=[gaussian]", "t_end=20",
             "equilibration_time=1", "inspect.population_cells=20", "inspect.max_seconds=5",
             "inspect.n_cells=20", "inspect.record_windows=200", "threads=1"]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SbmlWarning)
        with pytest.raises(ConfigError) as info:
            inspection.run(compose_cfg("inspect", small))
    message = str(info.value)
    assert "the network stops" in message and "(e.g. X = 0)" in message, message
    assert "Choose a lump" not in message
    report = next((tmp_path / "data" / "inspect").glob("*/inspect.json"))
    summary = read_json(report)
    assert summary["occupancy"]["method"] == ("exact" if max_states else "simulated")
    assert summary["stopped"]["share"] == pytest.approx(1.0)
    assert summary["stopped"]["state"] == {"X": 0}
    flags = summary["network"]["inputs"][0]["flags"]
    assert flags and "never fires" in flags[0], flags


def test_species_in_laws_from_the_yaml_and_the_identity_of_older_models(tmp_path) -> None:
    """The yaml's `species_in_laws: counts` reaches the reader (a StochSS export with volume
    1000 is read over counts); unset, the key (and `reactant_guard`, added after it) stays out
    of the spec's digests (the full model's law, every artefact's sources), so yamls written
    before them keep their artefacts."""
    import hashlib
    import json

    from surrogate.models.sbml_agent import ABSTRACTION_KEYS, SbmlAgentModel
    from tests.sbml.test_reader import stochss_export

    text = stochss_export(1000.0)
    counts = SbmlAgentModel(str(write_model(tmp_path, text, inputs={"k1": "L"}, lump="X >= 20",
                                            species_in_laws="counts")))  # fmt: skip
    kinetics = counts.internal.kinetics
    state = torch.tensor([[20, 10]])
    assert (
        kinetics.propensities(state, torch.tensor([[5.0]]))[0, 1].item() == 0.5 * 10 * 20 * 19 / 2
    )
    unset = SbmlAgentModel(str(write_model(tmp_path, DIMERISATION, inputs={"k_c": "L"},
                                           lump="D >= 2")))  # fmt: skip
    law = {k: v for k, v in unset.settings.items()
           if k not in ABSTRACTION_KEYS and k not in ("species_in_laws", "reactant_guard")}  # fmt: skip
    digest = hashlib.sha256(json.dumps(law, sort_keys=True, default=str).encode()).hexdigest()
    assert unset.full_model_identity({})["model_sources"]["settings"] == digest
    read = {k: v for k, v in unset.settings.items()
            if k not in ("species_in_laws", "reactant_guard")}  # fmt: skip
    spec = hashlib.sha256(json.dumps(read, sort_keys=True, default=str).encode()).hexdigest()
    assert unset.sources()["spec"] == spec  # every artefact's identity, as before the key


def test_reactant_guard_from_the_yaml(tmp_path) -> None:
    """Unset, a law that fires without its reactants is guarded (Wilkinson's ch05-act laws:
    0 while I, A lack the molecule); `reactant_guard: false` reaches the reader (the laws as
    written) and is in the spec's identity; `true` is the default's law."""
    from surrogate.models.sbml_agent import SbmlAgentModel
    from tests.sbml.test_reader import activation_text

    def model(**spec: object) -> SbmlAgentModel:
        with pytest.warns(SbmlWarning, match="can fire without their reactants"):
            return SbmlAgentModel(str(write_model(tmp_path, activation_text(),
                                                  inputs={"Activation.alpha": "L"},
                                                  lump="A >= 1", **spec)))  # fmt: skip

    state, inputs = torch.tensor([[1, 0, 1, 0, 0, 1, 0]]), torch.tensor([[0.5]])
    unset, written, guarded = model(), model(reactant_guard=False), model(reactant_guard=True)
    assert unset.internal.kinetics.propensities(state, inputs).tolist() == [[0, 1, 0, 0, 0]]
    assert guarded.internal.kinetics.propensities(state, inputs).tolist() == [[0, 1, 0, 0, 0]]
    assert written.internal.kinetics.propensities(state, inputs).tolist() == [[0.5, 1, 3, 0, 0]]
    assert written.sources()["spec"] != unset.sources()["spec"]


def test_a_waste_counter_does_not_hold_the_settling_run_back(tmp_path) -> None:
    """StochSS's Brusselator counts its waste (C, D: made, never consumed nor read): their
    means grow for ever, so the settling run used to double its horizon until the budget and
    call every grid point unsettled (the occupancy refusal then only a warning, the burn-in
    advice a lower bound). A birth-death X with a waste counter W now settles, W's growth is
    reported, and the counter is named in the notes."""
    import numpy as np

    from surrogate.diagnosis.options import InspectOptions
    from surrogate.diagnosis.population import Grid
    from surrogate.diagnosis.probe import counter_species
    from surrogate.diagnosis.simulated import simulate_fixed_inputs
    from surrogate.models.sbml_agent import SbmlAgentModel
    from surrogate.stages.settings.inspection import inspect_defaults
    from tests.sbml.builder import Reaction, Species, build

    text = build("waste", [Species("X", amount=0), Species("W", amount=0)], {"k": 2.0, "g": 1.0},
                 [Reaction("birth", "k", {}, {"X": 1}),
                  Reaction("death", "g * X", {"X": 1}, {"W": 1})])  # fmt: skip
    model = SbmlAgentModel(str(write_model(tmp_path, text, inputs={"k": "40 * L"}, lump="X >= 3",
                                           body={"kind": "static"})))  # fmt: skip
    assert counter_species(model.internal) == [1]
    v = np.array([0.05, 0.04, 0.06])
    grid = Grid(("L",), v[:, None], np.array([-1, 0, 0]), v.min(keepdims=True),
                           v[:1], v.max(keepdims=True))  # fmt: skip
    torch.manual_seed(0)
    options = InspectOptions.from_mapping(
        {**inspect_defaults(), "n_cells": 200, "record_windows": 200, "max_time": 80.0}
    )
    fixed = simulate_fixed_inputs(model, grid, options, 0.05, torch.device("cpu"),
                                             30.0)  # fmt: skip
    assert fixed.settled.all(), fixed.notes
    assert any("not waited for: W" in note for note in fixed.notes)
    assert fixed.horizon < 80.0  # settled on X and phi, not stopped at max_time


def test_a_start_the_noise_hides_is_not_taken_for_a_settled_curve() -> None:
    """BioModels' repressilator (BIOMD0000000012) from its file's counts (PX = 0): once the
    inspector thinned its cells to 25 per point, the oscillation spread the cells so widely
    over their cycle that the noise band around the plateau covered PX = 0, and every species
    and phi "settled in 0 s" (burn-in 50 s "enough", while a population after it had phi = 1
    in 0.3 % of cells against a stationary 16-26 %). Cells that all start from one state whose
    distance from the plateau exceeds the tolerance but lies within the band are now not
    settled; with enough cells to see the departure they settle at the first sample."""
    import numpy as np

    from surrogate.evaluate.dynamics import settling_from_cells

    rng = np.random.default_rng(0)
    times = np.linspace(0.0, 100.0, 65)

    def cells(n: int) -> np.ndarray:
        v = rng.normal(1000.0, 2000.0, size=(n, times.size))
        v[:, 0] = 0.0  # the file's count
        return v

    few = settling_from_cells(times, cells(25))
    assert not few.settled
    many = settling_from_cells(times, cells(2500))
    assert many.settled and many.time == times[1]
    # a start within the tolerance of the plateau is settled at once, whatever the noise
    near = cells(25)
    near[:, 0] = near[:, 1:].mean()
    assert settling_from_cells(times, near).settled


def test_the_noise_lines_name_each_quantity_beside_its_own_floor() -> None:
    """The Tyson oscillator's report said "linear: largest KS 0.340 vs noise floor 0.360;
    above noise: on, off": the largest KS (t=25 s) and the largest floor were one quantity,
    while `on` and `off` were above their own floors. Each quantity above noise is now named
    with its KS and its floor."""
    import pandas as pd

    from surrogate.stages.reproduce import noise_line

    table = pd.DataFrame({"quantity": ["t=25 s", "on", "off"], "ks": [0.34, 0.199, 0.145],
                          "ks_noise_floor": [0.36, 0.101, 0.067],
                          "within_noise": [True, False, False]})  # fmt: skip
    assert noise_line("linear", table) == (
        "- **linear**: above noise: on (KS 0.199 vs noise floor 0.101), off (KS 0.145 vs "
        "noise floor 0.067)."
    )
    table["within_noise"] = True
    assert "every quantity within" in noise_line("linear", table)

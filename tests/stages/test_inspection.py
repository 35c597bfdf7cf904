"""The inspect stage end to end: its report and refusal, the cost probe before any estimate,
collect's early stop, bad settings refused by name (the measurements themselves:
tests/diagnosis/test_inspection.py).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from surrogate.diagnosis.options import InspectOptions
from surrogate.errors import ConfigError
from surrogate.fields import ConstantField
from surrogate.io import read_json
from surrogate.models.sbml_agent import SbmlAgentModel
from surrogate.simulate.decision import FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.transitions import CollectOptions, collect_transitions
from surrogate.stages import inspection
from tests.diagnosis.test_inspection import (
    DT,
    G,
    K,
    birth_death,
    network_model,
    poisson_tail,
    telegraph,
)
from tests.sbml.builder import Reaction, Species

# ----------------------------------------------------------------------------------------------
# the stage, refusal and collect's early stop


def test_the_stage_writes_its_report_and_refuses_an_always_true_lump(tmp_path, compose_cfg) -> None:
    """End to end (exact network, one field; static cells, so one input value L): report.md,
    inspect.json and the manifest, the occupancy the Poisson tail at k L / g, reused the second
    time; a lump true in every state is refused with its occupancy measured."""
    _, spec = birth_death(tmp_path, "X >= 1", reservoir=True)
    small = ["model=sbml", f"model.spec={spec}", "fields=[gaussian]", "t_end=20",
             "equilibration_time=1", "inspect.population_cells=20", "inspect.max_seconds=5",
             "inspect.pilot.enabled=false"]  # fmt: skip
    out = inspection.run(compose_cfg("inspect", small))
    summary = read_json(out / "inspect.json")
    assert (out / "report.md").exists() and (out / "manifest.json").exists()
    assert summary["occupancy"]["method"] == "exact" and summary["refused"] is None
    level = summary["grid"]["median"][0]
    assert summary["occupancy"]["value"] == pytest.approx([poisson_tail(1, K * level / G)])
    report = (out / "report.md").read_text()
    assert "## The chain kind, measured" in report
    assert (
        "skipped (inspect.pilot.enabled=false)" in report
        and summary["recommendation"]["kind"] is None
    )
    # the next run, printed as one command that passes the stages' checks
    after = summary["recommendation"]["next"]
    assert f"## Next\n\n`{after['command']}`" in report and f"model.spec={spec}" in after["command"]
    assert after["command"].startswith("python3 scripts/reproduce.py") and not after["dropped"]
    assert inspection.run(compose_cfg("inspect", small)) == out  # reused
    (tmp_path / "always").mkdir()
    _, always = birth_death(tmp_path / "always", "X >= 0", reservoir=True)
    with pytest.raises(ConfigError, match=r"always true.*P\(phi = 1\) = 100\.000%"):
        inspection.run(compose_cfg("inspect", [*small, f"model.spec={always}"]))


def runaway(tmp_path: Path) -> tuple[SbmlAgentModel, Path]:
    """Autocatalysis A -> 2A at 50 s A from A = 10 (s = L, 1 in the file): e^(50 t), ~25
    events per window of 0.05 s from the file's counts, ~1e10 a second later."""
    return network_model(tmp_path, "runaway", [Species("A", amount=10)], {"k": 50.0, "s": 1.0},
                         [Reaction("grow", "k * s * A", {"A": 1}, {"A": 2})], {"s": "L"},
                         "A >= 20")  # fmt: skip


def test_a_runaway_network_is_refused_by_the_cost_probe_in_seconds(tmp_path, compose_cfg) -> None:
    """The probe (0.5 s: a tenth of inspect.max_seconds=5) stops the runaway's burn-in, and the
    refusal gives the rate it reached, the growth from the file's counts and the remedies."""
    from surrogate.stages.settings import InspectSettings

    _, spec = runaway(tmp_path)
    small = ["model=sbml", f"model.spec={spec}", "fields=[gaussian]", "inspect.max_seconds=5"]
    settings = InspectSettings.from_config(compose_cfg("inspect", small))
    settings.setup.model.internal.prepare()  # the compile is not the probe's
    start = __import__("time").perf_counter()
    with pytest.raises(ConfigError) as error:
        inspection.cost_probe(settings, InspectOptions.from_mapping(settings.options))
    assert __import__("time").perf_counter() - start < 3.0
    message = str(error.value)
    assert "ran out of the cost probe's 0.5 s" in message, message
    rate = float(message.split("fire ~")[1].split(" events")[0].replace(",", ""))
    assert rate > 1000, message  # the file's counts say 25
    assert "x the 25 estimated from the file's counts" in message
    assert "Fastest-growing: A = " in message and "from 10." in message
    for remedy in ("units", "model.burn_in", "inspect.max_seconds", "device=cuda"):
        assert remedy in message


def test_a_network_that_stays_put_passes_the_cost_probe(tmp_path, compose_cfg) -> None:
    """The open birth-death process (not enumerable: burned in from X = 0) passes with its
    rate measured: k s + g X <= ~0.1 + 0.05 X events per window of 0.05 s."""
    from surrogate.stages.settings import InspectSettings

    _, spec = birth_death(tmp_path, "X >= 2", reservoir=False)
    settings = InspectSettings.from_config(compose_cfg("inspect", ["model=sbml",
                                                                   f"model.spec={spec}"]))  # fmt: skip
    probe = inspection.cost_probe(settings, InspectOptions.from_mapping(settings.options))
    assert probe is not None and probe["completed"] and probe["reached_s"] == pytest.approx(1.0)
    assert probe["events_per_window_file"] == pytest.approx(K * DT)
    assert 0 < probe["events_per_window_end"] < 2.0
    # out of budget at once (a loaded machine): steady, so not refused
    tight = InspectSettings.from_config(compose_cfg("inspect", ["model=sbml", f"model.spec={spec}",
                                                                "inspect.max_seconds=1e-3"]))  # fmt: skip
    probe = inspection.cost_probe(tight, InspectOptions.from_mapping(tight.options))
    assert probe is not None and not probe["completed"] and probe["growth"] < 10


def test_collect_stops_early_when_one_lump_is_almost_never_seen(tmp_path) -> None:
    """A gene ON 1e-4 of the time: collect stops at 5 % of collect.max_time with the occupancy
    measured and the advice to change the lump or inspect it, not to raise max_time."""
    model = telegraph(tmp_path, 1e-4, 1.0)
    field = ConstantField(1.0)
    torch.manual_seed(0)
    sim = Simulator(model, FullDecision(model.internal), field, DT)
    perturbation = model.body.perturbation(field, model.perturbation_options)
    with pytest.raises(ConfigError) as error:
        collect_transitions(sim, perturbation, n_cells=20, n_per_state=5000, perturb_rate=0.1,
                            options=CollectOptions(equilibration_time=1.0, max_time=400.0),
                            progress=False)  # fmt: skip
    message = str(error.value)
    assert message.startswith("collect stopped early") and "inspect_model.py" in message
    assert "phi = on in 0.000% of the" in message and "recorded in 20 s" in message
    assert "change the lump" in message.lower() and "raise collect.max_time" not in message


def _short_collection(tmp_path: Path, n_per_state: int) -> str:
    """The message of a collection of a lump ON 30 % of the time (20 cells, max_time 20 s)
    that cannot reach ``n_per_state`` rows per origin."""
    model = telegraph(tmp_path, 0.43, 1.0)
    field = ConstantField(1.0)
    torch.manual_seed(0)
    sim = Simulator(model, FullDecision(model.internal), field, DT)
    perturbation = model.body.perturbation(field, model.perturbation_options)
    with pytest.raises(ConfigError) as error:
        collect_transitions(sim, perturbation, n_cells=20, n_per_state=n_per_state,
                            perturb_rate=0.1,
                            options=CollectOptions(equilibration_time=1.0, max_time=20.0),
                            progress=False)  # fmt: skip
    return str(error.value)


def test_collect_at_max_time_says_what_time_or_cells_would_do(tmp_path) -> None:
    """A lump ON 30 % of the time with too little time: the message gives the measured
    occupancy and the max_time at which the rows would be reached (~5000 / 120 per s + 1 s)."""
    message = _short_collection(tmp_path, 5000)
    assert message.startswith("collect reached collect.max_time=20 s")
    needed = float(message.split("collect.max_time ~ ")[1].split(" s")[0])
    assert 30 < needed < 60, message


def test_collect_stops_early_when_its_rate_falls_far_short_of_max_time(tmp_path) -> None:
    """The same lump with 2.4x the rows wanted (~130 s of recording where max_time gives 20 s:
    its rarer origin projected to ~1/7 of them, between 1/4 and the almost-never 1/10):
    collect stops at 5 % of max_time, not at its end, and says what time or cells would do,
    not to change the lump (a common lump, only a slow rate)."""
    message = _short_collection(tmp_path, 12000)
    assert message.startswith("collect stopped early") and "recorded in 1 s" in message
    needed = float(message.split("collect.max_time ~ ")[1].split(" s")[0])
    assert 60 < needed < 250, message
    assert "collect.n_cells ~ " in message and "change the lump" not in message.lower()


def test_bad_inspect_settings_are_refused_by_name_and_the_command_reproduces(compose_cfg) -> None:
    """An unknown inspect key, quantiles out of order, a share outside (0, 1) are refused naming
    the setting; the command the report prints composes to the same identity."""
    from hydra import compose, initialize_config_dir

    from surrogate.config import CONF_DIR
    from surrogate.stages.settings import InspectSettings

    for override, message in (("+inspect.cells=3", r"unknown inspect setting\(s\) \['cells'\]"),
                              ("inspect.quantiles=[0.9,0.1]", "inspect.quantiles must be"),
                              ("inspect.min_occupancy=1.5", "inspect.min_occupancy must be a share"),
                              ("inspect.pilot.enabled=2", "inspect.pilot.enabled must be true or false"),
                              ("inspect.pilot.n_per_state=0", "inspect.pilot.n_per_state must be a positive"),
                              ("inspect.pilot.n_per_state=1.5", "inspect.pilot.n_per_state must be a positive integer"),
                              ("inspect.pilot.n_cells=1", "inspect.pilot.n_cells=1 held-out cell"),
                              ("inspect.pilot.t_end=-1", "inspect.pilot.t_end must be a positive"),
                              ("+inspect.pilot.cells=3", r"unknown inspect.pilot setting\(s\) \['cells'\]"),
                              ("inspect.pilot=3", "inspect.pilot must be a group")):  # fmt: skip
        with pytest.raises(ConfigError, match=message):
            InspectSettings.from_config(compose_cfg("inspect", [override]))
    given = ["fields=[gaussian]", "t_end=40", "inspect.n_cells=30", "collect.n_per_state=500",
             "gp=clock", "seed=2", "inspect.pilot.n_cells=30", "inspect.pilot.enabled=false"]  # fmt: skip
    settings = InspectSettings.from_config(compose_cfg("inspect", given))
    words = settings.command().split()[2:]
    data = f"data_dir={settings.job.data_dir}"
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        again = InspectSettings.from_config(compose(config_name="inspect",
                                                    overrides=[data, *words]))  # fmt: skip
    assert again.identity() == settings.identity(), settings.command()

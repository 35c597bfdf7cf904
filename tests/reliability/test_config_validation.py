"""Bad settings are refused up front, by name, before any stage starts its work."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from hydra.errors import ConfigCompositionException, MissingConfigException

from surrogate.config import CONF_DIR
from surrogate.errors import ConfigError
from surrogate.stages import collect, fidelity, reproduce, train
from surrogate.stages import evaluate as evaluate_stage
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.settings.train import TrainSettings
from surrogate.stages.train import load_transitions

from .conftest import compose_in

REPO = CONF_DIR.parent

VALIDATORS: dict[str, Callable] = {
    "collect": collect.validate,
    "train": train.validate,
    "simulate": simulate_stage.validate,
    "evaluate": evaluate_stage.validate,
    "reproduce": reproduce.validate,
    "fidelity": fidelity.validate,
}

# (stage, overrides, text the message must contain: the setting's name and what is allowed)
BAD_INPUTS = [
    # time stepping
    ("simulate", ["dt=0"], "dt must be a positive number"),
    ("collect", ["dt=-0.05"], "dt must be a positive number"),
    ("simulate", ["dt=20.0", "record_interval=20.0", "t_end=40.0"], "model.tau"),
    ("simulate", ["t_end=0"], "t_end must be a positive number"),
    ("simulate", ["backend=numpy"], "backend must be one of ['auto', 'torch', 'numba']"),
    ("reproduce", ["backend=gpu"], "backend must be one of ['auto', 'torch', 'numba']"),
    ("simulate", ["t_end=-5.0"], "t_end must be a positive number"),
    ("simulate", ["t_end=2.01"], "t_end=2.01 s must be a positive multiple of dt"),
    ("simulate", ["n_cells=0"], "n_cells must be a positive number"),
    ("simulate", ["n_cells=2.5"], "n_cells must be a positive integer"),
    ("simulate", ["record_interval=0"], "record_interval must be a positive number"),
    ("simulate", ["dt=0.5", "record_interval=0.25"], "larger than record_interval"),
    ("simulate", ["equilibration_time=-1.0"], "equilibration_time must be a non-negative"),
    ("simulate", ["start=[1.0]"], "start must be two coordinates"),
    ("simulate", ["seed=-1"], "seed must be a non-negative integer"),
    # device and names
    ("simulate", ["device=tpu"], "device='tpu'"),
    (
        "simulate",
        ["decision.name=foo"],
        "decision.name must be one of ['full', 'abstract', 'exact']",
    ),
    ("simulate", ["decision=exact", "decision.mode=foo"], "decision.mode must be one of"),
    ("simulate", ["decision=abstract", "decision.mode=foo"], "decision.mode must be one of"),
    ("simulate", ["decision=abstract", "decision.train_field=foo"], "unknown field 'foo'"),
    ("simulate", ["decision=abstract", "decision.lookup_size=[1]"], "decision.lookup_size"),
    ("simulate", ["decision=abstract", "decision.lookup_size=[8,8]"], "decision.lookup_size"),
    ("simulate", ["decision=abstract", "decision.initial=burned"], "decision.initial must be one"),
    (
        "simulate",
        ["decision=abstract", "decision.initial=stationary", "gp=svgp"],
        "decision.initial=stationary starts a K-lumps chain",
    ),
    (
        "fidelity",
        ["fidelity.initial=stationary", "gp=svgp"],
        "fidelity.initial=stationary starts a K-lumps",
    ),
    ("simulate", ["decision=abstract", "gp.inputs=[m,L,F,cheyp]"], "at most 3 inputs"),
    ("simulate", ["decision=abstract", "gp.kernel=foo"], "gp.kernel: unknown kernel 'foo'"),
    ("train", ["gp.kernel=foo"], "gp.kernel: unknown kernel 'foo'; allowed values"),
    ("train", ["+gp.foo=1"], "unknown gp setting(s) ['foo']"),
    ("simulate", ["model.motor_sampler=foo"], "model.motor_sampler must be one of"),
    ("simulate", ["model.tumble_mode=foo"], "model.tumble_mode must be one of"),
    ("simulate", ["+model.foo=1"], "unknown model setting(s) ['foo']"),
    ("simulate", ["model._target_=builtins.dict"], "did not return a surrogate.models.Model"),
    ("simulate", ["~model._target_"], "model config needs a `_target_`"),
    ("collect", ["model.perturbation.radius=-1.0"], "radius must be a finite number > 0"),
    ("collect", ["model.perturbation.sampling=foo"], "model.perturbation.sampling must be one of"),
    ("collect", ["+model.perturbation.foo=1"], "unknown model.perturbation setting(s) ['foo']"),
    ("simulate", ["field._target_=surrogate.fields.Nope"], "surrogate.fields.Nope"),
    ("simulate", ["field.amplitude=-1.0"], "field.amplitude must be a positive number"),
    ("reproduce", ["fields=[gaussian,foo]"], "unknown field 'foo'"),
    # model constants: probabilities, rates, counts
    ("simulate", ["model.n_motors=0"], "model.n_motors must be a positive number"),
    ("simulate", ["model.n_motors=2.5"], "model.n_motors must be an integer"),
    ("simulate", ["model.yp_adapted=0.0"], "model.yp_adapted must lie in (0, model.alpha"),
    ("simulate", ["model.yp_adapted=6.0"], "model.yp_adapted must lie in (0, model.alpha"),
    ("simulate", ["model.cv=0.0"], "model.cv must be a positive number"),
    ("simulate", ["model.mu=-1.0"], "model.mu must be a positive number"),
    ("simulate", ["model.mu=true"], "model.mu must be a finite number"),
    ("simulate", ["model.g0=nan"], "model.g0 must be a finite number"),
    ("simulate", ["model.m_min=9.0"], "model.m_min"),
    # GP settings
    ("train", ["gp.validation_fraction=0.0"], "gp.validation_fraction must lie in (0, 1)"),
    ("train", ["gp.validation_fraction=1.0"], "gp.validation_fraction must lie in"),
    ("train", ["gp.validation_fraction=1.5"], "gp.validation_fraction must lie in"),
    ("train", ["gp.lr=0.0"], "gp.lr must be > 0"),
    ("train", ["gp.epochs=0"], "gp.epochs must be >= 1"),
    ("train", ["gp.n_inducing=500"], "gp.n_inducing=500 exceeds the 160 training points"),
    ("train", ["gp.grid_size=[1]"], "gp.grid_size must be 1 integers >= 2"),
    ("train", ["gp.grid_size=[5,5]"], "gp.grid_size must be 1 integers >= 2"),
    ("train", ["gp.grid_size=1"], "gp.grid_size must be 1 integers >= 2"),
    ("train", ["gp.inputs=[foo]"], "gp.inputs: ['foo']"),
    ("train", ["gp.diagnostic.n_cells=0"], "gp.diagnostic.n_cells must be a positive"),
    ("train", ["+gp.diagnostic.foo=1"], "unknown gp.diagnostic setting(s) ['foo']"),
    ("train", ["gp.threads=0"], "gp.threads must be a positive integer or null"),
    ("train", ["gp.labels=soft"], "gp.labels must be one of ['auto', 'outcome', 'expected']"),
    (
        "train",
        ["gp.labels=expected", "collect.expected_labels=false"],
        "gp.labels=expected trains on expected labels, but collect.expected_labels=false",
    ),
    ("train", ["gp.labels=expected", "gp.bins=0"], "gp.labels=expected trains on the expected"),
    (
        "train",
        ["gp.bins=0"],  # gp.labels=auto (the default): the collection records expected labels
        "gp.labels=auto picks, where the table has them, the expected labels (fractions), which "
        "need binned training, but gp.bins=0",
    ),
    ("collect", ["collect.expected_labels=maybe"], "collect.expected_labels must be true or false"),
    (
        "train",
        ["transitions=/nonexistent.parquet"],
        "transitions=/nonexistent.parquet: no such file",
    ),
    # collect settings
    ("collect", ["collect.perturb_rate=-0.1"], "collect.perturb_rate must be a non-negative"),
    ("collect", ["collect.perturb_rate=30.0"], "collect.perturb_rate=30/s cannot be met"),
    ("collect", ["collect.n_per_state=0"], "collect.n_per_state must be a positive"),
    ("collect", ["collect.record_every=0"], "collect.record_every must be a positive"),
    ("collect", ["collect.probe_seconds=-1"], "collect.probe_seconds must be a non-negative"),
    # evaluate / reproduce
    ("evaluate", ["evaluate.noise_seed_offset=0"], "evaluate.noise_seed_offset"),
    ("evaluate", ["evaluate.times=[5.0]"], "evaluate.times [5.0] lie outside"),
    ("evaluate", ["evaluate.subsample=0"], "evaluate.subsample must be a positive"),
    ("evaluate", ["evaluate.figures=maybe"], "evaluate.figures must be true or false"),
    ("evaluate", ["evaluate.full_seed=-1"], "evaluate.full_seed must be a non-negative"),
    ("evaluate", ["evaluate.band_factor=0"], "evaluate.band_factor"),
    ("evaluate", ["decision.mode=foo"], "decision.mode must be one of"),
    ("evaluate", ["decision.name=full"], "use decision=abstract"),
    ("reproduce", ["n_cells=0"], "n_cells must be a positive number"),
    ("reproduce", ["decision.lookup_size=[0,4]"], "decision.lookup_size"),
    ("reproduce", ["background=false"], "background was removed: reproduce's second process"),
    ("reproduce", ["background=auto"], "background was removed"),
    ("reproduce", ["batch=1"], "batch must be true or false"),
    ("simulate", ["n_cells=2000000000000"], "split the population into shards"),
    # fidelity: every setting read after training and simulation is refused before either
    ("fidelity", ["fidelity.ks_max=abc"], "fidelity.ks_max must be a positive number"),
    ("fidelity", ["fidelity.ks_factor=0"], "fidelity.ks_factor must be a positive number"),
    ("fidelity", ["fidelity.sim_seed=x"], "fidelity.sim_seed must be a non-negative integer"),
    ("fidelity", ["fidelity.sim_seed=-1"], "fidelity.sim_seed must be a non-negative integer"),
    (
        "fidelity",
        ["fidelity.duration_tolerance=-1"],
        "fidelity.duration_tolerance must be a positive number",
    ),
    ("fidelity", ["fidelity.noise_seed_offset=0"], "fidelity.noise_seed_offset must be a non-zero"),
    (
        "fidelity",
        ["fidelity.sim_seed=10", "fidelity.noise_seed_offset=-4"],
        "fidelity.noise_seed_offset must be a non-zero integer with sim_seed + k x offset",
    ),
    ("fidelity", ["fidelity.train_seeds=[0,0]"], "fidelity.train_seeds lists a seed twice"),
    (
        "fidelity",
        ["fidelity.noise_seed_offset=-1000", "fidelity.train_seeds=[3000]"],
        "seed 3000 would draw its chains on gaussian from seed 5000, the seed of the full model",
    ),
    ("fidelity", ["fidelity.times=[a]"], "fidelity.times must be a list of times"),
    ("fidelity", ["fidelity.times=[5.0]"], "fidelity.times 5 outside (0, t_end=2]"),
    ("fidelity", ["fidelity.alpha=abc"], "fidelity.alpha must be one of [0.001, 0.01, 0.05]"),
    ("fidelity", ["fidelity.mode=foo"], "fidelity.mode must be one of ['lookup', 'classifier']"),
    ("fidelity", ["fidelity.lookup_size=[1]"], "fidelity.lookup_size"),
    ("fidelity", ["fidelity.exact_psi=maybe"], "fidelity.exact_psi must be true or false"),
    ("fidelity", ["fidelity.n_cells=null"], "fidelity.n_cells is required"),
    ("fidelity", ["fidelity.start=[1.0]"], "fidelity.start must be two coordinates"),
    (
        "fidelity",
        ["fidelity.equilibration_time=-1.0"],
        "fidelity.equilibration_time must be a non-negative",
    ),
    (
        "simulate",
        ["model=ecoli_phospho", "model.burn_in=-1.0"],
        "model.burn_in must be a finite number of seconds >= 0",
    ),
]


@pytest.mark.parametrize(
    ("stage", "overrides", "message"),
    BAD_INPUTS,
    ids=[f"{s}:{' '.join(o)}" for s, o, _ in BAD_INPUTS],
)
def test_bad_setting_is_refused_by_name(
    tmp_path: Path, stage: str, overrides: list[str], message: str
) -> None:
    cfg = compose_in(tmp_path / "data", stage, overrides)
    with pytest.raises(ConfigError) as info:
        VALIDATORS[stage](cfg)
    assert message in str(info.value)
    assert not (tmp_path / "data").exists()  # validation writes nothing


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
@pytest.mark.parametrize("stage", ["collect", "train", "simulate"])
def test_cuda_without_cuda_is_refused(tmp_path: Path, stage: str) -> None:
    cfg = compose_in(tmp_path / "data", stage, ["device=cuda"])
    with pytest.raises(ConfigError, match=r"device='cuda'.*CUDA is not available.*device=cpu"):
        VALIDATORS[stage](cfg)


@pytest.mark.parametrize("group", ["field", "model", "decision", "gp", "collect"])
def test_unknown_config_group_option_is_hydras_error(tmp_path: Path, group: str) -> None:
    """``field=foo`` etc. fail in Hydra's composition, listing the available options."""
    with pytest.raises(MissingConfigException) as info:
        compose_in(tmp_path / "data", "simulate", [f"{group}=foo"])
    text = str(info.value)
    assert f"Could not find '{group}/foo'" in text
    assert f"Available options in '{group}'" in text


def test_unknown_key_without_plus_is_hydras_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigCompositionException, match="Could not override 'model.foo'"):
        compose_in(tmp_path / "data", "simulate", ["model.foo=1"])


# ---------------------------------------------------------------------------------------------
# validation happens before any expensive work


def _forbid(monkeypatch: pytest.MonkeyPatch, target: str) -> None:
    def expensive(*args, **kwargs):
        raise AssertionError(f"{target} ran before the config was validated")

    monkeypatch.setattr(target, expensive)


def test_collect_validates_before_simulating(tiny, monkeypatch) -> None:
    _forbid(monkeypatch, "surrogate.stages.collect.collect_transitions")
    _forbid(monkeypatch, "surrogate.stages.collect.Simulator")
    with pytest.raises(ConfigError, match="collect.perturb_rate"):
        collect.run(tiny("collect", ["collect.perturb_rate=-1.0"]))


def test_train_validates_before_loading_data(tiny, monkeypatch) -> None:
    _forbid(monkeypatch, "surrogate.stages.train.load_transitions")
    _forbid(monkeypatch, "surrogate.stages.train.fit_psi")
    # no collected data either: the bad setting is named, not the missing artefact
    with pytest.raises(ConfigError, match="gp.kernel"):
        train.run(tiny("train", ["gp.kernel=foo"]))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["fidelity.ks_max=abc"], "fidelity.ks_max"),
        (["fidelity.noise_seed_offset=0"], "fidelity.noise_seed_offset"),
    ],
)
def test_fidelity_validates_before_training(tiny, monkeypatch, overrides, message) -> None:
    """Settings the fidelity stage reads only after training and simulating are refused
    before either starts."""
    _forbid(monkeypatch, "surrogate.stages.fidelity.collect")
    _forbid(monkeypatch, "surrogate.stages.fidelity.train")
    with pytest.raises(ConfigError, match=message):
        fidelity.run(tiny("fidelity", overrides))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["decision.train_field=foo"], "unknown field 'foo'"),
        (["gp.validation_fraction=0.0"], "gp.validation_fraction"),
        (["collect.perturb_rate=-1.0"], "collect.perturb_rate"),
    ],
)
def test_simulate_validates_the_abstraction_settings_before_lookups(
    tiny, monkeypatch, overrides: list[str], message: str
) -> None:
    _forbid(monkeypatch, "surrogate.stages.train.resolve_abstraction")
    _forbid(monkeypatch, "surrogate.stages.train.load_abstraction")
    _forbid(monkeypatch, "surrogate.stages.simulate.build_decision")
    _forbid(monkeypatch, "surrogate.stages.simulate.simulate_population")
    with pytest.raises(ConfigError, match=message):
        simulate_stage.run(tiny("simulate", ["decision=abstract", *overrides]))


def test_evaluate_validates_before_simulating(tiny, monkeypatch) -> None:
    _forbid(monkeypatch, "surrogate.stages.evaluate.ensure_run")
    _forbid(monkeypatch, "surrogate.stages.simulate.run")
    with pytest.raises(ConfigError, match="evaluate.noise_seed_offset"):
        evaluate_stage.run(tiny("evaluate", ["evaluate.noise_seed_offset=0"]))


def test_train_refuses_minibatch_expected_labels_before_collecting(tiny, monkeypatch) -> None:
    """gp.bins=0 with gp.labels=auto (default) and a collection that records expected labels
    is refused when the settings are read, not after the collection; with gp.labels=outcome
    the same collection trains by minibatch."""
    _forbid(monkeypatch, "surrogate.stages.collect.collect_transitions")
    _forbid(monkeypatch, "surrogate.stages.train.load_transitions")
    with pytest.raises(ConfigError, match=r"gp\.labels=auto .* gp\.bins=0"):
        train.run(tiny("train", ["gp.bins=0"]))
    # minibatch needs Adam: the default K lumps fit by Newton, which bins (its own error)
    with pytest.raises(ConfigError, match=r"gp\.optimizer=newton .* or set gp\.optimizer=adam"):
        TrainSettings.from_config(tiny("train", ["gp.bins=0", "gp.labels=outcome"]))
    TrainSettings.from_config(
        tiny("train", ["gp.bins=0", "gp.labels=outcome", "gp.optimizer=adam"])
    )


def test_an_external_table_with_expected_labels_and_minibatch_is_refused(tmp_path) -> None:
    """An external table's columns are known only when it is read: its expected labels picked
    by gp.labels=auto with gp.bins=0 are refused there, naming the table and both settings."""
    import pandas as pd

    path = tmp_path / "table.csv"
    pd.DataFrame({"dG": [0.1, 0.2], "phi": [0.0, 1.0], "phi_next": [0.0, 1.0],
                  "phi_next_expected": [0.2, 0.9]}).to_csv(path, index=False)  # fmt: skip
    settings = TrainSettings.from_config(
        compose_in(
            tmp_path / "data", "train", ["gp.bins=0", "gp.optimizer=adam", f"+transitions={path}"]
        )
    )
    with pytest.raises(ConfigError, match=rf"{path} has expected labels: gp\.labels=auto .* "
                                          r"gp\.bins=0 \(minibatch"):  # fmt: skip
        load_transitions(settings)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["n_cells=0"], "n_cells"),
        (["decision.mode=foo"], "decision.mode"),
        (["evaluate.times=[1000.0]"], "evaluate.times"),
    ],
)
def test_reproduce_validates_every_stage_before_collecting(
    tiny, monkeypatch, overrides: list[str], message: str
) -> None:
    _forbid(monkeypatch, "surrogate.stages.reproduce.collect")
    _forbid(monkeypatch, "surrogate.stages.reproduce.train")
    _forbid(monkeypatch, "surrogate.stages.evaluate.evaluate")
    with pytest.raises(ConfigError, match=message):
        reproduce.run(tiny("reproduce", overrides))


def test_script_reports_a_bad_setting_in_one_line(tmp_path: Path) -> None:
    """The command line: ``error: <message>`` naming the setting, exit status 2, no traceback."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [
            sys.executable,
            "scripts/simulate.py",
            f"data_dir={tmp_path / 'data'}",
            "dt=0",
            "threads=1",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert "error: dt must be a positive number, got 0" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "data" / "simulate").exists()

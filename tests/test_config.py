"""Every config group composes and instantiates; settings are built once and their commands
reproduce them."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from surrogate.config import CONF_DIR, build_field, build_model, group_config, group_options
from surrogate.errors import ConfigError
from surrogate.fields import Field
from surrogate.io import MANIFEST
from surrogate.models.base import Model
from surrogate.models.ecoli import EcoliModel
from surrogate.stages.settings import (
    CollectSettings,
    ModelSetup,
    SimulateSettings,
    TrainSettings,
)

PRIMARY = ["collect", "train", "simulate"]
FIELDS = sorted(p.stem for p in (CONF_DIR / "field").glob("*.yaml"))
DECISIONS = sorted(p.stem for p in (CONF_DIR / "decision").glob("*.yaml"))
GPS = sorted(p.stem for p in (CONF_DIR / "gp").glob("*.yaml"))
EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))


def test_the_groups_exist() -> None:
    assert {"gaussian", "linear", "dynamic", "zero"} <= set(FIELDS)
    assert {"full", "abstract", "exact"} <= set(DECISIONS)
    assert "paper" in EXPERIMENTS


@pytest.mark.parametrize("name", PRIMARY)
def test_primary_configs_compose_and_validate(compose_cfg, name: str) -> None:
    cfg = compose_cfg(name)
    setup = ModelSetup.from_config(cfg)
    assert isinstance(setup.model, EcoliModel) and isinstance(setup.model, Model)


@pytest.mark.parametrize("field", FIELDS)
def test_every_field_instantiates(compose_cfg, field: str) -> None:
    cfg = compose_cfg("simulate", [f"field={field}"])
    assert isinstance(build_field(cfg.field), Field)


@pytest.mark.parametrize("decision", DECISIONS)
def test_every_decision_composes_and_validates(compose_cfg, decision: str) -> None:
    cfg = compose_cfg("simulate", [f"decision={decision}"])
    assert cfg.decision.name == decision
    assert SimulateSettings.from_config(cfg).decision.name == decision


@pytest.mark.parametrize("gp", GPS)
def test_every_gp_config_builds_settings(compose_cfg, gp: str) -> None:
    cfg = compose_cfg("train", [f"gp={gp}"])
    settings = TrainSettings.from_config(cfg)
    # gp=auto takes gp=classes's recipe for E. coli (it declares classes)
    expected = group_config("gp", "classes") if gp == "auto" else cfg.gp
    assert settings.gp.n_inducing == expected["n_inducing"]
    # the model's signal by default, and the switch clock with gp.history=age
    assert settings.inputs == (("dG", "phi_age") if cfg.gp.history == "age" else ("dG",))


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes(compose_cfg, experiment: str) -> None:
    cfg = compose_cfg("simulate", [f"experiment={experiment}"])
    SimulateSettings.from_config(cfg)


def test_overrides_reach_the_model(compose_cfg) -> None:
    cfg = compose_cfg("simulate", ["model.n_motors=10", "model.tau=20", "dt=0.02"])
    model = build_model(cfg.model)
    assert (model.params.n_motors, model.params.tau, cfg.dt) == (10, 20.0, 0.02)


def test_the_model_is_selected_by_target(compose_cfg) -> None:
    cfg = compose_cfg("simulate", ["model._target_=builtins.dict"])
    with pytest.raises(ConfigError, match="did not return a surrogate.models.Model"):
        build_model(cfg.model)


def test_inputs_choice(compose_cfg) -> None:
    assert TrainSettings.from_config(compose_cfg("train", ["gp.inputs=inputs"])).inputs == (
        "m",
        "L",
    )
    both = TrainSettings.from_config(compose_cfg("train", ["gp.inputs=[F,L]"])).inputs
    assert both == ("F", "L")
    with pytest.raises(ConfigError, match="gp.inputs.*provides inputs"):
        TrainSettings.from_config(compose_cfg("train", ["gp.inputs=[foo]"]))


@pytest.mark.parametrize("name", group_options("model"))
def test_group_config_is_the_composed_model(compose_cfg, name: str) -> None:
    """``group_config`` (the base of a command's overrides) applies a model config's defaults
    list as Hydra does: e.g. ecoli_phospho is the shared cell constants plus its own keys."""
    composed = OmegaConf.to_container(compose_cfg("simulate", [f"model={name}"]).model)
    assert group_config("model", name) == composed


def test_the_phospho_commands_reproduce_the_settings(compose_cfg, tmp_path) -> None:
    """A model whose config composes a shared base: its commands name only what differs."""
    cfg = compose_cfg("collect", ["model=ecoli_phospho", "model.tau=20", "model.cheZ=4.0"])
    settings = CollectSettings.from_config(cfg)
    again = CollectSettings.from_config(
        _compose_command(settings.command(), str(tmp_path / "data"))
    )
    assert again.identity() == settings.identity(), settings.command()


def test_a_collection_already_made_is_not_refused_for_memory(compose_cfg, monkeypatch) -> None:
    """The table's memory is checked where it would be collected: with too little free, a
    new collection is refused naming collect.n_per_state, one already made (its manifest
    written) is read and not refused."""
    from surrogate.stages.settings import common

    monkeypatch.setattr(common, "free_memory_bytes", lambda: 2**20)  # 1 MiB free
    cfg = compose_cfg("collect", [])
    with pytest.raises(ConfigError, match="collect.n_per_state=.*GiB"):
        CollectSettings.from_config(cfg)
    monkeypatch.setattr(common, "free_memory_bytes", lambda: None)  # unreadable: not checked
    settings = CollectSettings.from_config(cfg)
    settings.directory.mkdir(parents=True)
    (settings.directory / MANIFEST).write_text("{}")
    monkeypatch.setattr(common, "free_memory_bytes", lambda: 2**20)
    assert CollectSettings.from_config(cfg).directory == settings.directory


def _compose_command(command: str, data_dir: str):
    """Compose the config a printed command would run (script name -> primary config)."""
    words = shlex.split(command)
    script = words[1].rsplit("/", 1)[-1].removesuffix(".py")
    overrides = [w for w in words[2:] if w != "-m"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name=script, overrides=[f"data_dir={data_dir}", *overrides])


@pytest.mark.parametrize(
    "overrides",
    [
        [],
        ["field=linear", "dt=0.02", "seed=3", "collect.n_per_state=500", "model.n_motors=6"],
        ["model.perturbation.radius=3.0", "collect.record_every=5", "field.amplitude=0.2"],
    ],
)
def test_commands_reproduce_the_settings(compose_cfg, tmp_path, overrides: list[str]) -> None:
    """The command a missing artefact names makes exactly that artefact (same identity)."""
    cfg = compose_cfg("simulate", ["decision=abstract", "gp.n_inducing=50", *overrides])
    sim = SimulateSettings.from_config(cfg)
    train = sim.decision.train
    assert train is not None and isinstance(train.source, CollectSettings)
    for settings, cls in (
        (train.source, CollectSettings),
        (train, TrainSettings),
        (sim, SimulateSettings),
    ):
        again = cls.from_config(_compose_command(settings.command(), str(tmp_path / "data")))
        assert again.identity() == settings.identity(), settings.command()
        assert again.directory == settings.directory


def test_compile_is_part_of_a_runs_identity(compose_cfg) -> None:
    """A compiled and an eager run with one seed differ (kernels round differently), so they
    must not share a directory."""
    eager = SimulateSettings.from_config(compose_cfg("simulate"))
    compiled = SimulateSettings.from_config(compose_cfg("simulate", ["compile=true"]))
    assert eager.identity()["compile"] is False and compiled.identity()["compile"] is True
    assert eager.directory != compiled.directory
    assert "compile=true" in compiled.command()


def test_evaluation_times_follow_t_end_unless_set(compose_cfg) -> None:
    from surrogate.stages.settings import EvaluateSettings, ReproduceSettings

    cfg = compose_cfg("reproduce", ["t_end=30.0"])
    settings = ReproduceSettings.from_config(cfg)  # was: times beyond t_end refused
    assert settings.evaluations["gaussian"].times == (7.5, 15.0, 22.5, 30.0)
    paper = EvaluateSettings.from_config(compose_cfg("evaluate", ["experiment=paper"]))
    assert paper.times == (125.0, 250.0, 375.0, 500.0)


def test_the_clock_recipe_bins_its_axes_and_leaves_two_state_fits_as_they_were(
    compose_cfg,
) -> None:
    """gp=clock: psi over (dG, phi_age) on 200 x 20 bins; the clock's keys enter a fit's
    identity only when it has a clock (two-state fits keep their artefact directories)."""
    clock = TrainSettings.from_config(compose_cfg("train", ["gp=clock"]))
    assert clock.inputs == ("dG", "phi_age") and clock.gp.bins == (200, 20)
    assert clock.fit_identity()["gp"]["history"] == "age"
    plain = TrainSettings.from_config(compose_cfg("train"))
    assert not {"history", "max_age", "clock_bins"} & set(plain.fit_identity()["gp"])
    with pytest.raises(ConfigError, match="gp.history"):
        TrainSettings.from_config(compose_cfg("train", ["gp.history=clock"]))


@pytest.mark.parametrize("knee", ["0", "-1.0", "fast", "true", "inf"])
def test_a_clock_knee_that_is_no_positive_number_is_refused(compose_cfg, knee: str) -> None:
    with pytest.raises(ConfigError, match=r"gp.clock_knee must be a number of seconds > 0"):
        TrainSettings.from_config(compose_cfg("train", ["gp=clock", f"gp.clock_knee={knee}"]))


def test_a_clock_on_a_log_axis_is_a_fit_of_its_own(compose_cfg) -> None:
    """gp.clock_knee warps the clock psi reads (log(1 + a / knee)); null leaves the linear
    clock's identity as it was, a knee is a fit of its own, and a two-state fit ignores it."""
    linear = TrainSettings.from_config(compose_cfg("train", ["gp=clock"]))
    assert "clock_knee" not in linear.fit_identity()["gp"]
    assert linear.kind.input_warps(linear.gp_config) == {}
    log = TrainSettings.from_config(compose_cfg("train", ["gp=clock", "gp.clock_knee=0.5"]))
    assert log.fit_identity()["gp"]["clock_knee"] == 0.5
    assert log.kind.input_warps(log.gp_config) == {"phi_age": 0.5}
    assert log.fit_directory != linear.fit_directory
    plain = TrainSettings.from_config(compose_cfg("train", ["gp=svgp", "gp.clock_knee=0.5"]))
    assert plain.kind.input_warps(plain.gp_config) == {}
    assert "clock_knee" not in plain.fit_identity()["gp"]


def test_class_moves_by_relaxation_are_checked_and_keep_learned_identities(
    compose_cfg, tmp_path
) -> None:
    """gp.class_moves: learned fits keep their identity; relaxation enters it with its sample's
    settings; bad values, a two-state fit and classes that are not shared bins (E. coli's
    motor counts) are refused by name."""
    classes = TrainSettings.from_config(compose_cfg("train", ["gp=classes"]))
    assert classes.class_moves == "learned"
    assert not {"class_moves", "relaxation"} & set(classes.fit_identity()["gp"])
    for bad, message in (
        ("gp.class_moves=drift", "gp.class_moves must be one of"),
        ("gp.relaxation.n_cells=3", "gp.relaxation.n_cells"),
        ("gp.relaxation.lags=[100,50]", "gp.relaxation.lags"),
        ("gp.relaxation.lags=[50]", "gp.relaxation.lags"),
        ("gp.relaxation=7", "gp.relaxation must be a mapping"),
        ("+gp.relaxation.every=1", r"unknown gp.relaxation setting\(s\) \['every'\]"),
        ("gp.class_moves=relaxation", "shared by both"),  # E. coli: motor counts, not bins
    ):
        with pytest.raises(ConfigError, match=message):
            TrainSettings.from_config(compose_cfg("train", ["gp=classes", bad]))
    with pytest.raises(ConfigError, match="K-lumps option"):
        TrainSettings.from_config(compose_cfg("train", ["gp=svgp", "+gp.class_moves=relaxation"]))
    # the auto-regulatory network with declared bins shared by both lumps (its yaml's
    # classes: auto would run the chooser, a minute of simulation)
    import yaml

    example = Path(__file__).resolve().parents[1] / "examples" / "autoregulation" / "model.yaml"
    spec = yaml.safe_load(example.read_text())
    spec.update(network=str(example.parent / spec["network"]),
                classes={"expression": "P + 2 * P2", "edges": [747, 881, 1134]})  # fmt: skip
    declared = tmp_path / "ar.yaml"
    declared.write_text(yaml.safe_dump(spec))
    relax = TrainSettings.from_config(compose_cfg("train", [
        "model=sbml", f"model.spec={declared}", "gp=classes",
        "gp.class_moves=relaxation"]))  # fmt: skip
    moves = relax.fit_identity()["gp"]["class_moves"]
    assert moves["kind"] == "relaxation" and moves["cells"] == 600 and len(moves["lags"]) == 4


def test_the_classes_recipe_is_checked_and_leaves_two_state_identities_as_they_were(
    compose_cfg,
) -> None:
    """gp=classes: the K-lumps chain's key enters a fit's identity (and its directory's name)
    only when set; an unknown lumping, a clock beside classes, or a classifier-mode run of the
    chain (a table) are refused by name."""
    classes = TrainSettings.from_config(compose_cfg("train", ["gp=classes"]))
    assert classes.lumps == "classes" and classes.fit_identity()["gp"]["lumps"] == "classes"
    assert "lumps=classes" in classes.fit_directory.name
    plain = TrainSettings.from_config(compose_cfg("train", ["gp=svgp"]))
    assert plain.lumps == "phi" and "lumps" not in plain.fit_identity()["gp"]
    # the class law's own keys: resolved in its identity, absent from a two-state fit's
    gp = classes.fit_identity()["gp"]
    assert gp["min_events"] == {"outcome": 50, "expected": 1.0} and gp["max_label_weight"] == 1000.0
    assert not {"min_events", "max_label_weight"} & set(plain.fit_identity()["gp"])
    lighter = TrainSettings.from_config(
        compose_cfg("train", ["gp=classes", "gp.max_label_weight=1"])
    )
    assert lighter.max_label_weight == 1.0 and lighter.fit_directory != classes.fit_directory
    for bad in ("gp.max_label_weight=0.5", "gp.max_label_weight=inf", "gp.min_events=-1",
                "gp.min_events=many"):  # fmt: skip
        with pytest.raises(ConfigError, match=bad.split("=")[0]):
            TrainSettings.from_config(compose_cfg("train", ["gp=classes", bad]))
    with pytest.raises(ConfigError, match="gp.lumps"):
        TrainSettings.from_config(compose_cfg("train", ["gp.lumps=motors"]))
    with pytest.raises(ConfigError, match="no switch clock"):
        TrainSettings.from_config(compose_cfg("train", ["gp=classes", "gp.history=age"]))
    with pytest.raises(ConfigError, match="no classifier mode"):
        SimulateSettings.from_config(
            compose_cfg("simulate", ["decision=abstract", "gp=classes", "decision.mode=classifier"])
        )
    exact = SimulateSettings.from_config(compose_cfg("simulate", ["decision=exact"]))
    assert "lumps" not in exact.identity()["decision"]
    with pytest.raises(ConfigError, match="decision.lumps"):
        SimulateSettings.from_config(
            compose_cfg("simulate", ["decision=exact", "decision.lumps=x"])
        )


def test_group_config_is_composed_once_per_version_of_its_files(tmp_path, monkeypatch) -> None:
    """Composed once and reused (a report asks ~120 times), yet a copy each time, and a base
    file edited is read again."""
    import os

    import surrogate.config as config

    group = tmp_path / "thing"
    group.mkdir()
    (group / "base.yaml").write_text("a: 1\nb: 2\n")
    (group / "top.yaml").write_text("defaults:\n  - base\n  - _self_\nb: 3\n")
    monkeypatch.setattr(config, "CONF_DIR", tmp_path)
    first = config.group_config("thing", "top")
    assert first == {"a": 1, "b": 3}
    first["a"] = 99  # the caller's copy
    assert config.group_config("thing", "top") == {"a": 1, "b": 3}
    (group / "base.yaml").write_text("a: 5\nb: 2\n")
    stat = (group / "base.yaml").stat()
    os.utime(group / "base.yaml", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert config.group_config("thing", "top") == {"a": 5, "b": 3}


def test_keep_switches_is_checked_and_leaves_the_default_identity_alone(compose_cfg) -> None:
    """collect.keep_switches: auto, true or false (false by default); auto is false for E.
    coli's thinned rows with expected labels, true without them, false where every window is
    recorded; false leaves a collection's identity (its directory) as before the key; true
    names another table, records no expected labels (gp.labels=expected is refused saying
    why) and is refused with minibatch training and with a sequential design, each before any
    work."""
    plain = CollectSettings.from_config(compose_cfg("collect", []))
    assert "keep_switches" not in plain.identity()["collect"] and not plain.keep_switches
    kept = CollectSettings.from_config(compose_cfg("collect", ["collect.keep_switches=true"]))
    assert kept.keep_switches and kept.directory != plain.directory
    assert kept.identity()["kept"] == "class_moves"  # E. coli declares classes: kept too
    assert "kept" not in plain.identity()
    assert plain.expected_labels and not kept.expected_labels
    no_labels = CollectSettings.from_config(compose_cfg("collect", ["collect.expected_labels=false",
                                                                    "collect.keep_switches=auto"]))  # fmt: skip
    assert not CollectSettings.from_config(
        compose_cfg("collect", ["collect.expected_labels=false"])
    ).keep_switches  # default: false
    assert no_labels.keep_switches  # auto: thinned rows without expected labels keep switches
    every = CollectSettings.from_config(compose_cfg("collect", ["collect.expected_labels=false",
                                                                "collect.record_every=1",
                                                                "collect.keep_switches=auto"]))  # fmt: skip
    assert not every.keep_switches  # every window recorded: nothing more to keep
    with pytest.raises(ConfigError, match="collect.keep_switches must be auto, true or false"):
        CollectSettings.from_config(compose_cfg("collect", ["collect.keep_switches=3"]))
    with pytest.raises(ConfigError, match="keep_switches=true records none"):
        TrainSettings.from_config(compose_cfg("train", ["collect.keep_switches=true",
                                                        "gp.labels=expected"]))  # fmt: skip
    with pytest.raises(ConfigError, match="gp.bins=0"):
        TrainSettings.from_config(compose_cfg("train", ["collect.keep_switches=true",
                                                        "gp.bins=0", "gp.labels=outcome"]))  # fmt: skip
    with pytest.raises(ConfigError, match="sequential design"):
        CollectSettings.from_config(compose_cfg("collect", ["collect.keep_switches=true",
                                                            "collect.design.target_error=0.05"]))  # fmt: skip

"""The stages chained on tiny settings: collect -> train -> simulate (full, abstract) -> evaluate."""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from omegaconf import DictConfig

from surrogate.errors import ConfigError, MissingArtefactError
from surrogate.evaluate.statistics import load_run
from surrogate.io import load_tensors
from surrogate.simulate.support import TrainingHistogram
from surrogate.stages import collect, train
from surrogate.stages import evaluate as evaluate_stage
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.settings import EvaluateSettings
from tests.conftest import composer

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

TINY = [
    "collect.n_per_state=400",
    "collect.n_cells=100",
    "gp.n_inducing=16",
    "gp.epochs=8",
    "gp.batch_size=200",
    "n_cells=40",
    "t_end=20.0",
    "equilibration_time=1.0",
    "gp.grid_size=[12]",
    "gp.diagnostic.n_cells=100",
    "gp.diagnostic.t_end=10.0",
]


def _train_overrides() -> list[str]:
    """TINY's collect and gp settings: what the train stage reads."""
    return [o for o in TINY if o.split("=")[0].split(".")[0] in ("collect", "gp")]


@pytest.fixture(scope="module")
def trained_data(tmp_path_factory) -> Path:
    """The data directory of :func:`trained`, shared by the tests that build on it."""
    return tmp_path_factory.mktemp("trained") / "data"


@pytest.fixture(scope="module")
def trained(trained_data):
    """A tiny collect + train, made once for the module: the tests below read it, or add
    artefacts of their own settings beside it (:func:`beside`), and never change it."""
    cfg = composer(trained_data)("train", _train_overrides())
    collect_dir = collect.run(cfg)
    train_dir = train.run(cfg)
    return cfg, collect_dir, train_dir


@pytest.fixture
def beside(trained, trained_data) -> Callable[..., DictConfig]:
    """Compose configs whose artefacts go beside :func:`trained`'s (which they reuse)."""
    return composer(trained_data)


def test_collect_writes_columns_counts_and_manifest(trained) -> None:
    cfg, collect_dir, _ = trained
    table = pd.read_parquet(collect_dir / "transitions.parquet")
    assert {"m", "L", "F", "cheyp", "dG", "phi", "phi_next", "cell", "t"} <= set(table.columns)
    assert (table["phi"] == 0).sum() == 400 and (table["phi"] == 1).sum() == 400
    assert set(table["phi_next"].unique()) <= {0, 1}
    assert table["phi_next_expected"].between(0, 1).all()  # E. coli gives expected labels
    assert np.isfinite(table[["m", "L", "dG"]].to_numpy()).all()
    manifest = json.loads((collect_dir / "manifest.json").read_text())
    assert manifest["counts_per_origin"] == {"tumble": 400, "run": 400}
    assert manifest["seed"] == cfg.seed and manifest["config"]["dt"] == cfg.dt
    assert sum(manifest["counts"].values()) == 800
    assert manifest["wall_time_s"] > 0 and "torch" in manifest["versions"]
    assert (collect_dir / "coverage.png").stat().st_size > 0


def test_train_writes_artefacts_and_round_trips(trained) -> None:
    cfg, collect_dir, train_dir = trained
    for name in (
        "psi.pt",
        "train_metrics.json",
        "psi_grid.csv",
        "psi_surfaces.png",
        "psi_diagnostic.png",
        "manifest.json",
    ):
        assert (train_dir / name).exists(), name
    grid = pd.read_csv(train_dir / "psi_grid.csv")
    assert list(grid.columns) == ["phi", "dG", "p"] and len(grid) == 2 * 12
    assert grid["p"].between(0, 1).all()
    load_tensors(train_dir / "psi.pt")  # loads with weights_only=True
    psi = train.load_abstraction(train_dir)
    assert psi.input_names == ("dG",) and psi.lump_names == ("tumble", "run")
    # the saved grid is reproduced exactly by the reloaded model
    p = psi(torch.tensor(grid["phi"].to_numpy()), torch.tensor(grid[["dG"]].to_numpy()))
    np.testing.assert_allclose(p.numpy(), grid["p"].to_numpy(), rtol=0, atol=1e-6)
    # the same abstraction is found from the settings of its config alone
    psi2 = train.load_abstraction(train.validate(cfg))
    with pytest.raises(TypeError, match="validate"):  # never a raw config below the edge
        train.load_abstraction(cfg)
    z = torch.tensor([[0.3], [0.9]])
    assert torch.equal(psi2(torch.tensor([1, 0]), z), psi(torch.tensor([1, 0]), z))
    metrics = json.loads((train_dir / "train_metrics.json").read_text())
    for name in ("psi_0", "psi_1"):
        v = metrics[name]["validation"]
        assert {"brier", "brier_baseline", "mean_log_predictive", "accuracy", "calibration"} <= set(
            v
        )
    d = metrics["diagnostic"]
    assert d["reference"] == "exact" and d["n_occupancy"] == 100 * 200 // 10
    # the training rows' histogram (diagnostic, outside the fit's identity) in both manifests
    manifest = json.loads((train_dir / "manifest.json").read_text())
    fit_manifest = json.loads((Path(manifest["fit"]) / "manifest.json").read_text())
    hist = TrainingHistogram.from_dict(fit_manifest["support_histogram"])
    assert manifest["support_histogram"] == fit_manifest["support_histogram"]
    table = pd.read_parquet(collect_dir / "transitions.parquet")
    assert hist == TrainingHistogram.of_rows(
        table[["dG"]].to_numpy(), table["phi"], table["phi"] != table["phi_next"], ["dG"]
    )
    assert [sum(c) for c in hist.counts] == [400, 400] and hist.bins == (64,)
    assert [hist.lo[0], hist.hi[0]] == fit_manifest["domain"]["dG"]
    assert "support_histogram" not in train.validate(cfg).fit_identity()
    for phi in ("phi0", "phi1"):
        assert 0 < d[phi]["mean_switching_reference"] < 1
        learned, reference = d[phi]["mean_switching_learned"], d[phi]["mean_switching_reference"]
        assert d[phi]["rel_bias"] == pytest.approx(learned / reference - 1, rel=1e-12)
        assert d[phi]["p90_abs_rel_error"] >= 0 and d[phi]["mean_abs_rel_error"] >= 0


def test_the_fit_runs_on_gp_threads(compose_cfg) -> None:
    """``gp.threads`` sets the fit's torch threads (its result depends on them), recorded in
    the manifest and in the abstraction's identity; the job's own count is restored after."""
    overrides = _train_overrides()
    cfg = compose_cfg("train", [*overrides, "gp.threads=2"])
    collect.run(cfg)
    before = torch.get_num_threads()
    out = train.run(cfg)
    assert torch.get_num_threads() == before
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["fit_threads"] == 2 and manifest["settings"]["fit"]["fit_threads"] == 2
    assert out != train.validate(compose_cfg("train", [*overrides, "gp.threads=1"])).directory
    assert "gp.threads=2" in train.validate(cfg).command()


def test_the_fits_identity_holds_the_resolved_thread_count(compose_cfg) -> None:
    """``gp.threads=null`` fits on the job's threads: one and two threads are two fits (psi
    moves by up to 3 % between them), not one directory a single run and a sweep share; the
    command names the count that reproduces it."""
    overrides = _train_overrides()
    before = torch.get_num_threads()
    made = {}
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            made[threads] = train.validate(compose_cfg("train", overrides))
    finally:
        torch.set_num_threads(before)
    one, two = made[1], made[2]
    assert (one.fit_threads, two.fit_threads) == (1, 2)
    assert one.fit_identity()["fit_threads"] == 1 and two.fit_identity()["fit_threads"] == 2
    assert one.fit_directory != two.fit_directory and one.directory != two.directory
    assert "gp.threads=1" in one.command() and "gp.threads=2" in two.command()


def test_the_device_type_is_part_of_every_random_streams_identity(compose_cfg) -> None:
    """CPU and CUDA draw different random streams from one seed: collections, occupancy runs,
    fits and simulations on each have their own directories."""
    import dataclasses

    from surrogate.stages.settings import SimulateSettings

    cpu = SimulateSettings.from_config(compose_cfg("simulate", [*TINY, "decision=abstract"]))
    job = dataclasses.replace(cpu.job, device=torch.device("cuda"))
    train_cpu = cpu.decision.train
    assert train_cpu is not None
    train_cuda = dataclasses.replace(train_cpu, job=job,
                                     source=dataclasses.replace(train_cpu.source, job=job))  # fmt: skip
    pairs = [
        (cpu, cpu.replace(job=job)),
        (train_cpu.source, train_cuda.source),
        (train_cpu.occupancy(), train_cuda.occupancy()),
    ]
    for a, b in pairs:
        assert a.identity()["device"] == "cpu" and b.identity()["device"] == "cuda"
        assert a.directory != b.directory
    assert train_cpu.fit_directory != train_cuda.fit_directory


def test_a_compiled_run_that_falls_back_to_eager_is_refused(compose_cfg, monkeypatch) -> None:
    """torch.compile failing mid-stage must not leave an eager run in a directory whose
    identity says compile=true: the stage stops, naming compile=false, and writes no manifest."""
    from surrogate.errors import CompileError

    def broken(fn, *args, **kwargs):
        def call(*a, **k):
            raise RuntimeError("no compiler here")

        return call

    monkeypatch.setattr(torch, "compile", broken)
    run = [o for o in TINY if not o.startswith(("collect", "gp"))]
    cfg = compose_cfg("simulate", [*run, "decision=full", "compile=true", "backend=torch"])
    settings = simulate_stage.validate(cfg)
    with pytest.raises(CompileError, match="compile=false"):
        simulate_stage.simulate(settings)
    assert not (settings.directory / "manifest.json").exists()


def test_the_diagnostic_and_the_grid_do_not_refit(trained, beside, caplog) -> None:
    """Other ``gp.diagnostic`` or ``gp.grid_size`` settings reuse the fit (same classifiers,
    same simulations) and re-run only the diagnostic and the grid, in their own directory."""
    cfg, _, train_dir = trained
    first = train.validate(cfg)
    other_cfg = beside("train", [*_train_overrides(), "gp.diagnostic.n_cells=50",
                                 "gp.grid_size=[7]"])  # fmt: skip
    other = train.validate(other_cfg)
    assert other.fit_directory == first.fit_directory and other.directory != train_dir
    assert other.fit_identity() == first.fit_identity()
    before = (first.fit_directory / "psi.pt").stat().st_mtime_ns
    with caplog.at_level(logging.INFO, logger="surrogate.io"):
        out = train.run(other_cfg)
    assert "fit exists, reusing" in caplog.text
    assert (first.fit_directory / "psi.pt").stat().st_mtime_ns == before
    assert (out / "psi.pt").read_bytes() == (first.fit_directory / "psi.pt").read_bytes()
    assert len(pd.read_csv(out / "psi_grid.csv")) == 2 * 7
    metrics = json.loads((out / "train_metrics.json").read_text())
    assert metrics["diagnostic"]["n_occupancy"] == 50 * 200 // 10
    old = json.loads((train_dir / "train_metrics.json").read_text())
    assert old["diagnostic"]["n_occupancy"] == 100 * 200 // 10  # the first one's is kept
    # a simulation of either uses the same abstraction: one run directory
    sim = [*TINY, "decision=abstract"]
    a = simulate_stage.validate(beside("simulate", sim))
    b = simulate_stage.validate(
        beside("simulate", [*sim, "gp.diagnostic.n_cells=50", "gp.grid_size=[7]"])
    )
    assert a.directory == b.directory


def test_a_reference_too_noisy_to_judge_is_made_again_larger(trained, beside, monkeypatch,
                                                              caplog) -> None:  # fmt: skip
    """A model with no exact psi is judged against the full model's binned frequencies; where
    their error on psi's bias is above the verdict's 3 % tolerance the train stage makes the
    diagnostic again with the cells the verdict would advise, up to ``gp.diagnostic.max_cells``
    (the same run ``gp.diagnostic.n_cells`` makes), instead of leaving the user a rerun. The
    verdict then reads the cells that ran."""
    from surrogate.stages.reproduce import diagnostic_cells

    monkeypatch.setattr(train, "exact_psi_function", lambda model, dt: None)
    cfg = beside("train", [*_train_overrides(), "gp.diagnostic.n_cells=20",
                           "gp.diagnostic.max_cells=60"])  # fmt: skip
    settings = train.validate(cfg)
    with caplog.at_level(logging.INFO, logger="surrogate.stages.train"):
        out = train.run(cfg)
    metrics = json.loads((out / "train_metrics.json").read_text())
    d = metrics["diagnostic"]
    assert d["reference"] == "empirical" and d["grown_from"] == 20
    assert d["settings"]["n_cells"] == 60 and d["n_occupancy"] == 60 * 200 // 10
    assert "made again at 60 cells (gp.diagnostic.max_cells=60)" in caplog.text
    assert diagnostic_cells(settings.diagnostic, d) == 60
    from surrogate.stages.reproduce import _diagnostic_text  # the report says so

    assert "(60 cells from" in _diagnostic_text(metrics, ("run", "tumble"))
    assert "grown from 20 cells, whose reference was too noisy" in _diagnostic_text(
        metrics, ("run", "tumble"))  # fmt: skip
    # the same run the setting makes: its occupancy directory, reused
    larger = train.validate(beside("train", [*_train_overrides(), "gp.diagnostic.n_cells=60"]))
    assert larger.occupancy().directory.is_dir()
    assert larger.occupancy().directory != settings.occupancy().directory
    # never: the first run's reference is the record
    caplog.clear()
    never = beside("train", [*_train_overrides(), "gp.diagnostic.n_cells=20",
                             "gp.diagnostic.max_cells=0"])  # fmt: skip
    with caplog.at_level(logging.INFO, logger="surrogate.stages.train"):
        kept = json.loads((train.run(never) / "train_metrics.json").read_text())["diagnostic"]
    assert "grown_from" not in kept and kept["settings"]["n_cells"] == 20
    assert "gp.diagnostic.max_cells=0 leaves no more cells" in caplog.text
    # nor where the larger run would take longer than the stages' warning threshold
    caplog.clear()
    monkeypatch.setattr(train, "GROW_MAX_SECONDS", 0.0)
    slow = beside("train", [*_train_overrides(), "gp.diagnostic.n_cells=20",
                            "gp.diagnostic.max_cells=40"])  # fmt: skip
    with caplog.at_level(logging.INFO, logger="surrogate.stages.train"):
        kept = json.loads((train.run(slow) / "train_metrics.json").read_text())["diagnostic"]
    assert "grown_from" not in kept
    assert "not made here (gp.diagnostic.n_cells=40 makes it)" in caplog.text
    with pytest.raises(ConfigError, match="gp.diagnostic.max_cells must be a whole number"):
        train.validate(beside("train", [*_train_overrides(), "gp.diagnostic.max_cells=2.5"]))
    with pytest.raises(ConfigError, match="gp.diagnostic.max_cells must be a non-negative"):
        train.validate(beside("train", [*_train_overrides(), "gp.diagnostic.max_cells=-1"]))


def test_train_without_collect_names_the_command(compose_cfg) -> None:
    cfg = compose_cfg("train", ["field=linear"])
    with pytest.raises(MissingArtefactError, match=r"python scripts/collect.py .*field=linear"):
        train.run(cfg)


@pytest.mark.parametrize("mode", ["lookup", "classifier"])
def test_full_vs_abstract_end_to_end(trained, beside, mode: str) -> None:
    overrides = [*TINY, "decision=abstract", f"decision.mode={mode}", "decision.lookup_size=[64]",
                 "evaluate.times=null", "evaluate.subsample=200", "evaluate.run_missing=true"]  # fmt: skip
    if (
        mode == "classifier"
    ):  # the two-state chain's GP every step (K lumps, the default, is a table)
        overrides.append("gp=svgp")
        train.run(beside("train", [*_train_overrides(), "gp=svgp"]))
    cfg = beside("evaluate", overrides)
    out = evaluate_stage.run(cfg)
    table = pd.read_csv(out / "comparison.csv")
    assert table["quantity"].tolist() == [
        "distance_t5",
        "distance_t10",
        "distance_t15",
        "distance_t20",
        "run",
        "tumble",
    ]
    assert table["ks"].between(0, 1).all() and table["ks_noise_floor"].notna().all()
    summary = json.loads((out / "summary.json").read_text())
    # runs timed apart make no speed-up (scripts/speed.py measures one side by side)
    assert summary["speedup_loop"] is None and not summary["speed_comparable"]
    assert all(v > 0 for v in summary["cell_steps_per_s"].values())
    assert set(summary["mean_durations"]) == {"full", "candidate", "full_repeat"}
    for name in (
        "distance_histograms.png",
        "distance_over_time.png",
        "durations.png",
        "comparison.md",
    ):
        assert (out / name).exists()
    # the abstract run is a complete simulation artefact in the same format as the full run
    abstract = load_run(EvaluateSettings.from_config(cfg).candidate.directory)
    assert abstract.observables["cell"].nunique() == 40
    assert abstract.manifest["decision"] == "abstract"


def test_evaluation_without_figures_writes_the_same_tables(trained, beside) -> None:
    """evaluate.figures=false (reproduce's exact-psi evaluations): the same comparison, no
    figures, in a directory of its own."""
    overrides = [*TINY, "decision=abstract", "decision.lookup_size=[64]", "evaluate.times=null",
                 "evaluate.subsample=200", "evaluate.run_missing=true"]  # fmt: skip
    with_figures = evaluate_stage.run(beside("evaluate", overrides))
    without = evaluate_stage.run(beside("evaluate", [*overrides, "evaluate.figures=false"]))
    assert without != with_figures
    assert not list(without.glob("*.png"))
    figures = {p.name for p in with_figures.glob("*.png")}
    assert figures == {"distance_histograms.png", "distance_over_time.png", "distance_drift.png",
                       "durations.png"}  # fmt: skip
    pd.testing.assert_frame_equal(
        pd.read_csv(without / "comparison.csv"), pd.read_csv(with_figures / "comparison.csv")
    )
    assert (without / "observables_over_time.csv").exists()


def test_simulate_abstract_without_training_names_the_command(compose_cfg) -> None:
    cfg = compose_cfg("simulate", ["decision=abstract", "n_cells=4", "t_end=1.0"])
    with pytest.raises(MissingArtefactError, match="python scripts/train.py"):
        simulate_stage.run(cfg)


def test_collect_records_nothing_inside_the_blackout_after_a_jump(compose_cfg) -> None:
    """Windows within collect.blackout_time of a perturbation are never recorded (their hidden
    motor state belongs to the old inputs), and with a blackout of 0 they are."""

    def table(blackout: float):
        cfg = compose_cfg("collect", ["collect.n_per_state=400", "collect.n_cells=100",
                                      "collect.perturb_rate=1.0", "collect.record_every=2",
                                      f"collect.blackout_time={blackout}"])  # fmt: skip
        return pd.read_parquet(collect.run(cfg) / "transitions.parquet")

    with_blackout = table(1.0)
    jumped = with_blackout["since_jump"] >= 0
    assert jumped.sum() > 100  # at 1 jump/s most cells have jumped
    assert (with_blackout.loc[jumped, "since_jump"] >= 20).all()  # 1 s = 20 steps
    without = table(0.0)
    assert (without["since_jump"].between(0, 19)).sum() > 50


def test_a_clock_on_a_log_axis_trains_and_runs(compose_cfg) -> None:
    """gp=clock with gp.clock_knee: the saved psi reads its clock as log(1 + a / knee) (fitted
    on the warped clocks), the simulation's table reads it in seconds, one node per step."""
    from surrogate.gp import load_psi
    from surrogate.gp.predictor import log_warp

    clock = ["gp=clock", "gp.max_age=2", "gp.clock_knee=0.25", "gp.clock_bins=8"]
    collect.run(compose_cfg("collect", [o for o in TINY if o.startswith("collect")]))
    out = train.run(compose_cfg("train", [*_train_overrides(), *clock]))
    psi, meta = load_psi(out / "psi.pt")
    assert psi.warps == {"phi_age": 0.25} and meta["settings"]["gp"]["clock_knee"] == 0.25
    assert psi.domain["phi_age"][1] == pytest.approx(2.0)  # the raw clock's range
    z = torch.tensor([[0.5, 0.0], [0.5, 1.0], [0.5, 2.0]])
    phi = torch.tensor([1, 1, 1])
    warped = log_warp(z, psi.input_names, psi.warps)
    assert warped[:, 1].tolist() == pytest.approx([0.0, np.log(5.0), np.log(9.0)])
    assert torch.equal(psi(phi, z), psi.evaluate(phi, z))  # warped once, not twice
    run = simulate_stage.run(compose_cfg("simulate", [*TINY, *clock, "decision=abstract"]))
    assert (run / "manifest.json").is_file()


def test_the_perturbation_left_null_is_the_models(compose_cfg, tmp_path) -> None:
    """collect.perturb_rate and collect.blackout_time left null are the model's: E. coli's 0.1/s
    and 1 s (the options, so the identity, its collections had before), a network yaml's own
    (`collect: {blackout_time, perturb_rate}`: one slow to settle after a jump), and a value on
    the command line over either."""
    import yaml

    from surrogate.stages.settings import CollectSettings

    ecoli = CollectSettings.from_config(compose_cfg("collect"))
    assert (ecoli.options["perturb_rate"], ecoli.options["blackout_time"]) == (0.1, 1.0)
    spec = yaml.safe_load((EXAMPLES / "gene_switch" / "model.yaml").read_text())
    network = (EXAMPLES / "gene_switch" / spec["network"]).resolve()
    spec.update(network=str(network), collect={"blackout_time": 20.0, "perturb_rate": 0.025})
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump(spec))
    slow = CollectSettings.from_config(compose_cfg("collect", ["model=sbml",
                                                               f"model.spec={path}"]))  # fmt: skip
    assert (slow.options["perturb_rate"], slow.options["blackout_time"]) == (0.025, 20.0)
    given = CollectSettings.from_config(compose_cfg("collect", ["model=sbml", f"model.spec={path}",
                                                                "collect.blackout_time=5"]))  # fmt: skip
    assert given.options["blackout_time"] == 5.0
    assert given.directory != slow.directory


def test_the_blackout_collect_advises_passes_collects_checks(compose_cfg) -> None:
    """Every blackout the lag can advise (from any blackout below the settled rows' 20 s, at
    E. coli's rate of jumps and others) passes collect's own settings checks, with the run's
    config and without it (a collection the choice makes); one the checks refuse is not
    printed, and says why."""
    from surrogate.diagnosis.jumps import SETTLED_AFTER, blackout_advice
    from surrogate.stages.collect import check_collection, validate

    cfg = compose_cfg("collect")
    settings = validate(cfg)
    lag = {"settled_after_s": SETTLED_AFTER, "lagging": [("run", 0.0, 2.0, 0.8)]}
    for blackout in (0.0, 1.0, 5.0, 19.0):
        for rate in (0.1, 1.0, 0.01):
            advice = blackout_advice(lag, blackout, rate)
            assert advice and advice[0] == f"collect.blackout_time={SETTLED_AFTER:g}"
            assert check_collection(settings, cfg, advice) is None, advice
            assert check_collection(settings, None, advice) is None, advice
    refused = check_collection(settings, cfg, ("collect.blackout_time=-2",))
    assert refused is not None and "collect.blackout_time" in refused


def test_the_verdict_reads_the_blackout_its_collection_advised(compose_cfg) -> None:
    """The reproduce verdict's blackout remedy is the one collect wrote beside its rows
    (``after_jump.advice``, checked there); none for a collection without it."""
    from surrogate.io import read_manifest, write_json
    from surrogate.stages.reproduce import collection_blackout

    path = collect.run(compose_cfg("collect", [o for o in TINY if o.startswith("collect")]))
    settings = train.validate(compose_cfg("train", _train_overrides()))
    manifest = read_manifest(path)
    assert collection_blackout(settings) == tuple((manifest.get("after_jump") or {})
                                                  .get("advice", ()))  # fmt: skip
    advice = ["collect.blackout_time=20", "collect.perturb_rate=0.025"]
    write_json(path / "manifest.json", {**manifest, "after_jump": {"advice": advice}})
    assert collection_blackout(settings) == tuple(advice)


def _lagging(path: Path) -> dict:
    """Collection ``path``'s manifest, made to say its rows lag 0-2 s after a jump (the lag
    ends within the measurement), with collect's advice for it; the original, for restoring."""
    from surrogate.io import read_manifest, write_json

    manifest = read_manifest(path)
    lag = {"settled_after_s": 20.0, "lagging": [("run", 0.0, 2.0, 0.8)],
           "advice": ["collect.blackout_time=20", "collect.perturb_rate=0.025"]}  # fmt: skip
    write_json(path / "manifest.json", {**manifest, "after_jump": lag})
    return manifest


def test_train_leaves_out_the_rows_collect_measured_lagging(
    compose_cfg, monkeypatch, caplog
) -> None:
    """gp.jump_rows=auto: where collect measured rows lagging a jump (a lag that ends within
    its bins) the fit reads only rows 20 s or more after one (or before the first), says so,
    and records it for its manifest; gp.jump_rows=keep reads every row under another fit
    identity; a collection that did not lag keeps every row; too few settled rows per origin
    keep every row, with a warning naming the blackout."""
    from surrogate.io import write_json
    from surrogate.stages import train as train_stage

    path = collect.run(compose_cfg("collect", [o for o in TINY if o.startswith("collect")]))
    auto = train.validate(compose_cfg("train", _train_overrides()))
    keep = train.validate(compose_cfg("train", [*_train_overrides(), "gp.jump_rows=keep"]))
    assert "jump_rows" not in auto.fit_identity()["gp"]  # fits before the key keep theirs
    assert keep.fit_identity()["gp"]["jump_rows"] == "keep"
    everything, _ = train_stage.load_transitions(keep)
    manifest = _lagging(path)
    try:
        dt = auto.setup.dt
        settled = (everything["since_jump"] < 0) | (everything["since_jump"] * dt >= 20.0)
        assert 0 < settled.sum() < len(everything)
        monkeypatch.setattr(train_stage, "MIN_SETTLED_ROWS", 1)
        with caplog.at_level(logging.INFO, logger="surrogate.stages.train"):
            kept, _ = train_stage.load_transitions(auto)
        assert len(kept) == int(settled.sum())
        assert ((kept["since_jump"] < 0) | (kept["since_jump"] * dt >= 20.0)).all()
        assert kept.attrs["jump_rows"] == {"mode": "auto", "window_s": 20.0,
                                           "rows": len(everything), "kept": len(kept)}  # fmt: skip
        assert f"{len(kept)} of {len(everything)} rows kept" in caplog.text
        assert len(train_stage.load_transitions(keep)[0]) == len(everything)
        # too few settled rows for an origin: every row, and the blackout named
        monkeypatch.setattr(train_stage, "MIN_SETTLED_ROWS", len(everything))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="surrogate.stages.train"):
            fallback, _ = train_stage.load_transitions(auto)
        assert len(fallback) == len(everything)
        assert fallback.attrs["jump_rows"]["kept"] == len(everything)
        assert "collect.blackout_time=20" in caplog.text
    finally:
        write_json(path / "manifest.json", manifest)
    assert len(train_stage.load_transitions(auto)[0]) == len(everything)  # nothing lagged
    assert "jump_rows" not in train_stage.load_transitions(auto)[0].attrs


def test_collect_tops_up_the_settled_rows_where_rows_lag(compose_cfg, monkeypatch) -> None:
    """collect.top_up=auto: where the first pass's rows lag a jump within the measurement,
    fresh cells collected with the blackout add settled rows until each origin has
    n_per_state (every row they add settled, under new cell numbers), the manifest records it
    and advises no blackout; off keeps the table and advises it; a bad value is refused."""
    from surrogate.diagnosis.jumps import settled_rows
    from surrogate.io import read_manifest
    from surrogate.stages import collect as collect_stage

    def lagging(*args, **kwargs):
        return {"settled_after_s": 20.0, "lagging": [("run", 0.0, 2.0, 0.8)]}

    monkeypatch.setattr(collect_stage, "after_jump_lag", lagging)
    base = ["collect.n_per_state=400", "collect.n_cells=100", "collect.perturb_rate=0.5",
            "collect.max_time=400"]  # fmt: skip
    off = collect.run(compose_cfg("collect", [*base, "collect.top_up=off"]))
    first = pd.read_parquet(off / "transitions.parquet")
    assert len(first) == 800 and "top_up" not in read_manifest(off)
    assert read_manifest(off)["after_jump"]["advice"][0] == "collect.blackout_time=20"
    auto = collect.run(compose_cfg("collect", base))
    assert auto != off  # off enters the identity, auto (the default) does not
    table = pd.read_parquet(auto / "transitions.parquet")
    manifest = read_manifest(auto)
    record, dt = manifest["top_up"], collect.validate(compose_cfg("collect", base)).setup.dt
    settled = settled_rows(table["since_jump"].to_numpy(), dt, 20.0)
    before = settled_rows(first["since_jump"].to_numpy(), dt, 20.0)
    assert record["settled_before"] == [int((before & (first["phi"] == p)).sum()) for p in (0, 1)]
    assert record["per_origin"] == 400 - min(record["settled_before"]) > 0
    assert record["perturb_rate"] == 0.025 and record["blackout_time"] == 20.0
    assert len(table) == 800 + record["rows"] == 800 + 2 * record["per_origin"]
    added = table.iloc[800:]
    assert settled[800:].all() and (added["cell"] >= 100).all()
    assert min(int((settled & (table["phi"] == p)).sum()) for p in (0, 1)) >= 400
    pd.testing.assert_frame_equal(table.iloc[:800], first)  # the first pass as it was
    assert manifest["after_jump"]["advice"] == []
    # a top-up that stops short keeps the first pass, records why and advises the blackout
    passes = []
    real = collect_stage.collect_transitions

    def short_second(*args, **kwargs):
        passes.append(kwargs["n_per_state"])
        if len(passes) > 1:
            raise ConfigError("collect reached collect.max_time short of the rows wanted")
        return real(*args, **kwargs)

    monkeypatch.setattr(collect_stage, "collect_transitions", short_second)
    short = collect.run(compose_cfg("collect", [*base, "collect.n_cells=101"]))
    assert len(passes) == 2 and len(pd.read_parquet(short / "transitions.parquet")) == 800
    assert "max_time short" in read_manifest(short)["top_up"]["skipped"]
    assert read_manifest(short)["after_jump"]["advice"][0] == "collect.blackout_time=20"
    with pytest.raises(ConfigError, match="collect.top_up must be one of"):
        collect.validate(compose_cfg("collect", [*base, "collect.top_up=always"]))


def test_a_bad_jump_rows_setting_is_refused(compose_cfg) -> None:
    with pytest.raises(ConfigError, match="gp.jump_rows must be one of"):
        train.validate(compose_cfg("train", [*_train_overrides(), "gp.jump_rows=sometimes"]))


def test_no_blackout_is_named_where_the_fit_left_the_lagging_rows_out(compose_cfg) -> None:
    """The verdict's blackout (collect's advice) is named where the fit trained on the lagging
    rows: as the fit's manifest records, else as gp.jump_rows would (a fit not made yet); the
    fidelity report's whatever the fit read, with the share it read."""
    from surrogate.io import MANIFEST, write_json
    from surrogate.stages.reproduce import collection_blackout, kept_share

    path = collect.run(compose_cfg("collect", [o for o in TINY if o.startswith("collect")]))
    auto = train.validate(compose_cfg("train", _train_overrides()))
    keep = train.validate(compose_cfg("train", [*_train_overrides(), "gp.jump_rows=keep"]))
    manifest = _lagging(path)
    advice = ("collect.blackout_time=20", "collect.perturb_rate=0.025")
    try:
        assert collection_blackout(auto) == ()  # not fitted: auto would leave them out
        assert collection_blackout(keep) == advice
        auto.fit_directory.mkdir(parents=True, exist_ok=True)
        for kept, named, share in ((100, (), 0.25), (400, advice, None)):  # the fit's record
            write_json(auto.fit_directory / MANIFEST,
                       {"jump_rows": {"mode": "auto", "window_s": 20.0, "rows": 400,
                                      "kept": kept}})  # fmt: skip
            assert collection_blackout(auto) == named
            assert kept_share(auto) == share
            # the fidelity report names it either way: it records more of the rows read
            assert collection_blackout(auto, unless_left_out=False) == advice
    finally:
        write_json(path / "manifest.json", manifest)
        (auto.fit_directory / MANIFEST).unlink(missing_ok=True)


@pytest.mark.parametrize(("lookup", "blocks", "backend"),
                         [("[64]", 3, "numba"), ("null", 2, "numba"), ("null", 2, "torch")],
                         ids=["own_tables", "stacked_tables", "stacked_tables_torch"])  # fmt: skip
def test_runs_simulated_together_are_the_standalone_runs(
    trained, beside, caplog, lookup: str, blocks: int, backend: str
) -> None:
    """reproduce simulates its runs as one batch: with the per-cell kernel or the eager torch
    step, each run is its standalone run bit for bit (same directory, same files), whatever
    else is in the batch. With the default table size the abstraction's and the exact chain's
    tables (both 4,096 nodes over dG) are stacked into one decision block."""
    from surrogate.stages.settings import ReproduceSettings

    # stacking needs the two-state chain's table (K lumps, the default, keeps its own block)
    chain = ["gp=svgp"] if lookup == "null" else []
    if chain:
        train.run(beside("train", [*_train_overrides(), *chain]))
    cfg = beside("reproduce", [*TINY, f"decision.lookup_size={lookup}",
                               "fields=[gaussian,linear]", "record_cells=16",
                               f"backend={backend}", *chain])  # fmt: skip
    settings = ReproduceSettings.from_config(cfg)
    runs = settings.runs()
    assert {s.decision.name for s in runs} == {"full", "abstract", "exact"} and len(runs) == 8
    for s in runs:  # all made here: the tests beside this one made some of the same runs
        shutil.rmtree(s.directory, ignore_errors=True)
    with caplog.at_level(logging.INFO, logger="surrogate.stages.simulate"):
        dirs = simulate_stage.simulate_together(runs)
    assert (
        f"(320 cells, {blocks} decision blocks, 2 distinct fields; {backend} loop)" in caplog.text
    )
    batched = {d: (pd.read_parquet(d / "observables.parquet"),
                   pd.read_parquet(d / "duration_histogram.parquet")) for d in dirs}  # fmt: skip
    for d in dirs:
        assert json.loads((d / "manifest.json").read_text())["batched"]["n_cells"] == 8 * 40
    for s in (runs[0], runs[3], runs[-1]):  # one of each kind, standalone
        for f in s.directory.iterdir():
            f.unlink()
        s.directory.rmdir()
        simulate_stage.simulate(s)
        observables, durations = batched[s.directory]
        pd.testing.assert_frame_equal(pd.read_parquet(s.directory / "observables.parquet"),
                                      observables)  # fmt: skip
        pd.testing.assert_frame_equal(
            pd.read_parquet(s.directory / "duration_histogram.parquet"), durations
        )
        assert observables["cell"].nunique() == 16


def test_runs_are_locked_in_one_global_order(compose_cfg, monkeypatch) -> None:
    """simulate_together takes its runs' locks in one global order (by directory), whatever
    order its caller lists them in: two jobs sharing runs in opposite orders (e.g.
    ``fields=[gaussian,linear]`` and ``[linear,gaussian]``) cannot deadlock."""
    from surrogate.stages.settings import SimulateSettings

    run = [o for o in TINY if not o.startswith(("collect", "gp"))]
    runs = [SimulateSettings.from_config(compose_cfg("simulate", [*run, "decision=full",
                                                                   f"field={name}"]))
            for name in ("linear", "gaussian")]  # fmt: skip
    taken: list[Path] = []

    @contextlib.contextmanager
    def lock(directory):
        taken.append(Path(directory))
        yield Path(directory)

    monkeypatch.setattr(simulate_stage, "artefact_lock", lock)
    monkeypatch.setattr(simulate_stage, "_simulate_group", lambda group: None)
    orders = []
    for listed in (runs, runs[::-1]):
        taken.clear()
        simulate_stage.simulate_together(listed)
        orders.append(list(taken))
    assert len(orders[0]) == 2 and orders[0] == orders[1] == sorted(orders[0])


def test_compiled_runs_of_a_batch_have_their_own_identity(compose_cfg) -> None:
    """Compiled kernels fused for a batch round differently from a standalone run's: such runs
    carry the batch's id and name reproduce as the command that makes them."""
    from surrogate.stages.settings import ReproduceSettings

    eager = ReproduceSettings.from_config(compose_cfg("reproduce", ["fields=[gaussian]"]))
    compiled = ReproduceSettings.from_config(
        compose_cfg("reproduce", ["fields=[gaussian]", "compile=true"])
    )
    assert all("batch" not in s.identity() for s in eager.runs())
    ids = {s.identity()["batch"] for s in compiled.runs()}
    assert len(ids) == 1
    assert all(s.command().startswith("python scripts/reproduce.py") for s in compiled.runs())
    unbatched = ReproduceSettings.from_config(
        compose_cfg("reproduce", ["fields=[gaussian]", "compile=true", "batch=false"])
    )
    assert all("batch" not in s.identity() for s in unbatched.runs())


def test_a_run_outside_the_trained_inputs_warns_with_the_share(compose_cfg, caplog) -> None:
    """An abstraction over the raw inputs (m, L) trained in L1 (L <= 0.1 mM), simulated in a
    field ten times as strong: L leaves the trained range in (nearly) every sampled cell-step,
    which the manifest records per input and one warning names; in L1 itself it stays inside."""
    tiny = [*TINY, "gp.inputs=inputs", "record_interval=1.0"]
    cfg = compose_cfg("train", [o for o in tiny if o.split(".")[0] in ("collect", "gp")])
    collect.run(cfg)
    train.run(cfg)
    inside = simulate_stage.run(compose_cfg("simulate", [*tiny, "decision=abstract"]))
    with caplog.at_level(logging.WARNING, logger="surrogate.simulate.support"):
        outside = simulate_stage.run(
            compose_cfg("simulate", [*tiny, "decision=abstract", "field.amplitude=1.0"])
        )
    home = json.loads((inside / "manifest.json").read_text())["outside_training"]
    away = json.loads((outside / "manifest.json").read_text())["outside_training"]
    assert home["share_outside"] <= 0.01 and away["share_outside"] > 0.9
    # and the density check beside it: the shares of cell-steps inside the range in sparse bins
    assert 0 <= home["share_sparse"] <= 1 - home["share_outside"] and "sparse_where" in home
    assert away["share_sparse"] <= 1 - away["share_outside"]
    assert away["sampled_cell_steps"] == 40 * 20  # 40 cells, every 1 s of 20 s
    L = away["inputs"]["L"]
    assert L["share_above"] > 0.9 and L["seen"][1] > 0.5 > 0.1 >= L["trained"][1]
    (record,) = [r for r in caplog.records if "outside its training data" in r.getMessage()]
    assert f"L seen [{L['seen'][0]:.4g}, {L['seen'][1]:.4g}]" in record.getMessage()


def test_speed_times_both_models_side_by_side(trained, beside) -> None:
    from surrogate.stages import speed

    cfg = beside("speed", [*TINY, "decision.lookup_size=[64]", "steps=5"])
    out = speed.run(cfg)
    result = json.loads((out / "speed.json").read_text())
    assert result["steps"] == 5 and result["n_cells"] == 40
    loops = result["loops"]
    for name in ("full", "abstract"):  # E. coli: both models on both loops
        assert set(loops[name]) == {"torch", "numba"}
        for entry in loops[name].values():
            assert entry["steps"] == 5 and entry["seconds"] > 0 and entry["n_cells"] == 40
    best = {name: max(loops[name].values(), key=lambda e: e["cell_steps_per_s"])
            for name in ("full", "abstract")}  # fmt: skip
    assert result["speedup"] == pytest.approx(best["full"]["seconds"] / best["abstract"]["seconds"])
    for loop, label in (("torch", "torch step"), ("numba", "numba kernel")):
        assert result["same_loop"][label] == pytest.approx(
            loops["full"][loop]["seconds"] / loops["abstract"][loop]["seconds"]
        )
    with pytest.raises(ConfigError, match="loops must be auto or a list"):
        speed.run(beside("speed", [*TINY, "decision.lookup_size=[64]", "loops=[gpu]"]))
    with pytest.raises(ConfigError, match="decision=abstract"):
        speed.run(beside("speed", [*TINY, "decision=full"]))


def test_auto_labels_are_the_expected_labels_where_the_table_has_them(compose_cfg) -> None:
    """gp.labels=auto trains on the expected labels where the table has them, on the outcomes
    otherwise; outcome and expected choose."""
    from surrogate.stages.settings import TrainSettings

    columns = ["dG", "phi", "phi_next", "phi_next_expected"]
    auto = TrainSettings.from_config(compose_cfg("train"))
    assert auto.label_column(columns) == "phi_next_expected"
    assert auto.label_column(columns[:-1]) == "phi_next"
    outcome = TrainSettings.from_config(compose_cfg("train", ["gp.labels=outcome"]))
    assert outcome.label_column(columns) == "phi_next"
    expected = TrainSettings.from_config(compose_cfg("train", ["gp.labels=expected"]))
    assert expected.label_column(columns) == "phi_next_expected"


def test_train_manifest_names_the_labels(trained) -> None:
    _, _, train_dir = trained
    manifest = json.loads((train_dir / "manifest.json").read_text())
    assert manifest["label_column"] == "phi_next_expected"


def test_the_occupancy_run_is_seeded_and_reused(compose_cfg, caplog) -> None:
    from surrogate.stages.occupancy import OCCUPANCY, occupancy
    from surrogate.stages.settings import TrainSettings

    train_only = _train_overrides()
    settings = TrainSettings.from_config(compose_cfg("train", train_only)).occupancy()
    rows = occupancy(settings)
    assert len(rows) == 100 * 200 // 10 and {"dG", "phi", "phi_next"} <= set(rows.columns)
    manifest = json.loads((settings.directory / "manifest.json").read_text())
    assert manifest["stage"] == "occupancy" and manifest["rows"] == len(rows)
    again = pd.read_parquet(settings.directory / OCCUPANCY)
    (settings.directory / "manifest.json").unlink()  # incomplete: made again, the same rows
    pd.testing.assert_frame_equal(occupancy(settings), again)
    with caplog.at_level(logging.INFO, logger="surrogate.io"):
        occupancy(settings)
    assert "occupancy run exists, reusing" in caplog.text


def test_reproduce_writes_the_report_of_every_field(beside) -> None:
    """reproduce (one process) makes every run, the learned and the exact chain's evaluations
    on each field, and the report; a rerun reuses all of it."""
    from surrogate.stages import reproduce
    from surrogate.stages.settings import ReproduceSettings

    cfg = beside("reproduce", [*TINY, "fields=[gaussian,linear,dynamic]", "record_cells=16"])
    out = reproduce.run(cfg)
    report = (out / "report.md").read_text()  # the exact chain: adapted cells, not a bound
    assert "The exact lumped psi (cells adapted to their current input)" in report
    assert "best two-state" not in report and "best any" not in report
    assert "| sparse | sparse where |" in report  # the density check's column beside the range
    # too few switches in TINY's rows for a classifier's own-rows check: no column, no note
    assert "own rows: predicted / observed" not in report and "*Own rows*" not in report
    manifest = json.loads((out / "manifest.json").read_text())
    assert set(manifest["evaluations"]) == set(manifest["exact"]) == {"gaussian", "linear",
                                                                        "dynamic"}  # fmt: skip
    for d in [*manifest["evaluations"].values(), *manifest["exact"].values()]:
        assert (Path(d) / "comparison.csv").exists()
    settings = ReproduceSettings.from_config(cfg)
    assert all((s.directory / "manifest.json").exists() for s in settings.runs())
    assert manifest["speed"]["field"] == "gaussian"
    assert reproduce.run(cfg) == out
    assert json.loads((out / "manifest.json").read_text())["speed"] == manifest["speed"]


def test_reproduce_unbatched_reports_only_the_side_by_side_speed_up(compose_cfg) -> None:
    """batch=false: each run times its own loop, apart from the others (a cold compile or a
    busy machine in one of them), so the report's speed-up is the side-by-side measurement,
    and no ratio of the runs' own times."""
    from surrogate.stages import reproduce

    cfg = compose_cfg("reproduce", [*TINY, "fields=[gaussian]", "exact_psi=false", "batch=false"])
    out = reproduce.run(cfg)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["speed"]["field"] == "gaussian" and manifest["speed"]["n_cells"] == 40
    summary = evaluate_stage.read_summary(manifest["evaluations"]["gaussian"])
    assert summary["speedup_loop"] is None  # the runs' own times: timed apart
    report = (out / "report.md").read_text()
    speed = report[report.index("## Speed") :]
    assert "timed apart" in speed and "measured side by side in this process" in speed


def test_the_k_lumps_chain_trains_is_diagnosed_and_simulates(compose_cfg, caplog) -> None:
    """gp=classes end to end on tiny settings: the class chain is written beside psi, scored
    against E. coli's exact class law where the occupancy run lives (every class the run
    visits, their shares adding up to 1), and `decision=abstract gp=classes` runs it."""
    tiny = _train_overrides()
    cfg = compose_cfg("train", ["gp=classes", *tiny, "gp.n_inducing=8"])
    collect.run(cfg)
    with caplog.at_level(logging.INFO, logger="surrogate.stages.train"):
        train_dir = train.run(cfg)
    assert (train_dir / "class_chain.pt").exists()
    chain = train.load_class_chain(train_dir)
    diagnostic = json.loads((train_dir / "train_metrics.json").read_text())["class_diagnostic"]
    assert diagnostic["reference"] == "exact"
    visited = {k: v for k, v in diagnostic.items() if isinstance(v, dict)}
    assert set(visited) <= set(chain.class_names) and len(visited) >= 4
    assert sum(v["share"] for v in visited.values()) == pytest.approx(1.0)
    assert all(np.isfinite(v["rel_bias"]) for v in visited.values())
    assert "K lumps, leaving" in caplog.text
    # the report scores the chain it simulates, class by class
    from surrogate.stages.reproduce import _diagnostic_text

    metrics = json.loads((train_dir / "train_metrics.json").read_text())
    text = _diagnostic_text(metrics, ("tumble", "run"))
    assert "K-lumps chain" in text and all(f"| {name} |" in text for name in visited)
    sim = compose_cfg("simulate", ["decision=abstract", "gp=classes", *TINY, "gp.n_inducing=8"])
    run_dir = simulate_stage.run(sim)
    run = load_run(run_dir)
    assert run.observables["cell"].nunique() == 40 and run.manifest["decision"] == "abstract"
    # the training rows per class beside the per-state ones (outside the fit's identity), and
    # the run's cells checked against their own class's rows
    manifest = json.loads((train_dir / "manifest.json").read_text())
    per_class = TrainingHistogram.from_dict(manifest["support_class_histogram"])
    per_state = TrainingHistogram.from_dict(manifest["support_histogram"])
    assert per_class.classes == chain.class_names and per_class.bins == per_state.bins
    assert sum(map(sum, per_class.counts)) == sum(map(sum, per_state.counts))
    assert "support_class_histogram" not in train.validate(cfg).fit_identity()
    report = run.manifest["outside_training"]
    assert report["classes"] == list(chain.class_names) and "sparse_class" in report


def test_a_collection_that_keeps_every_switch_trains_and_says_so(compose_cfg) -> None:
    """collect.keep_switches=true through the stages: the table holds every switch and (E.
    coli declares classes) every class move of its simulated time and the thinned held rows,
    each with its windows; the manifest records the windows per origin; train fits psi on the
    outcomes, its support histogram counting windows."""
    import json

    from surrogate.gp.windows import WINDOWS

    keep = ["collect.keep_switches=true", "collect.record_every=5"]
    out = collect.run(compose_cfg("collect", [*[o for o in TINY if o.startswith("collect")],
                                              *keep]))  # fmt: skip
    table = pd.read_parquet(out / "transitions.parquet")
    changed = table["phi_class"] != table["phi_class_next"]  # a switch changes the class too
    assert set(table.loc[changed, WINDOWS]) == {1.0} and set(table.loc[~changed, WINDOWS]) == {5.0}
    manifest = json.loads((out / "manifest.json").read_text())
    assert sum(manifest["windows_per_origin"].values()) == pytest.approx(table[WINDOWS].sum())
    fit = train.run(compose_cfg("train", [*_train_overrides(), *keep, "gp=svgp"]))
    meta = json.loads((fit / "manifest.json").read_text())
    assert meta["label_column"] == "phi_next"  # E. coli's expected labels not recorded
    per_state = meta["support_histogram"]["counts"]
    assert sum(map(sum, per_state)) == pytest.approx(table[WINDOWS].sum(), abs=2)


def test_the_reports_classifier_table_reads_each_fits_own_rows() -> None:
    """A classifier's own-rows check as the report's two columns: the ratios' range and the
    group farthest off in SE, marked off where a group is."""
    import numpy as np

    from surrogate.gp.own_rows import own_rows_check
    from surrogate.stages.reproduce import _own_rows_columns

    x = np.linspace(0, 1, 50)[:, None]
    n = np.full(50, 1000.0)
    fine = _own_rows_columns(own_rows_check(np.full(50, 0.1), x, n, n * 0.1))
    assert fine == {"own rows: predicted / observed": "1.000-1.000",
                    "farthest off": "+0.0% (0.0 SE)"}  # fmt: skip
    off = _own_rows_columns(own_rows_check(np.full(50, 0.15), x, n, n * 0.1))
    assert off["farthest off"].startswith("+50.0%") and off["farthest off"].endswith(", off)")
    assert _own_rows_columns(None) == {}

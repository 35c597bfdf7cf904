"""Sweeps: the job wrapper (threads, status files, failures), launchers, and the sweep summary."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from surrogate import cli
from surrogate.errors import ConfigError, MissingArtefactError
from surrogate.io import JOB_STATUS, read_json
from surrogate.sweep import summarize

ROOT = Path(__file__).resolve().parents[1]

# A reproduce job in seconds: one field, 20 cells for 10 s, 300 transitions per origin state,
# the two-state chain (these tests are about launchers, not the K lumps gp=auto trains for E.
# coli) from 2 epochs of a 10-inducing-point GP, a diagnostic of 100 cells for 10 s, a coarse
# lookup table (over the default single input, the E. coli model's signal dG).
TINY = [
    "gp=svgp",
    "fields=[gaussian]",
    "n_cells=20",
    "t_end=10",
    "equilibration_time=1",
    "collect.n_per_state=300",
    "gp.epochs=2",
    "gp.n_inducing=10",
    "gp.diagnostic.n_cells=100",
    "gp.diagnostic.t_end=10.0",
    "decision.lookup_size=[64]",
    "evaluate.times=null",
    "evaluate.subsample=50",
]


def run_script(name: str, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    """``python scripts/<name> args`` in ``cwd``, output captured."""
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / name), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )


def statuses(sweep_dir: Path) -> dict[int, dict]:
    """job number -> job_status.json of a sweep."""
    return {
        int(p.parent.name): json.loads(p.read_text()) for p in sweep_dir.glob(f"*/{JOB_STATUS}")
    }


# ----------------------------------------------------------------------------------------------
# the wrapper, without a Hydra runtime


@pytest.mark.parametrize(
    ("launcher", "cores", "expected"),
    [
        ({"_target_": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher",
          "n_jobs": -1}, 2, 1),
        ({"_target_": "x.JoblibLauncher", "n_jobs": 3}, 8, 2),
        ({"_target_": "x.JoblibLauncher", "n_jobs": 1}, 8, 8),
        ({"_target_": "x.JoblibLauncher", "n_jobs": -2}, 8, 1),
        ({"_target_": "x.JoblibLauncher", "n_jobs": 16}, 8, 1),
        ({"_target_": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher",
          "cpus_per_task": 4}, 64, 4),
        ({"_target_": "hydra._internal.core_plugins.basic_launcher.BasicLauncher"}, 8, None),
        ({}, 8, None),
    ],
)  # fmt: skip
def test_default_threads(launcher: dict, cores: int, expected: int | None) -> None:
    assert cli.default_threads(launcher, cores=cores) == expected


@pytest.mark.parametrize("bad", [0, -1, "two", True, 1.5])
def test_threads_setting_is_validated(bad: object) -> None:
    with pytest.raises(ConfigError, match="threads must be a positive integer or null"):
        cli.resolve_threads({"threads": bad}, {})


def test_ok_job_records_status_and_sets_threads(tmp_path: Path) -> None:
    before = torch.get_num_threads()
    ctx = cli.JobContext(
        multirun=True, output_dir=tmp_path / "job", overrides=["dt=0.1"], job_num=3
    )
    cfg = OmegaConf.create({"threads": 1, "progress": True, "data_dir": "data"})
    try:
        out = cli.execute("collect", lambda c: tmp_path / "artefact", cfg, ctx)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    assert out == str((tmp_path / "artefact").resolve())
    assert cfg.progress is False  # multirun: no interleaved progress bars
    status = read_json(tmp_path / "job" / JOB_STATUS)
    assert status["status"] == "ok" and status["artefact_dir"] == out
    assert status["overrides"] == ["dt=0.1"] and status["job_num"] == 3 and status["threads"] == 1
    assert status["error"] is None and status["wall_time_s"] >= 0


@pytest.mark.parametrize("error", [RuntimeError("boom"), MissingArtefactError("no boom here")])
def test_multirun_failure_is_recorded_not_raised(tmp_path: Path, error: Exception) -> None:
    def stage(cfg: object) -> Path:
        raise error

    ctx = cli.JobContext(multirun=True, output_dir=tmp_path, overrides=["gp.kernel=x"])
    assert cli.execute("train", stage, OmegaConf.create({}), ctx) is None
    status = read_json(tmp_path / JOB_STATUS)
    assert status["status"] == "failed" and status["artefact_dir"] is None
    assert status["error_type"] == type(error).__name__ and status["error"] == str(error)
    assert str(error) in status["traceback"] and status["overrides"] == ["gp.kernel=x"]


def test_single_run_errors_reach_the_user(tmp_path: Path, capsys) -> None:
    ctx = cli.JobContext(multirun=False, output_dir=tmp_path)

    def user_error(cfg: object) -> Path:
        raise ConfigError("dt must be positive")

    with pytest.raises(SystemExit) as exit_:
        cli.execute("simulate", user_error, OmegaConf.create({}), ctx)
    assert exit_.value.code == 2
    assert capsys.readouterr().err == "error: dt must be positive\n"
    assert read_json(tmp_path / JOB_STATUS)["status"] == "failed"

    def bug(cfg: object) -> Path:
        raise KeyError("a bug")

    with pytest.raises(KeyError):  # not ours: the traceback is what a developer needs
        cli.execute("simulate", bug, OmegaConf.create({}), ctx)


def test_relative_data_dir_is_anchored_where_the_command_ran(tmp_path, monkeypatch) -> None:
    job_dir = tmp_path / "job"
    job_dir.mkdir()
    monkeypatch.chdir(job_dir)  # as with hydra.job.chdir=true
    cfg = OmegaConf.create({"data_dir": "data", "progress": True})
    ctx = cli.JobContext(multirun=True, original_cwd=tmp_path, overrides=["progress=true"])
    cli.prepare_config(cfg, ctx)
    assert cfg.data_dir == str(tmp_path / "data")
    assert cfg.progress is True  # asked for on the command line


def test_single_run_user_error_is_one_clean_line(tmp_path: Path) -> None:
    result = run_script("simulate.py", "dt=0.3", f"data_dir={tmp_path}")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith("error: record_interval=1 s must be")


def test_summary_of_failed_and_missing_jobs(tmp_path: Path) -> None:
    """Without dt swept there is no plot; a job without job_status.json is reported missing."""
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    task = {"hydra": {"overrides": {"task": ["seed=0,1", "n_cells=5"]}}}
    OmegaConf.save(OmegaConf.create(task), sweep / "multirun.yaml")
    for num in (0, 1):
        (sweep / str(num) / ".hydra").mkdir(parents=True)
        OmegaConf.save(OmegaConf.create([f"seed={num}", "n_cells=5"]),
                       sweep / str(num) / ".hydra" / "overrides.yaml")  # fmt: skip
    ctx = cli.JobContext(multirun=True, output_dir=sweep / "0", overrides=["seed=0", "n_cells=5"])
    cli.execute("simulate", _raise_config_error, OmegaConf.create({}), ctx)
    df, csv, png = summarize(sweep)
    assert png is None and csv == sweep / "summary.csv"
    assert list(df.columns[:3]) == ["job", "seed", "status"]
    assert df["status"].tolist() == ["failed", "missing"] and df["seed"].tolist() == [0, 1]
    assert df.loc[0, "error_type"] == "ConfigError" and "bad n_cells" in df.loc[0, "error"]
    assert "no job_status.json" in df.loc[1, "error"]
    assert pd.read_csv(csv).shape[0] == 2

    result = run_script("summarize.py", str(sweep), "--strict")
    assert result.returncode == 1 and "2 job(s), 0 ok, 2 failed or missing" in result.stdout
    result = run_script("summarize.py", str(tmp_path / "nowhere"))
    assert result.returncode == 2 and result.stderr.startswith("error: sweep directory")


def _raise_config_error(cfg: object) -> Path:
    raise ConfigError("bad n_cells")


def test_job_results_columns_by_stage(tmp_path: Path) -> None:
    """The summary's result columns per stage, from hand-written artefacts: generic names
    (psi_0/psi_1, phi0/phi1, final_mean_<observable>), not the E. coli ones."""
    from surrogate.io import write_json, write_manifest
    from surrogate.sweep import job_results

    train = tmp_path / "train"
    write_manifest(
        train, stage="train", config={}, seed=0, wall_time_s=3.5,
        brier={"psi_0": 0.1, "psi_1": 0.2}, brier_baseline={"psi_0": 0.3, "psi_1": 0.4},
        diagnostic={"phi0": {"rel_bias": -0.05}, "phi1": {"rel_bias": 0.25}},
    )  # fmt: skip
    assert job_results(train) == {
        "brier_psi_0": 0.1, "brier_psi_1": 0.2,
        "brier_baseline_psi_0": 0.3, "brier_baseline_psi_1": 0.4,
        "switch_bias_phi0": -0.05, "switch_bias_phi1": 0.25, "train_s": 3.5,
    }  # fmt: skip

    simulate = tmp_path / "simulate"
    write_manifest(
        simulate, stage="simulate", config={}, seed=0, n_cells=10, loop_time_s=1.0,
        cell_steps_per_s=5.0, final_means={"distance": 1.5, "speed": 0.02},
    )  # fmt: skip
    assert job_results(simulate) == {
        "n_cells": 10, "loop_time_s": 1.0, "cell_steps_per_s": 5.0,
        "final_mean_distance": 1.5, "final_mean_speed": 0.02,
    }  # fmt: skip

    candidate = tmp_path / "candidate"
    write_manifest(candidate, stage="simulate", config={}, seed=0, abstraction_dir=str(train))
    evaluate = tmp_path / "evaluate"
    write_manifest(
        evaluate, stage="evaluate", config={"field": {"_target_": "a.b.MyField"}}, seed=0,
        runs={"full": "x", "candidate": str(candidate), "full_repeat": "y"},
    )  # fmt: skip
    write_json(evaluate / "summary.json", {"max_ks": 0.3, "max_ks_noise_floor": 0.2,
                                          "all_within_noise": False, "speedup_loop": None,
                                          "speed_comparable": False})  # fmt: skip
    out = job_results(evaluate)
    assert out["max_ks_MyField"] == 0.3 and out["max_ks_noise_MyField"] == 0.2
    assert out["within_noise_MyField"] is False
    assert out["speedup_MyField"] is None  # runs not measured comparably: no speed-up
    assert out["brier_psi_1"] == 0.2 and out["switch_bias_phi1"] == 0.25  # its abstraction


# ----------------------------------------------------------------------------------------------
# tiny sweeps through real launchers


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """The directory both sweeps run in: relative data_dir `data` lands here, and the second
    sweep reuses what the first made."""
    return tmp_path_factory.mktemp("sweeps")


def _artefact_manifests(data: Path) -> dict[Path, int]:
    return {
        p: p.stat().st_mtime_ns
        for stage in ("collect", "train", "simulate", "evaluate")
        for p in (data / stage).glob("*/manifest.json")
    }


@pytest.mark.slow
def test_joblib_sweep_of_reproduce(workdir: Path) -> None:
    """2 dt through the joblib launcher (loky processes, 2 at a time), with the default
    relative data_dir and threads chosen by the wrapper; then a rerun reuses it all. (Kernels
    swept beside dt: the submitit test below.)"""
    sweep = workdir / "sweep_joblib"
    args = ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}",
            "dt=0.05,0.1", *TINY]  # fmt: skip
    result = run_script("reproduce.py", *args, cwd=workdir)
    assert result.returncode == 0, result.stderr[-3000:]

    jobs = statuses(sweep)
    assert sorted(jobs) == [0, 1]
    assert all(j["status"] == "ok" for j in jobs.values()), jobs
    assert {j["threads"] for j in jobs.values()} == {max(1, cli.available_cores() // 2)}
    # every job its own reproduce directory, evaluation, abstraction and collection
    reports = [read_json(Path(j["artefact_dir"]) / "manifest.json") for j in jobs.values()]
    assert len({j["artefact_dir"] for j in jobs.values()}) == 2
    assert len({r["evaluations"]["gaussian"] for r in reports}) == 2
    assert len({r["train"] for r in reports}) == 2
    assert len({r["collect"] for r in reports}) == 2
    data = workdir / "data"  # relative data_dir resolved in the launching directory
    assert all(Path(j["artefact_dir"]).is_relative_to(data) for j in jobs.values())

    df = pd.read_csv(sweep / "summary.csv")
    assert len(df) == 2 and (df["status"] == "ok").all()
    assert set(df["dt"]) == {0.05, 0.1}
    assert df["max_ks_gaussian"].between(0, 1).all() and (df["speedup_gaussian"] > 0).all()
    for phi in (0, 1):
        assert df[f"brier_psi_{phi}"].between(0, 1).all()
        assert df[f"brier_baseline_psi_{phi}"].between(0, 1).all()
        # the learned switching probabilities' relative bias where the population lives
        assert df[f"switch_bias_phi{phi}"].notna().all()
    assert (sweep / "summary.png").stat().st_size > 0

    before = _artefact_manifests(data)
    # the same jobs through Hydra's basic launcher (one process, no workers to spawn), on the
    # threads the wrapper gave the joblib jobs: what a job makes does not depend on its launcher
    threads = f"threads={max(1, cli.available_cores() // 2)}"
    rerun = run_script("reproduce.py", "-m", f"hydra.sweep.dir={sweep}_again", threads, *args[4:],
                       cwd=workdir)  # fmt: skip
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert all(j["status"] == "ok" for j in statuses(Path(f"{sweep}_again")).values())
    assert _artefact_manifests(data) == before  # nothing recomputed, nothing new


@pytest.mark.slow
def test_submitit_sweep_survives_a_failing_job(workdir: Path) -> None:
    """Through submitit_local, with hydra.job.chdir=true: the job with an invalid kernel fails,
    the sweep completes, and the summary reports it with its error. (Each dt its own
    collection: the joblib test above.)"""
    sweep = workdir / "sweep_submitit"
    result = run_script(
        "reproduce.py", "-m", "hydra/launcher=submitit_local", f"hydra.sweep.dir={sweep}",
        "hydra.job.chdir=true", "threads=1", "gp.kernel=rbf,bogus", "dt=0.1", *TINY,
        cwd=workdir,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]

    df = pd.read_csv(sweep / "summary.csv")
    assert len(df) == 2
    failed, ok = df[df["gp.kernel"] == "bogus"], df[df["gp.kernel"] == "rbf"]
    assert len(failed) == len(ok) == 1
    assert (failed["status"] == "failed").all() and (failed["error_type"] == "ConfigError").all()
    assert failed["error"].str.contains("unknown kernel 'bogus'").all()
    assert (ok["status"] == "ok").all() and ok["max_ks_gaussian"].notna().all()
    # artefacts stayed in the launching directory although the job ran in its output dir
    assert all(Path(p).is_relative_to(workdir / "data") for p in ok["artefact_dir"])

"""The background worker: jobs in a second process, in order, failures reported, nothing lost;
and reproduce with it gives the report it gives without it."""

from __future__ import annotations

import json
import logging
import operator
import os
import shutil
import subprocess
import sys
import time
import types
from pathlib import Path

import pandas as pd
import pytest

from surrogate.stages import background, reproduce
from surrogate.stages.background import Worker
from surrogate.stages.head_start import wants_worker
from surrogate.stages.occupancy import OCCUPANCY, occupancy
from surrogate.stages.settings import ReproduceSettings, TrainSettings

from .test_stages import TINY


def test_jobs_run_in_order_and_their_logs_come_back(tmp_path: Path, caplog) -> None:
    first, second = tmp_path / "a.txt", tmp_path / "b.txt"
    worker = Worker(threads=1)
    write = worker.submit(first.write_text, "written by the worker")
    move = worker.submit(os.rename, first, second)  # needs the first job done
    hello = worker.submit(logging.getLogger("surrogate.test").info, "hello %s", "there")
    pause = worker.submit(time.sleep, 1.0)
    with caplog.at_level(logging.INFO, logger="surrogate.test"):
        assert worker.result(write) and worker.result(move) and worker.result(pause)
        assert worker.idle()
        assert worker.result(hello)  # re-emitted now, a second after it was logged
    assert second.read_text() == "written by the worker" and not first.exists()
    (record,) = [r for r in caplog.records if r.name == "surrogate.test"]
    assert record.getMessage() == "[background] hello there"
    assert record.created < time.time() - 0.9  # the worker's time, not the re-emission's
    worker.close()


def test_a_failed_job_is_reported_and_the_next_still_runs(tmp_path: Path, caplog) -> None:
    worker = Worker(threads=1)
    bad = worker.submit(int, "not a number")
    unpicklable = worker.submit(operator.call, lambda: None)  # cannot be sent: fails in its turn
    good = worker.submit((tmp_path / "ok").write_text, "ok")
    with caplog.at_level(logging.WARNING, logger="surrogate.stages.background"):
        assert not worker.result(bad)
        assert not worker.result(unpicklable)
        assert worker.result(good)
    assert "ValueError: invalid literal" in caplog.text
    assert "job failed" in caplog.text and (tmp_path / "ok").read_text() == "ok"
    worker.close()


def test_a_dead_worker_fails_its_pending_jobs(tmp_path: Path, caplog) -> None:
    worker = Worker(threads=1)
    dies = worker.submit(os._exit, 3)
    after = worker.submit((tmp_path / "never").write_text, "x")
    with caplog.at_level(logging.WARNING, logger="surrogate.stages.background"):
        assert not worker.result(dies) and not worker.result(after)
    assert "exited with code 3" in caplog.text and not (tmp_path / "never").exists()
    worker.close()


def test_a_result_is_answered_once_and_logged_once(caplog) -> None:
    worker = Worker(threads=1)
    bad = worker.submit(int, "x")
    with caplog.at_level(logging.WARNING, logger="surrogate.stages.background"):
        assert not worker.result(bad) and not worker.result(bad)
    assert caplog.text.count("a background job failed") == 1
    worker.close()


def test_a_job_the_worker_cannot_import_fails_alone(tmp_path: Path) -> None:
    """Picklable here, but its module exists only in this process: the worker reports the
    failed import and runs the next job."""
    module = types.ModuleType("surrogate_only_in_the_parent")

    def job() -> None:
        pass

    job.__module__, job.__qualname__ = module.__name__, "job"
    module.job = job  # type: ignore[attr-defined]
    sys.modules[module.__name__] = module
    try:
        worker = Worker(threads=1)
        lost = worker.submit(module.job)
        after = worker.submit((tmp_path / "after").write_text, "ran")
        assert not worker.result(lost) and worker.result(after)
        assert (tmp_path / "after").read_text() == "ran"
        worker.close()
    finally:
        del sys.modules[module.__name__]


def test_close_reads_what_was_not_asked_for() -> None:
    """A job whose log records exceed the pipe's buffer, never asked for: close() still ends."""
    worker = Worker(threads=1)
    worker.submit(logging.getLogger("surrogate.test").info, "x" * 300_000)
    t0 = time.perf_counter()
    worker.close()
    assert time.perf_counter() - t0 < 60


def _log_a_lot() -> None:
    """A job whose result (its log records) is larger than a pipe's buffer (64 KiB)."""
    logging.getLogger("surrogate.test").info("x" * 300_000)


def _blocked_worker() -> Worker:
    """A worker blocked on sending a large result while the next job, larger than the pipe's
    buffer too, is being sent to it: nobody reads either pipe until the caller does."""
    worker = Worker(threads=1)
    worker.submit(_log_a_lot)
    worker.submit(len, "y" * 1_000_000)
    time.sleep(2.0)  # the first result fills its pipe, the second job fills the other
    return worker


@pytest.mark.timeout(60)
def test_close_reads_results_while_the_last_jobs_are_sent() -> None:
    """close() reads the results while the feeding thread still sends: a result and the next
    job each above the pipe's buffer would otherwise block worker, thread and caller."""
    worker = _blocked_worker()
    try:
        worker.close()
        assert worker._received == 2 and worker._process.poll() == 0  # type: ignore[union-attr]
    finally:
        if worker._process is not None and worker._process.poll() is None:
            worker._process.kill()


@pytest.mark.timeout(60)
def test_cancel_ends_a_worker_blocked_on_its_pipes() -> None:
    worker = _blocked_worker()
    try:
        worker.cancel()
        assert worker._process is not None and worker._process.poll() is not None
        assert not worker._thread.is_alive()
    finally:
        if worker._process is not None and worker._process.poll() is None:
            worker._process.kill()


def test_the_worker_ends_when_its_parent_dies(tmp_path: Path) -> None:
    code = (
        "import os, sys, time\n"
        "from surrogate.stages.background import Worker\n"
        "w = Worker(threads=1)\n"
        "w.submit(time.sleep, 60)\n"
        "while w._process is None: time.sleep(0.05)\n"
        "print(w._process.pid, flush=True)\n"
        "os._exit(0)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, cwd=Path(__file__).resolve().parents[2])  # fmt: skip
    pid = int(out.stdout.split()[0])
    deadline = time.time() + 20
    while time.time() < deadline and _alive(pid):
        time.sleep(0.2)
    assert not _alive(pid)


def _alive(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    if stat.exists():
        return stat.read_text().split(")")[-1].split()[0] != "Z"  # a zombie has ended
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_no_process_means_every_job_fails_cleanly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(background.sys, "executable", "/nonexistent/python")
    worker = Worker(threads=1)
    assert not worker.result(worker.submit(int, "1"))
    assert worker.idle()
    worker.close()


def test_cancel_stops_a_busy_worker() -> None:
    worker = Worker(threads=1)
    worker.submit(time.sleep, 60)
    time.sleep(0.5)
    assert not worker.idle()
    t0 = time.perf_counter()
    worker.cancel()
    assert time.perf_counter() - t0 < 10
    assert worker._process is not None and worker._process.poll() is not None


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc")
def test_the_worker_sizes_its_numba_pool(tmp_path: Path) -> None:
    """Its numba pool is created at its thread count: idle pool threads would spin on the
    parent's cores."""
    worker = Worker(threads=1)
    assert worker.result(worker.submit(shutil.copyfile, "/proc/self/environ", tmp_path / "env"))
    worker.close()
    env = dict(v.split("=", 1) for v in (tmp_path / "env").read_text().split("\0") if "=" in v)
    assert env["NUMBA_NUM_THREADS"] == "1"


def test_the_occupancy_run_is_seeded_and_reused(compose_cfg, caplog) -> None:
    train_only = [o for o in TINY if o.split("=")[0].split(".")[0] in ("collect", "gp")]
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


def test_auto_starts_a_worker_only_with_two_threads() -> None:
    assert not wants_worker("auto", True, 1, "cpu") and wants_worker(True, True, 1, "cpu")
    assert wants_worker("auto", True, 2, "cpu") and not wants_worker(False, True, 2, "cpu")
    assert not wants_worker("auto", True, 2, "cuda")  # two processes would share its memory
    assert not wants_worker(True, False, 2, "cpu")  # batch=false: one process


def _report_tables(out: Path) -> dict[str, pd.DataFrame]:
    manifest = json.loads((out / "manifest.json").read_text())
    dirs = {**manifest["evaluations"], **{f"exact:{k}": v for k, v in manifest["exact"].items()}}
    return {k: pd.read_csv(Path(v) / "comparison.csv") for k, v in dirs.items()}


@pytest.mark.parametrize("broken", [False, True])
def test_reproduce_with_a_worker_gives_the_report_without_one(
    compose_cfg, tmp_path: Path, caplog, monkeypatch: pytest.MonkeyPatch, broken: bool
) -> None:
    """The runs, the diagnostic and every evaluation are the same with the worker as without
    it (the runs bit for bit: each run's numbers do not depend on its batch), and a worker that
    cannot start loses nothing: this process makes everything itself."""
    overrides = [*TINY, "fields=[gaussian,linear,dynamic]", "record_cells=16"]
    alone = compose_cfg("reproduce", [*overrides, "background=false",
                                      f"data_dir={tmp_path / 'alone'}"])  # fmt: skip
    shared = compose_cfg("reproduce", [*overrides, "background=true",
                                       f"data_dir={tmp_path / 'shared'}"])  # fmt: skip
    if broken:
        monkeypatch.setattr(background.sys, "executable", "/nonexistent/python")
    with caplog.at_level(logging.INFO):
        out = reproduce.run(shared)
    assert "in a background process" in caplog.text
    assert ("a background job failed" in caplog.text) == broken
    if not broken:
        assert "[background] full simulation" in caplog.text
        assert "[background] evaluate dynamic (abstract)" in caplog.text
    reference = reproduce.run(alone)
    report = (out / "report.md").read_text()  # the exact chain: adapted cells, not a bound
    assert "The exact lumped psi (cells adapted to their current input)" in report
    assert "best two-state" not in report and "best any" not in report
    tables, expected = _report_tables(out), _report_tables(reference)
    assert tables.keys() == expected.keys() and len(tables) == 6
    for name, table in tables.items():
        pd.testing.assert_frame_equal(table, expected[name], obj=name)
    settings = ReproduceSettings.from_config(shared)
    for run in settings.runs():
        mine = run.directory / "observables.parquet"
        theirs = Path(str(mine).replace(str(tmp_path / "shared"), str(tmp_path / "alone")))
        pd.testing.assert_frame_equal(pd.read_parquet(mine), pd.read_parquet(theirs))
    metrics = [json.loads((Path(d) / "train_metrics.json").read_text())["diagnostic"]
               for d in (json.loads((o / "manifest.json").read_text())["train"]
                         for o in (out, reference))]  # fmt: skip
    assert metrics[0]["phi0"] == metrics[1]["phi0"] and metrics[0]["phi1"] == metrics[1]["phi1"]


def test_the_script_gives_its_worker_a_head_start(tmp_path: Path) -> None:
    """``scripts/reproduce.py`` starts its worker on the composed config before it imports
    torch: the worker collects (or waits for this process's collection) and makes the runs
    that need no abstraction; the report's tables are those of a run without a worker."""
    root = Path(__file__).resolve().parents[2]
    overrides = [*TINY, "fields=[gaussian,linear]", "record_cells=16", "progress=false"]
    out = {}
    for setting in ("true", "false"):
        data = tmp_path / setting
        result = subprocess.run(
            [sys.executable, str(root / "scripts" / "reproduce.py"), *overrides,
             f"background={setting}", f"data_dir={data}", f"hydra.run.dir={data}/hydra"],
            cwd=root, capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr[-3000:]
        out[setting] = (data, result.stderr + result.stdout)
    log = out["true"][1]
    assert "in a background process (" in log and "): the collection, then" in log
    assert "[background] full simulation" in log and "background worker done" in log
    assert "background" not in out["false"][1].replace("background=false", "")
    (report,) = (out["true"][0] / "reproduce").glob("*/manifest.json")
    (reference,) = (out["false"][0] / "reproduce").glob("*/manifest.json")
    tables, expected = _report_tables(report.parent), _report_tables(reference.parent)
    assert tables.keys() == expected.keys() and len(tables) == 4
    for name, table in tables.items():
        pd.testing.assert_frame_equal(table, expected[name], obj=name)


def test_a_job_holding_a_tensor_runs_in_the_worker(tmp_path: Path) -> None:
    """Jobs go over the pipe as plain pickles: torch's multiprocessing reductions (shared
    memory, an authenticated resource sharer) would fail in a worker that is not a
    multiprocessing child (AuthenticationError), and the parent would do the job itself."""
    import torch
    import torch.multiprocessing  # registers the sharing reductions

    worker = Worker(threads=1)
    path = tmp_path / "tensor.pt"
    saved = worker.submit(torch.save, torch.arange(5.0), path)
    assert worker.result(saved)
    worker.close()
    torch.testing.assert_close(torch.load(path, weights_only=True), torch.arange(5.0))

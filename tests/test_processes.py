"""Spawned worker processes (surrogate/processes.py)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest


def _double(x: int) -> int:
    return 2 * x


def _threads_and_log(x: int) -> int:
    import torch

    logging.getLogger("surrogate.test_processes").info("worker %d here", x)
    return torch.get_num_threads()


def test_a_pool_runs_on_its_threads_and_logs_through_this_process(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Each worker runs on the threads asked for, and its log records reach this process's
    handlers (pytest's capture here, the job's console and log file in a stage)."""
    from surrogate.processes import spawned_pool

    with caplog.at_level(logging.INFO), spawned_pool(2, threads=1) as pool:
        assert list(pool.map(_double, [1, 2, 3])) == [2, 4, 6]
        assert set(pool.map(_threads_and_log, [7, 8])) == {1}
    assert {"worker 7 here", "worker 8 here"} <= {r.getMessage() for r in caplog.records}


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="prctl: Linux")
def test_a_fitting_process_ends_when_its_job_is_killed(tmp_path: Path) -> None:
    """A job killed outright (SIGKILL: no pool shutdown) takes its fitting processes with it:
    an orphaned worker kept a fit running for minutes after its job was gone."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "job.py"
    script.write_text(
        "import logging, multiprocessing, os, sys, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from surrogate.processes import worker_start\n"
        "if __name__ == '__main__':\n"
        "    ctx = multiprocessing.get_context('spawn')\n"
        "    pool = ProcessPoolExecutor(1, mp_context=ctx, initializer=worker_start,\n"
        "                               initargs=(ctx.Queue(), logging.INFO, os.getpid()))\n"
        "    print(pool.submit(os.getpid).result(), flush=True)\n"
        "    pool.submit(time.sleep, 600)\n"
        "    time.sleep(600)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    job = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                           env=env)  # fmt: skip
    try:
        worker = int(job.stdout.readline())  # type: ignore[union-attr]
        os.kill(job.pid, signal.SIGKILL)
        job.wait(10)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                os.kill(worker, 0)  # still there (or a zombie not yet reaped by init)
                with open(f"/proc/{worker}/stat") as stat:
                    if stat.read().split(") ")[1].startswith("Z"):
                        break
            except (ProcessLookupError, FileNotFoundError):
                break
            time.sleep(0.2)
        else:
            os.kill(worker, signal.SIGKILL)
            pytest.fail("the worker outlived its killed job by 20 s")
    finally:
        job.kill()

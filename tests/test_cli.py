"""The scripts' exit: fast where nothing is left to wait for, normal where a thread still runs."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path


def _run(body: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    code = textwrap.dedent(f"""
        import atexit, pathlib, sys, threading, time
        from surrogate.cli import exit_when_done
        marker = pathlib.Path({str(tmp_path / "exit_handler_ran")!r})
        atexit.register(marker.write_text, "yes")
        sys.stdout.write("unflushed output")
    """) + textwrap.dedent(body)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)  # fmt: skip


def test_exit_when_done_runs_exit_handlers_and_flushes(tmp_path: Path) -> None:
    proc = _run("exit_when_done(3)\nprint('not reached')\n", tmp_path)
    assert proc.returncode == 3
    assert proc.stdout == "unflushed output"
    assert (tmp_path / "exit_handler_ran").read_text() == "yes"


def test_exit_when_done_waits_for_a_live_thread(tmp_path: Path) -> None:
    """A non-daemon thread (e.g. a joblib launcher's manager) is left to the normal exit,
    which lets it finish first."""
    proc = _run(
        """
        def work():
            time.sleep(0.5)
            print(" thread finished", flush=True)
        threading.Thread(target=work).start()
        exit_when_done(4)
        """,
        tmp_path,
    )
    assert proc.returncode == 4
    assert proc.stdout == "unflushed output thread finished\n"
    assert (tmp_path / "exit_handler_ran").read_text() == "yes"

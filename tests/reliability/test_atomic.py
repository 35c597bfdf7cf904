"""Atomic writes: a stage killed at any moment leaves the previous complete artefact or none."""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest

from surrogate.config import CONF_DIR
from surrogate.errors import ArtefactError
from surrogate.evaluate.statistics import load_run
from surrogate.io import (
    LOCK,
    MANIFEST,
    artefact_lock,
    clean_stale_tmp,
    read_json,
    read_manifest,
    write_atomic,
    write_csv,
    write_json,
)
from surrogate.stages import collect
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.collect import TRANSITIONS

from .conftest import COLLECT, collect_dir, compose_in, simulate_dir

REPO = CONF_DIR.parent
PACKAGE = REPO / "surrogate"
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}


def _tmp_files(directory: Path) -> list[Path]:
    return sorted(directory.glob(".*.tmp")) if directory.exists() else []


def _wait_for(predicate, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Poll until ``predicate()``; fail if the process ends first or time runs out."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if proc.poll() is not None:
            out = proc.stdout.read() if proc.stdout else ""
            pytest.fail(f"process ended (rc {proc.returncode}) before the kill point:\n{out}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("timed out waiting for the kill point")
        time.sleep(0.005)


def _kill(proc: subprocess.Popen, sig: signal.Signals) -> int:
    proc.send_signal(sig)
    try:
        return proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()


# ---------------------------------------------------------------------------------------------
# the write primitive


def test_a_failing_writer_keeps_the_previous_file(tmp_path: Path) -> None:
    path = write_json(tmp_path / "a.json", {"version": 1})

    def half_then_fail(tmp: Path) -> None:
        tmp.write_text('{"version": 2, "half')
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        write_atomic(path, half_then_fail)
    assert read_json(path) == {"version": 1}
    assert not _tmp_files(tmp_path)


def test_artefacts_get_ordinary_permissions(tmp_path: Path) -> None:
    umask = os.umask(0)
    os.umask(umask)
    path = write_csv(tmp_path / "t.csv", pd.DataFrame({"a": [1]}))
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600


def test_sigkill_during_a_write_leaves_the_previous_file(tmp_path: Path) -> None:
    """A process killed halfway through writing leaves the old content and a .tmp no loader reads;
    the next stage to lock the directory removes the leftover."""
    path = write_json(tmp_path / "a.json", {"version": 1})
    ready = tmp_path / "ready"
    script = textwrap.dedent(f"""
        import time
        from pathlib import Path
        from surrogate.io import write_atomic

        def slow(tmp):
            tmp.write_text('{{"version": 2, "hal')
            Path({str(ready)!r}).touch()
            time.sleep(60)

        write_atomic({str(path)!r}, slow)
    """)
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        env=ENV,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    _wait_for(ready.exists, proc)
    assert _kill(proc, signal.SIGKILL) == -signal.SIGKILL
    assert read_json(path) == {"version": 1}
    leftovers = _tmp_files(tmp_path)
    assert [p.name.startswith(".a.json.") for p in leftovers] == [True]
    with artefact_lock(tmp_path):
        assert not _tmp_files(tmp_path)
    assert read_json(path) == {"version": 1}


def test_the_lock_excludes_other_processes_and_dies_with_its_holder(tmp_path: Path) -> None:
    probe = textwrap.dedent(f"""
        import fcntl, sys
        with open({str(tmp_path / LOCK)!r}, "a+b") as fh:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                sys.exit(3)
    """)
    with artefact_lock(tmp_path):
        assert subprocess.run([sys.executable, "-c", probe], timeout=60).returncode == 3
    assert subprocess.run([sys.executable, "-c", probe], timeout=60).returncode == 0


def test_clean_stale_tmp_removes_only_temporaries(tmp_path: Path) -> None:
    for name in (
        ".observables.parquet.abc123.tmp",
        ".manifest.json.x.tmp",
        "keep.parquet",
        "b.tmp",
    ):
        (tmp_path / name).write_text("x")
    removed = clean_stale_tmp(tmp_path)
    assert sorted(p.name for p in removed) == [
        ".manifest.json.x.tmp",
        ".observables.parquet.abc123.tmp",
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.tmp", "keep.parquet"]


def test_every_file_write_in_the_package_goes_through_io() -> None:
    """Audit: writing methods (``df.to_csv``, ``fig.savefig``, ``torch.save``, ``p.write_text``,
    ``open(..., "w")``, ...) are only called in surrogate/io.py; the streaming recorders write a
    temporary Parquet file and rename it. (Functions imported from surrogate.io are fine.)"""
    methods = {
        "to_parquet",
        "to_csv",
        "to_json",
        "to_pickle",
        "to_hdf",
        "savefig",
        "save",
        "write_text",
        "write_bytes",
        "dump",
        "write_table",
        "ParquetWriter",
        "touch",
    }
    allowed = {"surrogate/io.py", "surrogate/simulate/recorders.py"}
    offences = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = str(path.relative_to(REPO))
        if rel in allowed:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call):
                continue
            func = node.func
            if isinstance(func, ast.Attribute) and func.attr in methods:
                offences.append(f"{rel}:{node.lineno}: .{func.attr}(...)")
            if (
                isinstance(func, ast.Name | ast.Attribute)
                and getattr(func, "id", getattr(func, "attr", "")) == "open"
            ):
                mode = node.args[1] if len(node.args) > 1 else None
                mode = next((k.value for k in node.keywords if k.arg == "mode"), mode)
                if isinstance(mode, ast.Constant) and set(str(mode.value)) & set("wax+"):
                    offences.append(f"{rel}:{node.lineno}: open(..., {mode.value!r})")
    assert not offences, "direct writes outside surrogate.io:\n" + "\n".join(offences)


# ---------------------------------------------------------------------------------------------
# whole stages killed mid-run


# a time loop long enough to be killed 0.3 s into it on a fast box (1.5 s on one core of the
# 2026-12-02 box, where 200 cells x 200 s had shrunk to 0.19 s and ended before the kill),
# short enough to rerun (~20 s, estimated, on the slowest box measured here, where the old
# 200 cells x 200 s took ~2 s)
SIM_KILL = ["n_cells=1000", "t_end=400.0", "equilibration_time=1.0"]


def _start_simulate(data_dir: Path, extra: list[str]) -> subprocess.Popen:
    args = [f"data_dir={data_dir}", "progress=false", "threads=1", *SIM_KILL, *extra]
    return subprocess.Popen(
        [sys.executable, "scripts/simulate.py", *args],
        cwd=REPO,
        env=ENV,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        # a shell's background job ignores SIGINT, and its children inherit that: the test sends
        # SIGINT, so the child takes the default handling back
        preexec_fn=_default_sigint,
    )


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _assert_nothing_readable(directory: Path) -> None:
    assert not (directory / MANIFEST).exists()
    for name in ("observables.parquet", "durations.parquet"):
        assert not (directory / name).exists()
    with pytest.raises(ArtefactError):  # MissingArtefactError: the run reads as absent
        load_run(directory)


@pytest.mark.parametrize(
    ("sig", "delay"),
    [(signal.SIGKILL, 0.0), (signal.SIGKILL, 0.3), (signal.SIGINT, 0.3)],
    ids=["SIGKILL-at-start", "SIGKILL-in-loop", "SIGINT-in-loop"],
)
def test_simulate_killed_mid_run_leaves_no_partial_artefact(
    tmp_path: Path, sig: signal.Signals, delay: float
) -> None:
    data = tmp_path / "data"
    seed = [f"seed={int(sig) * 10 + int(delay * 10)}"]
    cfg = compose_in(data, "simulate", SIM_KILL + seed)
    target = simulate_dir(cfg)
    proc = _start_simulate(data, seed)
    # the recorders open their temporary tables as the run starts; the time loop follows
    _wait_for(lambda: bool(_tmp_files(target)), proc)
    time.sleep(delay)
    rc = _kill(proc, sig)
    assert rc != 0, "the run finished before it was killed; make it longer"
    _assert_nothing_readable(target)
    leftovers = _tmp_files(target)
    if sig == signal.SIGINT:
        assert not leftovers  # KeyboardInterrupt: the recorders abort and remove their files
    assert all(p.name.startswith(".") and p.suffix == ".tmp" for p in leftovers)
    if delay == 0.0:
        return  # the rerun is the same as after the in-loop kill
    # a rerun ignores the leftovers and completes cleanly
    out = simulate_stage.run(cfg)
    assert out == target
    run = load_run(out)
    assert read_manifest(out)["seed"] == cfg.seed
    assert run.observables["cell"].nunique() == 1000
    assert run.record_times[-1] == pytest.approx(400.0)
    clean_stale_tmp(out)  # what a locking stage does on its next run
    assert not _tmp_files(out)


def test_collect_killed_mid_run_leaves_nothing_and_the_rerun_cleans_up(tmp_path: Path) -> None:
    data = tmp_path / "data"
    cfg = compose_in(data, "collect", ["seed=3"])
    target = collect_dir(cfg)
    args = [f"data_dir={data}", "progress=false", "threads=1", "seed=3", *COLLECT]
    proc = subprocess.Popen(
        [sys.executable, "scripts/collect.py", *args],
        cwd=REPO,
        env=ENV,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    # the stage takes its lock (creating the directory) just before it starts simulating
    _wait_for(lambda: (target / LOCK).exists(), proc)
    assert _kill(proc, signal.SIGKILL) == -signal.SIGKILL
    assert not (target / MANIFEST).exists() and not (target / TRANSITIONS).exists()
    # leftovers of a run killed while writing (planted: the window is too short to hit reliably)
    stale = [target / ".transitions.parquet.k1ll3d.tmp", target / ".manifest.json.k1ll3d.tmp"]
    for p in stale:
        p.write_bytes(b"PAR1 half a table")
    out = collect.run(cfg)
    assert not _tmp_files(out)
    assert len(pd.read_parquet(out / TRANSITIONS)) == 400
    assert read_manifest(out)["stage"] == "collect"


def test_a_failed_rerun_keeps_the_previous_complete_artefact(tiny, copy_data, monkeypatch) -> None:
    """``force`` recomputes; if that fails before writing, the old artefact is still complete."""
    cfg = tiny("collect")
    before = pd.read_parquet(collect_dir(cfg) / TRANSITIONS)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("surrogate.stages.collect.collect_transitions", interrupted)
    with pytest.raises(KeyboardInterrupt):
        collect.run(cfg, force=True)
    read_manifest(collect_dir(cfg))
    pd.testing.assert_frame_equal(pd.read_parquet(collect_dir(cfg) / TRANSITIONS), before)


def test_publish_syncs_the_directory_after_the_rename(tmp_path: Path, monkeypatch) -> None:
    """The rename that makes an artefact visible survives a crash only once its directory is
    fsynced: publish syncs the file before and the directory after the rename."""
    import os
    import stat

    from surrogate.io import publish

    synced: list[tuple[bool, bool]] = []  # (is a directory, target already renamed)
    real_fsync = os.fsync
    target = tmp_path / "out.json"

    def recording_fsync(fd: int) -> None:
        synced.append((stat.S_ISDIR(os.fstat(fd).st_mode), target.exists()))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    tmp = tmp_path / ".out.json.x.tmp"
    tmp.write_text("{}")
    publish(tmp, target)
    assert synced == [(False, False), (True, True)]

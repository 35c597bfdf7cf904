"""Work that does not need the abstraction, done in a second process while this one trains it.

A report's full-model runs (and the exact-psi chain's, the evaluations and the diagnostic's
occupancy run) depend on the model and the fields only, not on the learned psi, so they need
not wait for collection and training: reproduce hands them to one :class:`Worker` process at its
start and does only the abstraction's share itself. GP training at the paper's size keeps about
one core busy, so on two cores the worker's share costs almost no wall-clock time. While the
worker is busy this process leaves it its threads (idle OpenMP threads spin, and two busy
threads on one core slow both).

Results do not depend on this: every run of a batch draws from its own generator, seeded as its
standalone run, and the per-cell kernel and eager CPU steps are elementwise per cell, so a run
is the same bit for bit whichever runs share its batch (tested). Runs compiled with
``torch.compile`` round differently per batch shape: reproduce keeps those in one batch (its
worker then only collects). Nothing is lost when the worker fails: a job that did not finish wrote
nothing (every stage writes atomically, manifest last), and its caller makes what is missing.

Jobs travel over a private pipe to a child process of this one (multiprocessing's
``Connection``), never through files; the child is a fresh ``python -c`` that imports only what
its jobs need (a spawned multiprocessing child would first import this process's ``__main__``).
This module imports nothing heavy, so a script can start its worker before it imports torch.
"""

from __future__ import annotations

import logging
import os
import pickle
import queue
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

log = logging.getLogger(__name__)


#: seconds between checks of the results pipe while close() waits for the feeding thread
POLL_S = 0.05


def worker_threads(threads: int) -> int:
    """A worker's share of a process's ``threads`` (half, at least one)."""
    return max(1, int(threads) // 2)


class Worker:
    """A second Python process that runs jobs in the order they were submitted.

    A job is a module-level function (the worker imports it by name) with picklable arguments
    (settings objects, not open resources) that writes artefacts as every stage does; its
    return value is not sent back. :meth:`result` waits for a job and re-emits the log records
    it made here, with their times.

    Args:
        threads: the worker's torch and numba threads (its numba pool is created that size:
            idle pool threads would spin on this process's cores).
        after: called in a helper thread before the process starts (e.g. waiting for a
            background compilation that its jobs would otherwise repeat); jobs submitted
            meanwhile are queued.
        nice: added to the worker's niceness (e.g. 10: it yields to this process).

    Example:
        >>> worker = Worker(threads=1)  # doctest: +SKIP
        >>> ticket = worker.submit(simulate_together, runs)
        >>> ...  # this process trains meanwhile
        >>> worker.result(ticket)  # True, or False (logged) when the job failed
        >>> worker.close()
    """

    def __init__(
        self, threads: int, after: Callable[[], object] | None = None, nice: int = 0
    ) -> None:
        self.threads = max(1, int(threads))
        self.nice = int(nice)
        self._jobs: queue.Queue[tuple[Callable[..., object], tuple[Any, ...]] | None]
        self._jobs = queue.Queue()
        self._submitted = 0
        self._results: dict[int, tuple[str, Any]] = {}
        self._reported: set[int] = set()
        self._received = 0
        self._process: subprocess.Popen[bytes] | None = None
        self._receive: Connection | None = None
        self._send: Connection | None = None
        self._error: str | None = None
        self._started = threading.Event()
        self._cancelled = threading.Event()
        self._t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._feed, args=(after,), daemon=True)
        self._thread.start()

    def submit(self, job: Callable[..., object], *args: Any) -> int:
        """Queue ``job(*args)``; returns its ticket for :meth:`result`."""
        self._jobs.put((job, args))
        self._submitted += 1
        return self._submitted - 1

    def idle(self) -> bool:
        """Whether every submitted job has finished (without waiting)."""
        if not self._started.is_set() or self._receive is None:
            return self._error is not None
        while self._received < self._submitted and self._poll():
            self._read_one()
        return self._received >= self._submitted

    def result(self, ticket: int) -> bool:
        """Wait for job ``ticket``, re-log its records here; return whether it succeeded (a
        warning says why not; its caller makes what is missing)."""
        self._started.wait()
        while self._received <= ticket and self._receive is not None and self._error is None:
            self._read_one()
        status, payload = self._results.get(ticket, ("error", self._error))
        if ticket in self._reported:  # asked again: the same answer, logged once
            return status == "ok"
        self._reported.add(ticket)
        if status != "ok":
            message, trace = payload if isinstance(payload, tuple) else (payload, "")
            log.warning("a background job failed (%s); its work is done here", message)
            log.debug("the background job's traceback:\n%s", trace)
            return False
        for fields in payload:  # with the worker's times: the log says when it happened
            logger = logging.getLogger(fields["name"])
            if logger.isEnabledFor(fields["levelno"]):
                fields = {**fields, "msg": f"[background] {fields['msg']}", "args": None}
                logger.handle(logging.makeLogRecord(fields))
        return True

    def close(self) -> None:
        """Let the worker finish its jobs and end; wait for it, reading its results while the
        last jobs are still being sent: a result and the next job each larger than a pipe's
        buffer would otherwise block the worker, the feeding thread and this process on one
        another."""
        self._jobs.put(None)
        self._started.wait()  # bounded: waits for `after` at most
        while self._thread.is_alive():
            if (
                self._receive is not None
                and self._received < self._submitted
                and self._poll(POLL_S)
            ):
                self._read_one()
            else:
                self._thread.join(POLL_S)
        while self._receive is not None and self._received < self._submitted:
            self._read_one()
        if self._process is not None:
            self._process.wait()
        if self._receive is not None:
            self._receive.close()
        log.info("background worker done (%.1f s after it was started)",
                 time.perf_counter() - self._t0)  # fmt: skip

    def cancel(self) -> None:
        """Stop the worker now (this process failed; its work is not needed): a job it did
        not finish wrote nothing. The process ends first: the feeding thread may be blocked
        sending it a job while it is blocked sending a result nobody reads."""
        self._cancelled.set()
        self._jobs.put(None)
        self._started.wait()  # bounded: waits for `after` at most
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            self._process.wait()
        self._thread.join()  # a send to the ended process fails at once
        if self._receive is not None:
            self._receive.close()

    def _poll(self, timeout: float = 0.0) -> bool:
        assert self._receive is not None
        try:
            return self._receive.poll(timeout)
        except (OSError, EOFError):
            return True  # _read_one records the failure

    def _read_one(self) -> None:
        assert self._receive is not None
        try:
            self._results[self._received] = self._receive.recv()
        except (OSError, EOFError):
            code = self._process.wait() if self._process is not None else None
            self._error = f"the worker exited with code {code}"
            for t in range(self._received, self._submitted):
                self._results[t] = ("error", self._error)
            self._received = self._submitted
            return
        self._received += 1

    def _feed(self, after: Callable[[], object] | None) -> None:
        try:
            self._start_process(after)
        except BaseException as exc:  # no second process: every job is done by the caller
            self._error = f"{type(exc).__name__}: {exc}"
            return
        finally:
            self._started.set()
        send = self._send
        assert send is not None
        try:
            while (job := self._jobs.get()) is not None and not self._cancelled.is_set():
                try:
                    data = _dumps(job)
                except Exception as exc:  # e.g. unpicklable: the job fails in its turn
                    data = _dumps((_fail, (f"{type(exc).__name__}: {exc}",)))
                send.send_bytes(data)
            send.send_bytes(
                _dumps(None)
            )  # stop (not only EOF: another process may hold the pipe's end)
        except (OSError, EOFError):
            pass  # the worker died: result() reports it
        finally:
            send.close()

    def _start_process(self, after: Callable[[], object] | None) -> None:
        if after is not None:
            after()
        jobs_r, jobs_w = os.pipe()
        results_r, results_w = os.pipe()
        try:
            code = (
                f"import os; os.nice({self.nice}); from surrogate.stages.background import serve; "
                f"serve({jobs_r}, {results_w}, {os.getpid()})"
            )
            env = {**os.environ, "NUMBA_NUM_THREADS": str(self.threads)}
            self._process = subprocess.Popen(
                [sys.executable, "-c", code, str(self.threads)],
                pass_fds=(jobs_r, results_w),
                env=env,
            )
        except BaseException:
            os.close(jobs_w)
            os.close(results_r)
            raise
        finally:
            os.close(jobs_r)
            os.close(results_w)
        self._receive = Connection(results_r)
        self._send = Connection(jobs_w)


def _fail(message: str) -> None:
    raise RuntimeError(message)


def _dumps(obj: object) -> bytes:
    """A plain pickle: ``Connection.send`` would use multiprocessing's reductions, with which
    torch sends tensors through shared memory and an authenticated resource sharer that a worker
    started with ``subprocess`` cannot reach (AuthenticationError); plain pickles copy them."""
    return pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)


def serve(jobs_fd: int, results_fd: int, parent: int | None = None) -> None:
    """The worker's loop (``python -c``; the thread count is its first argument): run each job
    received on ``jobs_fd`` and send ("ok", log records) or ("error", (message, traceback))
    back, until a stop (None) or the end of the pipe. It ends itself if ``parent`` dies
    (checked every 0.5 s): a killed reproduce leaves no worker behind."""
    import torch

    torch.set_num_threads(max(1, int(sys.argv[1])))
    if parent is not None:
        threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()
    jobs, results = Connection(jobs_fd), Connection(results_fd)
    while True:
        try:
            item = pickle.loads(jobs.recv_bytes())
        except EOFError:
            break
        except Exception as exc:  # a job it cannot unpickle fails alone (the bytes were read)
            results.send(("error", (f"{type(exc).__name__}: {exc}", traceback.format_exc())))
            continue
        if item is None:
            break
        job, args = item
        try:
            results.send(("ok", run_logged(job, args)))
        except Exception as exc:  # reported to the parent, which does the job itself
            results.send(("error", (f"{type(exc).__name__}: {exc}", traceback.format_exc())))
    results.close()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)  # every job is done and reported: skip the interpreter's teardown (~1 s)


def _exit_with(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def run_logged(job: Callable[..., object], args: tuple[Any, ...]) -> list[dict[str, Any]]:
    """``job(*args)``; returns the log records it emitted (name, level, message, time) for the
    parent process to re-emit."""
    records: list[dict[str, Any]] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append({"name": record.name, "levelno": record.levelno,
                            "levelname": record.levelname, "msg": record.getMessage(),
                            "created": record.created, "msecs": record.msecs})  # fmt: skip

    handler = Collect(logging.INFO)
    root = logging.getLogger()
    root.addHandler(handler)
    level = root.level
    root.setLevel(logging.INFO)
    try:
        job(*args)
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
    return records


__all__ = ["Worker", "run_logged", "serve", "worker_threads"]

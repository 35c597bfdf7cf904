"""Spawned worker processes for independent fits: each on a fixed number of torch threads, its
log records printed by the job's own handlers, and ended when the job's process dies.

Spawned, not forked: a fork copies torch's (and numba's) thread pools in whatever state they
are, and a forked OpenMP runtime can hang. A worker pays its imports once (torch and gpytorch,
2-4 s), so a pool pays off for fits of tens of seconds and more.

Example:
    >>> with spawned_pool(2, threads=1) as pool:
    ...     sizes = list(pool.map(len, ["ab", "cde"]))
"""

from __future__ import annotations

import contextlib
import logging
import logging.handlers
import multiprocessing
import os
import signal
import sys
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

__all__ = ["PR_SET_PDEATHSIG", "RecordQueue", "end_with_parent", "spawned_pool", "worker_start"]

#: prctl's option that sends the calling process a signal when its parent dies (linux/prctl.h)
PR_SET_PDEATHSIG = 1


class RecordQueue:
    """The workers' log records on their way to the parent: a ``SimpleQueue`` with the methods
    ``QueueHandler`` and ``QueueListener`` call. Its put writes the record into the pipe before
    it returns; a ``multiprocessing.Queue`` hands it to a feeder thread, which could still hold
    a worker's last record when that task's result had arrived and the pool's listener stopped
    (the record lost: seen as a flaky test)."""

    def __init__(self, context: Any) -> None:
        self._queue = context.SimpleQueue()

    def put_nowait(self, item: Any) -> None:
        """Write ``item`` into the pipe (blocking only while another writer holds it)."""
        self._queue.put(item)

    put = put_nowait

    def get(self, block: bool = True) -> Any:
        """The next item (waits for one: the listener always blocks)."""
        return self._queue.get()


@contextlib.contextmanager
def spawned_pool(workers: int, threads: int | None = None) -> Iterator[ProcessPoolExecutor]:
    """``workers`` spawned processes (each on ``threads`` torch threads where given), whose log
    records go through this process's handlers. On leaving, queued tasks are cancelled and the
    processes let go without waiting for their interpreters to close (a task still running ends
    with its result unread; a worker whose job dies ends too: :func:`end_with_parent`)."""
    context = multiprocessing.get_context("spawn")
    records = RecordQueue(context)
    listener = logging.handlers.QueueListener(records, *logging.getLogger().handlers,
                                              respect_handler_level=True)  # fmt: skip
    listener.start()
    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=worker_start,
                               initargs=(records, logging.getLogger().level, os.getpid(),
                                         threads))  # fmt: skip
    try:
        yield pool
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
        listener.stop()


def worker_start(
    records: RecordQueue, level: int, parent: int | None = None, threads: int | None = None
) -> None:
    """A worker process: its log records to ``records`` (the parent's handlers print them), its
    torch threads ``threads`` (where given); on Linux it ends with the job's process ``parent``
    (:func:`end_with_parent`)."""
    if parent is not None:
        end_with_parent(parent)
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    root = logging.getLogger()
    root.handlers[:] = [logging.handlers.QueueHandler(records)]
    root.setLevel(level)


def end_with_parent(parent: int) -> None:
    """On Linux, have the kernel send this process SIGTERM when the process that started it
    (pid ``parent``) dies, however it dies: a job killed (not only stopped by Ctrl-C, which
    shuts its pool down) left its fitting processes computing for minutes with no one to read
    their result. Elsewhere nothing (the pool's workers then end at their next task)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):  # no libc prctl: nothing to ask
        return
    if os.getppid() != parent:  # the parent died before the request: end now
        os.kill(os.getpid(), signal.SIGTERM)

"""torch's CPU threads: how idle OpenMP threads wait (set at the package's import), and one
thread for a block of work."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["WAIT_KEYS", "one_thread", "other_runnable", "passive_wait", "wait_policy"]

#: the variables that say how an idle OpenMP thread waits; the runtime (GNU libgomp in torch's
#: pip wheel, which its oneMKL uses too; numba's ``omp`` layer) reads them once, when it loads
WAIT_KEYS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def other_runnable(samples: int = 3, interval: float = 0.004) -> int | None:
    """Processes runnable beside this one now: the fewest of ``samples`` reads of Linux's
    ``procs_running`` (``/proc/stat``) ``interval`` s apart, less this one (the fewest, so a
    passing kernel thread is not counted; a job that keeps a core busy is in every read). None
    where the count cannot be read (not Linux)."""
    counts = []
    for k in range(samples):
        try:
            with open("/proc/stat") as stat:
                line = next(x for x in stat if x.startswith("procs_running"))
        except (OSError, StopIteration):
            return None
        counts.append(int(line.split()[1]))
        if k + 1 < samples:
            time.sleep(interval)
    return max(0, min(counts) - 1)


def wait_policy(others: int | None, cores: int) -> str | None:
    """``"PASSIVE"`` where other runnable processes leave fewer than two of ``cores`` free
    (``others >= cores - 1``), else None (libgomp's default, a spin before sleeping).

    Measured on a 2-core box (docs/performance.md, "On a busy machine"): the fit's steps on 2
    threads beside two busy processes took 19x longer spinning than sleeping; on the quiet box
    sleeping took 2.4x longer than spinning (a sleeping thread wakes late for each of the many
    small parallel regions), and the quick start's training doubled. So each is kept where it
    wins, as the machine is when the package is imported."""
    if others is None:
        return None
    return "PASSIVE" if others >= cores - 1 else None


def passive_wait(others: int | None = None) -> bool:
    """Let idle OpenMP threads sleep at once (``OMP_WAIT_POLICY=PASSIVE``) where the machine is
    busy now (:func:`wait_policy` of ``others``, default :func:`other_runnable`) and the
    environment says nothing of how they wait (neither of :data:`WAIT_KEYS` set).

    libgomp's default spins 300,000 times first: on a machine busy with other work the spinning
    threads take the cores the working ones wait for (the GP fit's steps on 2 threads 4-15x
    slower than on 1 beside two busy processes); on a quiet one the spin is what makes 2
    threads fast. Called at :mod:`surrogate`'s import, so the scripts (which import it before
    torch) and the processes they start inherit it; work that starts beside a run already going
    is not seen. ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` in the environment keeps the
    user's choice.

    Returns:
        Whether the runtime will read the policy: torch not yet imported in this process.
    """
    if not any(key in os.environ for key in WAIT_KEYS):
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
        policy = wait_policy(other_runnable() if others is None else others, cores)
        if policy is not None:
            os.environ["OMP_WAIT_POLICY"] = policy
    return "torch" not in sys.modules


# at the package's import (its __init__ imports this module first), before torch loads libgomp
passive_wait()


@contextmanager
def one_thread(active: bool) -> Iterator[None]:
    """torch on one CPU thread inside where ``active`` (and more are set), the count restored
    after: for work a second thread slows (small transforms) or breaks (large batched LU on
    oneMKL, :func:`surrogate.ctmc.lumped.stationary_distribution`).

    Example:
        >>> with one_thread(True):
        ...     torch.get_num_threads()
        1
    """
    import torch  # here: this module is imported by the package's __init__, before torch

    threads = torch.get_num_threads()
    if not active or threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)

"""torch's CPU threads: how idle OpenMP threads wait (set at the package's import), and one
thread for a block of work."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["WAIT_KEYS", "one_thread", "passive_wait"]

#: the variables that say how an idle OpenMP thread waits; the runtime (GNU libgomp in torch's
#: pip wheel, which its oneMKL uses too; numba's ``omp`` layer) reads them once, when it loads
WAIT_KEYS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def passive_wait() -> bool:
    """Let idle OpenMP threads sleep at once (``OMP_WAIT_POLICY=PASSIVE``) where the
    environment says nothing of how they wait (neither of :data:`WAIT_KEYS` set).

    libgomp's default spins 300,000 times first: on a machine busy with other work the spinning
    threads take the cores the working ones wait for (the GP fit's steps on 2 threads 4-15x
    slower than on 1 beside two busy processes; docs/performance.md, "On a busy machine").
    Called at :mod:`surrogate`'s import, so the scripts (which import it before torch) and the
    processes they start inherit it. ``OMP_WAIT_POLICY=ACTIVE`` or ``GOMP_SPINCOUNT`` in the
    environment keeps the user's choice.

    Returns:
        Whether the runtime will read the policy: torch not yet imported in this process.
    """
    if not any(key in os.environ for key in WAIT_KEYS):
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
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

"""torch's CPU thread count, lowered to one for a block of work and restored after."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["one_thread"]


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
    threads = torch.get_num_threads()
    if not active or threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)

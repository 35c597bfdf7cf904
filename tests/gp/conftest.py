"""Fixtures shared by the GP tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """One torch intra-op thread for a module's tests: the 2 cores are shared with other test
    processes, and OpenMP oversubscription makes small-matrix fits ~10x slower under
    contention (small fits gain nothing from more threads). Use with
    ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)

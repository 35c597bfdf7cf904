"""The background precompile: a process started at a stage's start, awaited by the simulator."""

from __future__ import annotations

import pytest

from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import precompile
from surrogate.simulate.precompile import (
    kernel_wanted,
    precompile_in_background,
    wait_for_precompile,
)


def test_kernel_wanted_follows_the_backend_rule() -> None:
    assert kernel_wanted("numba", False) and kernel_wanted("numba", True)
    assert kernel_wanted("auto", False) and not kernel_wanted("auto", True)
    assert not kernel_wanted("torch", False)


def test_a_background_precompile_runs_once_and_is_awaited(monkeypatch: pytest.MonkeyPatch) -> None:
    """The target runs in a separate process, a second request while it is in flight starts
    nothing, and waiting clears it."""
    model = EcoliModel()
    monkeypatch.setattr(type(model), "kernel_precompiler", lambda self: "pathlib:Path.home")
    monkeypatch.setattr(precompile, "_running", {})
    assert precompile_in_background(model)
    assert not precompile_in_background(model)  # in flight already
    assert not precompile_in_background(model, device="cuda")  # the kernel runs on the CPU
    wait_for_precompile()
    assert precompile._running == {}
    assert wait_for_precompile() < 0.1  # nothing left to wait for
    # a failing target is harmless: the first call compiles instead
    monkeypatch.setattr(type(model), "kernel_precompiler", lambda self: "no_such_module:f")
    assert precompile_in_background(model)
    wait_for_precompile()
    assert precompile._running == {}


def test_nothing_is_started_when_the_kernel_is_cached(monkeypatch: pytest.MonkeyPatch) -> None:
    from surrogate.models.ecoli import kernel

    kernel.precompile()  # compiled (or loaded) here, so numba's cache holds it
    assert kernel.is_compiled_on_disk()
    assert EcoliModel().kernel_precompiler() is None
    monkeypatch.setattr(precompile, "_running", {})
    assert not precompile_in_background(EcoliModel())

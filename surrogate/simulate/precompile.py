"""Compile a model's per-cell kernel in a background process while a stage does other work.

numba compiles the E. coli kernel once per machine (~4.5 s, then its on-disk cache serves every
process). A stage that will simulate starts that compilation in a separate process at its
start, so it overlaps collection and GP training instead of adding to them; the simulator
waits for it before it first calls a kernel (:func:`wait_for_precompile`). If the background
process fails or is slow, nothing is lost: the first call compiles (or loads) as it would have.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import time

import torch

from surrogate.models.base import Model

log = logging.getLogger(__name__)

#: precompile processes in flight, by target ("module:function")
_running: dict[str, subprocess.Popen[bytes]] = {}


def precompile_in_background(model: Model, device: str | torch.device = "cpu") -> bool:
    """Start compiling ``model``'s per-cell kernel in a background process (CPU only: the
    kernel runs there); return whether one was started (False: no kernel, cached already, or
    one is in flight)."""
    if torch.device(device).type != "cpu":
        return False
    target = model.kernel_precompiler()
    if target is None or target in _running:
        return False
    code = "import os; os.nice(19); " + precompiler_code(target)
    try:
        _running[target] = subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
    except OSError as exc:  # no process to spare: the first call compiles instead
        log.debug("no background precompile (%s)", exc)
        return False
    log.info("compiling the per-cell kernel in the background (once per machine)")
    return True


def precompiler_code(target: str) -> str:
    """Python source for a fresh process (``python -c``) that imports ``target``'s module and
    calls it (``"module:function"`` from :meth:`~surrogate.models.base.Model.kernel_precompiler`,
    a name in the model's code, never user input), then prints the seconds the call took."""
    module, _, function = target.partition(":")
    return (
        f"import time; from {module} import {function} as compile_kernel; "
        "t0 = time.perf_counter(); compile_kernel(); print(time.perf_counter() - t0)"
    )


def kernel_wanted(backend: str, compile: bool) -> bool:
    """Whether a run with these settings asks for the per-cell kernel (``backend=numba``, or
    ``auto`` without ``compile``; :class:`~surrogate.simulate.Simulator` decides the rest)."""
    return backend == "numba" or (backend == "auto" and not compile)


def wait_for_precompile() -> float:
    """Wait for the background precompiles in flight; return the seconds waited."""
    t0 = time.perf_counter()
    for target, process in list(_running.items()):
        process.wait()
        _running.pop(target, None)
        if process.returncode != 0:  # the first call compiles instead
            log.debug("background precompile %s exited with %d", target, process.returncode)
    waited = time.perf_counter() - t0
    if waited > 0.1:
        log.info("waited %.1f s for the per-cell kernel's compilation", waited)
    return waited


__all__ = ["kernel_wanted", "precompile_in_background", "precompiler_code", "wait_for_precompile"]

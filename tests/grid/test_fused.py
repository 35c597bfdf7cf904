"""The grid field's fused step (surrogate/grid/fused.py, torch.compile on CUDA) against the eager
step: the same concentrations and ledger to float64 rounding over a run, every branch (uptake,
secretion, decay, sources; dense, transformed and explicit solvers; both boundaries)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.grid import GridField
from surrogate.grid.fused import FusedStep

EPS = float(np.finfo(np.float64).eps)
DT = 0.05
#: relative agreement asked of the fused step over a run (the brief's, ~1e4 roundings)
RTOL = 1e-12


def _field(boundary="no_flux", solver="spectral", fuse="eager") -> GridField:
    """A channel with a consumed attractant, a secreted and decaying signal, and a source."""
    return GridField(
        [[0.0, 4.0], [-0.25, 0.25]], [64, 8],
        {"attractant": {"diffusion": 8e-4, "initial": "0.1 * x / 4", "source": 1e-4,
                        "uptake": {"vmax": 1e8, "km": 0.01}},
         "signal": {"diffusion": 4e-4, "decay": 0.01,
                    "secretion": {"rate_on": 2e5, "rate_off": 5e4}}},
        depth=0.1, boundary=boundary, solver=solver, fuse=fuse,
    )  # fmt: skip


def _walk(n: int, steps: int, device: torch.device | str, seed: int = 0):
    """Each step's agents: crowded positions drifting along the channel (some beyond its
    walls), phi drawn at random."""
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(n, 2, generator=g, dtype=torch.float32)
    p = p * torch.tensor([0.5, 0.6]) + torch.tensor([0.2, -0.3])
    for _ in range(steps):
        p = p + 0.03 * torch.randn(n, 2, generator=g) + torch.tensor([0.01, 0.0])
        phi = torch.rand(n, generator=g) < 0.5
        yield p.to(device), phi.to(device)


def _run(field: GridField, device, steps: int, n: int = 3_000, dense: bool = True):
    """The state and the agents' reads after ``steps`` steps of :func:`_walk` (the spectral
    solver's transforms where not ``dense``)."""
    field.reset(device)
    if not dense:
        field._solver.dense = False  # type: ignore[union-attr]
    reads = []
    for position, phi in _walk(n, steps, device):
        reads.append(field(position, 0.0))
        field.step(position, phi, DT)
    s = field.state
    return s.concentration, s.taken, s.secreted, s.supplied, s.decayed, torch.stack(reads)


def _assert_close(got, want, rtol=RTOL) -> None:
    """Each of ``got`` within ``rtol`` of ``want``'s largest value; the agents' float32 reads
    within one float32 rounding (a float64 difference of 1e-16 may cross a rounding edge)."""
    for g, w in zip(got, want, strict=True):
        tol = (
            max(rtol, 2 * float(torch.finfo(torch.float32).eps))
            if w.dtype == torch.float32
            else rtol
        )
        scale = float(w.abs().max())
        assert float((g - w).abs().max()) <= tol * scale, (g, w)


CASES = [("no_flux", "spectral", True), ("periodic", "spectral", True),
         (["no_flux", "periodic"], "spectral", False), ("no_flux", "explicit", True)]  # fmt: skip


@pytest.mark.parametrize(("boundary", "solver", "dense"), CASES)
def test_the_fused_step_run_eagerly_is_the_eager_step(boundary, solver, dense) -> None:
    """fused_step as plain torch (what inductor compiles) against GridField.step (numba's
    exchange on the CPU): 40 steps, concentrations, ledger and the agents' reads."""
    eager, fused = _field(boundary, solver), _field(boundary, solver, fuse="compile")
    fused._fused = FusedStep(fallback=False)
    fused._fused._compiled = fused._fused._eager  # the function itself, uncompiled
    got, want = _run(fused, "cpu", 40, dense=dense), _run(eager, "cpu", 40, dense=dense)
    _assert_close(got, want)
    assert float(got[1][0]) > 0 and float(got[2][1]) > 0 and float(got[4][1]) > 0
    scale = fused.state.initial + fused.state.secreted + fused.state.supplied
    assert bool((fused.balance().abs() <= 40 * 64 * EPS * scale).all()), fused.balance()


def test_the_fused_step_traces_as_one_graph() -> None:
    """torch.compile traces fused_step whole (fullgraph=True: a graph break is an error), and
    the traced graph (aot_eager: torch's own kernels, no code generated) is the eager step's
    to float64 rounding. Inductor's kernels are compared on CUDA below."""
    fused = _field(fuse="compile")
    fused._fused = FusedStep(backend="aot_eager", fallback=False)
    _assert_close(_run(fused, "cpu", 5), _run(_field(), "cpu", 5))
    assert fused._fused.error is None and fused.step_path == "compiled"


def test_fuse_auto_keeps_the_eager_step_on_the_cpu_and_a_bad_setting_is_refused() -> None:
    field = _field(fuse="auto")
    assert field._fused_step(torch.device("cpu")) is None
    _run(field, "cpu", 1)
    assert field.step_path == "eager" and field._fused is None
    assert _field(fuse="compile")._fused_step(torch.device("cpu")) is not None
    with pytest.raises(ConfigError, match=r"field.fuse must be one of \['auto', 'eager'"):
        _field(fuse="triton")


def test_a_failed_compile_falls_back_to_the_eager_function_with_a_warning() -> None:
    step = FusedStep()

    def broken(*args):
        raise RuntimeError("no compiler")

    step._compiled = broken
    field = _field(fuse="compile")
    field._fused = step  # as fuse=auto makes it on CUDA: fallback=True
    with pytest.warns(UserWarning, match="no compiler"):
        got = _run(field, "cpu", 3)
    assert step.error is not None
    assert field.step_path == "eager (torch.compile failed: RuntimeError: no compiler)"
    _assert_close(got, _run(_field(), "cpu", 3))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize(("boundary", "solver", "dense"),
                         [(["no_flux", "periodic"], "spectral", True), ("periodic", "explicit", True)])  # fmt: skip
def test_the_compiled_step_on_cuda_is_the_eager_step(boundary, solver, dense) -> None:
    """fuse=auto on CUDA (inductor's Triton kernels) against fuse=eager on CUDA: 200 steps of
    30,000 crowded agents (the deposit's 128 private copies), to 1e-12 relative; the bench's
    geometry (the dense step) and the explicit solver (its step after the fused exchange)."""
    cuda = torch.device("cuda")
    fused = _field(boundary, solver, fuse="auto")
    got = _run(fused, cuda, 200, n=30_000, dense=dense)
    assert fused.step_path == "compiled", fused.step_path
    want = _run(_field(boundary, solver), cuda, 200, n=30_000, dense=dense)
    _assert_close(got, want)
    scale = fused.state.initial + fused.state.secreted + fused.state.supplied
    assert bool((fused.balance().abs() <= 200 * 64 * EPS * scale).all()), fused.balance()


def test_a_reset_or_the_next_step_compiles_nothing_new() -> None:
    """One graph for a field's run and the next (same sizes and dt): a reset makes a new solver
    and ledger, which enter as tensors, not objects torch.compile would guard on."""
    graphs = []

    def counting(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    field = _field(fuse="compile")
    field._fused = FusedStep(backend=counting, fallback=False)
    _run(field, "cpu", 4)
    _run(field, "cpu", 4)
    assert len(graphs) == 1


def test_a_deep_copy_of_a_field_compiles_its_own_step() -> None:
    """A replicate's copy of a field (surrogate/simulate/batch.py) gets a fresh compiled step,
    not the original's code object and cache, and steps as the original."""
    import copy

    field = _field(fuse="compile")
    field._fused = FusedStep(backend="aot_eager", fallback=False)
    want = _run(field, "cpu", 3)
    twin = copy.deepcopy(field)
    assert twin._fused is not field._fused and twin._fused._eager is not field._fused._eager
    _assert_close(_run(twin, "cpu", 3), want, rtol=0.0)

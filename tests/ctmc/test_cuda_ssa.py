"""The CUDA SSA (surrogate/ctmc/cuda_ssa.py) without a GPU: on numba's CUDA simulator it makes
the compiled CPU SSA's events cell for cell from the same streams (plain kinetics, rules, time
and state events, and an agent's network window by window); its kernels compile to PTX for a
Hopper GPU where NVVM is installed; it is refused clearly where it cannot run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from surrogate.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
cuda = pytest.importorskip("numba.cuda", reason="numba-cuda is not installed")


def test_the_cuda_ssa_makes_the_compiled_ssas_events_on_the_simulator() -> None:
    # the checkout first, then whatever the caller's path holds (packages installed beside it)
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": path}
    done = subprocess.run(
        [sys.executable, "-W", "ignore", str(ROOT / "tests" / "ctmc" / "cuda_sim_check.py")],
        env=env, capture_output=True, text=True, timeout=900, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    same = [line for line in done.stdout.splitlines() if line.startswith("SAME")]
    assert len(same) == 7, done.stdout  # six networks and the agent route
    assert "events=0" not in done.stdout  # every network made events


#: what numba-cuda raises where NVRTC or NVVM is not installed
_MISSING_LIBRARY = {"DynamicLibNotFoundError", "NvvmSupportError", "CudaSupportError"}


def _nvvm() -> bool:
    """Whether numba-cuda's compiler runs here (NVVM and NVRTC, from a CUDA toolkit or
    ``numba-cuda[cu13]``): a trivial kernel compiles to PTX."""
    from numba import types

    import surrogate.ctmc.cuda_ssa  # noqa: F401 - what the package sets up before it compiles

    def trivial(a):  # pragma: no cover - compiled, never called
        a[0] = 1.0

    try:
        cuda.compile_ptx(trivial, (types.Array(types.float64, 1, "C"),), cc=(9, 0))
    except Exception as error:
        # only a missing library means "no compiler here"; anything else is a failure to see
        # (on an H200 a numpy the compiler could not load was once skipped as "no NVVM")
        if type(error).__name__ in _MISSING_LIBRARY:
            return False
        raise
    return True


@pytest.mark.skipif(not _nvvm(), reason="no NVVM here (pip install 'numba-cuda[cu13]')")
def test_the_kernels_compile_for_a_hopper_gpu() -> None:
    """numba-cuda's real compiler (not the simulator) on the plain and the events kernel."""
    from numba import types

    from surrogate.ctmc.codegen import load_generated
    from surrogate.ctmc.cuda_ssa import cuda_source
    from surrogate.sbml import read_sbml

    i64, f64, u64 = types.int64, types.float64, types.uint64
    b1 = types.Array(types.boolean, 1, "C")
    head = (types.Array(i64, 2, "C"), types.Array(f64, 2, "C"), types.Array(f64, 1, "C"),
            types.Array(u64, 2, "C"), *[types.Array(i64, 1, "C")] * 3, i64,
            types.Array(i64, 2, "C"))  # fmt: skip
    events = (types.Array(f64, 1, "C"), types.Array(types.boolean, 2, "C"),
              types.Array(i64, 1, "C"), types.Array(i64, 1, "C"), b1, b1)  # fmt: skip
    data = ROOT / "tests" / "data"
    for path in (
        data / "sbml" / "hill_repression.xml",
        data / "dsmts" / "00033" / "00033-sbml-l3v1.xml",
    ):
        kinetics = read_sbml(path).kinetics
        module = load_generated(cuda_source(kinetics), prefix="cudassa")
        if kinetics.has_rules_or_events:
            kernel, signature = module.advance_cells_events, (*head, *events)
        else:
            kernel, signature = module.advance_cells, head
        ptx, _ = cuda.compile_ptx(kernel.py_func, signature, cc=(9, 0))
        assert ".entry" in ptx and "sm_90" in ptx


def test_ssa_cuda_on_the_cpu_is_refused_naming_the_setting() -> None:
    from surrogate.models.network import NetworkInternalModel
    from surrogate.sbml import read_sbml_string
    from tests.models.test_network_events import crossing_counter

    sbml = read_sbml_string(crossing_counter(), inputs=["kb"])
    internal = NetworkInternalModel(sbml, ["kb"], "y >= 10", ssa="cuda")
    with pytest.raises(ConfigError, match=r"model\.ssa=cuda runs on a CUDA GPU"):
        internal.initial_state(torch.full((2, 1), 3.0))
    auto = NetworkInternalModel(sbml, ["kb"], "y >= 10")
    assert auto.backend(torch.device("cpu")) == "compiled"


def test_the_cuda_ssa_refuses_cpu_tensors_off_the_simulator() -> None:
    from surrogate.ctmc.cuda_ssa import CudaSSA, cuda_ssa_available
    from surrogate.sbml import read_sbml

    kinetics = read_sbml(ROOT / "tests" / "data" / "sbml" / "dimerisation.xml").kinetics
    if not cuda_ssa_available():
        with pytest.raises(RuntimeError, match="model.ssa=batched"):
            CudaSSA(kinetics)
        return
    ssa = CudaSSA(kinetics)  # pragma: no cover - a machine with a GPU
    with pytest.raises(ValueError, match="on a CUDA GPU"):
        ssa.advance(torch.zeros((1, kinetics.network.n_species), dtype=torch.int64),
                    torch.zeros((1, kinetics.n_inputs)), 0.1, torch.zeros((1, 4), dtype=torch.int64))  # fmt: skip

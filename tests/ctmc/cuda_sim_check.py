"""Run in a fresh process with NUMBA_ENABLE_CUDASIM=1 (tests/ctmc/test_cuda_ssa.py): the CUDA SSA
on numba's simulator against the compiled CPU SSA, the same streams, cell by cell; prints one
line per network and exits non-zero on the first difference."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from surrogate.ctmc import CellStreams, CompiledSSA
from surrogate.ctmc.cuda_ssa import CudaSSA, simulated
from surrogate.ctmc.events import EventState, start_events
from surrogate.sbml import read_sbml

ROOT = Path(__file__).resolve().parents[1] / "data"
#: (file, windows): a general-kinetics network and DSMTS cases with events and rules
CASES = (
    (ROOT / "sbml" / "hill_repression.xml", (0.3, 0.7, 0.5)),
    (ROOT / "sbml" / "dimerisation.xml", (0.5, 0.5)),
    (ROOT / "dsmts" / "00028" / "00028-sbml-l3v1.xml", (10.0, 20.0, 25.0)),
    (ROOT / "dsmts" / "00019" / "00019-sbml-l3v1.xml", (10.0, 20.0)),
    (ROOT / "dsmts" / "00029" / "00029-sbml-l3v1.xml", (10.0, 20.0, 25.0)),
    (ROOT / "dsmts" / "00033" / "00033-sbml-l3v1.xml", (10.0, 20.0, 25.0)),
)
N_CELLS = 4


def main() -> int:
    assert simulated(), "set NUMBA_ENABLE_CUDASIM=1 before numba is imported"
    for path, windows in CASES:
        model = read_sbml(path)
        kinetics, n = model.kinetics, N_CELLS
        counts = model.initial_states(n)
        inputs = torch.zeros((n, kinetics.n_inputs), dtype=torch.float64)
        clock_cpu = clock_gpu = None
        if kinetics.has_rules_or_events:
            counts, start = start_events(kinetics, counts, inputs)
            clock_cpu = start if kinetics.events else None
            if clock_cpu is not None:
                clock_gpu = EventState(start.time.clone(), start.triggers.clone())
        streams = CellStreams.from_seed(7, n)
        words = torch.from_numpy(streams.state.copy().view(np.int64))
        cpu, gpu = CompiledSSA(kinetics, parallel=False), CudaSSA(kinetics)
        state_cpu = state_gpu = counts
        for dt in windows:
            state_cpu, events_cpu = cpu.advance(state_cpu, inputs, dt, streams, clock=clock_cpu)
            state_gpu, events_gpu = gpu.advance(state_gpu, inputs, dt, words, clock=clock_gpu)
            same = (
                torch.equal(state_cpu, state_gpu)
                and torch.equal(events_cpu, events_gpu)
                and np.array_equal(streams.state.view(np.int64), words.numpy())
                and (clock_cpu is None or torch.equal(clock_cpu.time, clock_gpu.time))
                and (clock_cpu is None or torch.equal(clock_cpu.triggers, clock_gpu.triggers))
            )
            if not same:
                print(f"DIFFER {path.name} dt={dt}: {state_cpu.tolist()} vs {state_gpu.tolist()}")
                return 1
        print(f"SAME {path.name} events={int(events_cpu.sum())}")
    return agent_route()


def agent_route() -> int:
    """An agent's internal network (a rule and a state event, inputs changing every window)
    through :class:`NetworkInternalModel` with ``ssa=cuda`` and ``ssa=compiled``: the same
    states, window by window."""
    from surrogate.models.network import NetworkInternalModel
    from surrogate.sbml import read_sbml_string
    from tests.models.test_network_events import crossing_counter

    sbml = read_sbml_string(crossing_counter(), inputs=["kb"])
    states = {}
    for ssa in ("compiled", "cuda"):
        internal = NetworkInternalModel(sbml, ["kb"], "y >= 10", ssa=ssa, burn_in=2.0)
        assert internal.backend(torch.device("cpu")) == ssa
        torch.manual_seed(0)
        state = internal.initial_state(torch.full((8, 1), 3.0))
        trace = []
        for level in (3.0, 6.0, 0.5, 4.0):
            state = internal.advance(state, torch.full((8, 1), level), 1.0)
            trace.append([s.clone() for s in state])
        states[ssa] = trace
    for a, b in zip(states["compiled"], states["cuda"], strict=True):
        if not all(torch.equal(u, v) for u, v in zip(a, b, strict=True)):
            print(f"DIFFER agent route: {a[0].tolist()} vs {b[0].tolist()}")
            return 1
    print("SAME agent route (NetworkInternalModel, ssa=cuda vs compiled)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The benchmarks: measurements of speed and memory, never part of a stage's work.

* :mod:`surrogate.benchmarks.loop`: the full and the abstracted simulation and the stages around
  them (``python scripts/bench.py``, config ``conf/bench.yaml``), with its parts:
  :mod:`~surrogate.benchmarks.machine` (settings, machine, set-up),
  :mod:`~surrogate.benchmarks.timing` (throughput, step split, workload, memory),
  :mod:`~surrogate.benchmarks.layers` (the decision layer of each kind) and
  :mod:`~surrogate.benchmarks.lookup` (the abstraction's loop alone, ``lookup_only=true``);
* :mod:`surrogate.benchmarks.ssa`: the SSA backends on the phospho network
  (``python scripts/bench_ssa.py``).

Both modules' public names are re-exported here (the SSA bench's ``run_bench`` as
``run_ssa_bench``), each loaded on first use: the loop bench measures memory in fresh processes
that import it, and must not pay for the SSA bench's imports (numba, scipy, the SBML model).
"""

from __future__ import annotations

from typing import Any

#: both benches' public names
__all__ = [
    "bench_compiled",
    "bench_gillespy2",
    "bench_settings",
    "bench_torch",
    "cell_seconds_per_s",
    "compile_times",
    "equal_workload_ratio",
    "format_lookup_report",
    "format_report",
    "function_table",
    "machine_info",
    "main",
    "run_bench",
    "run_lookup_bench",
    "run_ssa_bench",
]


def __getattr__(name: str) -> Any:
    """The public name ``name`` from its module (imported on first use): the SSA bench's
    (``run_ssa_bench`` is its ``run_bench``) or else the loop bench's (its lookup-only part,
    its machine facts and its layers in their own modules)."""
    ssa = {"bench_compiled", "bench_gillespy2", "bench_torch", "cell_seconds_per_s",
           "compile_times", "equal_workload_ratio", "run_ssa_bench"}  # fmt: skip
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    # plain imports of the known submodules (no import by computed name: see test_safety)
    if name in ssa:
        from surrogate.benchmarks import ssa as ssa_module

        return getattr(ssa_module, "run_bench" if name == "run_ssa_bench" else name)
    if name == "function_table":
        from surrogate.benchmarks import layers

        return layers.function_table
    if name == "machine_info":
        from surrogate.benchmarks import machine

        return machine.machine_info
    from surrogate.benchmarks import loop as loop_module

    return getattr(loop_module, name)

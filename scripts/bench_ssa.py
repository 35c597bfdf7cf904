"""Benchmark the SSA backends on the E. coli phospho network (see surrogate/benchmarks/ssa.py).

python scripts/bench_ssa.py [--cells 20] [--t-end 10] [--repeats 3] [--out data/bench/ssa.json]
Every backend that compares simulates the same workload (cells x t_end simulated seconds);
GillesPy2 is optional: pip install -e ".[compare]".
"""

from __future__ import annotations

import argparse
from pathlib import Path

from surrogate.benchmarks.ssa import run_bench


def main() -> None:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--cells", type=int, default=20, help="trajectories per backend")
    parser.add_argument("--t-end", type=float, default=10.0, help="simulated seconds each")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (best kept)")
    parser.add_argument("--torch-cells", type=int, default=256, help="batched torch SSA cells")
    parser.add_argument("--torch-t-end", type=float, default=0.05, help="its simulated seconds")
    parser.add_argument("--dt", type=float, default=0.05, help="compiled SSA window (s)")
    parser.add_argument("--out", type=Path, default=Path("data/bench/ssa.json"))
    args = parser.parse_args()
    run_bench(
        cells=args.cells,
        t_end=args.t_end,
        repeats=args.repeats,
        torch_cells=args.torch_cells,
        torch_t_end=args.torch_t_end,
        dt=args.dt,
        output=args.out,
    )


if __name__ == "__main__":
    main()

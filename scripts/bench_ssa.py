"""Benchmark the SSA backends on the E. coli phospho network (see surrogate/bench_ssa.py).

python scripts/bench_ssa.py [--cells 256] [--windows 20] [--out data/bench/ssa.json]
GillesPy2 is optional: pip install -e ".[compare]".
"""

from __future__ import annotations

import argparse
from pathlib import Path

from surrogate.bench_ssa import run_bench


def main() -> None:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--cells", type=int, default=256, help="cells for the compiled SSA")
    parser.add_argument("--windows", type=int, default=20, help="windows for the compiled SSA")
    parser.add_argument("--torch-cells", type=int, default=256)
    parser.add_argument("--torch-windows", type=int, default=1)
    parser.add_argument("--trajectories", type=int, default=64, help="GillesPy2 trajectories")
    parser.add_argument("--t-end", type=float, default=1.0, help="GillesPy2 simulated seconds")
    parser.add_argument("--out", type=Path, default=Path("data/bench/ssa.json"))
    args = parser.parse_args()
    run_bench(
        args.cells,
        args.windows,
        args.torch_cells,
        args.torch_windows,
        args.trajectories,
        args.t_end,
        output=args.out,
    )


if __name__ == "__main__":
    main()

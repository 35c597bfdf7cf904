"""Benchmark psi_0 and psi_1 fitted one after the other or in two processes (see
surrogate/benchmarks/pair.py).

python scripts/bench_pair.py [--epochs 600] [--rows 200000] [--busy 0 1]
                             [--out data/bench/pair.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from surrogate.benchmarks.pair import run_bench


def main() -> None:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--epochs", type=int, default=600, help="natural-gradient steps per fit")
    parser.add_argument("--rows", type=int, default=200_000, help="rows per classifier")
    parser.add_argument("--busy", type=int, nargs="+", default=[0, 1],
                        help="busy-looping processes beside it, one run per count")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("data/bench/pair.json"))
    args = parser.parse_args()
    run_bench(epochs=args.epochs, rows=args.rows, busy=args.busy, output=args.out)


if __name__ == "__main__":
    main()

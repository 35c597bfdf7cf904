"""Benchmark torch threads on a busy machine (see surrogate/benchmarks/threads.py).

python scripts/bench_threads.py [--steps 40] [--repeats 3] [--busy 2] [--policies spin passive]
                                [--out data/bench/threads.json]
The GP fit's training steps on 1 and 2 threads, beside 0 and --busy busy-looping processes,
with idle OpenMP threads spinning (libgomp's default) or sleeping (OMP_WAIT_POLICY=PASSIVE).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from surrogate.benchmarks.threads import run_bench


def main() -> None:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=40, help="training steps per fit")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved repeats (median)")
    parser.add_argument("--busy", type=int, default=2, help="busy-looping processes beside it")
    parser.add_argument(
        "--policies",
        nargs="+",
        default=["spin", "passive"],
        help="OpenMP wait policies (spin: libgomp's default; passive)",
    )
    parser.add_argument("--out", type=Path, default=Path("data/bench/threads.json"))
    args = parser.parse_args()
    run_bench(
        steps=args.steps,
        repeats=args.repeats,
        busy=args.busy,
        policies=args.policies,
        output=args.out,
    )


if __name__ == "__main__":
    main()

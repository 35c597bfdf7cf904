"""Check the E. coli phospho network's calibration by simulation (compiled SSA).

python scripts/phospho_calibration.py [--cells 200] [--duration 10] [--out data/phospho.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from surrogate.models.ecoli_phospho.measure import measure


def main() -> None:
    """Parse arguments, measure, print and write JSON."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--cells", type=int, default=200)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--burn-in", type=float, default=2.0)
    parser.add_argument("--activity", type=float, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("data/phospho_calibration.json"))
    args = parser.parse_args()
    result = measure(
        args.cells, args.duration, args.burn_in, activity=args.activity, seed=args.seed
    )
    for key, value in result.items():
        print(f"{key:40s} {value}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()

"""Benchmark the simulators and the stages around them (see surrogate/benchmarks/loop.py).

python scripts/bench.py                 # full benchmark (a few minutes)
python scripts/bench.py quick=true      # smoke run (seconds)
python scripts/bench.py threads=[1] compile=[true] output=data/bench/mine.json
"""

import hydra
from omegaconf import DictConfig

from surrogate.benchmarks.loop import main as run_bench


@hydra.main(version_base="1.3", config_path="../conf", config_name="bench")
def main(cfg: DictConfig) -> str:
    """Hydra entry point."""
    return str(run_bench(cfg))


if __name__ == "__main__":
    main()

"""The cost of a coupled field beside its agents (see surrogate/benchmarks/field.py).

python scripts/bench_field.py                           # 1e6 abstracted cells, 512 x 64 grid
python scripts/bench_field.py n_cells=100000 steps=50   # a smaller population
"""

import hydra
from omegaconf import DictConfig

from surrogate.benchmarks.field import run_field_bench


@hydra.main(version_base="1.3", config_path="../conf", config_name="bench_field")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: the field's cost over the agents'."""
    return float(run_field_bench(cfg)["field_over_agents"])


if __name__ == "__main__":
    main()

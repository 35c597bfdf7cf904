"""Simulate a population with the full model or the learned abstraction.

python scripts/simulate.py                       # full model, gaussian field, 100 cells, 500 s
python scripts/simulate.py decision=abstract field=linear
"""

import hydra
from omegaconf import DictConfig

from surrogate.simulate.stage import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="simulate")
def main(cfg: DictConfig) -> str:
    """Hydra entry point."""
    return str(run(cfg))


if __name__ == "__main__":
    main()

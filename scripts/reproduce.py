"""The whole paper from one command: collect -> train -> simulate (L1, L2, L3) -> evaluate -> report.

    python scripts/reproduce.py                      # small default (a few minutes)
    python scripts/reproduce.py experiment=paper     # 100 cells, 500 s, dt 0.05 (Table 1)
"""

import hydra
from omegaconf import DictConfig

from surrogate.reproduce import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="reproduce")
def main(cfg: DictConfig) -> str:
    """Hydra entry point."""
    return str(run(cfg))


if __name__ == "__main__":
    main()

"""Collect perturbed micro-trajectory transitions (m, L, phi, phi_next) from the full model.

python scripts/collect.py                      # gaussian field, dt 0.05, 10k transitions per origin
python scripts/collect.py field=linear dt=0.02
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.collect import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="collect")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("collect", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

"""Loop speed of the full model and the abstraction, side by side in one process.

python scripts/speed.py                                  # the paper's workload, model=ecoli
python scripts/speed.py model=ecoli_phospho compile=false   # the SBML network (trained first)
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.speed import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="speed")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("speed", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

"""Choose the chain kind by held-out measurement (opt-in; docs/choice.md).

python scripts/choose.py                         # E. coli: two-state, clocks, K lumps, phases
python scripts/choose.py choose.max_ages=[1,3] choose.n_cells=200
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.choice import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="choose")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("choose", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()

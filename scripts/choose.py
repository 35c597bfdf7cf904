"""Choose the chain kind by held-out measurement (docs/choice.md): ``train.py`` with ``gp=auto``,
the default, which measures (``gp.choice.by=measure``).

python scripts/choose.py                          # E. coli: two-state, clocks, K lumps, phases
python scripts/choose.py gp.choice.max_ages=[1,3] gp.choice.n_cells=2000
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.train import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="choose")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("choose", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()

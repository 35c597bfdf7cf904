"""The whole paper from one command: collect -> train -> simulate (L1, L2, L3) -> evaluate -> report.

python scripts/reproduce.py                      # small default (a few minutes)
python scripts/reproduce.py experiment=paper     # 100 cells, 500 s, dt 0.05 (Table 1)
python scripts/reproduce.py -m hydra/launcher=joblib gp.kernel=rbf,matern52 dt=0.02,0.05
                                                 # a sweep, one job per core (docs/sweeps.md)
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.reproduce import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="reproduce")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("reproduce", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

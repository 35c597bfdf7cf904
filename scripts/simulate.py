"""Simulate a population with the full model or the learned abstraction.

python scripts/simulate.py                       # full model, gaussian field, 100 cells, 500 s
python scripts/simulate.py decision=abstract field=linear
python scripts/simulate.py -m shard.count=4 shard.index=0,1,2,3   # a population in 4 shards
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.shards import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="simulate")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("simulate", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

"""Merge the shards of a population run into one run directory (the unsharded format).

python scripts/simulate.py -m shard.count=4 shard.index=0,1,2,3 n_cells=10000
python scripts/merge_shards.py shard.count=4 n_cells=10000      # same settings as the shards
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage, task_overrides
from surrogate.stages.shards import merge


@hydra.main(version_base="1.3", config_path="../conf", config_name="simulate")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point; a missing shard's error names the command that makes it."""
    return run_stage("merge_shards", lambda c: merge(c, overrides=task_overrides()), cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

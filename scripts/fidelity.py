"""Fidelity at scale: abstractions of several training seeds vs the full model, every check named.

python scripts/fidelity.py                                   # 2,000 cells, 500 s, 4 fields, seeds 0-2
python scripts/fidelity.py fidelity.n_cells=500 fidelity.t_end=100.0   # a quicker look
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.fidelity import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="fidelity")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("fidelity", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

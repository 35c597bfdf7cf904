"""Train the GP classifiers psi0 (from TUMBLE) and psi1 (from RUN) on collected transitions.

python scripts/train.py                          # gaussian-field data, RBF kernel, 100 inducing points
python scripts/train.py field=linear gp.kernel=matern52
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.train import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("train", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

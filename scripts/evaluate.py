"""Compare an abstracted population run with the full model (KS, Wasserstein, noise floor).

python scripts/evaluate.py                               # gaussian field, needs both runs
python scripts/evaluate.py field=linear evaluate.run_missing=true
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.evaluate import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("evaluate", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

"""Stored full-model references for the fidelity check: made once, sharded and resumable.

python scripts/reference.py experiment=phospho          # the phospho check's four runs (~1.5 h, 2 cores)
python scripts/reference.py experiment=phospho fidelity.fields=[gaussian]   # one field's two runs
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.reference import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="fidelity")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("reference", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

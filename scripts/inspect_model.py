"""Inspect a model before collecting: its network, the inputs the fields give, phi's occupancy
and memory, the settling and relaxation times, what each stage costs and which abstraction to
use (report.md and inspect.json under data/inspect/<settings>/).

python3 scripts/inspect_model.py model=sbml model.spec=examples/toggle_switch/model.yaml
python3 scripts/inspect_model.py model=ecoli

(Not scripts/inspect.py: a script's folder comes first on sys.path, and a module named inspect
there would hide the standard library's from every script.)
"""

import hydra
from omegaconf import DictConfig

from surrogate.cli import exit_when_done, run_stage
from surrogate.stages.inspection import run


@hydra.main(version_base="1.3", config_path="../conf", config_name="inspect")
def main(cfg: DictConfig) -> str | None:
    """Hydra entry point (multirun jobs record failures instead of aborting the sweep)."""
    return run_stage("inspect", run, cfg)


if __name__ == "__main__":
    main()
    exit_when_done()  # skip the interpreter's teardown (~1 s with torch loaded)

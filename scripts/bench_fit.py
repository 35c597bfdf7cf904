"""Benchmark faster GP fits (see surrogate/benchmarks/fit.py).

python scripts/bench_fit.py [--threads 1] [--out data/bench/fit.json] [overrides] [--only N ...]
The default recipe's K-lumps fit (E. coli's 45 GPs) with Adam at 1,000 steps (the reference),
fewer Adam steps, NGD + Adam, L-BFGS and Adam + NGD refinement: wall and CPU seconds, final
negative ELBO and |Δpsi| against the reference's posterior sd where the data live. Reads the
quick start's collection (`python scripts/collect.py` with the same overrides makes it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hydra import compose, initialize_config_dir

from surrogate.benchmarks.fit import DEFAULT_METHODS, run_bench
from surrogate.gp.classes import ClassFitOptions, class_problems
from surrogate.models.capabilities import lump_classes_of
from surrogate.stages.settings.train import TrainSettings
from surrogate.stages.train import load_transitions

CONF = Path(__file__).resolve().parents[1] / "conf"


def main() -> None:
    """Parse arguments, build the train config's K-lumps problems and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--threads", type=int, default=1, help="torch threads of every fit")
    parser.add_argument("--out", type=Path, default=Path("data/bench/fit.json"))
    parser.add_argument("--only", type=int, nargs="*", help="method indices (0: the reference)")
    parser.add_argument("overrides", nargs="*", help="train config overrides (e.g. data_dir=...)")
    args = parser.parse_args()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        settings = TrainSettings.from_config(compose(config_name="train", overrides=args.overrides))
    classes = lump_classes_of(settings.setup.model.internal)
    if classes is None:
        parser.error(f"model {settings.setup.model.name!r} declares no classes (gp=classes)")
    table, _ = load_transitions(settings)
    options = ClassFitOptions(min_events=settings.min_events,
                              max_weight=settings.max_label_weight,
                              expected=settings.gp_config.get("labels", "outcome") != "outcome")  # fmt: skip
    problems, weights, _, _ = class_problems(table, settings.inputs, len(classes.names),
                                             settings.gp, options)  # fmt: skip
    methods = DEFAULT_METHODS
    if args.only:
        methods = tuple(DEFAULT_METHODS[i] for i in sorted({0, *args.only}))
    run_bench(problems, weights, settings.gp, methods, threads=args.threads, output=args.out)


if __name__ == "__main__":
    main()

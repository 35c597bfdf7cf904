"""The evaluate stage: an abstracted run vs a full run in the same field, beside the noise floor.

The noise floor is the same statistics between two full runs with different seeds: a reader sees
whether the abstraction's distance from the full model is larger than sampling noise.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import OmegaConf

from surrogate.config import field_name, positive, to_dict
from surrogate.errors import ConfigError, MissingArtefactError
from surrogate.evaluate.statistics import (
    SimulationRun,
    combine_with_noise_floor,
    comparison_table,
    default_times,
    load_run,
    mean_std_over_time,
    noise_floor_table,
)
from surrogate.io import (
    MANIFEST,
    artefact_dir,
    make_once,
    read_json,
    save_figure,
    write_json,
    write_manifest,
)
from surrogate.paths import SIMULATE_CMD, simulate_dir, simulate_settings
from surrogate.simulate import stage as simulate_stage

log = logging.getLogger(__name__)

EVALUATE_CMD = "python scripts/evaluate.py"
SUMMARY = "summary.json"
COMPARISON = "comparison"
NOISE_FLOOR = "noise_floor"


@dataclass
class RunSet:
    """The three simulation runs an evaluation compares."""

    full: SimulationRun
    abstract: SimulationRun
    full_repeat: SimulationRun | None


def run_config(cfg: Mapping[str, Any], decision: str, seed_offset: int = 0) -> Any:
    """The simulate config of one of the compared runs (same settings, another decision/seed)."""
    c = OmegaConf.create(to_dict(cfg))
    c.decision = to_dict(cfg["decision"]) if decision == "abstract" else {"name": "full"}
    if decision == "abstract" and c.decision.get("name") != "abstract":
        raise ConfigError(
            "evaluate needs decision=abstract settings (decision.train_field, decision.mode)"
        )
    c.seed = int(cfg["seed"]) + seed_offset
    return c


def _simulate_command(c: Any) -> str:
    parts = [SIMULATE_CMD, f"decision={c.decision.name}", f"field={field_name(to_dict(c.field))}",
             f"n_cells={c.n_cells}", f"t_end={c.t_end}", f"dt={c.dt}", f"seed={c.seed}"]  # fmt: skip
    return " ".join(parts)


def ensure_run(c: Any, run_missing: bool) -> Path:
    """The directory of a simulation run; simulate it if allowed, else name the command."""
    directory = simulate_dir(c)
    if not (directory / MANIFEST).exists():
        if not run_missing:
            raise MissingArtefactError(
                f"missing simulation {directory}. Run `{_simulate_command(c)}` first "
                f"(or evaluate with evaluate.run_missing=true)."
            )
        simulate_stage.run(c)
    return directory


def validate(cfg: Mapping[str, Any]) -> None:
    """Checks of an evaluate config (the runs' own checks happen in the simulate stage)."""
    simulate_stage.validate(run_config(cfg, "abstract"))
    e = cfg["evaluate"]
    positive(e, "subsample", "evaluate.", integer=True)
    times = e.get("times")
    if times is not None:
        try:
            values = [float(t) for t in times]
        except (TypeError, ValueError):
            raise ConfigError(
                f"evaluate.times must be a list of times in s (or null), got {times!r}"
            ) from None
        t_end = float(cfg["t_end"])
        bad = [t for t in values if not 0 <= t <= t_end]
        if bad:
            raise ConfigError(f"evaluate.times {bad} lie outside [0, t_end={t_end:g}] s")
    if e.get("noise_floor", True):
        offset = e.get("noise_seed_offset")
        seed = int(cfg["seed"])
        # offset 0 would compare the full run with itself: a noise floor of exactly zero
        if (
            isinstance(offset, bool)
            or not isinstance(offset, int)
            or offset == 0
            or seed + offset < 0
        ):
            raise ConfigError(
                f"evaluate.noise_seed_offset must be a non-zero integer with seed + offset >= 0 "
                f"(the noise floor's second full run uses seed + offset), got {offset!r}"
            )


def evaluate_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Everything that defines an evaluation (the abstract run's settings and ``evaluate``)."""
    return {
        "abstract": simulate_settings(run_config(cfg, "abstract")),
        # run_missing says how to get the inputs, not what the evaluation is
        "evaluate": {k: v for k, v in to_dict(cfg["evaluate"]).items() if k != "run_missing"},
    }


def evaluate_dir(cfg: Mapping[str, Any]) -> Path:
    """``data/evaluate/field=..._dt=..._n=..._T=..._seed=...-<hash>``."""
    settings = evaluate_settings(cfg)
    label = {"field": field_name(to_dict(cfg["field"])), "dt": float(cfg["dt"]), "n": cfg["n_cells"],
             "T": cfg["t_end"], "seed": cfg["seed"]}  # fmt: skip
    return artefact_dir(cfg["data_dir"], "evaluate", label, settings)


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Compare abstract vs full (and full vs full for the noise floor); return the directory."""
    validate(cfg)
    out = evaluate_dir(cfg)
    return make_once(out, evaluate_settings(cfg), EVALUATE_CMD, lambda _: _evaluate(cfg, out),
                     what="evaluation", force=force)  # fmt: skip


def _evaluate(cfg: Mapping[str, Any], out: Path) -> None:
    """Make sure the runs exist, compare them, then write tables, figures and (last) the manifest."""
    e = cfg["evaluate"]
    run_missing = bool(e.get("run_missing", False))
    dirs = {"full": ensure_run(run_config(cfg, "full"), run_missing),
            "abstract": ensure_run(run_config(cfg, "abstract"), run_missing)}  # fmt: skip
    if e.get("noise_floor", True):
        dirs["full_repeat"] = ensure_run(
            run_config(cfg, "full", int(e["noise_seed_offset"])), run_missing
        )
    t0 = time.perf_counter()
    runs = RunSet(load_run(dirs["full"]), load_run(dirs["abstract"]),
                  load_run(dirs["full_repeat"]) if "full_repeat" in dirs else None)  # fmt: skip
    times = (
        tuple(float(t) for t in e["times"])
        if e.get("times") is not None
        else default_times(runs.full)
    )
    seed = int(cfg["seed"])
    table = comparison_table(
        runs.full, runs.abstract, times=times, subsample=int(e["subsample"]), seed=seed
    )
    floor = None
    if runs.full_repeat is not None:
        floor = noise_floor_table(
            runs.full, runs.full_repeat, times=times, subsample=int(e["subsample"]), seed=seed
        )
        table = combine_with_noise_floor(table, floor)
    summary = summarise(runs, table)
    # from here the directory reads as incomplete until the new manifest is written last
    (out / MANIFEST).unlink(missing_ok=True)
    write_outputs(out, table, floor, runs, times)
    write_json(out / SUMMARY, summary)
    write_manifest(out, stage="evaluate", config=to_dict(cfg), seed=seed, runs={k: str(v) for k, v in dirs.items()},
                   settings=evaluate_settings(cfg), wall_time_s=time.perf_counter() - t0, times=list(times),
                   **summary)  # fmt: skip
    log.info(
        "evaluate %s: max KS (abstract vs full) %.3f, noise floor %s; loop speed-up %.1fx; artefacts in %s",
        field_name(to_dict(cfg["field"])), summary["max_ks"],
        f"{summary['max_ks_noise_floor']:.3f}" if summary["max_ks_noise_floor"] is not None else "n/a",
        summary["speedup_loop"], out,
    )  # fmt: skip


def summarise(runs: RunSet, table: pd.DataFrame) -> dict[str, Any]:
    """Headline figures: speed-ups (loop and wall time) and the largest KS distances."""
    full, abstract = runs.full.manifest, runs.abstract.manifest
    return {
        "speedup_loop": float(full["loop_time_s"]) / float(abstract["loop_time_s"]),
        "speedup_wall": float(full["wall_time_s"]) / float(abstract["wall_time_s"]),
        "loop_time_s": {
            "full": float(full["loop_time_s"]),
            "abstract": float(abstract["loop_time_s"]),
        },
        "cell_steps_per_s": {
            "full": float(full["cell_steps_per_s"]),
            "abstract": float(abstract["cell_steps_per_s"]),
        },
        "max_ks": float(table["ks"].max()),
        "max_ks_noise_floor": float(table["ks_noise_floor"].max())
        if "ks_noise_floor" in table
        else None,
        "all_within_noise": bool(table["within_noise"].all()) if "within_noise" in table else None,
        "lookup_max_deviation": abstract.get("lookup_max_deviation"),
    }


def write_outputs(
    out: Path,
    table: pd.DataFrame,
    floor: pd.DataFrame | None,
    runs: RunSet,
    times: tuple[float, ...],
) -> None:
    """Tables (CSV + Markdown) and figures (Figures 4 and 5 of the paper, durations)."""
    from surrogate.evaluate.figures import (
        plot_distance_histograms,
        plot_distance_over_time,
        plot_duration_histograms,
    )
    from surrogate.evaluate.report import write_comparison
    from surrogate.io import write_csv

    write_comparison(out, table, prefix=COMPARISON)
    if floor is not None:
        write_comparison(out, floor, prefix=NOISE_FLOOR)
    over_time = pd.concat(
        [
            mean_std_over_time(r).assign(model=name)
            for name, r in (("full", runs.full), ("abstract", runs.abstract))
        ]
    )
    write_csv(out / "distance_over_time.csv", over_time)
    save_figure(
        out / "distance_histograms.png", plot_distance_histograms(runs.full, runs.abstract, times)
    )
    save_figure(
        out / "distance_over_time.png",
        plot_distance_over_time(runs.full, runs.abstract, separate=True),
    )
    save_figure(out / "durations.png", plot_duration_histograms(runs.full, runs.abstract))


def read_summary(directory: str | Path) -> dict[str, Any]:
    """The summary.json of an evaluation directory."""
    return read_json(Path(directory) / SUMMARY, made_by=EVALUATE_CMD)

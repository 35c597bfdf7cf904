"""The evaluate stage: a candidate run (the learned abstraction, or the exact lumped psi) vs a
full run in the same field, beside the noise floor.

The noise floor is the same statistics between two full runs with different seeds: a reader sees
whether the candidate's distance from the full model is larger than sampling noise. Runs in a
grid field (experiment=band) also compare their bands, judged against that floor by one rule
(:mod:`surrogate.evaluate.band_fidelity`: ``band_fidelity.csv/.md/.png``).
``python scripts/evaluate.py [field=...] [decision=abstract|exact] [evaluate.run_missing=true]``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from surrogate.config import to_dict
from surrogate.errors import MissingArtefactError
from surrogate.evaluate.statistics import (
    SimulationRun,
    combine_with_noise_floor,
    comparison_table,
    load_run,
    mean_std_over_time,
    noise_floor_table,
)
from surrogate.grid import GridField
from surrogate.io import (
    MANIFEST,
    make_once,
    read_json,
    save_figure,
    write_csv,
    write_json,
    write_manifest,
)
from surrogate.simulate.profiles import Profiles
from surrogate.simulate.speed import LoopTiming
from surrogate.stages import budget
from surrogate.stages.artefacts import (
    BAND_FIDELITY,
    COMPARISON,
    KYMOGRAPH_FIGURE,
    NOISE_FLOOR,
    SUMMARY,
)
from surrogate.stages.settings import EVALUATE_CMD, EvaluateSettings, SimulateSettings
from surrogate.stages.simulate import simulate

log = logging.getLogger(__name__)

#: why evaluate reports no speed-up: its runs were timed apart
SIDE_BY_SIDE = (
    "the runs were timed apart, each with its own compile and machine load; `python "
    "scripts/speed.py` with the same settings times both loops side by side"
)
#: the second full run's label in the band comparison (the summary's keys say ``full_repeat``)
FLOOR = "full_repeat"


@dataclass
class RunSet:
    """The three simulation runs an evaluation compares."""

    full: SimulationRun
    candidate: SimulationRun
    full_repeat: SimulationRun | None


def validate(cfg: Mapping[str, Any]) -> EvaluateSettings:
    """Checks of an evaluate config (and of the runs it compares) and the estimated cost of
    the runs it would make; the typed settings."""
    settings = EvaluateSettings.from_config(cfg)
    budget.check(cfg, budget.evaluate_work(settings), "evaluate")
    return settings


def run(cfg: Mapping[str, Any], force: bool = False) -> Path:
    """Compare the candidate with the full model (and full vs full for the noise floor)."""
    # the train stage's fitter, imported on demand as run_missing's train (gp=auto's choice)
    from surrogate.stages.choice import settle
    from surrogate.stages.train import fit_candidate

    return evaluate(settle(validate, cfg, fit_candidate), config=to_dict(cfg), force=force)


def evaluate(
    settings: EvaluateSettings, config: Mapping[str, Any] | None = None, force: bool = False
) -> Path:
    """Run (or reuse) the evaluation described by ``settings``; return its directory."""
    out = settings.directory
    return make_once(out, settings.identity(), settings.command(),
                     lambda _: _evaluate(settings, out, config), what="evaluation", force=force)  # fmt: skip


def ensure_run(settings: SimulateSettings, run_missing: bool) -> Path:
    """The directory of a simulation run; simulate it if allowed, else name the command."""
    directory = settings.directory
    if not (directory / MANIFEST).exists():
        if not run_missing:
            raise MissingArtefactError(
                f"missing simulation {directory}. Run `{settings.command()}` first "
                f"(or evaluate with evaluate.run_missing=true)."
            )
        simulate(settings)
    return directory


def ensure_abstraction(settings: EvaluateSettings) -> Path | None:
    """The fit the candidate run needs, made before the first simulation: with
    ``evaluate.run_missing``, a missing candidate run's learned abstraction is collected and
    trained here (as reproduce does, and as the cost estimate counts it), so a missing fit never
    stops the evaluation after its full runs. Returns the train directory it made, else None
    (the candidate exists, needs no fit, or its fit exists)."""
    train_settings = settings.candidate.decision.train
    if (
        train_settings is None
        or not settings.run_missing
        or (settings.candidate.directory / MANIFEST).exists()
        or (train_settings.fit_directory / MANIFEST).exists()
    ):
        return None
    # imported only by evaluations that train (as the simulate stage loads a fit)
    from surrogate.stages.collect import collect
    from surrogate.stages.settings import CollectSettings
    from surrogate.stages.train import train

    log.info("evaluate: the candidate's abstraction is missing: collecting and training it "
             "before any simulation (`%s`)", train_settings.command())  # fmt: skip
    if isinstance(train_settings.source, CollectSettings):
        collect(train_settings.source)
    return train(train_settings)


def runs_of(settings: EvaluateSettings) -> dict[str, SimulateSettings]:
    """The runs an evaluation compares, by role: ``full``, ``candidate``, ``full_repeat``."""
    runs = {"full": settings.full, "candidate": settings.candidate}
    if settings.full_repeat is not None:
        runs["full_repeat"] = settings.full_repeat
    return runs


def check_runs(settings: EvaluateSettings) -> None:
    """Without ``evaluate.run_missing``, every run must exist before anything is read: refused
    at once, naming the command that makes each missing one (the full runs of a coupled field
    at ``evaluate.full_n_cells`` with their scaled ``field.depth``)."""
    if settings.run_missing:
        return
    runs = runs_of(settings).values()
    missing = [s for s in runs if not (s.directory / MANIFEST).exists()]
    if missing:
        commands = "\n".join(f"  `{s.command()}`" for s in missing)
        raise MissingArtefactError(
            f"missing simulation(s) of this evaluation ({len(missing)} of {len(runs)}). Run "
            f"first\n{commands}\n(or evaluate with evaluate.run_missing=true)."
        )


def _evaluate(settings: EvaluateSettings, out: Path, config: Mapping[str, Any] | None) -> None:
    """Make sure the runs exist, compare them, then write tables, figures and (last) the
    manifest."""
    check_runs(settings)
    ensure_abstraction(settings)
    dirs = {k: ensure_run(s, settings.run_missing) for k, s in runs_of(settings).items()}
    t0 = time.perf_counter()
    runs = RunSet(load_run(dirs["full"]), load_run(dirs["candidate"]),
                  load_run(dirs["full_repeat"]) if "full_repeat" in dirs else None)  # fmt: skip
    seed = settings.candidate.setup.seed
    table = comparison_table(runs.full, runs.candidate, times=settings.times,
                             subsample=settings.subsample, seed=seed)  # fmt: skip
    floor = None
    if runs.full_repeat is not None:
        floor = noise_floor_table(runs.full, runs.full_repeat, times=settings.times,
                                  subsample=settings.subsample, seed=seed)  # fmt: skip
        table = combine_with_noise_floor(table, floor)
    summary = summarise(runs, table)
    band = band_runs(settings, dirs)
    if band is not None:
        band_table, summary["band_fidelity"] = band_comparison(band, settings)
    # from here the directory reads as incomplete until the new manifest is written last
    (out / MANIFEST).unlink(missing_ok=True)
    write_outputs(out, table, floor, runs, settings)
    if band is not None:
        write_band_fidelity(out, band, band_table, summary["band_fidelity"], settings)
    write_json(out / SUMMARY, summary)
    write_manifest(out, stage="evaluate",
                   config=dict(config) if config is not None else settings.identity(), seed=seed,
                   runs={k: str(v) for k, v in dirs.items()}, settings=settings.identity(),
                   wall_time_s=time.perf_counter() - t0, times=list(settings.times),
                   **summary)  # fmt: skip
    floor_text = (
        f"{summary['max_ks_noise_floor']:.3f}"
        if summary["max_ks_noise_floor"] is not None
        else "n/a"
    )
    log.info(
        "evaluate %s (%s): max KS vs full %.3f, noise floor %s; artefacts in %s (no speed-up: "
        "%s)", settings.candidate.setup.field_name, settings.candidate.decision.name,
        summary["max_ks"], floor_text, out, SIDE_BY_SIDE,
    )  # fmt: skip
    if band is not None:
        log.info("band fidelity (%s): %s", BAND_FIDELITY, "passed" if summary["band_fidelity"][
            "passed"] else "FAILED")  # fmt: skip


def mean_durations(run: SimulationRun) -> dict[str, float | None]:
    """Mean segment duration (s) per lump name."""
    return {kind: run.mean_duration(kind) for kind in run.lump_names}


def mean_duration_errors(run: SimulationRun) -> dict[str, float | None]:
    """The standard error (s) of each mean segment duration, cells as clusters
    (:meth:`~surrogate.evaluate.statistics.SimulationRun.mean_duration_se`)."""
    return {kind: run.mean_duration_se(kind) for kind in run.lump_names}


def summarise(runs: RunSet, table: pd.DataFrame) -> dict[str, Any]:
    """Headline figures: each run's loop time and cell-steps per second, the largest KS
    distances, mean durations. No speed-up: the runs were timed apart (each its own loop, cold
    compile and machine load; docs/performance.md), so ``speedup_loop`` and ``speedup_wall``
    are None and ``speed_not_comparable`` is :data:`SIDE_BY_SIDE`, naming the command that
    measures the ratio side by side."""
    full, cand = runs.full.manifest, runs.candidate.manifest
    loops = {"full": LoopTiming.from_manifest(full), "candidate": LoopTiming.from_manifest(cand)}
    durations = {"full": mean_durations(runs.full), "candidate": mean_durations(runs.candidate)}
    errors = {"full": mean_duration_errors(runs.full),
              "candidate": mean_duration_errors(runs.candidate)}  # fmt: skip
    if runs.full_repeat is not None:
        durations["full_repeat"] = mean_durations(runs.full_repeat)
        errors["full_repeat"] = mean_duration_errors(runs.full_repeat)
    return {
        "candidate": cand.get("decision"),
        "speedup_loop": None,
        "speedup_wall": None,
        "speed_comparable": False,
        "speed_not_comparable": [SIDE_BY_SIDE],
        "loop_time_s": {k: t.seconds for k, t in loops.items()},
        "cell_steps": {k: t.n_cells * t.steps for k, t in loops.items()},
        "cell_steps_per_s": {k: t.cell_steps_per_s for k, t in loops.items()},
        "max_ks": float(table["ks"].max()),
        "max_ks_noise_floor": float(table["ks_noise_floor"].max())
        if "ks_noise_floor" in table
        else None,
        "all_within_noise": bool(table["within_noise"].all()) if "within_noise" in table else None,
        "mean_durations": durations,
        "mean_duration_errors": errors,
        "lookup_max_deviation": cand.get("lookup_max_deviation"),
    }


def write_outputs(
    out: Path,
    table: pd.DataFrame,
    floor: pd.DataFrame | None,
    runs: RunSet,
    settings: EvaluateSettings,
) -> None:
    """Tables (CSV + Markdown) and, unless ``evaluate.figures=false``, figures (Figures 4 and 5
    of the paper, durations; for runs in a grid field, their kymographs side by side)."""
    from surrogate.evaluate.figures import (
        plot_drift,
        plot_duration_histograms,
        plot_observable_histograms,
        plot_observable_over_time,
    )
    from surrogate.evaluate.report import write_comparison

    model = settings.candidate.setup.model
    labels = ("full", settings.candidate.decision.name)
    write_comparison(out, table, prefix=COMPARISON)
    if floor is not None:
        write_comparison(out, floor, prefix=NOISE_FLOOR)
    figures = bool(settings.options.get("figures", True))
    frames = []
    for name in runs.full.observable_names:
        for label, r in zip(labels, (runs.full, runs.candidate), strict=True):
            frames.append(mean_std_over_time(r, name).assign(observable=name, model=label))
        if not figures:
            continue
        axis = model.observable_label(name)
        save_figure(out / f"{name}_histograms.png", plot_observable_histograms(
            runs.full, runs.candidate, settings.times, labels, name=name, axis_label=axis), crop=False)  # fmt: skip
        save_figure(out / f"{name}_over_time.png", plot_observable_over_time(
            runs.full, runs.candidate, labels, separate=True, name=name, axis_label=axis), crop=False)  # fmt: skip
        save_figure(out / f"{name}_drift.png", plot_drift(
            runs.full, runs.candidate, runs.full_repeat, labels, name=name, axis_label=axis), crop=False)  # fmt: skip
    write_csv(out / "observables_over_time.csv", pd.concat(frames, ignore_index=True))
    if figures:
        save_figure(out / "durations.png",
                    plot_duration_histograms(runs.full, runs.candidate, labels), crop=False)  # fmt: skip
        write_kymograph(out, (runs.full, runs.candidate), labels)


def write_kymograph(
    out: Path, runs: tuple[SimulationRun, ...], labels: tuple[str, ...]
) -> Path | None:
    """``kymograph.png``: the runs' density and concentration over x and t side by side, when
    every one of them ran in a grid field (kept its profiles); else nothing (None)."""
    from surrogate.evaluate.kymograph import plot_kymograph
    from surrogate.simulate.profiles import PROFILES, read_profiles

    paths = [r.path for r in runs]
    if not all(p is not None and (p / PROFILES).exists() for p in paths):
        return None
    profiles = [read_profiles(p) for p in paths if p is not None]
    return save_figure(out / KYMOGRAPH_FIGURE, plot_kymograph(profiles, labels), crop=False)


def band_runs(settings: EvaluateSettings, dirs: Mapping[str, Path]) -> dict[str, Profiles] | None:
    """The runs' profiles by label (the full run first, then ``full_repeat``, then the
    candidate under its decision's name) when they ran in a grid field, else None.

    Raises:
        ArtefactError: a run in a grid field without its profiles (made before they were kept:
            rerun it).
    """
    from surrogate.simulate.profiles import read_profiles

    if not isinstance(settings.candidate.setup.field, GridField):
        return None
    labels = {"full": "full", "full_repeat": FLOOR, "candidate": settings.candidate.decision.name}
    order = [k for k in ("full", "full_repeat", "candidate") if k in dirs]
    return {labels[k]: read_profiles(dirs[k]) for k in order}


def band_comparison(
    band: Mapping[str, Profiles], settings: EvaluateSettings
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Every run's band against the full run's, the candidate judged against the floor
    (:func:`~surrogate.evaluate.band_fidelity.band_fidelity`)."""
    from surrogate.evaluate.band_fidelity import band_fidelity

    full, *others = band.items()
    floor = FLOOR if FLOOR in band else None
    return band_fidelity(full[1], dict(others), floor,
                         factor=float(settings.options.get("band_factor", 1.5)))  # fmt: skip


def write_band_fidelity(
    out: Path,
    band: Mapping[str, Profiles],
    table: pd.DataFrame,
    summary: Mapping[str, Any],
    settings: EvaluateSettings,
) -> None:
    """``band_fidelity.csv`` (per run and record time), ``band_fidelity.md`` (the setting, the
    rule, the checks, the figures) and, unless ``evaluate.figures=false``, ``band_fidelity.png``
    (fronts over time, KS over time against the floor and the critical value)."""
    from surrogate.evaluate.band_fidelity import band_markdown, plot_band_fidelity
    from surrogate.evaluate.report import format_markdown_table, write_report

    write_csv(out / f"{BAND_FIDELITY}.csv", table)
    figures: list[tuple[str, Path]] = []
    if settings.options.get("figures", True):
        floor = summary["floor"]
        thresholds = {label: next(c["threshold"] for c in cs if c["check"] == "max_ks")
                      for label, cs in summary["checks"].items()}  # fmt: skip
        tables = {label: g for label, g in table.groupby("run", sort=False)}
        fig = plot_band_fidelity(band, tables, floor, thresholds)
        figures = [("The depletion front of every run over time (left); the KS distance of each "
                    "run's cells' x from the full model's over time, the floor dashed, with the "
                    "critical value and the threshold on the largest (right)",
                    save_figure(out / f"{BAND_FIDELITY}.png", fig))]  # fmt: skip
        if (out / KYMOGRAPH_FIGURE).exists():
            figures.append(("Density and concentration over x and t, full and candidate",
                            out / KYMOGRAPH_FIGURE))  # fmt: skip
    runs = runs_of(settings)
    setting = "; ".join(
        f"{label}: {p.n_cells} cells, seed {runs[role].setup.seed}, depth "
        f"{runs[role].setup.field_config.get('depth')} mm, {p.t.size} records"
        for (role, label), p in zip(_roles(band), band.values(), strict=True)
    )  # fmt: skip
    rule = (
        f"Each run's band against the full run's at every record time they share (the "
        f"candidate's, and the second full run's: the noise floor). A check passes when the "
        f"candidate's figure is at most max({summary['factor']:g} x the floor's, its critical "
        f"value): the largest KS over the record times of the cells' x (from the counts per "
        f"grid column, each run's over its own total; critical value at alpha "
        f"{summary['alpha']:g} for the two sizes), the RMS difference of the depletion front "
        f"(critical: half a column) and the difference of the front's least-squares speed "
        f"(critical: z x its combined standard error). "
        f"{'All pass.' if summary['passed'] else 'Not all pass.'}"
    )
    per_time = format_markdown_table(table, floatfmt=".4g")
    write_report(out / f"{BAND_FIDELITY}.md", [
        ("Setting", setting), ("The rule", rule), ("Checks", band_markdown(summary)),
        ("Per record time", per_time)], figures, title="Band fidelity")  # fmt: skip


def _roles(band: Mapping[str, Profiles]) -> list[tuple[str, str]]:
    """``(role, label)`` of each run of :func:`band_runs`, in its order."""
    roles = {"full": "full", FLOOR: "full_repeat"}
    return [(roles.get(label, "candidate"), label) for label in band]


def read_summary(directory: str | Path) -> dict[str, Any]:
    """The summary.json of an evaluation directory."""
    return read_json(Path(directory) / SUMMARY, made_by=EVALUATE_CMD)


__all__ = [
    "band_comparison",
    "band_runs",
    "check_runs",
    "ensure_abstraction",
    "ensure_run",
    "evaluate",
    "mean_duration_errors",
    "mean_durations",
    "read_summary",
    "run",
    "runs_of",
    "summarise",
    "validate",
    "write_band_fidelity",
    "write_kymograph",
]

"""The whole paper from one command: collect -> train -> full and abstracted simulations on
several fields -> evaluate -> ``report.md`` with Table 1 beside the published one, the noise
floor, the abstraction's error where the population lives, speed-ups and figures.

``python scripts/reproduce.py [experiment=small|paper|large|phospho] [model=...]``. Every stage reuses
artefacts that already exist for the same settings. With ``exact_psi=true`` (where the model has
an exact lumped psi) the chain driven by it is evaluated too, beside the learned one: the psi of
cells adapted to their current input.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import torch

from surrogate.config import to_dict
from surrogate.diagnosis.jumps import lagging_window
from surrogate.diagnosis.remedies import DURATION_TOLERANCE, MeasuredChoice
from surrogate.evaluate.report import format_markdown_table, table1_markdown, write_report
from surrogate.evaluate.statistics import family_failures
from surrogate.io import (
    MANIFEST,
    artefact_lock,
    read_csv,
    read_json,
    read_manifest,
    write_json,
    write_manifest,
)
from surrogate.simulate.precompile import kernel_wanted, precompile_in_background
from surrogate.simulate.support import sparse_share
from surrogate.stages import budget
from surrogate.stages import evaluate as evaluate_stage
from surrogate.stages.artefacts import DIAGNOSTIC_FIGURE, REPORT, SURFACES_FIGURE
from surrogate.stages.choice import settle
from surrogate.stages.collect import collect
from surrogate.stages.settings import (
    FIDELITY_CMD,
    CollectSettings,
    ReproduceSettings,
    TrainSettings,
    command_line,
)
from surrogate.stages.settings.choice import CHOICE
from surrogate.stages.simulate import build_decision, simulate_together
from surrogate.stages.train import (
    class_diagnostic_by_lump,
    fit_candidate,
    percent,
    read_metrics,
    train,
)

log = logging.getLogger(__name__)


def validate(cfg: Mapping[str, Any]) -> ReproduceSettings:
    """Checks before any work: every field exists, every stage's settings are valid, the
    estimated cost of what is missing is said (or refused past ``max_hours``)."""
    settings = ReproduceSettings.from_config(cfg)
    budget.check(cfg, budget.reproduce_work(settings), "reproduce")
    return settings


def run(cfg: Mapping[str, Any]) -> Path:
    """Run every stage (reusing what exists) and write the report; return its directory."""
    return reproduce(settle(validate, cfg, fit_candidate), config=to_dict(cfg))


def reproduce(settings: ReproduceSettings, config: Mapping[str, Any] | None = None) -> Path:
    """Run the pipeline of ``settings`` and write ``report.md``."""
    t0 = time.perf_counter()
    tr = settings.train
    batch = settings.batch
    model = tr.setup.model
    runs = settings.runs()
    if tr.job.device.type == "cpu" and any(kernel_wanted(r.backend, r.compile) for r in runs):
        precompile_in_background(model, tr.job.device)  # overlaps collect and train
    collect_dir = collect(tr.source) if isinstance(tr.source, CollectSettings) else None
    train_dir = train(tr)
    if batch:  # every missing run in one batch
        simulate_together(runs)
    # the loop speed measured side by side once per report: runs timed apart (or in one
    # batch) make no ratio
    previous = settings.directory / MANIFEST
    speed = read_manifest(settings.directory).get("speed") if previous.exists() else None
    speed = speed or measure_stage_speed(settings)
    evaluations: dict[str, Path] = {}
    for name, e in settings.evaluations.items():
        log.info("field %s: full and abstracted simulations, evaluation", name)
        evaluations[name] = evaluate_stage.evaluate(e)
    exact: dict[str, Path] = {}
    for name, e in settings.exact.items():
        log.info("field %s: the chain driven by the exact lumped psi", name)
        exact[name] = evaluate_stage.evaluate(e)
    out = settings.directory
    with artefact_lock(out):  # also removes the temporaries of killed runs
        sections, figures = report_sections(
            settings, collect_dir, train_dir, evaluations, exact, out, speed, config
        )
        (out / MANIFEST).unlink(missing_ok=True)  # incomplete until the manifest is rewritten
        write_report(out / REPORT, sections, figures,
                     title=f"Statistical abstraction of {model.describe().split(':')[0]}: report")  # fmt: skip
        write_manifest(out, stage="reproduce",
                       config=dict(config) if config is not None else settings.identity(),
                       seed=tr.seed, settings=settings.identity(),
                       collect=str(collect_dir) if collect_dir else None, train=str(train_dir),
                       evaluations={k: str(v) for k, v in evaluations.items()},
                       exact={k: str(v) for k, v in exact.items()}, speed=speed,
                       wall_time_s=time.perf_counter() - t0)  # fmt: skip
    log.info("report written to %s", out / REPORT)
    return out


#: the side-by-side speed measurement: at most this many steps (best of two), cells as the runs'
SPEED_STEPS = 1000
SPEED_MAX_CELLS = 100_000


def measure_stage_speed(settings: ReproduceSettings) -> dict[str, Any]:
    """Loop speed of the full model and of the abstraction on the first field, measured side by
    side in this process as the runs are set up (cells, compile, device, each model on the loop
    ``backend`` picks for it): runs simulated in one batch have no loop time of their own."""
    from surrogate.simulate.speed import LoopTiming, SpeedWorkload, measure_speed, speed_summary

    name, e = next(iter(settings.evaluations.items()))
    run = e.candidate
    setup = run.setup
    steps = min(round(run.t_end / setup.dt), SPEED_STEPS)
    n = min(run.n_cells, SPEED_MAX_CELLS)
    decisions = {"full": build_decision(e.full)[0], "abstract": build_decision(run)[0]}
    log.info("measuring loop speed side by side: %d cells x %d steps (%s)", n, steps, name)
    workload = SpeedWorkload(n, steps, setup.dt, run.start,
                             chunk_steps=round(run.record_interval / setup.dt))  # fmt: skip
    result = measure_speed(setup.model, decisions, setup.field, workload, run.job.device,
                           compile=run.compile, backend=run.backend)  # fmt: skip
    summary = speed_summary([LoopTiming.from_mapping(result["full"])],
                            [LoopTiming.from_mapping(result["abstract"])])  # fmt: skip
    loops = {v["backend"] for v in result.values()}
    return {"field": name, "n_cells": n, "steps": steps, "compile": run.compile,
            "backend": "/".join(sorted(loops)), "threads": torch.get_num_threads(),
            **summary,
            **{k: {kk: vv for kk, vv in v.items() if kk != "compile_error"}
               for k, v in result.items()}}  # fmt: skip


def _tables(evaluations: Mapping[str, Path]) -> dict[str, pd.DataFrame]:
    return {
        name: read_csv(d / f"{evaluate_stage.COMPARISON}.csv", made_by=evaluate_stage.EVALUATE_CMD)
        for name, d in evaluations.items()
    }


def report_sections(
    settings: ReproduceSettings,
    collect_dir: Path | None,
    train_dir: Path,
    evaluations: Mapping[str, Path],
    exact: Mapping[str, Path],
    out: Path,
    speed: Mapping[str, Any] | None = None,
    config: Mapping[str, Any] | None = None,
) -> tuple[list[tuple[str, str]], list[tuple[str, Path]]]:
    """Markdown sections and figures of the report (``config``: the run's resolved config,
    against which the verdict's remedies are checked and compared with the previous run of
    the model; None: neither)."""
    tr = settings.train
    model = tr.setup.model
    lumps = model.internal.lump_names
    first = next(iter(settings.evaluations.values())).candidate
    tables = _tables(evaluations)
    summaries = {name: evaluate_stage.read_summary(d) for name, d in evaluations.items()}
    speedups = {speed["field"]: speed["speedup"]} if speed and speed["speedup"] else {}
    metrics = read_metrics(train_dir)
    data = "an external table"
    if collect_dir is not None:
        cm = read_manifest(collect_dir)
        counts = ", ".join(f"{v} from {k}" for k, v in cm["counts_per_origin"].items())
        data = f"{counts} collected in {cm['wall_time_s']:.1f} s"
    setting = (
        f"{model.describe()}. {first.n_cells} cells per run, t_end = {first.t_end:g} s, "
        f"dt = {first.setup.dt:g} s, seed {first.setup.seed}; abstraction over "
        f"`{', '.join(tr.inputs)}` trained on `{tr.setup.field_name}` transitions ({data}), GP "
        f"kernel `{tr.gp.kernel}` with {tr.gp.n_inducing} inducing points (trained in "
        f"{metrics['train_seconds_total']:.1f} s), decision mode `{first.decision.mode}`."
    )
    table1 = (
        "KS distance (p-value) between the full and the abstracted model: the observables at "
        "four times, and the segment durations (1,000 sampled each, as in the paper). The *noise "
        "floor* row is the same statistic between two full runs with different seeds; † marks a "
        "value above both the noise floor and the KS 5 % critical value.\n\n"
        + table1_markdown(tables, speedups, model.reference_table())
    )
    sections = [("Setting", setting), ("Table 1: abstracted vs full model", table1),
                ("Trust it, or what to try next",
                 _verdict(settings, tables, metrics, config, out))]  # fmt: skip
    noise_lines = [noise_line(name, table) for name, table in tables.items()
                   if "ks_noise_floor" in table]  # fmt: skip
    sections.append(("Against sampling noise", "\n".join(noise_lines) or "No noise floor."))
    choice_dir = settings.train.measured_choice()
    if choice_dir is not None:
        sections.append(("The chain kind, chosen by measurement", choice_text(choice_dir)))
    sections.append(("Segment durations", _durations_table(summaries, exact, lumps, metrics)))
    if exact:
        sections.append((
            "The exact lumped psi (cells adapted to their current input)",
            "The same comparison for the two-state chain driven by the internal model's exact "
            "lumped psi instead of the learned one: the switching probabilities of cells whose "
            "internal state is at its stationary law for their current input. Moving cells lag "
            "their input, so this is no bound on a two-state abstraction: a psi learned from the "
            "full model's transitions can pass checks it fails.\n\n"
            + table1_markdown(_tables(exact), {}),
        ))  # fmt: skip
    sections.append(
        ("The abstraction where the population lives", _diagnostic_text(metrics, lumps))
    )
    sections.append(("Inputs outside the training data", _outside_text(settings)))
    sections.append(
        ("Speed", "Not measured." if speed is None else _measured_speed_text(speed, settings.batch))
    )
    gp_rows = pd.DataFrame([
        {"classifier": f"{name} (from {metrics[name]['origin']})",
         **{k: metrics[name]["validation"][k]
            for k in ("brier", "brier_baseline", "mean_log_predictive", "accuracy", "n")},
         **_own_rows_columns(metrics[name].get("own_rows"))}
        for name in ("psi_0", "psi_1")
    ])  # fmt: skip
    own = any(metrics[name].get("own_rows") for name in ("psi_0", "psi_1"))
    sections.append(("Classifiers (held-out validation)", format_markdown_table(gp_rows, ".4f")
                     + (OWN_ROWS_NOTE if own else "")))  # fmt: skip
    artefacts = {"train": train_dir, **evaluations, **{f"exact {k}": v for k, v in exact.items()}}
    if collect_dir is not None:
        artefacts = {"collect": collect_dir, **artefacts}
    sections.append(("Artefacts", "\n".join(
        f"- {k}: `{os.path.relpath(v, out)}`" for k, v in artefacts.items())))  # fmt: skip
    figures = []
    for name, d in evaluations.items():  # next to Table 1: the drift, on the noise band
        for obs in first.setup.model.body.observable_names:
            if (d / f"{obs}_drift.png").exists():
                figures.append((f"{name}: the drift, mean {model.observable_label(obs)} minus "
                                f"the full model's, on its noise band", d / f"{obs}_drift.png"))  # fmt: skip
    figures.append(("The learned psi (paper Figure 3)", train_dir / SURFACES_FIGURE))
    if (train_dir / DIAGNOSTIC_FIGURE).exists():
        figures.append(("The learned psi against the reference where the population lives",
                        train_dir / DIAGNOSTIC_FIGURE))  # fmt: skip
    for name, d in evaluations.items():
        for obs in first.setup.model.body.observable_names:
            label = model.observable_label(obs)
            figures.append((f"{name}: {label}, full vs abstract (paper Figure 4)",
                            d / f"{obs}_histograms.png"))  # fmt: skip
            figures.append((f"{name}: mean and s.d. of {label} over time (paper Figure 5)",
                            d / f"{obs}_over_time.png"))  # fmt: skip
    return sections, figures


OWN_ROWS_NOTE = (
    "\n\n*Own rows*: the switches each classifier predicts over its own training rows against "
    "those the rows hold, in groups of about equal switches along each input: the range of "
    "the ratio and the group farthest off in SE; *off* where a group misses by more than 3 % "
    "and by more than the family-wise 1 % critical value: the fit stopped short of its rows or "
    'smooths over them (docs/performance.md, "A fit against its own rows").'
)


def _own_rows_columns(check: Mapping[str, Any] | None) -> dict[str, str]:
    """A classifier's own-rows check as the report's columns (none for a fit made before
    it was recorded)."""
    if not check:
        return {}
    ratios = [g["ratio"] for g in check["groups"]]
    big = check["largest"]
    return {"own rows: predicted / observed": f"{min(ratios):.3f}-{max(ratios):.3f}",
            "farthest off": f"{big['ratio'] - 1:+.1%} ({big['z']:.1f} SE"
                            f"{', off' if check['off'] else ''})"}  # fmt: skip


def choice_text(directory: Path) -> str:
    """The measured choice's record (``choice.json`` of ``directory``) as the report's section:
    why, and every candidate's held-out score."""
    record = read_json(directory / CHOICE, made_by="python scripts/train.py gp=auto")
    rows = []
    for r in record["scores"]:
        row = {"kind": r["kind"], "log-lik / window": f"{r['log_likelihood_per_window']:.5f}",
               "from best (SE)": "best" if r["diff_from_best"] == 0 else
               f"{r['diff_from_best']:+.1e} ({r['diff_se']:.0e})"}  # fmt: skip
        for key in r:
            if key.endswith("_ks") and not key.endswith("_ks_critical_05"):
                lump = key[: -len("_ks")]
                row[f"{lump} KS (crit)"] = f"{r[key]:.3f} ({r[key + '_critical_05']:.3f})"
                row[f"{lump} mean"] = f"{r[lump + '_mean_rel_diff']:+.1%}"
        row["holds durations"] = "yes" if r.get("holds_durations") else "no"
        if "own_rows_ratio" in r:  # the scored fit's largest miss of its own rows' switches
            row["own rows"] = (f"{r['own_rows_ratio'] - 1:+.1%} ({r['own_rows_z']:.1f} SE"
                               f"{', off' if r['own_rows_off'] else ''})")  # fmt: skip
        row["fit s"] = f"{r['fit_seconds']:.1f}"
        rows.append(row)
    held = record["heldout"]
    return (
        f"`gp=auto` chose **{record['chosen']}** (`{record['overrides']}`), because "
        f"{record['reason']}. Each candidate was fitted on this collection and scored on a "
        f"held-out full-model run ({held['cells']} cells x {held['windows']} windows, "
        f"another seed): the log-likelihood per window of the observed phi given the inputs, "
        f"and its durations simulated under the held-out inputs against the observed "
        f"(docs/choice.md); *own rows*: the scored fit's switches against those of its own "
        f'training rows, the group of its inputs farthest off (docs/performance.md, "A fit '
        f'against its own rows"). Record: {directory}.'
        + "".join(
            f" Left out, its fit failed: {name} ({why})."
            for name, why in (record.get("failed") or {}).items()
        )
        + "\n\n"
        + format_markdown_table(pd.DataFrame(rows), ".4f")
    )


def _durations_table(
    summaries: Mapping[str, Mapping[str, Any]],
    exact: Mapping[str, Path],
    lumps: tuple[str, str],
    metrics: Mapping[str, Any] | None = None,
) -> str:
    exact_summaries = {n: evaluate_stage.read_summary(d) for n, d in exact.items()}
    diagnostic = (metrics or {}).get("diagnostic") or {}
    rows = []
    for name, s in summaries.items():
        md, errors = s["mean_durations"], s.get("mean_duration_errors") or {}
        row: dict[str, Any] = {"field": name}
        for p, kind in reversed(list(enumerate(lumps))):
            full = md["full"][kind]
            row[f"{kind} full (s)"] = full
            row[f"{kind} abstract (s)"] = md["candidate"][kind]
            se = _difference_error(errors, kind, full)
            row[f"{kind} abstract vs full"] = _rel(md["candidate"][kind], full) + se
            bias = (diagnostic.get(f"phi{p}") or {}).get("rel_bias")
            predicted = None if bias is None or bias <= -1 else 1 / (1 + bias) - 1
            if predicted is not None and name == next(iter(summaries)):
                row[f"{kind} predicted by the bias"] = f"{100 * predicted:+.1f} %"
            if name in exact_summaries:
                ex = exact_summaries[name]["mean_durations"]["candidate"][kind]
                row[f"{kind} exact psi vs full"] = _rel(ex, full)
        rows.append(row)
    note = ("" if not diagnostic else " *Predicted by the bias*: the error of the mean "
            "duration that the learned psi's bias where the population lives implies (1 / (1 + "
            "bias) - 1), in the training field, where the diagnostic measured it.")  # fmt: skip
    return (
        "Mean segment duration of each model (all completed segments). *Abstract vs full*: the "
        "relative difference +- one standard error of it (the two runs' errors combined, each "
        "with cells as clusters: a cell's segments share its parameters and history; at 100 "
        "cells about 2 %, so a difference within ~2 of them is no evidence of bias; "
        "`python3 scripts/fidelity.py` checks at scale)."
        + note
        + "\n\n"
        + format_markdown_table(pd.DataFrame(rows).fillna(""), ".4f")
    )


def noise_line(name: str, table: pd.DataFrame) -> str:
    """One field's line of "Against sampling noise": each quantity above the noise with its KS
    beside its own noise floor (the largest KS and the largest floor are often different
    quantities, so "largest KS 0.34 vs noise floor 0.36; above noise: on" read as a
    contradiction), else that every quantity lies within."""
    rows = table[~table["within_noise"].astype(bool)]
    if rows.empty:
        return (f"- **{name}**: every quantity within the noise floor or the KS critical value "
                f"(largest KS {table['ks'].max():.3f}).")  # fmt: skip
    above = [f"{r.quantity} (KS {r.ks:.3f} vs noise floor {r.ks_noise_floor:.3f})"
             for r in rows.itertuples()]  # fmt: skip
    return f"- **{name}**: above noise: {', '.join(above)}."


def _verdict(
    settings: ReproduceSettings,
    tables: Mapping[str, pd.DataFrame],
    metrics: Mapping[str, Any],
    config: Mapping[str, Any] | None = None,
    out: Path | None = None,
) -> str:
    """Whether to trust the abstraction, and what to try next (:mod:`surrogate.diagnosis.advice`).
    With the run's ``config``: each remedy is checked by the stages' settings before it is
    printed, and one the previous run of the model advised that this run applied without a
    gain is not advised again (``out / verdict.json`` keeps what the next run compares with)."""
    from surrogate.diagnosis.advice import VerdictInputs, verdict
    from surrogate.models.count_classes import CountClasses
    from surrogate.models.network import NetworkInternalModel
    from surrogate.stages import advice
    from surrogate.stages.advice_check import checked

    tr = settings.train
    # the verdict counts a difference at a family-wise 5 % over the report's comparisons (the
    # tables' marks are per test: of 18 at 5 %, ~1 by chance)
    failures, m = family_failures(tables)
    outside = {name: read_manifest(e.candidate.directory).get("outside_training")
               for name, e in settings.evaluations.items()}  # fmt: skip
    source = tr.source
    n_per_state = (int(source.options["n_per_state"])
                   if isinstance(source, CollectSettings) else None)  # fmt: skip
    now = advice.outcome(failures)
    previous = _previous_verdict(settings, out) if config is not None else None
    diagnostic = metrics.get("diagnostic")
    if tr.kind.classes and metrics.get("class_diagnostic"):
        diagnostic = class_diagnostic_by_lump(metrics["class_diagnostic"], tr.setup.model.internal)
    # bins of a count: coarser classes are advised as concrete edges
    count_classes = getattr(tr.setup.model.internal, "count_classes", None)
    count_classes = count_classes if isinstance(count_classes, CountClasses) else None
    measured = VerdictInputs(
        diagnostic=diagnostic, lump_names=tr.setup.model.internal.lump_names, failures=failures,
        outside=outside, outside_warning=settings.job.outside_warning,
        tolerance=DURATION_TOLERANCE, kind=tr.kind,
        network=isinstance(tr.setup.model.internal, NetworkInternalModel),
        n_per_state=n_per_state, class_shares=metrics.get("class_shares"),
        max_age=tr.max_age if tr.kind.clock else None, count_classes=count_classes,
        choice=measured_choice(tr), wider_collection=tr.setup.model.wider_collection(),
        blackout=collection_blackout(tr),
        diagnostic_cells=diagnostic_cells(tr.diagnostic, metrics.get("diagnostic")),
        diagnostic_span=(float(tr.diagnostic["equilibration_time"]), float(tr.diagnostic["t_end"]))
        if tr.diagnostic.get("t_end") else None,
        burn_in=advisable_burn_in(config, tr.setup.model.internal),
    )  # fmt: skip
    # the causes this run finds (no remedy checked): a remedy whose cause went had its gain
    causes = {name for name, _, _ in verdict(measured).causes}
    tried = advice.tried_remedies(previous, config, now, causes) if config is not None else {}
    v = verdict(measured, check=None if config is None else
                (lambda overrides, what: checked(config, overrides, what)), tried=tried)  # fmt: skip
    if config is not None and out is not None:
        write_json(out / VERDICT, advice.verdict_record(v, config, now, tried))
    marked = sum(int((~t["within_noise"].astype(bool)).sum()) for t in tables.values()
                 if "within_noise" in t)  # fmt: skip
    counted = sum(len(q) for q in failures.values())
    note = (f"\n\n(The verdict counts a difference outside sampling noise at a family-wise 5 % "
            f"over the report's {m} comparisons, Bonferroni; the tables mark each test at 5 %: "
            f"{marked} marked, {counted} counted.)" if marked != counted else "")  # fmt: skip
    return v.markdown(confirm=fidelity_command(tr)) + note


def advisable_burn_in(config: Mapping[str, Any] | None, internal: Any) -> float | None:
    """The burn-in (s) the verdict may advise a longer one of, as ``++model.burn_in``: the
    model's where it is a yaml (``model.spec``: its keys are given so) and its cells' start
    simulates one (:func:`~surrogate.models.capabilities.burn_in_of`: not an enumerable
    network, drawn from its stationary law); else None (no value to advise)."""
    from surrogate.models.capabilities import burn_in_of

    if "spec" not in ((config or {}).get("model") or {}):
        return None
    return burn_in_of(internal) or None


def diagnostic_cells(
    options: Mapping[str, Any], diagnostic: Mapping[str, Any] | None
) -> int | None:
    """The cells the diagnostic ran with: its record's (the train stage grows a reference too
    noisy to judge, :func:`~surrogate.stages.train.grown_diagnostic`), else ``gp.diagnostic``'s
    ``options``; None where neither says."""
    used = ((diagnostic or {}).get("settings") or {}).get("n_cells") or options.get("n_cells")
    return int(used) if used else None


def collection_blackout(tr: TrainSettings, unless_left_out: bool = True) -> tuple[str, ...]:
    """The blackout collect advised for ``tr``'s collection (its manifest's
    ``after_jump.advice``, checked by collect before it was written); empty for an external
    table or a collection whose rows did not lag, and (``unless_left_out``) where ``tr``'s fit
    left the lagging rows out (``gp.jump_rows``, :func:`left_out_lagging_rows`): the
    blackout then records no other rows, only more of them."""
    if not isinstance(tr.source, CollectSettings):
        return ()
    lag = read_manifest(tr.source.directory, made_by=tr.source.command()).get("after_jump")
    advice = tuple(str(o) for o in (lag or {}).get("advice", ()))
    return () if advice and unless_left_out and left_out_lagging_rows(tr, lag) else advice


def kept_share(tr: TrainSettings) -> float | None:
    """The share of its collection's rows ``tr``'s fit read where it left the rows soon after
    a jump out (its manifest's ``jump_rows``); None where it read every row or is not made."""
    manifest = tr.fit_directory / MANIFEST
    if not manifest.exists():
        return None
    record = read_json(manifest, made_by=tr.command()).get("jump_rows") or {}
    kept, rows = int(record.get("kept", 0)), int(record.get("rows", 0))
    return kept / rows if 0 < kept < rows else None


def left_out_lagging_rows(tr: TrainSettings, lag: Mapping[str, Any] | None) -> bool:
    """Whether ``tr``'s fit left out the rows soon after a jump: as its manifest records
    (:func:`kept_share`), else as ``gp.jump_rows`` would on a collection whose ``after_jump``
    is ``lag`` (a fit not made yet: the pilot's rule-chosen chain)."""
    if (tr.fit_directory / MANIFEST).exists():
        return kept_share(tr) is not None
    return tr.jump_rows == "drop" or (tr.jump_rows == "auto" and lagging_window(lag) is not None)


def fidelity_command(tr: TrainSettings) -> str:
    """The check at scale of the run that trained ``tr``: ``scripts/fidelity.py`` with its
    model, training field, step and collection (not its seed: fidelity trains several); its
    chain where one was named (``gp=auto`` measures again per training seed)."""
    data = [o for o in tr.setup.overrides() if not o.startswith("seed=")]
    collect = tr.source._overrides() if isinstance(tr.source, CollectSettings) else []
    gp = tr.gp_overrides() if tr.auto_recipe is None else []
    return command_line(FIDELITY_CMD, data, collect, gp)


def measured_choice(tr: TrainSettings) -> MeasuredChoice | None:
    """What the verdict reads of the measured choice that made ``tr``'s chain (its record's
    ``choice.json`` and the ``gp.choice`` settings in its manifest), or None where the chain
    was named or the rule chose it."""
    from surrogate.models.capabilities import lump_classes_of

    directory = tr.measured_choice()
    if directory is None:
        return None
    record = read_json(directory / CHOICE, made_by="python scripts/train.py gp=auto")
    options = read_manifest(directory, made_by="python scripts/train.py gp=auto")["settings"][
        "choice"
    ]
    return MeasuredChoice(
        chosen=str(record["chosen"]), scores=tuple(record["scores"]),
        kinds=tuple(str(k) for k in options["kinds"]),
        max_ages=tuple(float(a) for a in options["max_ages"]), n_cells=int(options["n_cells"]),
        tie_se=float(options["tie_se"]),
        classes=lump_classes_of(tr.setup.model.internal) is not None,
        duration_tolerance=(None if options.get("duration_tolerance") is None
                            else float(options["duration_tolerance"])),
        thinned=isinstance(tr.source, CollectSettings) and tr.source.thinned,
    )  # fmt: skip


#: the verdict's record in a report's directory (:func:`~surrogate.stages.advice.verdict_record`)
VERDICT = "verdict.json"


def _previous_verdict(settings: ReproduceSettings, out: Path | None) -> dict[str, Any] | None:
    """The newest verdict record of another report of the same model (its directories under
    ``data_dir/reproduce`` start with ``model=<name>_``), or None."""
    name = next(iter(settings.evaluations.values())).candidate.setup.model.name
    root = settings.job.data_dir / "reproduce"
    found = [p for p in root.glob(f"model={name}_*/{VERDICT}")
             if out is None or p.parent.resolve() != out.resolve()]  # fmt: skip
    if not found:
        return None
    newest = max(found, key=lambda p: p.stat().st_mtime_ns)
    return dict(json.loads(newest.read_text()))


def _difference_error(errors: Mapping[str, Any], kind: str, reference: float | None) -> str:
    """`` +- x %``: the standard error of candidate - full relative to ``reference``, from
    the summary's ``mean_duration_errors`` (independent runs); empty where either is unknown."""
    a = (errors.get("candidate") or {}).get(kind)
    b = (errors.get("full") or {}).get(kind)
    if a is None or b is None or not reference:
        return ""
    return f" +- {100 * math.hypot(a, b) / reference:.1f} %"


def _rel(value: float | None, reference: float | None) -> str:
    if value is None or not reference:
        return ""
    return f"{100 * (value / reference - 1):+.1f} %"


def _diagnostic_text(metrics: Mapping[str, Any], lumps: tuple[str, str]) -> str:
    d = metrics.get("diagnostic") or {}
    rows = []
    for p in (0, 1):
        s = d.get(f"phi{p}")
        if s:
            rows.append({
                "leaving": lumps[p],
                "switching prob., learned": s["mean_switching_learned"],
                f"{d['reference']} reference": s["mean_switching_reference"],
                "bias": f"{100 * s['rel_bias']:+.1f} %",
                "mean abs. rel. error": f"{100 * s['mean_abs_rel_error']:.1f} %",
                "90th pct.": f"{100 * s['p90_abs_rel_error']:.1f} %",
            })  # fmt: skip
    if not rows:
        return "No diagnostic was computed."
    o = d.get("settings", {})
    text = (
        f"The learned switching probabilities against the {d['reference']} psi, weighted by "
        f"where an unperturbed full-model population lives ({o.get('n_cells')} cells from "
        f"{o.get('start')} for {o.get('t_end')} s in the training field; {d['n_occupancy']} "
        "occupied points"
        + (
            f"; grown from {d['grown_from']} cells, whose reference was too noisy to judge the bias"
            if d.get("grown_from")
            else ""
        )
        + "). The bias predicts the relative error of the mean segment duration "
        "(with the opposite sign).\n\n" + format_markdown_table(pd.DataFrame(rows), ".4f")
    )
    return (
        text
        + _class_diagnostic_text(metrics.get("class_diagnostic") or {})
        + _class_shares_text(metrics.get("class_shares") or {})
    )


def _class_shares_text(d: Mapping[str, Any]) -> str:
    """The K-lumps chain's class shares against the full model's (empty without them)."""
    if d.get("p_value") is None:
        return ""
    rows = [{"class": n, "full model": f"{100 * d['full'][n]:.1f} %",
             "chain": f"{100 * d['chain'][n]:.1f} %"} for n in d["full"]]  # fmt: skip
    return (
        f"\n\nThe chain's class shares, run as the diagnostic's population was ({d['n_chain']} "
        f"cells, {d['t']:g} s), against the full model's ({d['n_full']}): total variation "
        f"{100 * d['total_variation']:.1f} %, chi-square p = {d['p_value']:.2g}"
        + (" (they drift)" if d["drift"] else "")
        + ".\n\n"
        + format_markdown_table(pd.DataFrame(rows), ".4f")
    )


def _class_diagnostic_text(d: Mapping[str, Any]) -> str:
    """The K-lumps chain's law (what a gp.lumps=classes run simulates) where the population
    lives: per origin class, its chance of leaving the lump (empty without one)."""
    rows = [{"leaving class": name, "share": f"{100 * s['share']:.1f} %",
             "switching prob., learned": s["mean_switching_learned"],
             f"{d['reference']} reference": s["mean_switching_reference"],
             "bias": percent(s["rel_bias"])}
            for name, s in d.items() if isinstance(s, dict)]  # fmt: skip
    if not rows:
        return ""
    return (
        "\n\nThe simulated chain is the K-lumps chain over the model's classes; its law, scored "
        "the same way per origin class (the chance of leaving the class's lump; share: the "
        "class's part of the occupied points):\n\n"
        + format_markdown_table(pd.DataFrame(rows), ".4f")
    )


def _outside_text(settings: ReproduceSettings) -> str:
    """Per field: the share of the abstraction's sampled cell-steps whose inputs left the range
    its training data covered (its run's manifest, ``outside_training``)."""
    rows = []
    for name, e in settings.evaluations.items():
        report = read_manifest(e.candidate.directory).get("outside_training")
        if not report:
            continue
        sparse = sparse_share(report)
        where = report.get("sparse_where") or {}
        # checked per class (a K-lumps chain): the region's class before its interval
        cls = f"{report['sparse_class']}: " if report.get("sparse_class") is not None else ""
        for input_name, r in report["inputs"].items():
            row = {"field": name, "input": input_name,
                   "outside": f"{100 * report['share_outside']:.2f} %",
                   "below": f"{100 * r['share_below']:.2f} %",
                   "above": f"{100 * r['share_above']:.2f} %",
                   "seen": f"[{r['seen'][0]:.4g}, {r['seen'][1]:.4g}]",
                   "trained": f"[{r['trained'][0]:.4g}, {r['trained'][1]:.4g}]",
                   "sparse": "not stored" if sparse is None else f"{100 * sparse:.2f} %",
                   "sparse where": (f"{cls}[{where[input_name][0]:.4g}, "
                                    f"{where[input_name][1]:.4g}]"
                                    if input_name in where else "")}  # fmt: skip
            rows.append(row)
    if not rows:
        return "The abstraction's runs recorded no inputs (runs made before this was recorded)."
    return (
        "The share of the abstraction's cell-steps (sampled every record interval) whose inputs "
        "lay outside the range its training transitions covered (each input's min and max over "
        "the training rows). The lookup table clamps there, so those steps use the psi at the "
        "range's edge, not a learned value; a run warns above `outside_warning` (default 1 %). "
        "Sparse: the share inside the range in bins of the training rows' histogram (stored "
        "with the fit; `not stored` for an older fit) where a state (for a K-lumps chain, the "
        "cell's own class) has fewer rows than `support_min_rows` (default: 25 expected "
        "switches, or moves out of the class, a rate within 20 %), warned above the same "
        "threshold; sparse where: the most visited such region (after its class, per class)."
        "\n\n" + format_markdown_table(pd.DataFrame(rows))
    )


def _measured_speed_text(speed: Mapping[str, Any], batched: bool = True) -> str:
    from surrogate.simulate.speed import LoopTiming, loop_name

    rows = [{"model": k, "loop": loop_name(LoopTiming.from_mapping(speed[k])),
             "loop (s)": speed[k]["seconds"], "us/step": speed[k]["us_per_step"],
             "cell-steps/s": speed[k]["cell_steps_per_s"], "compile (s)": speed[k]["compile_s"]}
            for k in ("full", "abstract")]  # fmt: skip
    same = speed.get("same_loop") or {}
    fastest = speed.get("fastest") or {}
    if speed["speedup"]:
        ratio = (f"**{speed['speedup']:.4g}x** per cell-step, each model on the loop "
                 f"`backend={speed.get('backend', 'torch')}` picks for it (full: "
                 f"{fastest.get('full')}, abstraction: {fastest.get('abstract')}); "
                 + ("on the same loop: " + ", ".join(f"{k} {v:.4g}x" for k, v in same.items())
                    if same else "the two loops differ, so no same-loop ratio here "
                    "(`python scripts/speed.py` times both models on every loop)")
                 + " (excluding collection and training, as in the paper). ")  # fmt: skip
    else:
        ratio = f"none: {'; '.join(speed.get('speed_not_comparable', []))}. "
    runs = (
        "The runs above were simulated in one batch (one loop for several runs), so they "
        "have no loop time of their own. "
        if batched
        else "The runs above were timed apart "
        "(each with its own compile and machine load), so their times make no ratio. "
    )
    return (
        runs
        + f"Loop speed measured side by side in this process: "
        f"{speed['n_cells']} cells x {speed['steps']} steps in field {speed['field']}, "
        f"compile={str(speed['compile']).lower()}, {speed['threads']} thread(s), best of two, "
        f"after a warm-up (compile time separate). Abstraction speed-up: " + ratio
        + "Both models are batched over cells, so the ratio is far smaller than against a "
        "per-cell implementation.\n\n"
        + format_markdown_table(pd.DataFrame(rows), {"loop (s)": ".3f", "us/step": ".1f",
                                                     "cell-steps/s": ".3g", "compile (s)": ".1f"})
    )  # fmt: skip

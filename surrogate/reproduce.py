"""The whole paper from one command: collect -> train -> full and abstracted simulations on
L1, L2, L3 -> evaluate -> ``report.md`` with Table 1 beside the paper's, speed-ups and figures.

Every stage reuses artefacts that already exist for the same settings.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import OmegaConf

from surrogate import collect, train
from surrogate.config import field_config, to_dict, validate_common
from surrogate.errors import ConfigError
from surrogate.evaluate import stage as evaluate_stage
from surrogate.evaluate.report import format_markdown_table, table1_markdown, write_report
from surrogate.io import (
    MANIFEST,
    artefact_dir,
    artefact_lock,
    read_csv,
    read_json,
    read_manifest,
    write_manifest,
)
from surrogate.paths import abstraction_config, train_settings

log = logging.getLogger(__name__)

REPORT = "report.md"


def field_run_config(cfg: Mapping[str, Any], field: str) -> Any:
    """The evaluate config for one field: same settings, that field, missing runs simulated."""
    c = OmegaConf.create(to_dict(cfg))
    c.field = field_config(field)
    c.evaluate.run_missing = True
    return c


def train_config(cfg: Mapping[str, Any]) -> Any:
    """The collect/train config: the field the abstraction is trained on."""
    c = OmegaConf.create(to_dict(cfg))
    c.field = abstraction_config(cfg)["field"]
    return c


def validate(cfg: Mapping[str, Any]) -> None:
    """Checks before any work: every field exists, every stage's settings are valid."""
    fields = list(cfg.get("fields") or [])
    if not fields:
        raise ConfigError("fields must list at least one field, e.g. [gaussian, linear, dynamic]")
    for name in fields:
        field_config(str(name))
    validate_common(cfg)
    collect.validate(train_config(cfg))
    train.validate(train_config(cfg))
    # the simulate/evaluate settings too: a bad n_cells must not surface after collect and train
    for name in fields:
        evaluate_stage.validate(field_run_config(cfg, str(name)))


def reproduce_dir(cfg: Mapping[str, Any]) -> Path:
    """``data/reproduce/dt=..._n=..._T=..._kernel=..._seed=...-<hash>``."""
    settings = {"train": train_settings(train_config(cfg)), "fields": list(cfg["fields"]),
                **{k: to_dict(cfg)[k] for k in ("n_cells", "t_end", "record_interval", "start",
                                                "equilibration_time", "decision", "evaluate")}}  # fmt: skip
    label = {"dt": float(cfg["dt"]), "n": cfg["n_cells"], "T": cfg["t_end"],
             "kernel": cfg["gp"]["kernel"], "seed": cfg["seed"]}  # fmt: skip
    return artefact_dir(cfg["data_dir"], "reproduce", label, settings)


def run(cfg: Mapping[str, Any]) -> Path:
    """Run every stage (reusing what exists) and write the report; return its directory."""
    validate(cfg)
    t0 = time.perf_counter()
    tcfg = train_config(cfg)
    collect_dir = collect.run(tcfg)
    train_dir = train.run(tcfg)
    evaluations: dict[str, Path] = {}
    for name in cfg["fields"]:
        log.info("field %s: full and abstracted simulations, evaluation", name)
        evaluations[str(name)] = evaluate_stage.run(field_run_config(cfg, str(name)))
    out = reproduce_dir(cfg)
    with artefact_lock(out):  # also removes the temporaries of killed runs
        sections = report_sections(cfg, collect_dir, train_dir, evaluations, out)
        (out / MANIFEST).unlink(missing_ok=True)  # incomplete until the manifest is rewritten
        write_report(out / REPORT, *sections,
                     title="Statistical abstraction of E. coli chemotaxis: reproduction report")  # fmt: skip
        write_manifest(out, stage="reproduce", config=to_dict(cfg), seed=int(cfg["seed"]),
                       collect=str(collect_dir), train=str(train_dir),
                       evaluations={k: str(v) for k, v in evaluations.items()},
                       wall_time_s=time.perf_counter() - t0)  # fmt: skip
    log.info("report written to %s", out / REPORT)
    return out


def report_sections(
    cfg: Mapping[str, Any],
    collect_dir: Path,
    train_dir: Path,
    evaluations: Mapping[str, Path],
    out: Path,
) -> tuple[list[tuple[str, str]], list[tuple[str, Path]]]:
    """Markdown sections and figures of the report."""
    tables = {name: read_csv(d / f"{evaluate_stage.COMPARISON}.csv", made_by=evaluate_stage.EVALUATE_CMD)
              for name, d in evaluations.items()}  # fmt: skip
    summaries = {name: evaluate_stage.read_summary(d) for name, d in evaluations.items()}
    speedups = {name: s["speedup_loop"] for name, s in summaries.items()}
    metrics = read_json(train_dir / train.METRICS)
    collect_manifest = read_manifest(collect_dir)

    setting = (
        f"{cfg['n_cells']} cells per run, t_end = {cfg['t_end']} s, dt = {cfg['dt']} s, seed {cfg['seed']}; "
        f"abstraction trained on `{cfg['decision']['train_field']}` transitions "
        f"({collect_manifest['counts_per_origin']['tumble']} from TUMBLE, "
        f"{collect_manifest['counts_per_origin']['run']} from RUN; collected in "
        f"{collect_manifest['wall_time_s']:.1f} s), GP kernel `{cfg['gp']['kernel']}` with "
        f"{cfg['gp']['n_inducing']} inducing points (trained in {metrics['train_seconds_total']:.1f} s), "
        f"decision mode `{cfg['decision']['mode']}`."
    )
    table1 = (
        "KS distance (p-value) between the full and the abstracted model: cells' distance from the "
        "peak at four times, and run / tumble durations (1,000 sampled each, as in the paper). "
        "The *noise floor* row is the same statistic between two full runs with different seeds; "
        "† marks a value above both the noise floor and the KS 5 % critical value.\n\n"
        + table1_markdown(tables, speedups)
    )
    speed_rows = pd.DataFrame(
        [
            {
                "field": name,
                "full loop (s)": s["loop_time_s"]["full"],
                "abstract loop (s)": s["loop_time_s"]["abstract"],
                "full cell-steps/s": s["cell_steps_per_s"]["full"],
                "abstract cell-steps/s": s["cell_steps_per_s"]["abstract"],
                "speed-up": s["speedup_loop"],
                "paper speed-up": {"gaussian": 7.8, "linear": 9.4, "dynamic": 8.9}.get(
                    name, float("nan")
                ),
            }
            for name, s in summaries.items()
        ]
    )
    speed = (
        "Wall-clock time of the simulation loops, measured in this run on the same machine "
        "(excluding collection and training, as in the paper). Both models are batched over cells, "
        "so the ratio is far smaller than against a per-cell implementation; see the README's "
        "benchmark for throughput at larger populations.\n\n"
        + format_markdown_table(
            speed_rows,
            floatfmt={
                "full cell-steps/s": ".3g",
                "abstract cell-steps/s": ".3g",
                "speed-up": ".1f",
                "paper speed-up": ".1f",
            },
        )
    )
    noise_lines = []
    for name, table in tables.items():
        if "ks_noise_floor" not in table:
            continue
        above = table[~table["within_noise"].astype(bool)]["quantity"].tolist()
        noise_lines.append(
            f"- **{name}**: largest KS {table['ks'].max():.3f} vs noise floor {table['ks_noise_floor'].max():.3f}; "
            + (
                "every quantity within the noise floor or the KS critical value."
                if not above
                else f"above noise: {', '.join(above)}."
            )
        )
    gp_rows = pd.DataFrame(
        [
            {"classifier": name, **{k: metrics[name]["validation"][k] for k in
                                    ("brier", "brier_baseline", "mean_log_predictive", "accuracy", "n")}}
            for name in ("psi_tumble", "psi_run")
        ]
    )  # fmt: skip
    sections = [
        ("Setting", setting),
        ("Table 1: abstracted vs full model", table1),
        ("Against sampling noise", "\n".join(noise_lines) or "No noise floor was computed."),
        ("Speed", speed),
        ("Classifiers (held-out validation)", format_markdown_table(gp_rows, floatfmt=".4f")),
        (
            "Artefacts",
            "\n".join(
                f"- {k}: `{os.path.relpath(v, out)}`"
                for k, v in {"collect": collect_dir, "train": train_dir, **evaluations}.items()
            ),
        ),
    ]
    figures = [("GP probability surfaces (paper Figure 3)", train_dir / train.SURFACES_FIGURE)]
    for name, d in evaluations.items():
        figures.append(
            (
                f"{name}: distance histograms, full vs abstract (paper Figure 4)",
                d / "distance_histograms.png",
            )
        )
        figures.append(
            (
                f"{name}: mean and s.d. of distance over time (paper Figure 5)",
                d / "distance_over_time.png",
            )
        )
    return sections, figures

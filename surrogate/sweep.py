"""One table for a whole Hydra sweep: every job's settings, outcome and headline results.

Each job of a multirun writes ``job_status.json`` into its output directory (``surrogate.cli``):
ok/failed, the error, the overrides and the artefact directory. :func:`summarize` reads them all,
follows each artefact directory to its results (evaluate ``summary.json``, train manifests), and
writes ``summary.csv`` (one row per job) and ``summary.png`` (max KS distance and speed-up
against dt, one line per setting of the other swept parameters) into the sweep directory.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import OmegaConf

from surrogate.config import field_name
from surrogate.errors import ArtefactError, MissingArtefactError, SurrogateError
from surrogate.io import JOB_STATUS, read_json, read_manifest, save_figure, write_csv

log = logging.getLogger(__name__)

SUMMARY_CSV = "summary.csv"
SUMMARY_PNG = "summary.png"
SUMMARY_CMD = "python scripts/summarize.py"

#: Columns before the per-job results, in this order (swept parameters go after ``job``).
LEAD = ("job", "status", "stage", "error_type", "error")
#: Columns after the results.
TAIL = ("wall_time_s", "threads", "artefact_dir", "overrides", "job_dir")
#: (column prefix, axis label) of the plotted results; one panel column per field.
PLOTTED = (
    ("max_ks_", "max KS distance (abstract vs full)"),
    ("speedup_", "loop speed-up (full / abstract)"),
)


# ----------------------------------------------------------------------------------------------
# reading a sweep


def job_dirs(sweep_dir: str | Path) -> list[Path]:
    """Every Hydra job directory under ``sweep_dir`` (those holding ``.hydra/overrides.yaml``)."""
    root = Path(sweep_dir)
    found = [p.parent.parent for p in root.rglob("overrides.yaml") if p.parent.name == ".hydra"]
    return sorted({d for d in found if ".submitit" not in d.parts}, key=_job_sort_key)


def _job_sort_key(path: Path) -> tuple[float, str]:
    # numbered job dirs in numeric order (10 after 9), anything else after them
    return (float(path.name), "") if path.name.isdigit() else (math.inf, str(path))


def parse_overrides(overrides: Sequence[str]) -> dict[str, Any]:
    """``["dt=0.05", "gp.kernel=rbf"]`` -> ``{"dt": 0.05, "gp.kernel": "rbf"}`` (Hydra's parser,
    so values are typed as Hydra types them; lists and dicts become their override text)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed: dict[str, Any] = {}
    for o in OverridesParser.create().parse_overrides(list(overrides)):
        value = o.value()
        if not isinstance(value, str | int | float | bool) and value is not None:
            value = o.get_value_element_as_str() if not o.is_sweep_override() else str(value)
        parsed[o.key_or_group] = value
    return parsed


def swept_keys(sweep_dir: str | Path, jobs_overrides: Sequence[Mapping[str, Any]]) -> list[str]:
    """The parameters the sweep varied: sweep overrides (``a=1,2``, ``range(...)``) of the
    sweep's ``multirun.yaml``; without it, keys whose value differs between jobs."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    path = Path(sweep_dir) / "multirun.yaml"
    if path.exists():
        try:
            task = OmegaConf.load(path).hydra.overrides.task
            parsed = OverridesParser.create().parse_overrides([str(o) for o in task])
            return [o.key_or_group for o in parsed if o.is_sweep_override()]
        except Exception as exc:  # a hand-edited or foreign multirun.yaml: fall back
            log.warning("could not read the sweep's overrides from %s: %s", path, exc)
    keys: list[str] = []
    for ov in jobs_overrides:
        keys += [k for k in ov if k not in keys]
    return [k for k in keys if len({repr(ov.get(k)) for ov in jobs_overrides}) > 1]


def read_job(job_dir: Path) -> dict[str, Any]:
    """One job's row: its status (``missing`` without ``job_status.json``: killed, still
    running, or not run through surrogate.cli), overrides, and results where it succeeded."""
    overrides = [str(o) for o in OmegaConf.load(job_dir / ".hydra" / "overrides.yaml")]
    row: dict[str, Any] = {"job": int(job_dir.name) if job_dir.name.isdigit() else job_dir.name}
    status_path = job_dir / JOB_STATUS
    if status_path.exists():
        try:
            status = json.loads(status_path.read_text())
        except json.JSONDecodeError as exc:
            status = {"status": "missing", "error": f"{status_path} is corrupt: {exc}"}
    else:
        status = {"status": "missing", "error": f"no {JOB_STATUS}: the job was killed, is still "
                  "running, or did not run through surrogate.cli"}  # fmt: skip
    row.update({k: status.get(k) for k in ("status", "stage", "error_type", "error",
                                           "wall_time_s", "threads", "artefact_dir")})  # fmt: skip
    row["overrides"] = " ".join(overrides)
    row["job_dir"] = str(job_dir)
    row["_overrides"] = parse_overrides(overrides)
    if status.get("status") == "ok" and status.get("artefact_dir"):
        try:
            row.update(job_results(Path(status["artefact_dir"])))
        except (SurrogateError, KeyError, OSError, ValueError) as exc:
            row["note"] = f"results unreadable: {type(exc).__name__}: {exc}"
    return row


# ----------------------------------------------------------------------------------------------
# results of one job, by stage


def job_results(directory: Path) -> dict[str, Any]:
    """Headline results of a job's artefact directory, by the stage that made it."""
    manifest = read_manifest(directory)
    stage = manifest.get("stage")
    if stage == "reproduce":
        out: dict[str, Any] = {}
        for field, d in manifest["evaluations"].items():
            out.update(evaluation_results(Path(d), field))
        speed = manifest.get("speed")  # batched runs: measured side by side on one field
        if speed:
            out[f"speedup_{speed['field']}"] = speed.get("speedup")
        out.update(train_results(Path(manifest["train"])))
        return out
    if stage == "evaluate":
        field = field_name(manifest["config"]["field"])
        out = evaluation_results(directory, field)
        candidate = read_manifest(Path(manifest["runs"]["candidate"]))
        if candidate.get("abstraction_dir"):
            out.update(train_results(Path(candidate["abstraction_dir"])))
        return out
    if stage == "train":
        return train_results(directory, manifest)
    if stage == "simulate":
        out = {k: manifest.get(k) for k in ("n_cells", "loop_time_s", "cell_steps_per_s")}
        out.update({f"final_mean_{k}": v for k, v in (manifest.get("final_means") or {}).items()})
        return out
    if stage == "collect":
        return {"n_transitions": manifest.get("n_rows"), "collect_s": manifest.get("wall_time_s")}
    return {}


def evaluation_results(directory: Path, field: str) -> dict[str, Any]:
    """Per-field columns from an evaluate directory's ``summary.json``."""
    s = read_json(directory / "summary.json", made_by="python scripts/evaluate.py")
    return {
        f"max_ks_{field}": s.get("max_ks"),
        f"max_ks_noise_{field}": s.get("max_ks_noise_floor"),
        f"within_noise_{field}": s.get("all_within_noise"),
        f"speedup_{field}": s.get("speedup_loop"),
    }


def train_results(directory: Path, manifest: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Held-out Brier scores (and the constant predictor's), the switching probabilities'
    bias where the population lives, and training time."""
    m = manifest if manifest is not None else read_manifest(directory)
    out: dict[str, Any] = {}
    for name in ("psi_0", "psi_1"):
        out[f"brier_{name}"] = (m.get("brier") or {}).get(name)
        out[f"brier_baseline_{name}"] = (m.get("brier_baseline") or {}).get(name)
    diagnostic = m.get("diagnostic") or {}
    for p in (0, 1):
        d = diagnostic.get(f"phi{p}") or {}
        out[f"switch_bias_phi{p}"] = d.get("rel_bias")
    out["train_s"] = m.get("wall_time_s")
    return out


# ----------------------------------------------------------------------------------------------
# the table and the figure


def sweep_table(sweep_dir: str | Path) -> tuple[pd.DataFrame, list[str]]:
    """One row per job of the sweep, and the swept parameters (columns after ``job``)."""
    root = Path(sweep_dir)
    if not root.is_dir():
        raise MissingArtefactError(f"sweep directory {root} does not exist")
    dirs = job_dirs(root)
    if not dirs:
        raise ArtefactError(
            f"no Hydra jobs under {root} (no */.hydra/overrides.yaml); pass the directory a "
            f"multirun printed as 'sweep output dir'"
        )
    rows = [read_job(d) for d in dirs]
    swept = swept_keys(root, [r["_overrides"] for r in rows])
    for r in rows:
        ov = r.pop("_overrides")
        r.update({k: ov.get(k) for k in swept})
    df = pd.DataFrame(rows)
    results = sorted(c for c in df.columns if c not in (*LEAD, *TAIL, *swept, "note"))
    order = [*LEAD[:1], *swept, *LEAD[1:], *results, *(["note"] if "note" in df else []), *TAIL]
    return df[order], swept


def plot_sweep(df: pd.DataFrame, swept: Sequence[str]) -> Any | None:
    """Max KS and speed-up against dt, one line per setting of the other swept parameters, one
    column of panels per field; ``None`` when dt was not swept or no job has those results."""
    if "dt" not in swept:
        log.info("dt was not swept: no summary plot")
        return None
    ok = df[df["status"] == "ok"].copy()
    fields = sorted(
        c[len("max_ks_"):] for c in ok.columns
        if c.startswith("max_ks_") and not c.startswith("max_ks_noise_") and ok[c].notna().any()
    )  # fmt: skip
    if not fields:
        log.info("no successful job with evaluation results: no summary plot")
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    others = [k for k in swept if k != "dt"]
    ok["dt"] = pd.to_numeric(ok["dt"], errors="coerce")
    fig, axes = plt.subplots(len(PLOTTED), len(fields), figsize=(4.5 * len(fields), 6.5),
                             squeeze=False, sharex=True)  # fmt: skip
    groups = ok.groupby([ok[k].astype(str) for k in others], sort=True) if others else [((), ok)]
    for key, rows in groups:
        key = key if isinstance(key, tuple) else (key,)
        label = ", ".join(f"{k}={v}" for k, v in zip(others, key, strict=True)) or "all jobs"
        rows = rows.sort_values("dt")
        for j, field in enumerate(fields):
            for i, (prefix, _) in enumerate(PLOTTED):
                col = f"{prefix}{field}"
                if col in rows:
                    (line,) = axes[i, j].plot(rows["dt"], rows[col], marker="o", label=label)
                    noise = f"max_ks_noise_{field}"
                    if prefix == "max_ks_" and noise in rows and rows[noise].notna().any():
                        axes[i, j].plot(rows["dt"], rows[noise], ls=":", color=line.get_color())
    for j, field in enumerate(fields):
        axes[0, j].set_title(f"{field} (dotted: noise floor, full vs full)")
        axes[-1, j].set_xlabel("dt (s)")
        for i, (_, ylabel) in enumerate(PLOTTED):
            axes[i, j].set_ylabel(ylabel)
            axes[i, j].grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    n_failed = int((df["status"] != "ok").sum())
    fig.suptitle(
        f"Sweep: {len(ok)} successful job(s)"
        + (f", {n_failed} not shown (failed or missing)" if n_failed else "")
    )
    fig.tight_layout()
    return fig


def summarize(sweep_dir: str | Path) -> tuple[pd.DataFrame, Path, Path | None]:
    """Write ``summary.csv`` (and ``summary.png`` when dt was swept) into ``sweep_dir``.

    Returns:
        The table, the CSV path and the figure path (``None`` when no plot was made).
    """
    root = Path(sweep_dir)
    df, swept = sweep_table(root)
    csv = write_csv(root / SUMMARY_CSV, df)
    fig = plot_sweep(df, swept)
    png = save_figure(root / SUMMARY_PNG, fig) if fig is not None else None
    counts = df["status"].value_counts().to_dict()
    log.info("sweep %s: %d job(s): %s; summary in %s", root, len(df),
             ", ".join(f"{n} {s}" for s, n in sorted(counts.items())), csv)  # fmt: skip
    for _, r in df[df["status"] != "ok"].iterrows():
        where = ", ".join(f"{k}={r[k]}" for k in swept) or r["overrides"]
        kind = f"{r['error_type']}: " if isinstance(r.get("error_type"), str) else ""
        log.warning("job %s (%s) %s: %s%s", r["job"], where, r["status"], kind, r["error"])
    return df, csv, png

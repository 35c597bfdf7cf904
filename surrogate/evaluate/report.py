"""Markdown rendering of comparison tables and the evaluation report.

Tables are rendered by hand (no ``tabulate`` dependency). Everything is written atomically
through ``surrogate.io``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from surrogate.io import write_csv, write_text

#: The paper's Table 1 (Michaelides, Hillston & Sanguinetti): KS distance between 100 full and
#: 100 abstracted cells' distances from the peak at t = 125/250/375/500 s, and between 1,000
#: sampled run / tumble durations of each model, with the p-values printed under each distance,
#: and the observed speed-up. Quantity keys match ``comparison_table``'s ``quantity`` column.
#: Transcribed as published; note the linear field's t=125 s distance 0.010 cannot go with its
#: p-value 0.677 (with 100 cells per model a KS distance below 0.01 is impossible and 0.010 would
#: give p = 1), so it is probably a typo for 0.100.
PAPER_TABLE1: dict[str, dict[str, Any]] = {
    "gaussian": {
        "label": "Gaussian L1(r)",
        "ks": {
            "distance_t125": 0.110,
            "distance_t250": 0.160,
            "distance_t375": 0.170,
            "distance_t500": 0.160,
            "run": 0.039,
            "tumble": 0.101,
        },
        "ks_pvalue": {
            "distance_t125": 0.556,
            "distance_t250": 0.140,
            "distance_t375": 0.099,
            "distance_t500": 0.140,
            "run": 0.425,
            "tumble": 7e-5,
        },
        "speedup": 7.8,
    },
    "linear": {
        "label": "Linear L2(r)",
        "ks": {
            "distance_t125": 0.010,
            "distance_t250": 0.150,
            "distance_t375": 0.170,
            "distance_t500": 0.130,
            "run": 0.022,
            "tumble": 0.014,
        },
        "ks_pvalue": {
            "distance_t125": 0.677,
            "distance_t250": 0.193,
            "distance_t375": 0.100,
            "distance_t500": 0.344,
            "run": 0.967,
            "tumble": 0.100,
        },
        "speedup": 9.4,
    },
    "dynamic": {
        "label": "Dynamic Gaussian L3(r, t)",
        "ks": {
            "distance_t125": 0.140,
            "distance_t250": 0.070,
            "distance_t375": 0.140,
            "distance_t500": 0.080,
            "run": 0.047,
            "tumble": 0.039,
        },
        "ks_pvalue": {
            "distance_t125": 0.261,
            "distance_t250": 0.961,
            "distance_t375": 0.261,
            "distance_t500": 0.894,
            "run": 0.214,
            "tumble": 0.425,
        },
        "speedup": 8.9,
    },
}

#: The quantities of the paper's Table 1, in column order.
PAPER_QUANTITIES: tuple[str, ...] = (
    "distance_t125",
    "distance_t250",
    "distance_t375",
    "distance_t500",
    "run",
    "tumble",
)

#: Formats ``write_comparison`` uses: p-values span many decades, so fixed-point would show 0.
COMPARISON_FORMATS: dict[str, str] = {"ks_pvalue": ".3g", "ks_pvalue_full": ".3g"}

_DISTANCE_PREFIX = "distance_t"


def paper_table1_frame() -> pd.DataFrame:
    """``PAPER_TABLE1`` as a long table: ``field``, ``quantity``, ``ks``, ``ks_pvalue``."""
    rows = [
        {"field": name, "quantity": q, "ks": entry["ks"][q], "ks_pvalue": entry["ks_pvalue"][q]}
        for name, entry in PAPER_TABLE1.items()
        for q in PAPER_QUANTITIES
    ]
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------------------------
# markdown


def format_markdown_table(df: pd.DataFrame, floatfmt: str | Mapping[str, str] = ".3f") -> str:
    """Render ``df`` as a GitHub-flavoured Markdown table (no index).

    Args:
        df: The table.
        floatfmt: Format spec for float cells, or a mapping column -> spec (columns not named
            use ".3f").

    NaN and None render as empty cells, booleans as ``yes``/``no``; numeric columns are
    right-aligned; ``|`` inside text is escaped.
    """
    columns = [str(c) for c in df.columns]
    lines = [
        "| " + " | ".join(_escape(c) for c in columns) + " |",
        "|" + "|".join("---:" if _is_numeric(df[c]) else ":---" for c in df.columns) + "|",
    ]
    for row in df.itertuples(index=False, name=None):
        cells = [
            _format_cell(value, _spec(floatfmt, col))
            for value, col in zip(row, columns, strict=True)
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _spec(floatfmt: str | Mapping[str, str], column: str) -> str:
    if isinstance(floatfmt, str):
        return floatfmt
    return floatfmt.get(column, ".3f")


def _is_numeric(series: pd.Series) -> bool:
    return pd.api.types.is_numeric_dtype(series) and not pd.api.types.is_bool_dtype(series)


def _format_cell(value: Any, spec: str) -> str:
    if value is None or value is pd.NA or value is pd.NaT:
        return ""
    if isinstance(value, bool):  # before the number check: bool is an int subclass
        return "yes" if value else "no"
    if hasattr(value, "item") and not isinstance(value, str):  # numpy scalar -> Python
        value = value.item()
        if isinstance(value, bool):
            return "yes" if value else "no"
    if isinstance(value, float):
        return "" if math.isnan(value) else format(value, spec)
    return _escape(str(value))


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _fmt_p(p: float) -> str:
    # the paper prints 7e-5 for the smallest p-value; fixed point would say 0.000
    return f"{p:.3f}" if p >= 1e-3 else f"{p:.0e}"


def _distance_time(quantity: str) -> float:
    return float(quantity[len(_DISTANCE_PREFIX) :])


def table1_markdown(
    results: Mapping[str, pd.DataFrame],
    speedups: Mapping[str, float],
    floatfmt: str = ".3f",
) -> str:
    """Our KS distances beside the paper's Table 1, one block of sub-rows per field.

    Args:
        results: Field name ("gaussian", "linear", "dynamic", or another) -> a
            ``comparison_table`` (optionally passed through ``combine_with_noise_floor``).
        speedups: Field name -> our speed-up factor (missing fields show "–").
        floatfmt: Format of KS distances.

    Each field gets an ``ours`` row (``KS (p-value)``), a ``paper`` row (when the paper has the
    field) and a ``noise floor`` row (when the table has ``ks_noise_floor``). An ours-cell is
    marked ``†`` when ``within_noise`` is False. When our distance times differ from the paper's
    125/250/375/500 s (e.g. shorter runs), columns are matched by position and each of our
    cells states its time.
    """
    ours_distance = {name: _distance_rows(df) for name, df in results.items()}
    paper_times = [_distance_time(q) for q in PAPER_QUANTITIES[:4]]
    same_times = all(
        [_distance_time(q) for q in qs] == paper_times for qs in ours_distance.values()
    )
    n_dist = max([4, *(len(qs) for qs in ours_distance.values())])
    if same_times:
        dist_headers = [f"t={t:g} s" for t in paper_times]
    else:
        dist_headers = [
            f"distance {i + 1}" + (f" (paper t={paper_times[i]:g} s)" if i < 4 else "")
            for i in range(n_dist)
        ]
    header = ["Field", "Source", *dist_headers, "Run", "Tumble", "Speed-up"]
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join([":---", ":---", *["---:"] * (len(header) - 2)]) + "|",
    ]
    any_flag = False
    for name, df in results.items():
        by_q = df.set_index("quantity")
        dist_qs = ours_distance[name]
        cells: list[str] = []
        for i in range(n_dist):
            if i >= len(dist_qs):
                cells.append("")
                continue
            q = dist_qs[i]
            cell = _ours_cell(by_q.loc[q], floatfmt)
            cells.append(cell if same_times else f"{cell} @{_distance_time(q):g} s")
        for kind in ("run", "tumble"):
            cells.append(_ours_cell(by_q.loc[kind], floatfmt) if kind in by_q.index else "")
        any_flag = any_flag or any("†" in c for c in cells)
        sp = speedups.get(name)
        sp_cell = "–" if sp is None or not math.isfinite(float(sp)) else f"{float(sp):.1f}"
        lines.append("| " + " | ".join([name, "ours", *cells, sp_cell]) + " |")

        paper = PAPER_TABLE1.get(name)
        if paper is not None:
            pcells = [
                f"{paper['ks'][q]:{floatfmt}} ({_fmt_p(paper['ks_pvalue'][q])})"
                for q in PAPER_QUANTITIES[:4]
            ] + [""] * (n_dist - 4)
            pcells += [
                f"{paper['ks'][k]:{floatfmt}} ({_fmt_p(paper['ks_pvalue'][k])})"
                for k in ("run", "tumble")
            ]
            lines.append(
                "| " + " | ".join(["", "paper", *pcells, f"{paper['speedup']:.1f}"]) + " |"
            )

        if "ks_noise_floor" in df.columns:
            floor = by_q["ks_noise_floor"]
            fcells = [_num(floor.get(q), floatfmt) for q in dist_qs]
            fcells += [""] * (n_dist - len(dist_qs))
            fcells += [_num(floor.get(k), floatfmt) for k in ("run", "tumble")]
            lines.append("| " + " | ".join(["", "noise floor", *fcells, ""]) + " |")

    notes = [
        "",
        "Cells: KS distance (p-value). Run/tumble: a random subsample of durations from each "
        "model (1,000 in the paper). "
        "Noise floor: KS distance between two full-model runs with different seeds.",
    ]
    if any_flag:
        notes.append(
            "† KS distance above both the noise floor and the 5 % critical value "
            "(outside sampling noise)."
        )
    return "\n".join(lines + notes) + "\n"


def _distance_rows(df: pd.DataFrame) -> list[str]:
    qs = [str(q) for q in df["quantity"] if str(q).startswith(_DISTANCE_PREFIX)]
    return sorted(qs, key=_distance_time)


def _ours_cell(row: pd.Series, floatfmt: str) -> str:
    cell = f"{float(row['ks']):{floatfmt}} ({_fmt_p(float(row['ks_pvalue']))})"
    if "within_noise" in row.index and not bool(row["within_noise"]):
        cell += " †"
    return cell


def _num(value: Any, floatfmt: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return f"{float(value):{floatfmt}}"


# ----------------------------------------------------------------------------------------------
# files


def write_report(
    path: str | os.PathLike,
    sections: Sequence[tuple[str, str]],
    figures: Sequence[tuple[str, Path]],
    title: str = "Evaluation report",
) -> Path:
    """Write a Markdown report atomically: a title, ``## heading`` sections, then figures.

    Args:
        path: The report file (e.g. ``.../report.md``).
        sections: ``(heading, markdown body)`` pairs, in order.
        figures: ``(caption, image path)`` pairs; links are written relative to the report's
            directory so the report and its figures can be moved together.
        title: The top-level heading.
    """
    path = Path(path)
    parts = [f"# {title}", ""]
    for heading, body in sections:
        parts += [f"## {heading}", "", body.rstrip("\n"), ""]
    if figures:
        parts += ["## Figures", ""]
        for caption, fig_path in figures:
            rel = Path(os.path.relpath(Path(fig_path).resolve(), path.parent.resolve())).as_posix()
            parts += [f"![{caption}]({rel})", "", f"*{caption}*", ""]
    return write_text(path, "\n".join(parts).rstrip("\n") + "\n")


def write_comparison(
    directory: str | os.PathLike, table: pd.DataFrame, prefix: str = "comparison"
) -> tuple[Path, Path]:
    """Write ``table`` as ``<prefix>.csv`` (full precision) and ``<prefix>.md``, atomically."""
    directory = Path(directory)
    csv_path = write_csv(directory / f"{prefix}.csv", table)
    md_path = write_text(
        directory / f"{prefix}.md", format_markdown_table(table, floatfmt=COMPARISON_FORMATS)
    )
    return csv_path, md_path

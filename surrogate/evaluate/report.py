"""Markdown rendering of comparison tables and the evaluation report (for any model: the
published reference table, if any, comes from the model's ``reference_table`` hook).

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

#: Formats ``write_comparison`` uses: p-values span many decades, so fixed-point would show 0.
COMPARISON_FORMATS: dict[str, str] = {"ks_pvalue": ".3g", "ks_pvalue_full": ".3g"}

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


def split_quantity(quantity: str) -> tuple[str, float] | None:
    """``"distance_t125"`` -> ``("distance", 125.0)``; None for a duration row (``"run"``)."""
    name, sep, t = str(quantity).rpartition("_t")
    if not sep:
        return None
    try:
        return name, float(t)
    except ValueError:
        return None


def table1_markdown(
    results: Mapping[str, pd.DataFrame],
    speedups: Mapping[str, float],
    reference: Mapping[str, Mapping[str, Any]] | None = None,
    floatfmt: str = ".3f",
) -> str:
    """Our KS distances (the paper's Table 1 layout), one block of sub-rows per field.

    Args:
        results: Field name -> a ``comparison_table`` (optionally passed through
            ``combine_with_noise_floor``).
        speedups: Field name -> our speed-up factor (missing fields show "-").
        reference: Field name -> published figures to print beside ours (``{"ks": {quantity:
            value}, "ks_pvalue": {...}, "speedup": x}``, e.g. the model's
            ``reference_table()``), or None.
        floatfmt: Format of KS distances.

    Columns: every observable-at-time quantity (``<observable>_t<t>``, in time order), then the
    duration quantities. Each field gets an ``ours`` row (``KS (p-value)``), a ``published`` row
    (when ``reference`` has the field) and a ``noise floor`` row (when the table has
    ``ks_noise_floor``). An ours-cell is marked ``†`` when ``within_noise`` is False.
    """
    reference = reference or {}
    first = next(iter(results.values()))
    timed = [q for q in first["quantity"] if split_quantity(q) is not None]
    timed = sorted(timed, key=lambda q: (split_quantity(q)[0], split_quantity(q)[1]))  # type: ignore[index]
    durations = [q for q in first["quantity"] if split_quantity(q) is None]
    names = {split_quantity(q)[0] for q in timed}  # type: ignore[index]
    headers = [
        (f"t={split_quantity(q)[1]:g} s" if len(names) == 1 else f"{q}")  # type: ignore[index]
        for q in timed
    ]
    header = ["Field", "Source", *headers, *[d.capitalize() for d in durations], "Speed-up"]
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join([":---", ":---", *["---:"] * (len(header) - 2)]) + "|",
    ]
    quantities = [*timed, *durations]
    any_flag = False
    for name, df in results.items():
        by_q = df.set_index("quantity")
        cells = [_ours_cell(by_q.loc[q], floatfmt) if q in by_q.index else "" for q in quantities]
        any_flag = any_flag or any("†" in c for c in cells)
        sp = speedups.get(name)
        sp_cell = "–" if sp is None or not math.isfinite(float(sp)) else f"{float(sp):.1f}"
        lines.append("| " + " | ".join([name, "ours", *cells, sp_cell]) + " |")
        published = reference.get(name)
        if published is not None:
            pcells = [
                f"{published['ks'][q]:{floatfmt}} ({_fmt_p(published['ks_pvalue'][q])})"
                if q in published.get("ks", {}) else ""
                for q in quantities
            ]  # fmt: skip
            speed = published.get("speedup")
            lines.append("| " + " | ".join(
                ["", "published", *pcells, f"{speed:.1f}" if speed else ""]) + " |")  # fmt: skip
        if "ks_noise_floor" in df.columns:
            floor = by_q["ks_noise_floor"]
            fcells = [_num(floor.get(q), floatfmt) for q in quantities]
            lines.append("| " + " | ".join(["", "noise floor", *fcells, ""]) + " |")
    notes = [
        "",
        "Cells: KS distance (p-value). Durations: a random subsample from each model (1,000 in "
        "the paper). Noise floor: KS distance between two full-model runs with different seeds.",
    ]
    if any_flag:
        notes.append(
            "† KS distance above both the noise floor and the 5 % critical value "
            "(outside sampling noise)."
        )
    return "\n".join(lines + notes) + "\n"


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

"""Evaluation of an abstraction against the full model: statistics, figures and reports.

``statistics`` (with ``ks``, the samples and the KS statistic, and ``runs``, a run's artefacts)
and ``report`` are re-exported here; import ``surrogate.evaluate.figures``
and ``surrogate.evaluate.kymograph`` explicitly (they need matplotlib), and
``surrogate.evaluate.band`` (a travelling band's position and speed from a grid-field run's
profiles). Speed-ups: :func:`surrogate.simulate.speed.speedup` (one
formula, per cell-step, for every speed figure).
"""

from __future__ import annotations

from surrogate.evaluate.ks import compare_samples, ks_critical_value
from surrogate.evaluate.report import (
    format_markdown_table,
    split_quantity,
    table1_markdown,
    write_comparison,
    write_report,
)
from surrogate.evaluate.runs import (
    SimulationRun,
    default_times,
    distances_at,
    load_run,
    mean_std_over_time,
    observable_at,
)
from surrogate.evaluate.statistics import (
    PAPER_SUBSAMPLE,
    PAPER_TIMES,
    combine_with_noise_floor,
    comparison_table,
    family_failures,
    noise_floor_table,
)

__all__ = [
    "PAPER_SUBSAMPLE",
    "PAPER_TIMES",
    "SimulationRun",
    "combine_with_noise_floor",
    "compare_samples",
    "comparison_table",
    "default_times",
    "distances_at",
    "family_failures",
    "format_markdown_table",
    "ks_critical_value",
    "load_run",
    "mean_std_over_time",
    "noise_floor_table",
    "observable_at",
    "split_quantity",
    "table1_markdown",
    "write_comparison",
    "write_report",
]

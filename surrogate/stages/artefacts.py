"""The file names of the stages' artefacts, in one place.

A stage that reads another's artefact (train reads collect's transitions, reproduce links
train's figures) takes the name from here, not from the module of the stage that writes it: the
reader then imports nothing of the writer. The simulation recorders' files are named in
:mod:`surrogate.simulate.recorders`, the manifest in :mod:`surrogate.io`.
"""

from __future__ import annotations

from surrogate.kinds.files import CLASS_CHAIN, PSI

#: collect: the transitions table and the coverage figure
TRANSITIONS = "transitions.parquet"
COVERAGE_FIGURE = "coverage.png"

#: occupancy: the train diagnostic's unperturbed population
OCCUPANCY = "occupancy.parquet"

#: fit and train: the classifiers, their scores, the grid and the figures (the classifiers' file
#: and the K-lumps chain's, CLASS_CHAIN, are named by the kinds that read and write them)
METRICS = "train_metrics.json"
FIT_METRICS = "fit_metrics.json"
GRID = "psi_grid.csv"
SURFACES_FIGURE = "psi_surfaces.png"
DIAGNOSTIC_FIGURE = "psi_diagnostic.png"
HISTORY_FIGURE = "training_history.png"

#: simulate and evaluate, a run in a grid field: density and concentration over x and t
KYMOGRAPH_FIGURE = "kymograph.png"

#: evaluate: the summary (also read by sweep summaries) and the tables' stems (.csv, .md)
SUMMARY = "summary.json"
COMPARISON = "comparison"
NOISE_FLOOR = "noise_floor"
#: evaluate, runs in a grid field: the band against the full model's and the floor (.csv, .md,
#: .png)
BAND_FIDELITY = "band_fidelity"

#: reproduce and inspect: the report
REPORT = "report.md"

#: inspect: its figures as numbers (its figures: :mod:`surrogate.diagnosis.report`)
INSPECTION = "inspect.json"

__all__ = [
    "BAND_FIDELITY",
    "CLASS_CHAIN",
    "COMPARISON",
    "COVERAGE_FIGURE",
    "DIAGNOSTIC_FIGURE",
    "FIT_METRICS",
    "GRID",
    "HISTORY_FIGURE",
    "INSPECTION",
    "KYMOGRAPH_FIGURE",
    "METRICS",
    "NOISE_FLOOR",
    "OCCUPANCY",
    "PSI",
    "REPORT",
    "SUMMARY",
    "SURFACES_FIGURE",
    "TRANSITIONS",
]

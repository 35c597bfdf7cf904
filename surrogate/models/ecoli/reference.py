"""The paper's published figures for the E. coli model (its evaluation hook's reference)."""

from __future__ import annotations

from typing import Any

import pandas as pd

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


def paper_table1_frame() -> pd.DataFrame:
    """``PAPER_TABLE1`` as a long table: ``field``, ``quantity``, ``ks``, ``ks_pvalue``."""
    rows = [
        {"field": name, "quantity": q, "ks": entry["ks"][q], "ks_pvalue": entry["ks_pvalue"][q]}
        for name, entry in PAPER_TABLE1.items()
        for q in PAPER_QUANTITIES
    ]
    return pd.DataFrame(rows)

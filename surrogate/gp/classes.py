"""The K-lumps chain's law learned from transitions: one GP per (origin class, destination).

A chain over ``C`` classes needs, per origin class ``a``, the law ``P(class' = b | a, z)`` over
``C`` destinations. It is learned *one destination against the rest*: for each destination ``b``
reached from ``a`` a probit SVGP of the two-state abstraction's kind, ``g_b(z) ~ P(b | a, z)``,
on binned labels of the rows from ``a`` (:func:`~surrogate.gp.training.fit_classifiers`: all of
them side by side as one batched GP); the law is ``g_b / sum_b' g_b'`` (each ``g_b`` is already
a probability, so the normalisation only absorbs their small disagreement). The labels are the
windows' *expected* class laws where collect recorded them (``phi_class_next_expected_<b>``:
P(class' = b | the internal state at the window's start), a Rao-Blackwellised label with far less
variance than the 0/1 outcome; for a class that pins the internal state, none), else the 0/1
outcomes. Destinations never reached from ``a`` get probability 0, and one with too few events
to learn a surface (``min_events``) its constant mean label. With expected labels the events are
counted as the GP sees them, by label mass (the expected number of events), and a handful do:
each row carries its window's exact law, not one Bernoulli draw, so a rare destination's surface
is learned where a constant would put its mean over the collection's inputs everywhere (E. coli,
run with 2 CCW motors to tumble with none: 2.4x too likely where cells live with the old
threshold of 50 outcomes; docs/fidelity.md, "Memory").

The result is tabulated on a grid of the inputs (the chain reads it as a
:class:`~surrogate.simulate.classes.ClassTable`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ArtefactError
from surrogate.gp.binned import label_weight
from surrogate.gp.lookup import grid_nodes
from surrogate.gp.own_rows import summary
from surrogate.gp.settings import GPSettings
from surrogate.gp.training import fit_classifiers
from surrogate.gp.windows import row_windows

Domain = dict[str, tuple[float, float]]
#: per origin class, each destination's problem index (a GP) or constant rate
Plan = list[tuple[int, dict[int, int | float]]]

#: events a destination needs for a GP surface, by the labels trained on: 0/1 outcomes are
#: one Bernoulli draw per row; expected labels, counted by mass, carry each window's law
MIN_EVENTS = {"outcome": 50, "expected": 1.0}
#: the most Bernoulli draws one expected label counts as (its inverse dispersion, clipped):
#: 1,000 trusts a noise-free label like a thousand outcomes, enough for the rare tails
DEFAULT_MAX_LABEL_WEIGHT = 1000.0
#: the class law's fit for the same data and settings, in every K-lumps fit's identity (bump it
#: when a change here or in label_weight changes the fit): 2, weighted labels and label mass
CLASS_LAW_VERSION = 2


@dataclass(frozen=True)
class ClassFitOptions:
    """How :func:`fit_class_law` reads the table and fits (every field has its default).

    Attributes:
        nodes: grid nodes per input (default :func:`class_law_nodes`).
        origin: the column of the class before each window.
        destination: the column of the class after it.
        progress: show the fit's progress bar.
        device: where to fit.
        min_events: a destination with fewer events of either outcome (or an origin with fewer
            rows than twice the inducing points) gets its constant mean label, not a GP; events
            are the label mass with expected labels. Default :data:`MIN_EVENTS` for the labels
            used.
        expected: train on the expected class laws where the table has them (else, or with
            False, the 0/1 outcomes).
        max_weight: with expected labels, each GP's rows count as up to this many draws: the
            labels' inverse dispersion (:func:`~surrogate.gp.binned.label_weight`); 1: as
            0/1 outcomes.
    """

    nodes: Sequence[int] | None = None
    origin: str = "phi_class"
    destination: str = "phi_class_next"
    progress: bool = True
    device: torch.device | str = "cpu"
    min_events: float | None = None
    expected: bool = True
    max_weight: float | None = None


def fit_class_law(
    data: pd.DataFrame,
    input_names: Sequence[str],
    n_classes: int,
    domain: Domain,
    settings: GPSettings | None = None,
    options: ClassFitOptions = ClassFitOptions(),
) -> tuple[Tensor, dict[str, Any]]:
    """Learn ``P(class' | class, z)`` and tabulate it.

    Args:
        data: transitions with the ``input_names`` columns and the classes before
            (``options.origin``) and after (``options.destination``) each window, ints in
            ``[0, n_classes)``.
        input_names: the ``d`` inputs ``z``.
        n_classes: ``C``.
        domain: ``{input: (lo, hi)}``, the grid's span (e.g. the two-state fit's domain).
        settings: the GP settings of every binary classifier.
        options: the columns, grid, labels and where to fit (:class:`ClassFitOptions`).

    Returns:
        ``C x n_1..n_d x C`` float64 probabilities (rows sum to 1), and metrics: the labels
        used, per origin its rows, its destinations with their counts, and each classifier's
        held-out Brier score (on the 0/1 outcomes).

    Example:
        >>> law, metrics = fit_class_law(table, ["dG"], 7, {"dG": (-1.5, 2.5)})  # doctest: +SKIP
    """
    settings = settings or GPSettings()
    names = list(input_names)
    problems, weights, plan, metrics = class_problems(data, names, n_classes, settings, options)
    fitted = fit_classifiers(problems, settings, progress=options.progress, device=options.device,
                             desc="class chain", weights=weights) if problems else []  # fmt: skip
    bounds = [domain[n] for n in names]
    sizes = class_law_nodes(len(names), options.nodes)
    grid = grid_nodes(bounds, sizes).to(torch.float32)
    law = torch.zeros(n_classes, grid.shape[0], n_classes, dtype=torch.float64)
    for a, steps in plan:
        briers, row_weights, own_rows = {}, {}, {}
        for b, step in steps.items():
            if isinstance(step, float):
                law[a, :, b] = step
                continue
            clf = fitted[step]
            with torch.no_grad():
                law[a, :, b] = clf.predict_proba(grid.to(clf.device)).double().cpu().clamp(0, 1)
            briers[str(b)] = clf.validation.get("brier") if clf.validation else None
            row_weights[str(b)] = round(weights[step], 1)
            own_rows[str(b)] = summary(clf.own_rows)
        total = law[a].sum(-1, keepdim=True)
        if bool((total <= 0).any()):
            raise ArtefactError(f"the class chain's law from class {a} vanishes on its domain")
        law[a] = law[a] / total
        metrics[str(a)]["brier"] = briers
        metrics[str(a)]["row_weight"] = row_weights
        metrics[str(a)]["own_rows"] = own_rows  # each classifier against its own rows
    if not torch.isfinite(law).all():
        raise ArtefactError("the class chain's classifiers predict NaN/inf on their domain")
    metrics["classifiers"] = len(problems)
    metrics["constant_steps"] = sum(isinstance(v, float) for _, st in plan for v in st.values())
    metrics["nodes"] = sizes
    metrics["train_seconds"] = max((c.train_seconds for c in fitted), default=0.0)
    return law.reshape(n_classes, *sizes, n_classes), metrics


def class_problems(
    data: pd.DataFrame,
    input_names: Sequence[str],
    n_classes: int,
    settings: GPSettings,
    options: ClassFitOptions = ClassFitOptions(),
) -> tuple[list[tuple[Tensor, ...]], list[float], Plan, dict[str, Any]]:
    """The binary problems :func:`fit_class_law` fits (its arguments, which see): each
    ``(z, y, outcomes)`` (``n x d``, ``n``, ``n``), with the windows each row stands for
    where the table has them (:func:`~surrogate.gp.windows.row_windows`), and its likelihood
    weight; the plan, per origin class its destinations' problem index (int) or constant rate
    (float, in windows); and the metrics so far."""
    origin, destination, min_events = options.origin, options.destination, options.min_events
    names = list(input_names)
    missing = [c for c in (*names, origin, destination) if c not in data.columns]
    if missing:
        raise ArtefactError(
            f"transition data lacks column(s) {missing} for a class chain; it has "
            f"{list(data.columns)} (collect records the classes where the model declares them)"
        )
    a_col = data[origin].to_numpy().astype(np.int64)
    b_col = data[destination].to_numpy().astype(np.int64)
    if ((a_col < 0) | (a_col >= n_classes) | (b_col < 0) | (b_col >= n_classes)).any():
        raise ArtefactError(f"class columns must lie in [0, {n_classes})")
    columns = [f"{destination}_expected_{b}" for b in range(n_classes)]
    use_expected = options.expected and all(c in data.columns for c in columns)
    labels = (data[columns].to_numpy(dtype="float32") if use_expected
              else np.eye(n_classes, dtype=np.float32)[b_col])  # fmt: skip
    label_kind = "expected" if use_expected else "outcome"
    min_events = MIN_EVENTS[label_kind] if min_events is None else min_events
    max_weight = DEFAULT_MAX_LABEL_WEIGHT if options.max_weight is None else options.max_weight
    z_all = torch.tensor(data[names].to_numpy(dtype="float32"))
    # the windows each row stands for (a collection that keeps every switch), else one each
    windows = row_windows(data)
    w_all = np.ones(len(data)) if windows is None else windows
    # rows a binary classifier needs: its inducing points within the training split
    need = math.ceil(2 * settings.n_inducing / max(1e-9, 1.0 - settings.validation_fraction))
    problems: list[tuple[Tensor, ...]] = []
    weights: list[float] = []
    plan: Plan = []
    metrics: dict[str, Any] = {"labels": label_kind, "min_events": min_events}
    for a in range(n_classes):
        rows = np.flatnonzero(a_col == a)
        if rows.size == 0:
            raise ArtefactError(
                f"transition data has no rows from class {a}: collect more (collect.n_per_state)"
            )
        counts = np.bincount(b_col[rows], minlength=n_classes)
        w = w_all[rows]
        mass = (labels[rows] * w[:, None]).sum(0)  # in windows
        reached = [b for b in range(n_classes) if counts[b] > 0 or mass[b] > 0]
        steps: dict[int, int | float] = {}
        for b in reached:
            hits = float(mass[b]) if use_expected else float(w[b_col[rows] == b].sum())
            events = min(hits, float(w.sum()) - hits)
            if len(reached) > 1 and events >= min_events and rows.size >= need:
                hit = torch.tensor((b_col[rows] == b).astype(np.float32))
                y = torch.tensor(labels[rows, b])
                problems.append(
                    (z_all[rows], y, hit)
                    if windows is None
                    else (z_all[rows], y, hit, torch.tensor(w, dtype=torch.float32))
                )
                weights.append(label_weight(z_all[rows], y, settings.bins, max_weight)
                               if use_expected and max_weight > 1 and settings.bins
                               else 1.0)  # fmt: skip
                steps[b] = len(problems) - 1
            else:  # too few events to learn a surface: the constant mean label
                steps[b] = float(mass[b] / w.sum())
        plan.append((a, steps))
        metrics[str(a)] = {"rows": int(rows.size),
                           "destinations": {str(b): int(counts[b]) for b in reached}}  # fmt: skip
    return problems, weights, plan, metrics


def class_law_nodes(n_inputs: int, nodes: Sequence[int] | None) -> list[int]:
    """The grid size per input :func:`fit_class_law` uses: ``nodes``, else 1,024 nodes for
    one input and ~4,096 in all for more."""
    if nodes is not None:
        return list(nodes)
    return [1024] if n_inputs == 1 else [max(2, int(math.pow(4096, 1 / n_inputs)))] * n_inputs


__all__ = [
    "CLASS_LAW_VERSION",
    "DEFAULT_MAX_LABEL_WEIGHT",
    "MIN_EVENTS",
    "ClassFitOptions",
    "class_law_nodes",
    "class_problems",
    "fit_class_law",
]

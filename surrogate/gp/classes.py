"""The K-lumps chain's law learned from transitions: one GP per (origin class, destination).

A chain over ``C`` classes needs, per origin class ``a``, the law ``P(class' = b | a, z)`` over
``C`` destinations. It is learned as a *continuation-ratio* sequence of binary classifiers, each
one the probit SVGP of the two-state abstraction on binned 0/1 outcomes
(:func:`~surrogate.gp.training.fit_classifiers`, all of them side by side as one batched GP):
with the destinations of ``a`` in decreasing order of their counts ``b_1, b_2, ...``, classifier
``h_i(z) = P(class' = b_i | class' not in {b_1..b_(i-1)}, a, z)`` is fitted on the rows from
``a`` that did not go to an earlier destination. The law is then
``P(b_i) = h_i prod_(j < i) (1 - h_j)`` (the last destination takes the rest): a proper law at
every z whatever each classifier's error, and each classifier sees every row it can use.
Destinations never reached from ``a`` in the data get probability 0, and a step with too few
events to learn a surface (``min_events``) its constant maximum-likelihood rate.

The result is tabulated on a grid of the inputs (the chain reads it as a
:class:`~surrogate.simulate.classes.ClassTable`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from surrogate.errors import ArtefactError
from surrogate.gp.training import GPSettings, fit_classifiers

Domain = dict[str, tuple[float, float]]


def _grid(bounds: Sequence[tuple[float, float]], nodes: Sequence[int]) -> Tensor:
    """Every node of an evenly spaced grid ``prod(nodes) x d`` (last axis fastest)."""
    axes = [torch.linspace(lo, hi, n) for (lo, hi), n in zip(bounds, nodes, strict=True)]
    return torch.tensor(list(itertools.product(*[a.tolist() for a in axes])), dtype=torch.float32)


def fit_class_law(
    data: pd.DataFrame,
    input_names: Sequence[str],
    n_classes: int,
    domain: Domain,
    settings: GPSettings | None = None,
    nodes: Sequence[int] | None = None,
    origin: str = "phi_class",
    destination: str = "phi_class_next",
    progress: bool = True,
    device: torch.device | str = "cpu",
    min_events: int = 50,
) -> tuple[Tensor, dict[str, Any]]:
    """Learn ``P(class' | class, z)`` and tabulate it.

    Args:
        data: transitions with the ``input_names`` columns and the classes before (``origin``)
            and after (``destination``) each window, ints in ``[0, n_classes)``.
        input_names: the ``d`` inputs ``z``.
        n_classes: ``C``.
        domain: ``{input: (lo, hi)}``, the grid's span (e.g. the two-state fit's domain).
        settings: the GP settings of every binary classifier.
        nodes: grid nodes per input (default :func:`class_law_nodes`).
        progress: show the fit's progress bar.
        device: where to fit.
        min_events: a binary step with fewer events of either outcome (or fewer rows than
            twice the inducing points) gets the constant maximum-likelihood rate, not a GP.

    Returns:
        ``C x n_1..n_d x C`` float64 probabilities (rows sum to 1), and metrics: per origin its
        rows, its destinations in fitting order with their counts, and each classifier's
        held-out Brier score.

    Example:
        >>> law, metrics = fit_class_law(table, ["dG"], 7, {"dG": (-1.5, 2.5)})  # doctest: +SKIP
    """
    settings = settings or GPSettings()
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
    z_all = torch.tensor(data[names].to_numpy(dtype="float32"))
    problems: list[tuple[Tensor, Tensor]] = []
    plan: list[tuple[int, list[int], list[int | float]]] = []
    # rows a binary classifier needs: its inducing points within the training split
    need = math.ceil(
        2 * settings.n_inducing / max(1e-9, 1.0 - settings.validation_fraction)
    )  # origin, ordered destinations, problems
    metrics: dict[str, Any] = {}
    for a in range(n_classes):
        rows = np.flatnonzero(a_col == a)
        if rows.size == 0:
            raise ArtefactError(
                f"transition data has no rows from class {a}: collect more (collect.n_per_state)"
            )
        counts = np.bincount(b_col[rows], minlength=n_classes)
        order = [int(b) for b in np.argsort(-counts, kind="stable") if counts[b] > 0]
        fitted_here = []
        remaining = rows
        for b in order[:-1]:
            hit = b_col[remaining] == b
            if min(int(hit.sum()), int((~hit).sum())) >= min_events and remaining.size >= need:
                problems.append((z_all[remaining], torch.tensor(hit.astype(np.float32))))
                fitted_here.append(len(problems) - 1)
            else:  # too few events to learn a surface: the constant maximum-likelihood rate
                fitted_here.append(float(hit.mean()))
            remaining = remaining[~hit]
        plan.append((a, order, fitted_here))
        metrics[str(a)] = {"rows": int(rows.size),
                           "destinations": {str(b): int(counts[b]) for b in order}}  # fmt: skip
    fitted = fit_classifiers(problems, settings, progress=progress, device=device,
                             desc="class chain") if problems else []  # fmt: skip
    bounds = [domain[n] for n in names]
    sizes = class_law_nodes(len(names), nodes)
    grid = _grid(bounds, sizes)
    law = torch.zeros(n_classes, grid.shape[0], n_classes, dtype=torch.float64)
    for a, order, fitted_here in plan:
        rest = torch.ones(grid.shape[0], dtype=torch.float64)
        briers = []
        for b, index in zip(order[:-1], fitted_here, strict=True):
            if isinstance(index, float):
                h = torch.full((grid.shape[0],), index, dtype=torch.float64)
                briers.append(None)
            else:
                clf = fitted[index]
                with torch.no_grad():
                    h = clf.predict_proba(grid.to(clf.device)).double().cpu().clamp(0.0, 1.0)
                briers.append(clf.validation.get("brier") if clf.validation else None)
            law[a, :, b] = rest * h
            rest = rest * (1.0 - h)
        law[a, :, order[-1]] = rest
        metrics[str(a)]["brier"] = briers
    if not torch.isfinite(law).all():
        raise ArtefactError("the class chain's classifiers predict NaN/inf on their domain")
    metrics["classifiers"] = len(problems)
    metrics["constant_steps"] = sum(isinstance(i, float) for _, _, f in plan for i in f)
    metrics["nodes"] = sizes
    metrics["train_seconds"] = max((c.train_seconds for c in fitted), default=0.0)
    return law.reshape(n_classes, *sizes, n_classes), metrics


def class_law_nodes(n_inputs: int, nodes: Sequence[int] | None) -> list[int]:
    """The grid size per input :func:`fit_class_law` uses: ``nodes``, else 1,024 nodes for
    one input and ~4,096 in all for more."""
    if nodes is not None:
        return list(nodes)
    return [1024] if n_inputs == 1 else [max(2, int(math.pow(4096, 1 / n_inputs)))] * n_inputs


__all__ = ["class_law_nodes", "fit_class_law"]

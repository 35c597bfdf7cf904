"""The decision layers the benchmarks time, one per kind: the full model, psi's lookup table or
cached classifier (with the switch clock where psi reads one), the K-lumps chain's class table
(:func:`make_decision`, :func:`make_simulator`); a table from a smooth function of the signal
for the lookup-only bench (:func:`function_table`); the chains that bench runs side by side,
found in the kind registry by their config words (:func:`history_chains`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from surrogate.config import grid_size
from surrogate.fields import Field
from surrogate.kinds import ChainKind, decision_kind
from surrogate.kinds.base import find_kind, kind_values
from surrogate.models.base import Model
from surrogate.models.capabilities import signal_bounds_of
from surrogate.simulate.classes import ClassDecision, ClassTable
from surrogate.simulate.decision import AbstractDecision, FullDecision
from surrogate.simulate.loop import Simulator
from surrogate.simulate.memory import (
    AGE,
    MemoryDecision,
    has_history,
    tabulate_with_clock,
)


def make_decision(
    name: str, model: Model, tables: Mapping[str, Any], dt: float | None = None
) -> Any:
    """A decision layer: ``full``, ``lookup`` (table) or ``classifier`` (CachedPsi); a psi
    whose last input is the switch clock gets the chain with a clock (gp.history=age)."""
    if name not in tables and decision_kind(name).full:  # the one layer without a table
        return FullDecision(model.internal)
    psi = tables[name]
    names = tuple(psi.input_names)
    if isinstance(psi, ClassTable):  # the K-lumps chain (gp.lumps=classes)
        return ClassDecision(psi, model.internal, model.featurizer(names))
    if has_history(names):
        return MemoryDecision(psi, model.internal, model.featurizer(names[:-1]),
                              psi.domain[AGE][1], dt=dt)  # fmt: skip
    return AbstractDecision(psi, model.internal, model.featurizer(names))


def make_simulator(
    name: str,
    model: Model,
    field: Field,
    dt: float,
    device: torch.device,
    tables: Mapping[str, Any],
    compile: bool,
    backend: str = "torch",
) -> Simulator:
    """A simulator for one decision layer (``backend`` numba falls back to torch where the
    model has no kernel, e.g. the classifier; the results say which ran)."""
    backend = "auto" if backend == "numba" else backend
    return Simulator(model, make_decision(name, model, tables, dt), field, dt, device,
                     compile=compile, backend=backend)  # fmt: skip


def function_table(model: Model, dt: float, size: Any = None, max_age: float | None = None) -> Any:
    """A lookup table over the model's signal (its ``signal_bounds``) from a smooth psi with
    E. coli-like switching, no training: runs end at ~1/s and tumbles at ~5/s, each rate
    scaled by 0.5-1.5 across the signal's range (so the lookup's inputs matter). With
    ``max_age`` (s) the table also spans the switch clock (its last axis, ``size`` nodes too):
    the rates rise by up to 50 % with the time since the last switch."""
    from surrogate.gp import PsiLookupTable

    internal = model.internal
    names = tuple(internal.signal_names)
    bounds = signal_bounds_of(internal) or {}
    missing = [n for n in names if n not in bounds]
    if missing:
        raise ValueError(f"lookup_only needs the internal model's signal_bounds for {missing}")
    lo = torch.tensor([bounds[n][0] for n in names])
    width = torch.tensor([bounds[n][1] - bounds[n][0] for n in names])
    k = len(names)

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        s = ((z[:, :k] - lo) / width).mean(1).clamp(0.0, 1.0) + 0.5
        if max_age:
            s = s * (1.0 + 0.5 * z[:, k] / max_age)
        stop = -torch.expm1(-s * dt)  # run -> tumble at ~1/s
        start = -torch.expm1(-5.0 * s * dt)  # tumble -> run at ~5/s
        return torch.where(phi > 0, 1.0 - stop, start)

    ranges = [bounds[n] for n in names]
    if max_age:  # a clock node at every step, as the simulate stage tabulates a learned psi
        lead = grid_size(size, "lookup_size", len(names)) if size else None
        return tabulate_with_clock(psi, ranges, (*names, AGE), dt, max_age, lead)
    shape = grid_size(size, "lookup_size", len(names))
    return PsiLookupTable.from_function(psi, ranges, names, shape)


def history_chains() -> dict[str, ChainKind]:
    """The chains :func:`~surrogate.benchmarks.lookup.run_lookup_bench` runs side by side, by
    its ``histories`` word, found in the kind registry: a kind's word is the config string that
    selects it beside the two-state chain's (``none``; a switch clock's ``gp.history``, ``age``;
    a chain over classes' ``gp.lumps``, ``classes``). Only the kinds the bench can tabulate
    without a fit: those whose whole layer is psi's table (no artefact of their own) and those
    over the model's classes (the exact class table); in the registry's order of config values.
    """
    words = [*kind_values("history"), *kind_values("lumps")[1:]]
    out: dict[str, ChainKind] = {}
    for word in words:
        for lumps, history in ((ChainKind.lumps, word), (word, ChainKind.history)):
            kind = find_kind(lumps, history, ChainKind.class_moves_choices[0])
            if kind is not None and (kind.classes or not kind.files):
                out.setdefault(word, kind)
    return out


__all__ = ["function_table", "history_chains", "make_decision", "make_simulator"]

"""Decision layers packed for a model's compiled per-cell kernel (plain arrays and ints).

The simulator hands a model's :meth:`~surrogate.models.base.Model.cell_kernel` a
:class:`~surrogate.models.packed.PackedDecision` from :func:`pack_decision`, never its decision
layers or lookup tables: the kernel computes, the engine knows its own classes. Only the exact
classes of :data:`PACKERS` are packed (a subclass may override what a kernel would transcribe);
anything else is a block of kind ``unsupported`` naming it, which the kernel refuses
(:class:`~surrogate.errors.KernelUnsupported`), so the simulator keeps the torch step.

A new decision layer gets a kernel in two places: a packer here (a function
``(layer, slot) -> PackedBlock`` with a kind of its own, added to :data:`PACKERS`, building on
:func:`pack_tables` and :class:`~surrogate.models.packed.LayerState` for its tables and per-cell
state), and that kind's per-cell step in :mod:`surrogate.models.decision_kernel` (its pack, its
numba step over the kernel's features, its branch in ``decide``), which every model's kernel
calls; a model's kernel only accepts the kind.

Example:
    >>> packed = pack_decision(AbstractDecision(table, internal, featurize), dt=0.05)  # doctest: +SKIP
    >>> packed.blocks[0].kind, packed.blocks[0].tables.shape  # doctest: +SKIP
    ('chain', array([1024]))
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from surrogate.models.base import FeatureMap, Randoms
from surrogate.models.capabilities import randoms_of
from surrogate.models.packed import (
    CHAIN,
    CLASSES,
    EXACT,
    FULL,
    UNSUPPORTED,
    LayerState,
    PackedBlock,
    PackedClasses,
    PackedClock,
    PackedDecision,
    PackedTables,
)
from surrogate.simulate.classes import ClassDecision, ClassTable
from surrogate.simulate.decision import AbstractDecision, ExactDecision, FullDecision, is_fusable
from surrogate.simulate.decision_batch import DecisionBatch
from surrogate.simulate.memory import MemoryDecision
from surrogate.simulate.phases import PhaseDecision


@dataclass(frozen=True)
class Slot:
    """Where a layer sits: its cells ``[start, start + count)`` (``count`` None: the whole
    population), the decision's random rows ``rows`` (the layer's right-aligned in them) and
    the time step ``dt`` (s)."""

    start: int
    count: int | None
    rows: Randoms
    dt: float


def pack_decision(decision: Any, dt: float) -> PackedDecision:
    """``decision`` (a layer, or a
    :class:`~surrogate.simulate.decision_batch.DecisionBatch` of layers side by side) as blocks
    of plain arrays for a model's kernel.

    Args:
        decision: the simulator's decision layer.
        dt: the time step (s) it is stepped with.

    Returns:
        One block per layer, cells in order; layers the engine cannot pack are blocks of kind
        ``unsupported``.

    Raises:
        ValueError: stacked lookup tables that do not cover their block's cells.
    """
    rows = randoms_of(decision)
    if type(decision) is DecisionBatch:
        members: Sequence[Any] = decision.members
        sizes: Sequence[int | None] = decision.sizes
    else:
        members, sizes = [decision], [None]
    blocks = []
    start = 0
    for member, size in zip(members, sizes, strict=True):
        blocks.append(pack_layer(member, Slot(start, size, rows, float(dt))))
        start += size or 0
    return PackedDecision(tuple(blocks), rows, None if list(sizes) == [None] else start)


def pack_layer(layer: Any, slot: Slot) -> PackedBlock:
    """One layer as a block (kind ``unsupported`` where :data:`PACKERS` has no packer for its
    exact class)."""
    packer = PACKERS.get(type(layer))
    if packer is None:
        return PackedBlock(UNSUPPORTED, **_common(layer, slot),
                           why=f"decision layer {type(layer).__name__}")  # fmt: skip
    return packer(layer, slot)


def _common(layer: Any, slot: Slot) -> dict[str, Any]:
    """The fields every block has."""
    return {"layer": type(layer).__name__, "start": slot.start, "count": slot.count,
            "internal": getattr(layer, "internal", None), "fusable": is_fusable(layer)}  # fmt: skip


def pack_tables(psi: Any, count: int | None) -> tuple[PackedTables | None, str | None]:
    """A run probability's lookup tables for a block of ``count`` cells (None: any number),
    or None and why not (not a lookup table, or off the CPU).

    Raises:
        ValueError: stacked tables that do not cover ``count`` cells.
    """
    # a table exists only if gp's lookup module was imported: the engine does not import gp
    # itself (the loop imports this module at its top; gp brings gpytorch)
    lookup = sys.modules.get("surrogate.gp.lookup")
    if type(psi) is getattr(lookup, "StackedPsiLookup", None):
        tables, sizes = psi.tables, psi.sizes
        if count is not None and sum(sizes) != count:
            raise ValueError(f"stacked tables cover {sum(sizes)} cells, the block {count}")
    elif type(psi) is getattr(lookup, "PsiLookupTable", None):
        tables, sizes = [psi], [0 if count is None else count]
    else:
        return None, (f"run probability {type(psi).__name__} (the kernel reads lookup tables: "
                      "decision.mode=lookup)")  # fmt: skip
    if any(t.device.type != "cpu" for t in tables):
        return None, "lookup tables off the CPU"
    first = tables[0]
    affine = torch.stack([t.affine for t in tables]).numpy()  # (tables, d, 2) float32
    packed = PackedTables(
        table=torch.stack([t.table for t in tables]).reshape(-1).contiguous().numpy(),
        sizes=tuple(int(n) for n in sizes),
        origin=np.ascontiguousarray(affine[:, :, 0]),
        scale=np.ascontiguousarray(affine[:, :, 1]),
        shape=np.array(first.shape, dtype=np.int64),
        strides=np.array(first.strides, dtype=np.int64),
        layer=first.layer_size,
    )
    return packed, None


def _feature_fields(featurize: Any, why: str | None) -> dict[str, Any]:
    """A layer's feature names and the internal model they are computed with (or why not)."""
    features, features_of = None, None
    if featurize is not None:
        if type(featurize) is FeatureMap:
            features, features_of = tuple(featurize.names), featurize.internal
        elif why is None:
            why = f"feature map {featurize!r}"
    return {"features": features, "features_of": features_of, "why": why}


def _chain_fields(layer: AbstractDecision, slot: Slot) -> dict[str, Any]:
    """A two-state chain's draw row, feature names and tables (or why not)."""
    tables, why = pack_tables(layer.run_probability, slot.count)
    return {"decision_row": slot.rows.uniform - 1,  # the layer's one uniform, right-aligned
            "tables": tables, **_feature_fields(layer.featurize, why)}  # fmt: skip


def pack_class_table(table: ClassTable) -> tuple[PackedClasses | None, str | None]:
    """A K-lumps law as flat arrays (see :class:`~surrogate.models.packed.PackedClasses`), or
    None and why not (off the CPU). Each axis's origin and scale are the float32 numbers
    ``ClassTable`` computes positions with (``lo`` and ``(n - 1) / (hi - lo)``)."""
    if table.device.type != "cpu":
        return None, "a class table off the CPU"
    d = len(table.shape)
    origin, scale = np.zeros(d, np.float32), np.zeros(d, np.float32)
    nodes = np.ones(d, np.int64)
    for j, (n, (lo, hi)) in enumerate(zip(table.shape, table.bounds, strict=True)):
        if n > 1 and hi > lo:  # else the axis is constant (ClassTable._positions)
            origin[j], scale[j], nodes[j] = lo, (n - 1) / (hi - lo), n
    packed = PackedClasses(
        cdf=table.cdf.reshape(-1).contiguous().numpy(), origin=origin, scale=scale,
        nodes=nodes, strides=np.array(table.strides, dtype=np.int64),
        origin_stride=table.origin_stride,
        lumps=np.array(table.class_lumps, dtype=np.float32),
    )  # fmt: skip
    return packed, None


def _pack_full(layer: FullDecision, slot: Slot) -> PackedBlock:
    """The internal model's window: its state and first float64 uniform row."""
    return PackedBlock(FULL, **_common(layer, slot), state=LayerState(layer),
                       motor_row=slot.rows.uniform64 - layer.randoms.uniform64)  # fmt: skip


def _pack_chain(layer: AbstractDecision, slot: Slot) -> PackedBlock:
    """The two-state chain over lookup tables."""
    return PackedBlock(CHAIN, **_common(layer, slot), **_chain_fields(layer, slot))


def _pack_exact(layer: ExactDecision, slot: Slot) -> PackedBlock:
    """The chain over the internal model's exact psi (tabulated)."""
    return PackedBlock(EXACT, **_common(layer, slot), **_chain_fields(layer, slot))


def _pack_memory(layer: MemoryDecision, slot: Slot) -> PackedBlock:
    """The chain with a switch clock, psi's last input: in seconds (unit dt, capped at
    max_age), or, for a table with a node per step, in steps on a unit axis (exact nodes, as
    the torch layer's ``clock_nodes``)."""
    fields = _chain_fields(layer, slot)
    clock = PackedClock(cap=float(layer.max_age), unit=slot.dt)
    tables = fields["tables"]
    if tables is not None and layer.clock_nodes is not None:
        tables.origin[:, -1], tables.scale[:, -1] = 0.0, 1.0
        clock = PackedClock(cap=float(layer.clock_nodes), unit=1.0)
    return PackedBlock(CHAIN, **_common(layer, slot), **fields, state=LayerState(layer),
                       clock=clock)  # fmt: skip


def _pack_classes(layer: ClassDecision | PhaseDecision, slot: Slot) -> PackedBlock:
    """The K-lumps chain: its law, its ``d + 1`` uniform rows (right-aligned) and its
    classes."""
    classes, why = pack_class_table(layer.table)
    return PackedBlock(CLASSES, **_common(layer, slot), **_feature_fields(layer.featurize, why),
                       decision_row=slot.rows.uniform - layer.randoms.uniform,
                       state=LayerState(layer), classes=classes)  # fmt: skip


#: the packer of each decision layer class (exact classes: a subclass is not packed)
PACKERS: dict[type, Callable[[Any, Slot], PackedBlock]] = {
    FullDecision: _pack_full,
    AbstractDecision: _pack_chain,
    ExactDecision: _pack_exact,
    MemoryDecision: _pack_memory,
    ClassDecision: _pack_classes,
    # the hidden-phase chain draws its states as K lumps draw classes: the same block
    PhaseDecision: _pack_classes,
}

__all__ = ["PACKERS", "Slot", "pack_class_table", "pack_decision", "pack_layer", "pack_tables"]

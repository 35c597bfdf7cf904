"""What the engine hands a model's compiled per-cell kernel: decision layers as plain arrays.

A kernel (:meth:`~surrogate.models.base.Model.cell_kernel`) computes; it never reads the
engine's decision layers or lookup tables. The simulator packs the layer it runs
(:func:`surrogate.simulate.kernel_pack.pack_decision`) into a :class:`PackedDecision`: one
:class:`PackedBlock` per block of cells (a batch of runs has one per run), each with a ``kind``
code, the random rows it draws from, and its numbers (lookup tables, switch clock) as numpy
arrays and ints. A kernel runs the kinds it knows and raises
:class:`~surrogate.errors.KernelUnsupported` for the others (``why`` names what the engine
could not pack), so the simulator keeps its torch step for those.

The kinds (:data:`KINDS`):

* ``"full"``: the internal model's own window (``FullDecision``); its per-cell state
  (``state``) and first float64 uniform row (``motor_row``);
* ``"chain"``: the two-state chain phi' ~ Bernoulli(psi_phi(z)) over lookup tables
  (``AbstractDecision``; ``MemoryDecision`` adds ``clock``), the uniform of row
  ``decision_row``;
* ``"exact"``: the same chain whose tables are the internal model's exact psi
  (``ExactDecision``): a kernel may run it only where it computes that model's formulas;
* ``"classes"``: the K-lumps chain over classes finer than phi (``ClassDecision``): each
  cell's class (``state``, int64) moves by one categorical draw from a row of cumulative
  probabilities (``classes``), picked by stochastic rounding to a grid node per input axis;
  uniforms from row ``decision_row`` (one per axis, then the draw's); phi is the class's lump;
* ``"unsupported"``: a layer the engine cannot pack (``why`` says which).

This module imports nothing of the engine: models may import it (they may not import
:mod:`surrogate.simulate` or :mod:`surrogate.gp`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from surrogate.models.randoms import Randoms

FULL, CHAIN, EXACT, CLASSES, UNSUPPORTED = "full", "chain", "exact", "classes", "unsupported"
#: the kinds a :class:`PackedBlock` may have
KINDS = (FULL, CHAIN, EXACT, CLASSES, UNSUPPORTED)


@dataclass(frozen=True)
class PackedTables:
    """Lookup tables of psi, one per block of cells, on one grid shape.

    Table ``k`` starts at ``k * origins * layer`` in ``table``; its values for origin ``phi``
    (0 or 1) at ``phi * layer``; node ``(i_1, ..., i_d)`` at ``sum(i_a * strides[a])`` from
    there. Axis ``a`` of table ``k`` maps an input ``v`` to grid units
    ``(v - origin[k, a]) * scale[k, a]`` (multilinear interpolation between nodes, as
    ``surrogate.gp.lookup``).

    Attributes:
        table: flat float32 ``(tables * origins * layer,)``.
        sizes: cells per table, in order, where several are stacked; a single table serves
            any number of cells (its entry: the block's count, 0 for any).
        origin: float32 ``(tables, d)``: each axis's low end.
        scale: float32 ``(tables, d)``: grid nodes per unit of each axis.
        shape: int64 ``(d,)``: nodes per axis.
        strides: int64 ``(d,)``: elements between neighbouring nodes of each axis.
        layer: elements per origin layer (``prod(shape)``).
        origins: origin layers per table (2: phi = 0, 1).
    """

    table: np.ndarray
    sizes: tuple[int, ...]
    origin: np.ndarray
    scale: np.ndarray
    shape: np.ndarray
    strides: np.ndarray
    layer: int
    origins: int = 2

    @property
    def stacked(self) -> bool:
        """Whether several tables share the block (each for its own cells)."""
        return len(self.sizes) > 1

    def table_of_cell(self, n: int) -> np.ndarray:
        """Each cell's table index, int32 ``(n,)``, for a block of ``n`` cells.

        Raises:
            ValueError: stacked tables that do not cover exactly ``n`` cells.
        """
        if self.stacked and sum(self.sizes) != n:
            raise ValueError(f"stacked tables cover {sum(self.sizes)} cells, not {n}")
        sizes = self.sizes if self.stacked else (n,)
        return np.repeat(np.arange(len(sizes), dtype=np.int32), sizes)


@dataclass(frozen=True)
class PackedClock:
    """A chain's switch clock: each cell's steps since its phi last changed, psi's last input.

    psi reads ``min(steps * unit, cap)``; the clock restarts at 0 when phi changes, else counts
    on. With a table node per step (``unit`` 1 on a unit axis) the node is exact.

    Attributes:
        cap: the clock's cap (in the units psi reads: seconds, or steps when ``unit`` is 1).
        unit: seconds per step (``dt``), or 1 for a table with a node per step.
    """

    cap: float
    unit: float


@dataclass(frozen=True)
class PackedClasses:
    """A K-lumps chain's law (``surrogate.simulate.classes.ClassTable``) as flat arrays.

    A cell in class ``a`` at inputs ``v`` (``d`` axes) reads row
    ``a * origin_stride + sum(i_k * strides[k])``, where ``i_k`` is the lower node of axis
    ``k`` (``w = clamp((v_k - origin[k]) * scale[k], 0, nodes[k] - 1)`` in float32, node
    ``min(floor(w), nodes[k] - 2)``) plus 1 if that axis's uniform is below ``w - node``
    (stochastic rounding); an axis of ``nodes[k] == 1`` (one node, or an empty span) stays
    at node 0. The next class is the number of the row's ``C`` cumulative probabilities the
    draw's uniform reaches (at most ``C - 1``); phi is its lump.

    Attributes:
        cdf: float32 ``(rows * C,)``: the cumulative rows, row after row.
        origin: float32 ``(d,)``: each axis's low end.
        scale: float32 ``(d,)``: grid units per unit of each axis.
        nodes: int64 ``(d,)``: nodes per axis (1: the axis is constant).
        strides: int64 ``(d,)``: rows between neighbouring nodes of each axis.
        origin_stride: rows per origin class (``prod`` of the grid's shape).
        lumps: float32 ``(C,)``: each class's phi (0/1).
    """

    cdf: np.ndarray
    origin: np.ndarray
    scale: np.ndarray
    nodes: np.ndarray
    strides: np.ndarray
    origin_stride: int
    lumps: np.ndarray

    @property
    def n_classes(self) -> int:
        """``C``."""
        return int(self.lumps.shape[0])


class LayerState:
    """A decision layer's per-cell state tensor (motor states, switch clocks) for a kernel
    that advances it in place.

    Args:
        layer: the layer (its ``fused_state()[0]`` is the tensor, ``set_fused_state`` stores
            one).
    """

    def __init__(self, layer: Any) -> None:
        self._layer = layer
        self._owned: Tensor | None = None

    def current(self) -> Tensor:
        """The layer's state as it is (read it, do not write it)."""
        return self._layer.fused_state()[0]

    def writable(self) -> Tensor:
        """The layer's state, replaced once by a contiguous copy of its own (the torch step
        always makes new ones, so a tensor a caller holds never changes)."""
        state = self.current()
        if state is not self._owned:
            state = state.clone(memory_format=torch.contiguous_format)
            self._layer.set_fused_state((state,))
            self._owned = state
        return state


@dataclass(frozen=True)
class PackedBlock:
    """One decision block: cells ``[start, start + count)`` (``count`` None: every cell of the
    population, whatever its size) and its layer as plain numbers.

    Attributes:
        kind: one of :data:`KINDS`.
        layer: the layer's class name (for messages).
        start: the block's first cell.
        count: its cells, or None.
        internal: the layer's internal model (a kernel checks it is the one it computes).
        fusable: whether the layer has a pure window (else the SSA runs eagerly).
        why: what the engine could not pack (kind ``unsupported``; or the tables of a chain:
            then ``tables`` is None).
        state: the per-cell state the kernel advances (``full``: motor states; a clock;
            ``classes``: int64 classes), or None.
        motor_row: ``full``: the window's first float64 uniform row.
        decision_row: chains: the row of the draw's uniform; ``classes``: the first of its
            ``d + 1`` rows (one per input axis, then the categorical draw's).
        features: chains: psi's input names before the clock (None: the inputs x themselves,
            without a feature map).
        features_of: the internal model the feature map computes with (None without one).
        tables: chains: the lookup tables (None: see ``why``).
        clock: a chain's switch clock, or None.
        classes: ``classes``: the chain's law (None: see ``why``); ``state`` holds each
            cell's class (int64).
    """

    kind: str
    layer: str
    start: int
    count: int | None
    internal: Any
    fusable: bool
    why: str | None = None
    state: LayerState | None = None
    motor_row: int = 0
    decision_row: int = 0
    features: tuple[str, ...] | None = None
    features_of: Any = None
    tables: PackedTables | None = None
    clock: PackedClock | None = None
    classes: PackedClasses | None = None


@dataclass(frozen=True)
class PackedDecision:
    """A population's decision layer as blocks of cells.

    Attributes:
        blocks: the blocks, cells in order.
        randoms: the decision's random rows per cell and step (each block's right-aligned in
            them); a body's rows come after.
        total: the cells the blocks cover, or None (one block over any population).
    """

    blocks: tuple[PackedBlock, ...]
    randoms: Randoms
    total: int | None


__all__ = [
    "CHAIN",
    "CLASSES",
    "EXACT",
    "FULL",
    "KINDS",
    "UNSUPPORTED",
    "LayerState",
    "PackedBlock",
    "PackedClasses",
    "PackedClock",
    "PackedDecision",
    "PackedTables",
]

"""The decision kinds' per-cell steps, compiled (numba): written once, for any model's kernel.

A model's compiled per-cell kernel (e.g. :mod:`surrogate.models.ecoli.kernel`) computes its
body, its own internal model's window (kind ``full``) and its features; the step of every other
kind the engine packs (:mod:`surrogate.models.packed`) is here, as ``inline="always"`` scalar
functions the kernel calls per cell and step:

* :func:`lookup`: psi's multilinear interpolation in one of a chain's tables
  (``surrogate.gp.lookup._interpolate``: the lower node per axis, then torch.lerp along the
  last axis first);
* :func:`chain_step`: the two-state chain phi' ~ Bernoulli(psi_phi(z)), with its switch clock
  where it has one (``surrogate.simulate.memory.with_age`` and ``tick``);
* :func:`class_step`: the K-lumps chain's next class (``ClassTable.draw``, with the same
  uniforms in the same order);
* :func:`decide`: whichever of those a block packs; :func:`cell_state` and :func:`store_state`
  read and write a cell's decision state (table, clock, class);
* :func:`account`: ``Simulator._advance``'s segment bookkeeping.

Each computes the torch layer's operations in the same order and precision (float32), so a
kernel that calls them follows the torch step bit for bit up to its own formulas' rounding.

**Features.** A kernel hands its features as ``values``: a homogeneous tuple of float32 values
in the kernel's own order (it lives in registers: no array per step); a pack's ``features``
holds, per input axis, the index of that axis's value in the tuple, or :data:`CLOCK` for the
switch clock. The model maps feature names to its indices (:func:`feature_axes` checks them
against the tables).

**Packs.** A block's numbers travel as namedtuples of arrays and numbers, built from a
:class:`~surrogate.models.packed.PackedBlock` by :func:`chain_pack` and :func:`class_pack` and
bundled as a :class:`DecisionPack`; the kind a block does not use gets its empty placeholder
(:data:`NO_CHAIN`, :data:`NO_CLASSES`), so a kernel has one compiled signature for all kinds.
Three things numba asks of a kernel that takes them (the E. coli kernel does all three): called
from Python, it takes them as plain tuples (a namedtuple is typed in Python at every call); a
``prange`` loop takes no tuple of arrays, so a parallel kernel takes the tuples apart before
the loop and builds the namedtuples again inside it; and its per-cell loop compiles without
reference counts (numba's ``_nrt=False``), else every array of a pack is counted each time the
pack is handed to an inlined step (half the loop's speed, measured).

A kernel that inlines these functions and caches its machine code on disk names this module in
:func:`surrogate.scalar.renew_with` (numba stamps a cached function with its own file only).
"""

from __future__ import annotations

from collections import namedtuple
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np

from surrogate.errors import KernelUnsupported
from surrogate.models.packed import PackedBlock, PackedClasses, PackedClock, PackedTables
from surrogate.scalar import JIT_OPTIONS, numba_primitives

__all__ = [
    "CHAIN",
    "CLASSES",
    "CLOCK",
    "NO_CHAIN",
    "NO_CLASSES",
    "OWN",
    "Cells",
    "ChainPack",
    "ClassPack",
    "DecisionPack",
    "account",
    "cell_state",
    "chain_pack",
    "chain_step",
    "class_pack",
    "class_step",
    "decide",
    "feature_axes",
    "lookup",
    "own_pack",
    "store_state",
]

#: a feature index that reads the switch clock (psi's last input under gp.history=age)
CLOCK = -1
#: :attr:`DecisionPack.kind`: the model's own window (the kernel's code, e.g. motors), the
#: two-state chain over lookup tables (with or without a clock), the K-lumps chain
OWN, CHAIN, CLASSES = 0, 1, 2

#: The engine's per-cell arrays every kernel advances in place: ``phi`` (n,) uint8, ``seg``
#: (n,) int32 steps of the open segment, ``complete`` (n,) uint8 (whether a segment ended yet:
#: the first one is left-censored), and the out array ``ended`` (steps, n) int32 (each step's
#: ended segment length, signed by its phi, 0 where none ended).
Cells = namedtuple("Cells", ["phi", "seg", "complete", "ended"])

#: A two-state chain over lookup tables (:class:`~surrogate.models.packed.PackedTables`):
#: ``table`` flat float32, ``table_of_cell`` (block,) int32 each cell's table, ``layer``
#: elements per origin layer, ``shape`` and ``strides`` (d,) int64, ``origin`` and ``scale``
#: (tables, d) float32, ``features`` (d,) int64 feature indices, ``row`` the draw's uniform
#: row; the switch clock: ``ages`` (block,) float32 steps (in place), psi reads
#: ``min(ages * unit, cap)`` (``cap`` 0: no clock).
ChainPack = namedtuple(
    "ChainPack",
    ["table", "table_of_cell", "layer", "shape", "strides", "origin", "scale", "features",
     "row", "ages", "cap", "unit"],
)  # fmt: skip

#: A K-lumps chain (:class:`~surrogate.models.packed.PackedClasses`): ``cdf`` flat float32,
#: ``origin_stride`` rows per origin class, ``nodes`` and ``strides`` (d,) int64, ``origin``
#: and ``scale`` (d,) float32, ``features`` (d,) int64 feature indices, ``row`` the first of
#: the ``d + 1`` uniform rows, ``lumps`` (C,) float32 each class's phi, ``classes`` (block,)
#: int64 each cell's class (in place).
ClassPack = namedtuple(
    "ClassPack",
    ["cdf", "origin_stride", "nodes", "strides", "origin", "scale", "features", "row", "lumps",
     "classes"],
)  # fmt: skip

#: A block's decision for a kernel: ``kind`` (:data:`OWN`, :data:`CHAIN`, :data:`CLASSES`)
#: and both packs (the unused one a placeholder).
DecisionPack = namedtuple("DecisionPack", ["kind", "chain", "classes"])

_F32 = np.float32
_JIT: dict[str, Any] = {"inline": "always", **JIT_OPTIONS}
_clamp = numba_primitives()["clamp"]  # torch.clamp: NaN passes through


# -- the per-cell steps (numba; inlined into the kernel that calls them) -------------------------
@numba.njit(**_JIT)
def _lerp(a, b, w):
    """torch.lerp's formula (float32)."""
    if abs(w) < _F32(0.5):
        return a + w * (b - a)
    return b - (b - a) * (_F32(1.0) - w)


@numba.njit(**_JIT)
def _value(values, clock, index):
    """The feature of index ``index`` in ``values`` (:data:`CLOCK`: ``clock``)."""
    if index == CLOCK:
        return clock
    return values[index]


@numba.njit(**_JIT)
def lookup(phi_now, tab, values, clock, t):
    """p(phi' = 1) of a cell at ``phi_now`` (float32 0/1): psi interpolated in table ``tab``
    of the :class:`ChainPack` ``t`` at the features ``values`` (float32 tuple; ``clock``:
    the switch clock) of the axes ``t.features``, as gp.lookup._interpolate (lower node per
    axis, then lerp along the last axis first). At most 3 axes."""
    d = t.shape.shape[0]
    shape, strides, table = t.shape, t.strides, t.table
    base = tab * 2 * t.layer + (t.layer if phi_now > 0 else 0)
    fr0 = _F32(0.0)
    fr1 = _F32(0.0)
    fr2 = _F32(0.0)
    for a in range(d):
        value = _value(values, clock, t.features[a])
        top = _F32(shape[a] - 1)
        w = _clamp((value - t.origin[tab, a]) * t.scale[tab, a], _F32(0.0), top)
        # NaN stays NaN in w (and so in the probability); its index is clamped
        i = min(max(int(np.floor(w)) if w == w else 0, 0), shape[a] - 2)
        base += i * strides[a]
        if a == 0:
            fr0 = w - _F32(i)
        elif a == 1:
            fr1 = w - _F32(i)
        else:
            fr2 = w - _F32(i)
    if d == 1:
        return _lerp(table[base], table[base + strides[0]], fr0)
    if d == 2:
        s0, s1 = strides[0], strides[1]
        v0 = _lerp(table[base], table[base + s1], fr1)
        v1 = _lerp(table[base + s0], table[base + s0 + s1], fr1)
        return _lerp(v0, v1, fr0)
    s0, s1, s2 = strides[0], strides[1], strides[2]
    v00 = _lerp(table[base], table[base + s2], fr2)
    v01 = _lerp(table[base + s1], table[base + s1 + s2], fr2)
    v10 = _lerp(table[base + s0], table[base + s0 + s2], fr2)
    v11 = _lerp(table[base + s0 + s1], table[base + s0 + s1 + s2], fr2)
    return _lerp(_lerp(v00, v01, fr1), _lerp(v10, v11, fr1), fr0)


@numba.njit(**_JIT)
def chain_step(phi_now, age, tab, values, uniform, t):
    """One step of the two-state chain of :class:`ChainPack` ``t``: phi' = 1 where
    ``uniform`` < psi_phi (:func:`lookup` in table ``tab``), the switch clock ``age`` (float32
    steps) read as ``min(age * unit, cap)`` (memory.with_age) and advanced (memory.tick: 0
    where phi changed, else one more; unchanged without a clock).

    Returns:
        (phi', age') as float32.
    """
    clock = min(age * _F32(t.unit), _F32(t.cap))  # memory.with_age
    prob = lookup(phi_now, tab, values, clock, t)
    phi_after = _F32(1.0) if uniform < prob else _F32(0.0)
    if t.cap > 0:  # memory.tick
        age = _F32(0.0) if phi_after != phi_now else age + _F32(1.0)
    return phi_after, age


@numba.njit(**_JIT)
def class_step(cls, values, u, s, c, t):
    """The next class of cell ``c`` in class ``cls`` under the :class:`ClassPack` ``t``:
    ClassTable.draw (stochastic rounding to a node per axis with the uniforms
    ``u[s, t.row + a, c]``; then the categorical draw from one cumulative row with the uniform
    ``u[s, t.row + d, c]``), its positions in float32 in ClassTable._positions' order of
    operations. ``u``: float32 (steps, rows, n)."""
    d = t.nodes.shape[0]
    n_classes = t.lumps.shape[0]
    index = cls * t.origin_stride
    for a in range(d):
        n = t.nodes[a]
        if n <= 1:  # a constant axis: node 0
            continue
        value = _value(values, _F32(0.0), t.features[a])
        w = _clamp((value - t.origin[a]) * t.scale[a], _F32(0.0), _F32(n - 1))
        node = min(np.floor(w), _F32(n - 2))
        # NaN: node 0, never rounded up (as ClassTable._positions)
        i = int(node) if node == node else 0
        if u[s, t.row + a, c] < w - node:
            i += 1
        index += i * t.strides[a]
    v = u[s, t.row + d, c]
    base = index * n_classes
    nxt = 0
    for b in range(n_classes):
        if v >= t.cdf[base + b]:
            nxt += 1
    return min(nxt, n_classes - 1)


@numba.njit(**_JIT)
def cell_state(j, decision):
    """Cell ``j`` of the block's decision state: (its table, its clock in steps (float32), its
    class); 0 where the kind has none."""
    chain = decision.chain
    tab = chain.table_of_cell[j] if decision.kind == CHAIN else 0
    age = chain.ages[j] if decision.kind == CHAIN and chain.cap > 0 else _F32(0.0)
    cls = decision.classes.classes[j] if decision.kind == CLASSES else 0
    return tab, age, cls


@numba.njit(**_JIT)
def store_state(j, decision, age, cls):
    """Write cell ``j``'s clock and class back into the block's state arrays (those it has)."""
    if decision.kind == CHAIN and decision.chain.cap > 0:
        decision.chain.ages[j] = age
    if decision.kind == CLASSES:
        decision.classes.classes[j] = cls


@numba.njit(**_JIT)
def decide(phi_now, age, cls, tab, values, u, s, c, decision):
    """Step ``s`` of cell ``c`` (block cell state ``age``, ``cls``, ``tab``: see
    :func:`cell_state`) under a :class:`DecisionPack` of kind :data:`CHAIN` or
    :data:`CLASSES`, at the features ``values`` with the uniforms ``u`` (float32 (steps,
    rows, n)).

    Returns:
        (phi' float32, age', cls').
    """
    if decision.kind == CLASSES:
        cls = class_step(cls, values, u, s, c, decision.classes)
        return decision.classes.lumps[cls], age, cls
    chain = decision.chain
    phi_after, age = chain_step(phi_now, age, tab, values, u[s, chain.row, c], chain)
    return phi_after, age, cls


@numba.njit(**_JIT)
def account(cells, c, s, phi_before, phi_after):
    """Simulator._advance's bookkeeping of cell ``c`` at step ``s`` in :class:`Cells`
    ``cells``: a segment ends when phi switches (its length, signed by its phi, in
    ``ended[s, c]``; the first one is left-censored)."""
    switched = 1 if phi_after != phi_before else 0
    length = cells.seg[c] + 1
    sign = 1 if phi_before > 0 else -1
    cells.ended[s, c] = switched * cells.complete[c] * sign * length
    cells.seg[c] = length * (1 - switched)
    cells.complete[c] = max(cells.complete[c], switched)


# -- packs: from the engine's PackedBlock to the kernel's arguments -------------------------------
_NO_CLOCK = PackedClock(cap=0.0, unit=0.0)

#: the placeholder of a block without a two-state chain
NO_CHAIN = ChainPack(
    np.zeros(2, np.float32), np.zeros(1, np.int32), 1, np.zeros(1, np.int64),
    np.zeros(1, np.int64), np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32),
    np.zeros(1, np.int64), 0, np.zeros(1, np.float32), 0.0, 0.0,
)  # fmt: skip
#: the placeholder of a block without a K-lumps chain
NO_CLASSES = ClassPack(
    np.zeros(1, np.float32), 1, np.zeros(1, np.int64), np.zeros(1, np.int64),
    np.zeros(1, np.float32), np.zeros(1, np.float32), np.zeros(1, np.int64), 0,
    np.zeros(0, np.float32), np.zeros(1, np.int64),
)  # fmt: skip


def own_pack() -> DecisionPack:
    """The pack of a block the kernel decides itself (its own internal model's window)."""
    return DecisionPack(OWN, NO_CHAIN, NO_CLASSES)


def feature_axes(block: PackedBlock, indices: Sequence[int]) -> np.ndarray:
    """A chain's or K-lumps chain's ``features`` array: the kernel's feature ``indices`` of
    psi's inputs (in the block's order), then :data:`CLOCK` where the chain has a switch clock.

    Raises:
        KernelUnsupported: a count of axes other than the block's tables'.
    """
    axes = [*indices, *([CLOCK] if block.clock is not None else [])]
    if block.classes is not None:
        d, what = block.classes.nodes.shape[0], "class table"
    else:
        assert block.tables is not None
        d, what = block.tables.shape.shape[0], "lookup table"
    if len(axes) != d:
        raise KernelUnsupported(f"{len(axes)} features for a {what} over {d} axes")
    return np.array(axes, dtype=np.int64)


def chain_pack(
    tables: PackedTables,
    features: np.ndarray,
    row: int,
    table_of_cell: np.ndarray,
    clock: PackedClock | None = None,
    ages: np.ndarray | None = None,
) -> ChainPack:
    """A two-state chain's :class:`ChainPack`.

    Args:
        tables: the chain's lookup tables.
        features: (d,) int64 feature indices (:func:`feature_axes`).
        row: the draw's uniform row.
        table_of_cell: (block,) int32 each cell's table.
        clock: the switch clock, or None.
        ages: (block,) float32 each cell's clock in steps (advanced in place); with ``clock``.
    """
    c = clock or _NO_CLOCK
    return ChainPack(
        tables.table, table_of_cell, tables.layer, tables.shape, tables.strides, tables.origin,
        tables.scale, features, row, NO_CHAIN.ages if ages is None else ages, float(c.cap),
        float(c.unit),
    )  # fmt: skip


def class_pack(
    law: PackedClasses, features: np.ndarray, row: int, classes: np.ndarray
) -> ClassPack:
    """A K-lumps chain's :class:`ClassPack`.

    Args:
        law: the chain's law.
        features: (d,) int64 feature indices (:func:`feature_axes`).
        row: the first of its ``d + 1`` uniform rows.
        classes: (block,) int64 each cell's class (advanced in place).
    """
    return ClassPack(law.cdf, law.origin_stride, law.nodes, law.strides, law.origin,
                     law.scale, features, row, law.lumps, classes)  # fmt: skip

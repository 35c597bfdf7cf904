"""The E. coli step as a compiled per-cell kernel (numba): many steps per call, no per-step Python.

At small populations a batched torch step costs its ~450 tensor operations' dispatch (~0.5 ms
eager, ~0.12 ms compiled) whatever the number of cells; here one call advances every cell by
``k`` steps (a record interval) in machine code, each cell in its own registers, cells spread
over threads with ``prange``. It consumes the *same* random numbers as the torch step (the
simulator's :class:`~surrogate.simulate.loop.RandomBlock` rows, in the same layout), so with one
seed it follows the torch path's trajectories up to float rounding (tested step by step against
it): both compute the same operations in the same order, but the elementary functions (exp,
log, log1p, expm1, cos, sin) of torch's vectorised code and of numba's libm round differently
by an ulp now and then. Results never depend on the number of threads.

The body's formulas are not written here: the signal (receptor terms, F, activity, CheY-P,
dG), the motor rates, the OU step, movement and tumble angles, and one motor's exact window
(transition terms, thresholds, next state, RUN flag) are the scalar formulas of
:mod:`surrogate.models.ecoli.formulas`, which the torch step evaluates over tensors and this
kernel compiles per cell (:func:`surrogate.scalar.numba_formulas`), in the same operations and
precision (float32 state and signalling, float64 motor rates and transition terms). Fields are
generated from each field's formula (:mod:`surrogate.field_kernel`). What remains here is the
loop: the lookup of the abstraction (:func:`surrogate.gp.lookup._interpolate`, multilinear,
torch's lerp; the K-lumps chain's draw,
``surrogate.simulate.classes.ClassTable.draw``, with the same uniforms in the same order), the
per-cell control flow of the motors and the tumble (the torch step blends
with ``where``) and :meth:`Simulator._advance`'s segment bookkeeping. The tests compare the
kernel with the torch step.

Numbers are passed as flat arrays (layouts in :func:`pack_parameters` and
:func:`~surrogate.field_kernel.pack_field`; the decision layer as the engine packed it,
:class:`~surrogate.models.packed.PackedDecision`: the kernel never reads the engine's decision
layers or lookup tables); ``cache=True`` keeps the machine code on disk, so
only the first process compiles (~5 s), once per set of field formulas (the built-in fields'
set is the precompiled one) and again when the formulas' source changes
(:func:`surrogate.scalar.renew_with`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from surrogate import scalar
from surrogate.ctmc.compiled import match_torch_threads
from surrogate.errors import KernelUnsupported
from surrogate.field_kernel import field_set, field_value, pack_field
from surrogate.fields import Field, FieldBatch
from surrogate.models.base import Randoms
from surrogate.models.ecoli import formulas
from surrogate.models.ecoli.body import MAX_GAMMA_UNIFORMS
from surrogate.models.ecoli.internal import INPUTS, MotorInternalModel
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.packed import CHAIN, CLASSES, EXACT, FULL, PackedBlock, PackedDecision

# -- features of the abstraction's lookup table --------------------------------------------------
# what each name means here (its formula below); an internal model's feature of that name must
# compute the same (the model that hands the kernel its internal model vouches for that)
FEATURE_CODES = {"m": 0, "L": 1, "F": 2, "cheyp": 3, "dG": 4, "activity": 5}
#: the switch clock (s since phi last changed, capped): psi's last input under gp.history=age
CLOCK_CODE = 6

# -- float32 constants (signalling, OU, movement) and float64 constants (motors) ----------------
P32_NAMES = formulas.CONSTANTS
P64_NAMES = ("omega", "mu", "dt")

_JIT: dict[str, Any] = {"nogil": True, "cache": True, "fastmath": False, "error_model": "numpy"}
_F32 = np.float32


#: the body's formulas compiled (:mod:`surrogate.models.ecoli.formulas`), inlined here
_F = formulas.compiled()
_clamp = scalar.numba_primitives()["clamp"]  # torch.clamp: NaN passes through
_log_receptor_terms, _activity, _signal = _F.log_receptor_terms, _F.activity, _F.signal


@numba.njit(inline="always", **_JIT)
def _feature(code, m, ligand, energy, act, yp, dg, clock):
    """The column of FEATURE_CODES ``code`` (CLOCK_CODE: the switch clock ``clock``)."""
    if code == CLOCK_CODE:
        return clock
    if code == 0:
        return m
    if code == 1:
        return ligand
    if code == 2:
        return energy
    if code == 3:
        return yp
    if code == 5:
        return act
    return dg


@numba.njit(inline="always", **_JIT)
def _lerp(a, b, w):
    """torch.lerp's formula (float32)."""
    if abs(w) < _F32(0.5):
        return a + w * (b - a)
    return b - (b - a) * (_F32(1.0) - w)


@numba.njit(inline="always", **_JIT)
def _move_and_account(
    c, s, phi_before, phi_after, x, y, heading, u, body_row, gamma_k, per_tumble, p,
    seg, complete, ended,
):  # fmt: skip
    """ChemotacticBody.move (without the OU step; the angle drawn only when turning) and
    Simulator._advance's bookkeeping.

    Returns the new (x, y, heading); writes the cell's segment state and ``ended[s, c]``."""
    nx, ny = _F.run_step(x, y, heading, phi_after, p)
    if _F.turning(phi_before, phi_after, per_tumble) > 0:
        angle = _F.tumble_angle(u[s, :, c], body_row, gamma_k, p[formulas.TUMBLE_SCALE])
        heading = _F.turn(heading, angle, u[s, body_row + gamma_k, c], p)
    # a segment ends when phi switches; the first one is left-censored
    switched = 1 if phi_after != phi_before else 0
    length = seg[c] + 1
    sign = 1 if phi_before > 0 else -1
    ended[s, c] = switched * complete[c] * sign * length
    seg[c] = length * (1 - switched)
    complete[c] = max(complete[c], switched)
    return nx, ny, heading


@numba.njit(inline="always", **_JIT)
def _motors_step(dg, motors, j, c, s, u64, motor_row, q):
    """One exact window of cell c's motors (``motors[:, j]``, in place) at dG; its RUN flag
    (as motors.sample_motor_states and run_flag_from_states, motor by motor)."""
    kp, km = _F.rates(dg, q[0])
    t1_s, t1_c, t1_n, t2_cw, t2_n = _F.motor_thresholds(kp, km, q[2], q[1])
    n_ccw = _F32(0.0)
    lowest = _F32(2.0)
    for i in range(motors.shape[0]):
        new = _F.next_motor_state(motors[i, j], u64[s, motor_row + i, c], t1_s, t1_c, t1_n,
                                  t2_cw, t2_n)  # fmt: skip
        motors[i, j] = new
        n_ccw += _F.ccw(new)
        lowest = min(lowest, new)
    return _F.run_flag(n_ccw, lowest)


@numba.njit(inline="always", **_JIT)
def _lookup(phi_now, tab, m, ligand, energy, act, yp, dg, clock, table, layer, shape, strides,
            origin, scale, features):  # fmt: skip
    """p(phi' = 1): gp.lookup._interpolate in table ``tab`` (lower node per axis, then lerp
    along the last axis first)."""
    d = shape.shape[0]
    base = tab * 2 * layer + (layer if phi_now > 0 else 0)
    fr0 = _F32(0.0)
    fr1 = _F32(0.0)
    fr2 = _F32(0.0)
    for a in range(d):
        value = _feature(features[a], m, ligand, energy, act, yp, dg, clock)
        top = _F32(shape[a] - 1)
        w = _clamp((value - origin[tab, a]) * scale[tab, a], _F32(0.0), top)
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


@numba.njit(inline="always", **_JIT)
def _class_draw(cls, s, c, u, row, m, ligand, energy, act, yp, dg, cdf, origin_stride, nodes,
                strides, origin, scale, features, lumps):  # fmt: skip
    """The next class of a cell in class ``cls``: ClassTable.draw (stochastic rounding to a
    node per axis with the uniforms of rows ``row``, ``row + 1``, ...; then the categorical
    draw from one cumulative row with the uniform of row ``row + d``), its positions in
    float32 in ClassTable._positions' order of operations."""
    d = nodes.shape[0]
    n_classes = lumps.shape[0]
    index = cls * origin_stride
    for a in range(d):
        n = nodes[a]
        if n <= 1:  # a constant axis: node 0
            continue
        value = _feature(features[a], m, ligand, energy, act, yp, dg, _F32(0.0))
        w = _clamp((value - origin[0, a]) * scale[0, a], _F32(0.0), _F32(n - 1))
        node = min(np.floor(w), _F32(n - 2))
        # NaN: node 0, never rounded up (as ClassTable._positions)
        i = int(node) if node == node else 0
        if u[s, row + a, c] < w - node:
            i += 1
        index += i * strides[a]
    v = u[s, row + d, c]
    base = index * n_classes
    nxt = 0
    for b in range(n_classes):
        if v >= cdf[base + b]:
            nxt += 1
    return min(nxt, n_classes - 1)


@numba.njit(**_JIT)
def _advance_range(
    steps, step0, start, lo, hi, position, heading, meth, phi, seg, complete, last_x, ended,
    field_of_cell, fields, field_set, u, u64, z, body_row, ou_row, gamma_k, per_tumble, p, q,
    motors, motor_row,
    table, table_of_cell, layer, shape, strides, origin, scale, features, decision_row,
    ages, max_age, clock_unit, lumps, classes,
):  # fmt: skip
    """``steps`` steps of cells ``start + lo`` to ``start + hi`` of a block that starts at
    population cell ``start``: the full model when ``motors`` (M x block float32, 0 = S,
    1 = C, 2 = N) has rows, each motor by its exact exp(Q dt) with
    the float64 uniforms from row ``motor_row``; else the two-state chain
    phi' ~ Bernoulli(psi_phi(z)) with the uniform of row ``decision_row``, psi a multilinear
    lookup over ``features`` (codes of FEATURE_CODES) in the flat float32 ``table``: cell
    ``start + j`` reads table ``table_of_cell[j]`` (offset ``2 * layer`` each) with its box
    ``origin``/``scale`` (tables x d float32). With ``max_age > 0`` the chain has a switch
    clock (:class:`~surrogate.simulate.memory.MemoryDecision`): cell ``start + j``'s clock in
    steps is ``ages[j]`` (float32, in place), psi reads ``min(age clock_unit, max_age)`` as
    feature CLOCK_CODE (seconds: unit dt; a table with a node per step: unit 1 on a unit
    axis, so the node is exact, as the torch layer's clock_nodes), and the clock restarts at
    0 when phi changes, else counts on (memory.tick).

    With ``lumps`` (float32, the phi of each of ``C`` classes) non-empty, the block is a
    K-lumps chain (:class:`~surrogate.simulate.classes.ClassDecision`, packed as
    :class:`~surrogate.models.packed.PackedClasses`): cell ``start + j``'s class is
    ``classes[j]`` (int64, in place), drawn by :func:`_class_draw` from the cumulative rows
    ``table`` (``layer``: rows per origin class; ``shape``: nodes per axis, 1 for a constant
    axis; ``strides``; ``origin``/``scale`` of shape ``1 x d``; ``features``) with the
    ``d + 1`` uniforms from row ``decision_row``; phi is the class's lump.

    Cell ``c`` sees the field of row ``fields[field_of_cell[c]]`` (packed by
    :func:`~surrogate.field_kernel.pack_field` for the formulas of ``field_set``).

    Arrays are the simulator's tensors (in place): position (n, 2), heading, meth (n,) float32,
    phi, complete (n,) uint8, seg (n,) int32; last_x (n, 2) the last step's inputs; ended
    (steps, n) int32 out; random blocks u (steps, rows, n) float32, u64 (steps, rows, n) float64,
    z (steps, rows, n) float32. One function for both layers: one compilation.
    """
    full = motors.shape[0] > 0
    classed = lumps.shape[0] > 0
    dt = q[2]
    clocked = max_age > 0
    unit = _F32(clock_unit)
    cap = _F32(max_age)
    for j in range(lo, hi):
        c = start + j
        x, y, h, m = position[c, 0], position[c, 1], heading[c], meth[c]
        phi_now = _F32(phi[c])
        age = ages[j] if clocked else _F32(0.0)
        cls = classes[j] if classed else 0
        f = fields[field_of_cell[c]]
        tab = 0 if full or classed else table_of_cell[j]
        for s in range(steps):
            ligand = field_value(field_set, f, x, y, (step0 + s) * dt)
            last_x[c, 0] = m
            last_x[c, 1] = ligand
            lrt = _log_receptor_terms(ligand, p)
            energy, act, yp, dg = _signal(m, lrt, p)
            if full:
                phi_after = _motors_step(dg, motors, j, c, s, u64, motor_row, q)
            elif classed:
                cls = _class_draw(cls, s, c, u, decision_row, m, ligand, energy, act, yp, dg,
                                  table, layer, shape, strides, origin, scale, features, lumps)  # fmt: skip
                phi_after = lumps[cls]
            else:
                clock = min(age * unit, cap)  # memory.with_age
                prob = _lookup(phi_now, tab, m, ligand, energy, act, yp, dg, clock, table,
                               layer, shape, strides, origin, scale, features)  # fmt: skip
                phi_after = _F32(1.0) if u[s, decision_row, c] < prob else _F32(0.0)
                if clocked:  # memory.tick
                    age = _F32(0.0) if phi_after != phi_now else age + _F32(1.0)
            x, y, h = _move_and_account(
                c, s, phi_now, phi_after, x, y, h, u, body_row, gamma_k, per_tumble, p,
                seg, complete, ended,
            )  # fmt: skip
            m = _F.ou_step(m, lrt, z[s, ou_row, c], p)
            phi_now = phi_after
        position[c, 0], position[c, 1], heading[c], meth[c] = x, y, h, m
        phi[c] = np.uint8(phi_now)
        if clocked:
            ages[j] = age
        if classed:
            classes[j] = cls


@numba.njit(parallel=True, **_JIT)
def advance_cells(
    steps, step0, start, lo, hi, pieces, position, heading, meth, phi, seg, complete, last_x, ended,
    field_of_cell, fields, field_set, u, u64, z, body_row, ou_row, gamma_k, per_tumble, p, q,
    motors, motor_row,
    table, table_of_cell, layer, shape, strides, origin, scale, features, decision_row,
    ages, max_age, clock_unit, lumps, classes,
):  # fmt: skip
    """Cells ``start + lo`` to ``start + hi`` in ``pieces`` contiguous pieces (a few per
    thread: balanced) spread over numba's threads, each by :func:`_advance_range` (the other
    arguments as there). The parallel loop holds only that call:
    lowering ``prange`` around the whole inlined body more than doubled the one-time
    compilation (8.9 s vs 4.5 s measured) for the same speed at the paper's size."""
    pieces = max(1, min(hi - lo, pieces))
    for k in prange(pieces):
        _advance_range(
            steps, step0, start, lo + (hi - lo) * k // pieces, lo + (hi - lo) * (k + 1) // pieces,
            position, heading, meth, phi, seg, complete, last_x, ended, field_of_cell, fields,
            field_set, u, u64, z, body_row, ou_row, gamma_k, per_tumble, p, q, motors, motor_row, table,
            table_of_cell, layer, shape, strides, origin, scale, features, decision_row, ages,
            max_age, clock_unit, lumps, classes,
        )  # fmt: skip


# numba's cache follows this file only: also the formulas' (inlined above)
scalar.renew_with((_advance_range, advance_cells), (formulas, scalar))


# ---------------------------------------------------------------------------------------------
# The adaptor: from the simulator's objects (decision layers, fields, tensors) to flat arrays.
# ---------------------------------------------------------------------------------------------
def pack_parameters(params: EcoliParameters, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The constants of the kernels: float32 ``P32_NAMES`` (the torch step's Python floats,
    :func:`~surrogate.models.ecoli.formulas.constants`, rounded as torch rounds them) and
    float64 ``P64_NAMES``."""
    p32 = np.array(formulas.constants(params, dt), dtype=np.float32)
    p64 = np.array([params.omega, params.mu, dt], dtype=np.float64)
    return p32, p64


# placeholders for the arguments of the layer a block does not use (one compiled signature)
_NO_MOTORS = np.zeros((0, 0), dtype=np.float32)
_NO_U64 = np.zeros((1, 1, 1), dtype=np.float64)
_NO_TABLE = (np.zeros(2, dtype=np.float32), np.zeros(1, dtype=np.int32), 1,
             np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
             np.zeros((1, 1), dtype=np.float32), np.zeros((1, 1), dtype=np.float32),
             np.zeros(1, dtype=np.int64), 0)  # fmt: skip
_NO_CLOCK = (np.zeros(1, dtype=np.float32), 0.0, 0.0)
_NO_CLASSES = (np.zeros(0, dtype=np.float32), np.zeros(1, dtype=np.int64))
#: the built-in fields' formulas: the field set of the precompiled kernel
_BUILTIN_FIELD_SET = field_set([])


def _zero_cell_arguments() -> tuple[Any, ...]:
    """Arguments of :func:`advance_cells` for zero cells, typed exactly as the adaptor's (C
    contiguous, writable arrays of the same dtypes and ranks): its one compiled signature."""
    f32, i32, u8 = np.float32, np.int32, np.uint8
    p32 = np.zeros(len(P32_NAMES), dtype=f32)
    p64 = np.zeros(len(P64_NAMES), dtype=np.float64)
    return (1, 0, 0, 0, 0, 1, np.zeros((1, 2), f32), np.zeros(1, f32), np.zeros(1, f32),
            np.zeros(1, u8), np.zeros(1, i32), np.zeros(1, u8), np.zeros((1, 2), f32),
            np.zeros((1, 1), i32), np.zeros(1, i32), np.zeros((1, _BUILTIN_FIELD_SET.columns)),
            _BUILTIN_FIELD_SET, np.zeros((1, 1, 1), f32), _NO_U64, np.zeros((1, 1, 1), f32), 0, 0, 1, False,
            p32, p64, _NO_MOTORS, 0, *_NO_TABLE, *_NO_CLOCK, *_NO_CLASSES)  # fmt: skip


def precompile() -> None:
    """Compile :func:`advance_cells` (or load it from numba's on-disk cache) by calling it on
    zero cells. Run in a background process by
    :func:`surrogate.simulate.precompile.precompile_in_background` while a stage collects and
    trains, so the stage's first simulation finds the machine code cached."""
    advance_cells(*_zero_cell_arguments())


def is_compiled_on_disk() -> bool:
    """Whether numba's on-disk cache already holds :func:`advance_cells` for this machine
    (False where that cannot be told: then the caller precompiles, which costs only time)."""
    try:
        sig = tuple(numba.typeof(a) for a in _zero_cell_arguments())
        cache = advance_cells._cache
        key = cache._index_key(sig, advance_cells.targetctx.codegen())
        return key in cache._cache_file._load_index()
    except Exception:  # numba internals moved: say "not cached"
        return False


def _numpy(t: Tensor) -> np.ndarray:
    """A tensor's memory as a numpy array (CPU, contiguous: the kernel writes in place)."""
    if t.device.type != "cpu" or not t.is_contiguous():
        raise ValueError("the per-cell kernel needs contiguous CPU tensors")
    return t.view(torch.uint8).numpy() if t.dtype == torch.bool else t.numpy()


class _Block:
    """One packed decision block as the arguments of :func:`advance_cells`.

    Only the kinds whose formulas the kernel transcribes are accepted, over this model's own
    internal model and constants: the motor blocks (the full model, the exact chain) need the
    E. coli motors (:class:`MotorInternalModel`); a chain over lookup tables reads features of
    FEATURE_CODES of any internal model the kernel was given (see :class:`EcoliKernel`).

    Raises:
        KernelUnsupported: what the kernel does not run, naming it.
    """

    def __init__(self, block: PackedBlock, internal: Any) -> None:
        self.start, self.count, self.state = block.start, block.count, block.state
        self.clock = _NO_CLOCK_SETTINGS
        if block.kind not in (FULL, CHAIN, EXACT, CLASSES):
            raise KernelUnsupported(block.why or f"decision layer {block.layer}")
        if block.kind not in (CHAIN, CLASSES) and type(internal) is not MotorInternalModel:
            raise KernelUnsupported(
                f"a {block.layer} over {type(internal).__name__} (the kernel's full model and "
                "exact chain are the E. coli motors)"
            )
        if not block.fusable:
            raise KernelUnsupported(f"a {block.layer} without a pure window (motor SSA)")
        if not _same_internal(block.internal, internal):
            raise KernelUnsupported("a decision layer over another internal model")
        self.kind = {FULL: "motors", CLASSES: "classes"}.get(block.kind, "lookup")
        if block.kind == FULL:
            self.motor_row = block.motor_row
            return
        if block.kind == CLASSES:
            self._classes(block, internal)
            return
        tables = block.tables
        if tables is None or block.why is not None:
            raise KernelUnsupported(block.why or f"a {block.layer} without lookup tables")
        codes = _feature_codes(block, internal)
        if block.clock is not None:  # the clock is psi's last input
            codes.append(CLOCK_CODE)
            self.clock = (float(block.clock.cap), float(block.clock.unit))
        if len(codes) != tables.shape.shape[0]:
            raise KernelUnsupported(
                f"{len(codes)} features for a lookup table over {tables.shape.shape[0]} axes"
            )
        self.tables = tables
        self.table_args = (tables.table, tables.layer, tables.shape, tables.strides,
                           tables.origin, tables.scale, np.array(codes, dtype=np.int64),
                           block.decision_row)  # fmt: skip
        self._table_of_cell: np.ndarray | None = None

    def _classes(self, block: PackedBlock, internal: Any) -> None:
        """A K-lumps chain: its law's arrays in :func:`advance_cells`' table arguments."""
        law = block.classes
        if law is None or block.why is not None:
            raise KernelUnsupported(block.why or f"a {block.layer} without its class table")
        codes = _feature_codes(block, internal)
        if len(codes) != law.nodes.shape[0]:
            raise KernelUnsupported(
                f"{len(codes)} features for a class table over {law.nodes.shape[0]} axes"
            )
        self.lumps = law.lumps
        self.table_args = (law.cdf, law.origin_stride, law.nodes, law.strides,
                           law.origin.reshape(1, -1), law.scale.reshape(1, -1),
                           np.array(codes, dtype=np.int64), block.decision_row)  # fmt: skip

    def tables_for(self, n: int) -> np.ndarray:
        """Each cell's table for a block of ``n`` cells."""
        if self._table_of_cell is None or self._table_of_cell.shape[0] != n:
            self._table_of_cell = self.tables.table_of_cell(n)
        return self._table_of_cell


#: no switch clock: (cap, unit)
_NO_CLOCK_SETTINGS = (0.0, 0.0)


def _same_internal(a: Any, b: Any) -> bool:
    """Whether two internal models are the same for the kernel: one object, or the same motors
    (class and constants; the kernel computes with the model's constants)."""
    return a is b or (type(a) is type(b) is MotorInternalModel and a.params == b.params)


def _feature_codes(block: PackedBlock, internal: Any) -> list[int]:
    """The kernel's codes of the abstraction's input columns: the raw inputs (m, L) without a
    feature map (as the torch layer feeds x itself), else the map's names, each one the
    internal model computes (its inputs and features) and the kernel transcribes."""
    if block.features is None:
        return [FEATURE_CODES[n] for n in INPUTS]
    if not _same_internal(block.features_of, internal):
        raise KernelUnsupported(
            f"a feature map over another internal model ({type(block.features_of).__name__})"
        )
    known = (*internal.input_names, *internal.feature_names)
    unknown = [n for n in block.features if n not in FEATURE_CODES or n not in known]
    if unknown:
        raise KernelUnsupported(f"features {unknown}")
    return [FEATURE_CODES[n] for n in block.features]


class EcoliKernel:
    """The E. coli step for a whole population, many steps per call (see the module docstring).

    Built by :meth:`EcoliModel.cell_kernel` (and the ``cell_kernel`` of other models on the
    E. coli body, e.g. ``ecoli_phospho``) from the decision layer the engine packed
    (:class:`~surrogate.models.packed.PackedDecision`); raises
    :class:`~surrogate.errors.KernelUnsupported` for what it cannot run (Python fields,
    classifier or direct-exact decision layers, the SSA motor sampler, non-integer tumble
    shapes, a full model or exact chain over anything but the E. coli motors), so the
    simulator keeps the torch step for those.

    ``internal`` is the model's internal model, with the model's constants ``params`` and the
    inputs (m, L). With the E. coli motors (:class:`MotorInternalModel`) every decision layer
    above runs here; with another internal model (e.g. the phospho network) only two-state
    chains over lookup tables do, over its features of the names in FEATURE_CODES: the model
    that hands it over vouches that they compute the kernel's formulas (its ``cell_kernel``
    checks its internal model's class).

    Args:
        params: the model's constants.
        internal: the model's internal model.
        decision: the packed decision layer (blocks of cells, each its own layer).
        field: the field (or a batch of fields, block by block).
        dt: the time step (s).
    """

    def __init__(
        self,
        params: EcoliParameters,
        internal: Any,
        decision: PackedDecision,
        field: Field,
        dt: float,
    ) -> None:
        if params.motor_sampler == "ssa":
            raise KernelUnsupported("model.motor_sampler=ssa")
        # an internal model without constants of its own has its features from the body's
        # (the model that hands it over vouches for that, e.g. a yaml model on this body)
        if getattr(internal, "params", params) != params or tuple(internal.input_names) != INPUTS:
            raise KernelUnsupported(
                "an internal model with other constants or inputs than the model's (m, L)"
            )
        shape = float(params.tumble_shape)
        if not (shape.is_integer() and shape <= MAX_GAMMA_UNIFORMS):
            raise KernelUnsupported(f"a non-integer tumble_shape {shape:g}")
        self.gamma_k = int(shape)
        self.per_tumble = params.tumble_mode == "per_tumble"
        self.p32, self.p64 = pack_parameters(params, dt)
        # random rows: the decision's first (right-aligned per member), then the body's
        rows = decision.randoms
        self._rows = Randoms(rows.uniform + self.gamma_k + 1, rows.uniform64, rows.normal + 1)
        self.body_row, self.ou_row = rows.uniform, rows.normal
        self._body_args = (self.body_row, self.ou_row, self.gamma_k, self.per_tumble, self.p32,
                           self.p64)  # fmt: skip
        self.blocks = [_Block(b, internal) for b in decision.blocks]
        self._total = decision.total
        fields = field.fields if isinstance(field, FieldBatch) else [field]
        self.field_set = field_set(fields)
        self.fields = np.stack([pack_field(f, self.field_set) for f in fields])
        self._field_sizes: list[int] | None = field.sizes if isinstance(field, FieldBatch) else None
        self._field_total = None if self._field_sizes is None else sum(self._field_sizes)
        self._field_of_cell: np.ndarray | None = None

    def _cells(self, n: int) -> np.ndarray:
        """Each cell's field row, for a population of ``n`` cells (checked against the
        batch's blocks)."""
        for what, total in (("decision", self._total), ("field", self._field_total)):
            if total is not None and total != n:
                raise ValueError(f"the kernel's {what} blocks cover {total} cells, not {n}")
        if self._field_of_cell is None or self._field_of_cell.shape[0] != n:
            sizes = [n] if self._field_sizes is None else self._field_sizes
            self._field_of_cell = np.repeat(np.arange(len(sizes), dtype=np.int32), sizes)
        return self._field_of_cell

    def advance(self, state: Any, ended: Tensor, u: Tensor, u64: Tensor | None, z: Tensor) -> None:
        """Advance every cell of ``state`` (the simulator's ``PopulationState``) by
        ``ended.shape[0]`` steps in place, writing each step's ended segment lengths into
        ``ended`` (steps x n int32); ``u``, ``u64``, ``z`` are the steps' random numbers
        (steps x rows x n) in the simulator's layout."""
        self._run(state, ended, u, u64, z, dry=False)

    def warm_up(self, state: Any) -> None:
        """Compile the kernels this population needs (or load them from numba's cache) by
        calling them on zero cells: nothing changes."""
        n = state.n_cells
        copy = dataclasses.replace(
            state, body={k: v.clone() for k, v in state.body.items()}, phi=state.phi.clone(),
            segment_steps=state.segment_steps.clone(),
            segment_complete=state.segment_complete.clone(), inputs=torch.zeros((n, 2)),
        )  # fmt: skip
        r = self._rows
        u = torch.zeros((1, r.uniform, n))
        u64 = torch.zeros((1, r.uniform64, n), dtype=torch.float64) if r.uniform64 else None
        z = torch.zeros((1, r.normal, n))
        self._run(copy, torch.zeros((1, n), dtype=torch.int32), u, u64, z, dry=True)

    def _run(
        self,
        state: Any,
        ended: Tensor,
        u: Tensor,
        u64: Tensor | None,
        z: Tensor,
        dry: bool,
    ) -> None:
        steps = int(ended.shape[0])
        n = state.n_cells
        field_of_cell = self._cells(n)
        body = state.body
        if state.inputs is None or state.inputs.shape != (n, 2):
            state.inputs = torch.empty((n, 2), dtype=torch.float32)
        common = (_numpy(body["position"]), _numpy(body["heading"]), _numpy(body["m"]),
                  _numpy(state.phi), _numpy(state.segment_steps),
                  _numpy(state.segment_complete), _numpy(state.inputs), _numpy(ended),
                  field_of_cell, self.fields, self.field_set)  # fmt: skip
        un, zn = _numpy(u), _numpy(z)
        # as many kernel threads as torch uses (the threads setting; a sweep job's share), a
        # few pieces each (cells of one block cost alike; pieces balance what differs)
        threads = match_torch_threads()
        for b in self.blocks:
            count = n if b.count is None else b.count
            if count == 0:
                continue
            head = (steps, state.step, b.start, 0, 0 if dry else count, 4 * threads)
            # the per-cell state (motor states, clocks), advanced in place: the layer's own
            # copy (a dry run only reads it)
            own = None if b.state is None else (b.state.current() if dry else b.state.writable())
            if b.kind == "motors":
                assert own is not None and u64 is not None  # motor states, one u64 per motor
                advance_cells(*head, *common, un, _numpy(u64), zn, *self._body_args,
                              _numpy(own), b.motor_row, *_NO_TABLE, *_NO_CLOCK,
                              *_NO_CLASSES)  # fmt: skip
            elif b.kind == "classes":
                cdf, layer, nodes, strides, origin, scale, features, row = b.table_args
                assert own is not None  # each cell's class
                advance_cells(*head, *common, un, _NO_U64 if u64 is None else _numpy(u64), zn,
                              *self._body_args, _NO_MOTORS, 0, cdf, _NO_TABLE[1], layer, nodes,
                              strides, origin, scale, features, row, *_NO_CLOCK, b.lumps,
                              _numpy(own))  # fmt: skip
            else:
                table, layer, shape, strides, origin, scale, features, row = b.table_args
                clock = _NO_CLOCK if own is None else (_numpy(own), *b.clock)
                advance_cells(*head, *common, un, _NO_U64 if u64 is None else _numpy(u64), zn,
                              *self._body_args, _NO_MOTORS, 0, table, b.tables_for(count),
                              layer, shape, strides, origin, scale, features, row,
                              *clock, *_NO_CLASSES)  # fmt: skip
        if not dry:
            state.step += steps

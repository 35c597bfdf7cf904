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
generated from each field's formula (:mod:`surrogate.field_kernel`); a coupled field (the
agents change it every step) is read by the simulator before each call of one step and handed
over in the cells' inputs (``last_x``), and the simulator steps it between the calls. The
decision kinds other than the model's own window (the two-state chain over lookup tables, with
or without a switch clock, and the K-lumps chain) and the segment bookkeeping are the engine's
per-cell steps (:mod:`surrogate.models.decision_kernel`, the same for every model's kernel); this
kernel hands them its features as a float32 tuple indexed by :data:`FEATURE_CODES`
(:func:`_features`). What
remains here is the loop, the motors' window (the full model) and the per-cell control flow of
the motors and the tumble (the torch step blends with ``where``). The tests compare the kernel
with the torch step.

Numbers are passed as namedtuples of flat arrays and numbers (:data:`State`, :data:`Draws`,
:data:`Constants`, :data:`Fields`, :data:`Motors`; layouts in :func:`pack_parameters` and
:func:`~surrogate.field_kernel.pack_field`; the decision layer as the engine packed it,
:class:`~surrogate.models.packed.PackedDecision`, in the engine's
:class:`~surrogate.models.decision_kernel.DecisionPack`: the kernel never reads the engine's decision
layers or lookup tables); ``cache=True`` keeps the machine code on disk, so
only the first process compiles (~5 s), once per set of field formulas (the built-in fields'
set is the precompiled one) and again when the formulas' or the decision steps' source changes
(:func:`surrogate.scalar.renew_with`).
"""

from __future__ import annotations

import dataclasses
from collections import namedtuple
from typing import Any

import numba
import numpy as np
import torch
from numba import prange
from numba.core import options as numba_options
from torch import Tensor

import surrogate.models.decision_kernel as kd
from surrogate import scalar
from surrogate.ctmc.compiled import match_torch_threads
from surrogate.errors import KernelUnsupported
from surrogate.field_kernel import READ_OUTSIDE, FieldSet, field_set, field_value, pack_fields
from surrogate.fields import Field, FieldBatch
from surrogate.models.base import Randoms
from surrogate.models.ecoli import formulas
from surrogate.models.ecoli.body import MAX_GAMMA_UNIFORMS
from surrogate.models.ecoli.internal import INPUTS, MotorInternalModel
from surrogate.models.ecoli.parameters import EcoliParameters
from surrogate.models.packed import CHAIN, CLASSES, EXACT, FULL, PackedBlock, PackedDecision

# -- features of the abstraction's lookup table --------------------------------------------------
# what each name means here (its formula below); an internal model's feature of that name must
# compute the same (the model that hands the kernel its internal model vouches for that). Each
# code is the feature's index in the tuple of values the kernel hands the engine's decision
# steps (:func:`_features`; the switch clock is the engine's ``decision_kernel.CLOCK``)
FEATURE_CODES = {"m": 0, "L": 1, "F": 2, "cheyp": 3, "dG": 4, "activity": 5}

# -- float32 constants (signalling, OU, movement) and float64 constants (motors) ----------------
P32_NAMES = formulas.CONSTANTS
P64_NAMES = ("omega", "mu", "dt")

_JIT: dict[str, Any] = {"nogil": True, "cache": True, "fastmath": False, "error_model": "numpy"}
#: the per-cell loop without reference counts: it allocates nothing, and numba counts every
#: array of a pack each time it hands the pack to an inlined decision step (32 atomic updates a
#: step: the loop ran at half its speed, measured); numba's ``_nrt`` option, where it has one
_NO_REFCOUNTS: dict[str, Any] = (
    {"_nrt": False} if hasattr(numba_options.DefaultOptions, "_nrt") else {}
)
_F32 = np.float32

# -- the kernel's arguments, grouped: namedtuples inside, plain tuples at the call (_plain) -----
#: the body's per-cell arrays (in place): ``position`` (n, 2), ``heading``, ``meth`` (n,)
#: float32; ``last_x`` (n, 2) float32 the last step's inputs (m, L)
Body = namedtuple("Body", ["position", "heading", "meth", "last_x"])
#: every per-cell array: the engine's (:class:`~surrogate.models.decision_kernel.Cells`) and the body's
State = namedtuple("State", ["cells", "body"])
#: the steps' random numbers in the simulator's layout: ``u`` (steps, rows, n) float32, ``u64``
#: (steps, rows, n) float64, ``z`` (steps, rows, n) float32 normals
Draws = namedtuple("Draws", ["u", "u64", "z"])
#: the body's constants: its first uniform row ``body_row`` (then ``gamma_k`` for the tumble
#: angle's gamma), its normal row ``ou_row``, ``per_tumble`` (tumble_mode), the float32
#: constants ``p`` (P32_NAMES) and float64 ``q`` (P64_NAMES)
Constants = namedtuple("Constants", ["body_row", "ou_row", "gamma_k", "per_tumble", "p", "q"])
#: the fields: ``of_cell`` (n,) int32 each cell's row of ``rows`` (float64, packed by
#: :func:`~surrogate.field_kernel.pack_field` for the formulas of the kernel's field set)
Fields = namedtuple("Fields", ["of_cell", "rows"])
#: the full model's motors (kind ``full``): ``states`` (M, block) float32 (0 = S, 1 = C,
#: 2 = N; in place; no rows: not the full model) and the first float64 uniform row ``row``
Motors = namedtuple("Motors", ["states", "row"])


#: the body's formulas compiled (:mod:`surrogate.models.ecoli.formulas`), inlined here
_F = formulas.compiled()
_log_receptor_terms, _activity, _signal = _F.log_receptor_terms, _F.activity, _F.signal


@numba.njit(inline="always", **_JIT)
def _features(m, ligand, energy, act, yp, dg):
    """The features a decision layer may read, as a float32 tuple indexed by FEATURE_CODES."""
    return (m, ligand, energy, yp, dg, act)


@numba.njit(inline="always", **_JIT)
def _move(s, c, phi_before, phi_after, x, y, heading, draws, k):
    """ChemotacticBody.move (without the OU step; the angle drawn only when turning): the new
    (x, y, heading) of cell ``c`` at step ``s`` (``draws``: :data:`Draws`; ``k``:
    :data:`Constants`)."""
    p = k.p
    nx, ny = _F.run_step(x, y, heading, phi_after, p)
    if _F.turning(phi_before, phi_after, k.per_tumble) > 0:
        u = draws.u
        angle = _F.tumble_angle(u[s, :, c], k.body_row, k.gamma_k, p[formulas.TUMBLE_SCALE])
        heading = _F.turn(heading, angle, u[s, k.body_row + k.gamma_k, c], p)
    return nx, ny, heading


@numba.njit(inline="always", **_JIT)
def _motors_step(dg, motors, j, c, s, u64, q):
    """One exact window of cell c's motors (``motors.states[:, j]``, in place; :data:`Motors`)
    at dG; its RUN flag (as motors.sample_motor_states and run_flag_from_states, motor by
    motor)."""
    states, row = motors.states, motors.row
    kp, km = _F.rates(dg, q[0])
    t1_s, t1_c, t1_n, t2_cw, t2_n = _F.motor_thresholds(kp, km, q[2], q[1])
    n_ccw = _F32(0.0)
    lowest = _F32(2.0)
    for i in range(states.shape[0]):
        new = _F.next_motor_state(states[i, j], u64[s, row + i, c], t1_s, t1_c, t1_n,
                                  t2_cw, t2_n)  # fmt: skip
        states[i, j] = new
        n_ccw += _F.ccw(new)
        lowest = min(lowest, new)
    return _F.run_flag(n_ccw, lowest)


@numba.njit(**_NO_REFCOUNTS, **_JIT)
def _advance_range(steps, step0, start, lo, hi, state, draws, k, field_set, field, motors,
                   decision):  # fmt: skip
    """``steps`` steps of cells ``start + lo`` to ``start + hi`` of a block that starts at
    population cell ``start`` (block cell ``j`` is population cell ``start + j``).

    The decision: with ``decision.kind`` ``OWN`` the full model, each motor of
    ``motors.states`` (:data:`Motors`, M x block) by its exact exp(Q dt) with the float64
    uniforms from row ``motors.row``; else the engine's step of that kind
    (:func:`surrogate.models.decision_kernel.decide`: the two-state chain over lookup tables, with or
    without a switch clock, or the K-lumps chain) at the features of :func:`_features`.

    Args:
        steps: steps to take; ``step0``: the first one's index (the field's time).
        start, lo, hi: the block's first population cell; its cells ``[lo, hi)``.
        state: :data:`State`: the engine's :class:`~surrogate.models.decision_kernel.Cells` and the
            :data:`Body` (in place; ``cells.ended`` (steps, n) int32 out).
        draws: :data:`Draws`, (steps, rows, n) each.
        k: :data:`Constants`.
        field_set: the field formulas (:class:`~surrogate.field_kernel.FieldSet`).
        field: :data:`Fields`.
        motors: :data:`Motors` (no rows: not the full model).
        decision: :class:`~surrogate.models.decision_kernel.DecisionPack`.

    One function for every kind: one compilation.
    """
    cells, body = state.cells, state.body
    position, heading, meth, last_x = body.position, body.heading, body.meth, body.last_x
    u, z, p, q = draws.u, draws.z, k.p, k.q
    own = decision.kind == kd.OWN
    dt = q[2]
    for j in range(lo, hi):
        c = start + j
        x, y, h, m = position[c, 0], position[c, 1], heading[c], meth[c]
        phi_now = _F32(cells.phi[c])
        tab, age, cls = kd.cell_state(j, decision)
        f = field.rows[field.of_cell[c]]
        outside = f[0] == READ_OUTSIDE  # given in last_x (one step per call: EcoliKernel)
        for s in range(steps):
            if outside:
                ligand = last_x[c, 1]
            else:
                ligand = field_value(field_set, f, x, y, (step0 + s) * dt)
            last_x[c, 0] = m
            last_x[c, 1] = ligand
            lrt = _log_receptor_terms(ligand, p)
            energy, act, yp, dg = _signal(m, lrt, p)
            if own:
                phi_after = _motors_step(dg, motors, j, c, s, draws.u64, q)
            else:
                values = _features(m, ligand, energy, act, yp, dg)
                phi_after, age, cls = kd.decide(phi_now, age, cls, tab, values, u, s, c,
                                                decision)  # fmt: skip
            x, y, h = _move(s, c, phi_now, phi_after, x, y, h, draws, k)
            kd.account(cells, c, s, phi_now, phi_after)
            m = _F.ou_step(m, lrt, z[s, k.ou_row, c], p)
            phi_now = phi_after
        position[c, 0], position[c, 1], heading[c], meth[c] = x, y, h, m
        cells.phi[c] = np.uint8(phi_now)
        kd.store_state(j, decision, age, cls)


@numba.njit(parallel=True, **_JIT)
def advance_cells(steps, step0, start, count, pieces, state, draws, k, field_set, field, motors,
                  decision):  # fmt: skip
    """Cells ``start`` to ``start + count`` in ``pieces`` contiguous pieces (a few per thread:
    balanced) spread over numba's threads, each by :func:`_advance_range` (the other
    arguments as there, each namedtuple as a plain tuple of its fields in order: see
    :func:`_plain`). The parallel loop holds only that call:
    lowering ``prange`` around the whole inlined body more than doubled the one-time
    compilation (8.9 s vs 4.5 s measured) for the same speed at the paper's size.

    A parallel loop takes arrays and numbers, not tuples of arrays: the tuples are taken apart
    here and put together again in the loop as namedtuples (once per piece: free)."""
    (phi, seg, complete, ended), (position, heading, meth, last_x) = state
    u, u64, z = draws
    body_row, ou_row, gamma_k, per_tumble, p, q = k
    field_of_cell, field_rows = field
    motor_states, motor_row = motors
    kind, chain, classes = decision
    (table, table_of_cell, layer, shape, strides, origin, scale, chain_features, chain_row,
     ages, cap, unit) = chain  # fmt: skip
    (cdf, origin_stride, nodes, class_strides, class_origin, class_scale, class_features,
     class_row, lumps, cell_classes) = classes  # fmt: skip
    pieces = max(1, min(count, pieces))
    for i in prange(pieces):
        piece_decision = kd.DecisionPack(
            kind,
            kd.ChainPack(table, table_of_cell, layer, shape, strides, origin, scale,
                         chain_features, chain_row, ages, cap, unit),
            kd.ClassPack(cdf, origin_stride, nodes, class_strides, class_origin, class_scale,
                         class_features, class_row, lumps, cell_classes),
        )  # fmt: skip
        _advance_range(
            steps, step0, start, count * i // pieces, count * (i + 1) // pieces,
            State(kd.Cells(phi, seg, complete, ended), Body(position, heading, meth, last_x)),
            Draws(u, u64, z), Constants(body_row, ou_row, gamma_k, per_tumble, p, q), field_set,
            Fields(field_of_cell, field_rows), Motors(motor_states, motor_row), piece_decision,
        )  # fmt: skip


# numba's cache follows this file only: also the formulas' and the decision steps' (inlined)
scalar.renew_with((_advance_range, advance_cells), (formulas, scalar, kd))


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
_NO_MOTORS = Motors(np.zeros((0, 0), dtype=np.float32), 0)
_NO_U64 = np.zeros((1, 1, 1), dtype=np.float64)
#: the built-in fields' formulas: the field set of the precompiled kernel
_BUILTIN_FIELD_SET = field_set([])


def _plain(value: tuple[Any, ...]) -> tuple[Any, ...]:
    """A namedtuple (the namedtuples in it too) as plain tuples; a plain tuple as it is: numba
    types a plain tuple of arrays and numbers in C at each call, a namedtuple in Python
    (microseconds a call)."""
    if type(value) is tuple:
        return value
    return tuple(_plain(v) if isinstance(v, tuple) else v for v in value)


#: the decision pack of the full model (the kernel's own motors), and no motors, as plain tuples
_OWN, _PLAIN_NO_MOTORS = _plain(kd.own_pack()), _plain(_NO_MOTORS)


def _arguments(
    steps: int, step0: int, start: int, count: int, pieces: int, state: State, draws: Draws,
    k: tuple[Any, ...], fields: FieldSet, field: Fields, motors: Motors,
    decision: tuple[Any, ...],
) -> tuple[Any, ...]:  # fmt: skip
    """The arguments of :func:`advance_cells` (see :func:`_advance_range`; each namedtuple,
    :data:`Constants` and the decision pack too, may come as its plain tuple already)."""
    return (steps, step0, start, count, pieces, _plain(state), _plain(draws), _plain(k), fields,
            _plain(field), _plain(motors), _plain(decision))  # fmt: skip


def _zero_cell_arguments() -> tuple[Any, ...]:
    """Arguments of :func:`advance_cells` for zero cells, typed exactly as the adaptor's (C
    contiguous, writable arrays of the same dtypes and ranks): its one compiled signature."""
    f32, i32, u8 = np.float32, np.int32, np.uint8
    cells = kd.Cells(np.zeros(1, u8), np.zeros(1, i32), np.zeros(1, u8), np.zeros((1, 1), i32))
    body = Body(np.zeros((1, 2), f32), np.zeros(1, f32), np.zeros(1, f32), np.zeros((1, 2), f32))
    draws = Draws(np.zeros((1, 1, 1), f32), _NO_U64, np.zeros((1, 1, 1), f32))
    k = Constants(0, 0, 1, False, np.zeros(len(P32_NAMES), dtype=f32),
                  np.zeros(len(P64_NAMES), dtype=np.float64))  # fmt: skip
    field = Fields(np.zeros(1, i32), np.zeros((1, _BUILTIN_FIELD_SET.columns)))
    return _arguments(1, 0, 0, 0, 1, State(cells, body), draws, _plain(k), _BUILTIN_FIELD_SET,
                      field, _NO_MOTORS, _OWN)  # fmt: skip


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
        # the motors (the full model), a class table (K lumps), else a chain's lookup tables
        self.motors, self.classes = block.kind == FULL, block.kind == CLASSES
        if self.motors:
            self.motor_row = block.motor_row
            return
        law, tables = block.classes, block.tables
        if block.kind == CLASSES and (law is None or block.why is not None):
            raise KernelUnsupported(block.why or f"a {block.layer} without its class table")
        if block.kind != CLASSES and (tables is None or block.why is not None):
            raise KernelUnsupported(block.why or f"a {block.layer} without lookup tables")
        self.law, self.tables, self.clock = law, tables, block.clock
        self.features = kd.feature_axes(block, _feature_codes(block, internal))
        self.row = block.decision_row
        self._packed: tuple[int, Tensor | None, tuple[Any, ...]] | None = None

    def decision(self, n: int, own: Tensor | None) -> tuple[Any, ...]:
        """The block's :class:`~surrogate.models.decision_kernel.DecisionPack` for ``n`` cells and
        their per-cell state ``own`` (clocks, classes; None: a chain without a clock), as plain
        tuples (:func:`_plain`); kept while ``n`` and the state tensor stay the same."""
        if self._packed is not None and self._packed[0] == n and self._packed[1] is own:
            return self._packed[2]
        state = None if own is None else _numpy(own)
        if self.classes:
            assert self.law is not None and state is not None  # each cell's class
            classes = kd.class_pack(self.law, self.features, self.row, state)
            pack = kd.DecisionPack(kd.CLASSES, kd.NO_CHAIN, classes)
        else:
            assert self.tables is not None
            clock = self.clock if state is not None else None
            chain = kd.chain_pack(self.tables, self.features, self.row,
                                  self.tables.table_of_cell(n), clock, state)  # fmt: skip
            pack = kd.DecisionPack(kd.CHAIN, chain, kd.NO_CLASSES)
        self._packed = (n, own, _plain(pack))
        return self._packed[2]


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
        self._constants = _plain(Constants(self.body_row, self.ou_row, self.gamma_k,
                                           self.per_tumble, self.p32, self.p64))  # fmt: skip
        self.blocks = [_Block(b, internal) for b in decision.blocks]
        self._total = decision.total
        fields = field.fields if isinstance(field, FieldBatch) else [field]
        self.field_set, self.fields = pack_fields(fields)
        #: a coupled field's values are read by the simulator before each one-step call
        self.reads_outside = bool((self.fields[:, 0] == READ_OUTSIDE).any())
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
        if self.reads_outside and steps != 1:
            raise ValueError(f"a kernel in a coupled field takes one step per call (the inputs "
                             f"the simulator read before it), not {steps}")  # fmt: skip
        n = state.n_cells
        field_of_cell = self._cells(n)
        body = state.body
        if state.inputs is None or state.inputs.shape != (n, 2):
            state.inputs = torch.empty((n, 2), dtype=torch.float32)
        # the namedtuples' plain tuples (_plain), built as such: State(Cells, Body), Draws, Fields
        arrays = ((_numpy(state.phi), _numpy(state.segment_steps),
                   _numpy(state.segment_complete), _numpy(ended)),
                  (_numpy(body["position"]), _numpy(body["heading"]), _numpy(body["m"]),
                   _numpy(state.inputs)))  # fmt: skip
        draws = (_numpy(u), _NO_U64 if u64 is None else _numpy(u64), _numpy(z))
        field = (field_of_cell, self.fields)
        # as many kernel threads as torch uses (the threads setting; a sweep job's share), a
        # few pieces each (cells of one block cost alike; pieces balance what differs)
        threads = match_torch_threads()
        for b in self.blocks:
            count = n if b.count is None else b.count
            if count == 0:
                continue
            # the per-cell state (motor states, clocks, classes), advanced in place: the
            # layer's own copy (a dry run only reads it)
            own = None if b.state is None else (b.state.current() if dry else b.state.writable())
            if b.motors:
                assert own is not None and u64 is not None  # motor states, one u64 per motor
                motors, decision = (_numpy(own), b.motor_row), _OWN
            else:
                motors, decision = _PLAIN_NO_MOTORS, b.decision(count, own)
            advance_cells(steps, state.step, b.start, 0 if dry else count, 4 * threads, arrays,
                          draws, self._constants, self.field_set, field, motors,
                          decision)  # fmt: skip
        if not dry:
            state.step += steps

"""The compiled per-cell E. coli kernel (``backend=numba``) against the torch step.

The kernel consumes the same random numbers as the torch step, so from one seed both follow the
same trajectories up to float rounding: every step's segment ends and the final flags and
segment lengths equal for every cell (a rounding-level flip of a comparison u < p would send a
cell elsewhere: none does in any case here), and after 150 steps (300 for the phospho
abstraction) positions and headings within ``MOVE_ATOL``, methylation and inputs within
``STATE_ATOL`` (float32 ulps at their scale, twice the largest differences measured over every
case of this file; the transcendental functions of each step round differently in numba and
torch, and those differences accumulate over the steps; the operations are the same, in the
same order: the kernel compiles the torch step's formulas, surrogate.models.ecoli.formulas).
This checks the kernel's loop (fields, signalling, motor transition terms and sampling, lookup
interpolation over 1-3 features, movement, tumble angles, OU, segment bookkeeping) against the
torch step.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from surrogate.errors import ConfigError, KernelUnsupported
from surrogate.fields import (
    ConstantField,
    DynamicGaussianField,
    ExponentialField,
    ExpressionField,
    FieldBatch,
    GaussianField,
    LinearField,
)
from surrogate.gp import PsiLookupTable
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision, ExactDecision, FullDecision, Simulator
from surrogate.simulate.batch import BatchSimulator, Replicate
from surrogate.simulate.classes import ClassDecision, ClassTable, exact_class_table
from surrogate.simulate.kernel_pack import pack_decision
from surrogate.simulate.memory import AGE, MemoryDecision

DT = 0.05
N, STEPS = 400, 150  # 150 steps cross two blocks of random numbers (64 steps each)
#: float32 spacing at 2-4 (positions in mm, methylation): one rounding step at the state's scale
ULP = 2.0 * torch.finfo(torch.float32).eps
#: positions and headings (cos, sin): at most 13-16 ulps apart after 150-300 steps (measured)
MOVE_ATOL = 32 * ULP
#: methylation and the inputs (m, L): at most 2 ulps apart (measured)
STATE_ATOL = 4 * ULP


def _table(model: EcoliModel, names: tuple[str, ...]) -> PsiLookupTable:
    """A smooth psi over ``names`` (1-3 features) that switches where cells live."""
    internal = model.internal
    bounds = {
        "m": (1.0, 3.5),
        "L": (0.0, 0.12),
        "F": (-6.0, 6.0),
        "cheyp": (0.5, 5.0),
        "dG": internal.signal_bounds["dG"],
    }

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        s = z.sum(1) / len(names)
        return torch.where(phi > 0, torch.sigmoid(s - 4.0), torch.sigmoid(2.0 - s))

    size = {1: (1024,), 2: (64, 48), 3: (16, 12, 10)}[len(names)]
    return PsiLookupTable.from_function(psi, [bounds[n] for n in names], names, size)


def _decision(kind: str, model: EcoliModel):
    internal = model.internal
    if kind == "full":
        return FullDecision(internal)
    if kind == "exact":
        b = internal.signal_bounds["dG"]
        table = PsiLookupTable.from_function(internal_psi(model), [b], ("dG",), (1024,))
        return ExactDecision(internal, DT, table)
    if kind in ("clock", "clock_nodes"):  # the switch clock (gp.history=age): likelier to
        max_age = 2.0  # switch the longer in a state; clock_nodes: read at its node per step

        def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
            leave = (0.02 + 0.2 * z[:, 1] / max_age) * torch.sigmoid(z[:, 0])
            return torch.where(phi > 0, 1.0 - leave, 4.0 * leave)

        b = internal.signal_bounds["dG"]
        table = PsiLookupTable.from_function(psi, [b, (0.0, max_age)], ("dG", AGE), (64, 41))
        dt = DT if kind == "clock_nodes" else None
        layer = MemoryDecision(table, internal, model.featurizer(["dG"]), max_age, dt=dt)
        assert (layer.clock_nodes is not None) == (kind == "clock_nodes")
        return layer
    if kind == "classes":  # K lumps: the exact class chain over dG
        return ClassDecision(exact_class_table(internal, DT, size=256), internal,
                             model.featurizer(["dG"]))  # fmt: skip
    if kind == "classes_mL":  # K lumps over (m, L) without a feature map, a narrow L axis
        return ClassDecision(_class_table(model), internal)  # (clamped)
    if kind == "raw_inputs":  # no feature map: the table reads x = (m, L) itself
        return AbstractDecision(_table(model, ("m", "L")), internal)
    if kind == "dG_narrow":  # a box narrower than the values: the interpolation clamps
        adapted = model.params.delta_g_adapted
        table = PsiLookupTable.from_function(
            lambda phi, z: torch.sigmoid(z[:, 0] * (2 * phi - 1)), [(adapted - 0.05, adapted + 0.05)],
            ("dG",), (32,))  # fmt: skip
        return AbstractDecision(table, internal, model.featurizer(["dG"]))
    names = {"dG": ("dG",), "mL": ("m", "L"), "mLF": ("m", "L", "F"), "cheyp": ("cheyp",)}[kind]
    return AbstractDecision(_table(model, names), internal, model.featurizer(list(names)))


def _class_table(model: EcoliModel) -> ClassTable:
    """A class law over (m, L): class b drawn from class a with weight
    exp(-(a - b)^2 / width) + 0.02, the width growing with m and L (narrow: cells mostly
    stay; wide: they spread over the 7 classes of the motors); 17 x 9 nodes, L's box narrower
    than the values (clamped)."""
    internal = model.internal
    c = len(internal.class_names)
    a = torch.arange(c, dtype=torch.float64).reshape(c, 1, 1, 1)
    b = a.reshape(1, 1, 1, c)
    m = torch.linspace(1.5, 3.0, 17, dtype=torch.float64).reshape(1, 17, 1, 1)
    ligand = torch.linspace(0.0, 0.03, 9, dtype=torch.float64).reshape(1, 1, 9, 1)
    width = 0.2 + 4.0 * (m - 1.5) + 100.0 * ligand
    p = torch.exp(-((a - b) ** 2) / width) + 0.02  # (C, 17, 9, C)
    return ClassTable(p, [(1.5, 3.0), (0.0, 0.03)], ("m", "L"), internal.class_names,
                      internal.class_lumps, DT)  # fmt: skip


def internal_psi(model: EcoliModel):
    from surrogate.simulate.decision import ExactPsi

    return ExactPsi(model.internal, DT)


def _run(model, kind, field, backend, seed=3, n=N, steps=STEPS, start=(2.0, 0.0)):
    torch.manual_seed(seed)
    sim = Simulator(model, _decision(kind, model), field, DT, backend=backend)
    assert sim.backend == backend
    with torch.inference_mode():
        state = sim.initial_state(n, start, equilibration_time=1.0)
        sim.warm_up(state)
        ended = torch.cat([sim.advance(state, k) for k in (7, 20, steps - 27)])
    return state, ended


def _assert_same_trajectories(a, b) -> None:
    (sa, ea), (sb, eb) = a, b
    same = (ea == eb).all(0) & (sa.phi == sb.phi) & (sa.segment_steps == sb.segment_steps)
    assert bool(same.all()), f"{int((~same).sum())} cells diverged"
    torch.testing.assert_close(sa.body["position"], sb.body["position"], atol=MOVE_ATOL, rtol=0)
    ha, hb = sa.body["heading"], sb.body["heading"]  # angles: compare on the circle
    torch.testing.assert_close(torch.cos(ha), torch.cos(hb), atol=MOVE_ATOL, rtol=0)
    torch.testing.assert_close(torch.sin(ha), torch.sin(hb), atol=MOVE_ATOL, rtol=0)
    torch.testing.assert_close(sa.body["m"], sb.body["m"], atol=STATE_ATOL, rtol=0)
    torch.testing.assert_close(sa.inputs, sb.inputs, atol=STATE_ATOL, rtol=0)
    assert (ea != 0).sum() > N  # segments did end (the comparison is not vacuous)


@pytest.mark.parametrize(
    "kind",
    ["full", "dG", "mL", "mLF", "exact", "cheyp", "raw_inputs", "dG_narrow", "clock",
     "clock_nodes", "classes", "classes_mL"],
)  # fmt: skip
def test_kernel_follows_the_torch_step(kind) -> None:
    model = EcoliModel()
    _assert_same_trajectories(_run(model, kind, GaussianField(), "torch"),
                              _run(model, kind, GaussianField(), "numba"))  # fmt: skip


@pytest.mark.parametrize("kind", ["clock", "clock_nodes"])
def test_kernel_keeps_the_switch_clocks_as_the_torch_step(kind) -> None:
    """The chain with a clock: each cell's clock (steps since phi changed) after the runs is
    the torch step's, and the clocks matter (a cell's psi reads them)."""
    model = EcoliModel()
    clocks = {}
    for backend in ("torch", "numba"):
        torch.manual_seed(3)
        decision = _decision(kind, model)
        sim = Simulator(model, decision, GaussianField(), DT, backend=backend)
        assert sim.backend == backend
        with torch.inference_mode():
            state = sim.initial_state(N, (2.0, 0.0), equilibration_time=1.0)
            sim.warm_up(state)
            for k in (7, 20, STEPS - 27):
                sim.advance(state, k)
        clocks[backend] = decision.fused_state()[0]
    assert torch.equal(clocks["torch"], clocks["numba"])
    assert int(clocks["torch"].max()) > 40 and int((clocks["torch"] == 0).sum()) > 0


@pytest.mark.parametrize("kind", ["classes", "classes_mL"])
def test_kernel_draws_the_torch_steps_classes_step_by_step(kind) -> None:
    """The K-lumps chain: every cell's class after every step is the torch step's (the same
    uniforms in the same order, positions in the same float32 operations), and the classes
    move (every class is visited, a good share of cells change class)."""
    model = EcoliModel()
    classes = {}
    for backend in ("torch", "numba"):
        torch.manual_seed(3)
        decision = _decision(kind, model)
        sim = Simulator(model, decision, GaussianField(), DT, backend=backend)
        assert sim.backend == backend
        out = []
        with torch.inference_mode():
            state = sim.initial_state(N, (2.0, 0.0), equilibration_time=1.0)
            sim.warm_up(state)
            out.append(decision.fused_state()[0].clone())
            for _ in range(STEPS // 3):
                sim.advance(state, 3)
                out.append(decision.fused_state()[0].clone())
                lumps = decision.table.lumps[out[-1]]
                assert torch.equal(lumps.to(torch.uint8), state.phi.to(torch.uint8))
        classes[backend] = torch.stack(out)
    a, b = classes["torch"], classes["numba"]
    assert a.dtype == b.dtype == torch.int64
    assert torch.equal(a, b), f"{int((a != b).any(0).sum())} cells diverged"
    assert len(set(a.reshape(-1).tolist())) == 7 and int((a[1:] != a[:-1]).sum()) > N


@pytest.mark.parametrize("kind", ["full", "dG"])
def test_one_simulator_advances_populations_of_any_size(kind) -> None:
    """A simulator (and its kernel) reused for another population size advances every cell of
    it, as the torch step does (the bench reuses simulators across sizes)."""
    model = EcoliModel()
    out = {}
    for backend in ("torch", "numba"):
        sim = Simulator(model, _decision(kind, model), GaussianField(), DT, backend=backend)
        for n in (30, 300):
            torch.manual_seed(n)
            state = sim.initial_state(n, (2.0, 0.0))
            out[backend, n] = (state, sim.advance(state, 40))
    for n in (30, 300):
        (a, ea), (b, eb) = out["torch", n], out["numba", n]
        assert torch.equal(ea, eb) and torch.equal(a.phi, b.phi)
        torch.testing.assert_close(a.body["position"], b.body["position"], atol=MOVE_ATOL, rtol=0)


FIELDS = {
    "constant": ConstantField(0.05),
    "linear": LinearField(),
    "dynamic": DynamicGaussianField(spread_time=5.0),  # spreads visibly within 7.5 s
    "exponential": ExponentialField(length=2.0, peak=(1.0, -0.5)),
    "gaussian_off_centre": GaussianField(amplitude=0.2, variance=2.0, peak=(1.5, 0.5)),
}


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_kernel_reads_every_builtin_field_as_the_field_does(name) -> None:
    model = EcoliModel()
    field = FIELDS[name]
    _assert_same_trajectories(_run(model, "full", field, "torch"),
                              _run(model, "full", field, "numba"))  # fmt: skip


@pytest.mark.parametrize(
    "constants",
    [
        {"tumble_mode": "per_tumble"},
        {"n_motors": 10, "tumble_shape": 8.0, "tau": 5.0},
        {"tumble_shape": 5.0, "n_motors": 3},
    ],
)
def test_kernel_follows_the_model_constants(constants) -> None:
    model = EcoliModel(**constants)
    for kind in ("full", "dG"):
        _assert_same_trajectories(_run(model, kind, LinearField(), "torch"),
                                  _run(model, kind, LinearField(), "numba"))  # fmt: skip


#: formula fields: a ridge drifting along x in time; a patch with a hard edge (piecewise)
RIDGE = ExpressionField("a * exp(-0.5 * (x - 2 - t / 10)^2 / w) + 0.001 * (1 + sin(y))",
                        {"a": 0.1, "w": 2.0}, peak=(2.0, 0.0))  # fmt: skip
PATCH = ExpressionField("piecewise(0.08, hypot(x - 2, y) < r && t > 1, 0.02 * exp(-abs(y)))",
                        {"r": 1.5})  # fmt: skip


@pytest.mark.parametrize("name", ["ridge", "batch"])
def test_kernel_reads_an_expression_field_as_the_field_does(name) -> None:
    """A formula field runs in the kernel (code generated from the tree the torch step's code
    comes from), alone or beside built-in fields in one batch."""
    if name == "ridge":
        field = RIDGE
    else:
        field = FieldBatch([RIDGE, GaussianField(), PATCH, RIDGE], [N // 4] * 4)
    model = EcoliModel()
    for kind in ("full", "mL"):
        _assert_same_trajectories(_run(model, kind, field, "torch"),
                                  _run(model, kind, field, "numba"))  # fmt: skip


def test_kernel_replicates_in_a_batch_are_their_standalone_runs_bit_for_bit() -> None:
    """Cells never interact, so a batch of kernel runs (two decision blocks, one of them two
    stacked tables, three fields) gives each run exactly its standalone numbers."""
    model = EcoliModel()
    spec = [("full", GaussianField(), 50, 0), ("full", LinearField(), 70, 1),
            ("dG", DynamicGaussianField(), 40, 2), ("exact", GaussianField(), 30, 3),
            ("clock", GaussianField(), 30, 4), ("clock2", LinearField(), 20, 5)]  # fmt: skip
    decisions = {k: _decision(k, model) for k in ("dG", "exact", "clock")}
    decisions["clock2"] = _decision("clock", model)  # another table: the clocks' tables stack
    alone = []
    for kind, field, n, seed in spec:
        torch.manual_seed(seed)
        d = FullDecision(model.internal) if kind == "full" else decisions[kind]
        sim = Simulator(model, d, field, DT, backend="numba")
        state = sim.initial_state(n, (2.0, 0.0), equilibration_time=1.0)
        alone.append((state, sim.advance(state, 100)))
    reps = [Replicate(FullDecision(model.internal) if k == "full" else decisions[k], f, n, s)
            for k, f, n, s in spec]  # fmt: skip
    batch = BatchSimulator(model, reps, DT, backend="numba")
    assert batch.backend == "numba" and len(batch.decision.members) == 3
    assert type(batch.decision.members[2]) is MemoryDecision
    state = batch.initial_state(equilibration_time=1.0)
    ended = torch.cat([batch.advance(state, 20) for _ in range(5)])
    for i, cells in enumerate(batch.slices):
        a, a_ended = alone[i]
        for key in ("position", "heading", "m"):
            assert torch.equal(state.body[key][cells], a.body[key]), (i, key)
        assert torch.equal(state.phi[cells], a.phi)
        assert torch.equal(ended[:, cells], a_ended)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_class_chains_in_a_batch_are_their_standalone_runs_bit_for_bit(backend) -> None:
    """K-lumps chains beside other layers in one batch (their two uniform rows beside a
    chain's one, a full model's float64 rows): each run gets exactly its standalone numbers,
    classes included; one layer object serving two runs (consecutive: one block; apart: two)
    keeps each run's classes."""
    model = EcoliModel()
    decisions = {k: _decision(k, model) for k in ("classes", "classes_mL", "dG")}
    spec = [("classes", GaussianField(), 40, 0), ("classes", LinearField(), 30, 1),
            ("dG", LinearField(), 30, 2), ("full", GaussianField(), 20, 3),
            ("classes_mL", GaussianField(), 25, 4), ("classes", GaussianField(), 15, 5)]  # fmt: skip
    alone = []
    for kind, field, n, seed in spec:
        torch.manual_seed(seed)
        d = FullDecision(model.internal) if kind == "full" else decisions[kind]
        sim = Simulator(model, d, field, DT, backend=backend)
        state = sim.initial_state(n, (2.0, 0.0), equilibration_time=1.0)
        ended = sim.advance(state, 100)
        alone.append((state, ended, d.fused_state()[0].clone() if kind != "dG" else None))
    reps = [Replicate(FullDecision(model.internal) if k == "full" else decisions[k], f, n, s)
            for k, f, n, s in spec]  # fmt: skip
    batch = BatchSimulator(model, reps, DT, backend=backend)
    assert batch.backend == backend and len(batch.decision.members) == 5
    state = batch.initial_state(equilibration_time=1.0)
    ended = torch.cat([batch.advance(state, 20) for _ in range(5)])
    members = batch.decision.members
    for i, cells in enumerate(batch.slices):
        a, a_ended, a_classes = alone[i]
        for key in ("position", "heading", "m"):
            assert torch.equal(state.body[key][cells], a.body[key]), (i, key)
        assert torch.equal(state.phi[cells], a.phi), i
        assert torch.equal(ended[:, cells], a_ended), i
        if spec[i][0].startswith("classes"):
            k = next(g for g, group in enumerate(batch.groups) if i in group)
            offset = sum(spec[j][2] for j in batch.groups[k] if j < i)
            got = members[k].fused_state()[0][offset : offset + spec[i][2]]
            assert torch.equal(got, a_classes), i


@pytest.mark.parametrize("kind", ["full", "dG"])
def test_kernel_results_do_not_depend_on_the_thread_count(kind) -> None:
    """Cells are split over threads in contiguous pieces, each cell reading its own random
    numbers: one thread and three give the same numbers bit for bit."""
    model = EcoliModel()
    before = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, 3):
            torch.set_num_threads(threads)
            runs.append(_run(model, kind, GaussianField(), "numba", n=301, steps=60))
    finally:
        torch.set_num_threads(before)
    (a, a_ended), (b, b_ended) = runs
    assert torch.equal(a_ended, b_ended)
    for key in ("position", "heading", "m"):
        assert torch.equal(a.body[key], b.body[key]), key
    assert torch.equal(a.phi, b.phi) and torch.equal(a.segment_steps, b.segment_steps)


def test_the_kernel_leaves_torchs_thread_count_alone() -> None:
    """numba's OpenMP pool, started by the kernel's first call, sets the process's OpenMP
    thread count, which is torch's too: the kernel restores it (a job's ``threads`` setting,
    and the fit's identity resolved from it, must survive a simulation). In a fresh process
    with a two-thread pool: the pool starts once per process."""
    code = (
        "import torch; torch.set_num_threads(1)\n"
        "from surrogate.fields import GaussianField\n"
        "from surrogate.models.ecoli import EcoliModel\n"
        "from surrogate.simulate import FullDecision, Simulator\n"
        "m = EcoliModel()\n"
        "sim = Simulator(m, FullDecision(m.internal), GaussianField(), 0.05, backend='numba')\n"
        "state = sim.initial_state(10, (2.0, 0.0)); sim.warm_up(state); sim.advance(state, 3)\n"
        "print('threads', torch.get_num_threads())\n"
    )
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "NUMBA_NUM_THREADS": "2",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=root, timeout=300, check=True)  # fmt: skip
    assert out.stdout.split()[-2:] == ["threads", "1"], out.stdout + out.stderr[-2000:]


def test_precompile_compiles_the_signature_the_simulator_calls() -> None:
    """The background precompile calls the kernel with zero cells typed as the adaptor's
    arguments: a simulation afterwards adds no second compiled signature (other tests here
    compile others: one per set of field formulas)."""
    from surrogate.models.ecoli import kernel

    kernel.precompile()
    precompiled = set(kernel.advance_cells.signatures)
    _run(EcoliModel(), "full", GaussianField(), "numba", n=20, steps=30)
    _run(EcoliModel(), "mL", LinearField(), "numba", n=20, steps=30)
    assert set(kernel.advance_cells.signatures) == precompiled


class _UserField(GaussianField):
    """A field the kernel cannot know: a user's subclass with its own Python ``__call__``."""

    def __call__(self, position: torch.Tensor, t: float) -> torch.Tensor:
        return super().__call__(position, t) * 0.5


def test_auto_keeps_the_torch_step_where_the_kernel_cannot_run() -> None:
    model = EcoliModel()
    sim = Simulator(model, FullDecision(model.internal), _UserField(), DT, backend="auto")
    assert sim.backend == "torch" and "_UserField (a Python field" in sim.backend_note
    classifier = AbstractDecision(lambda phi, z: torch.full_like(z[:, 0], 0.5), model.internal,
                                  model.featurizer(["dG"]))  # fmt: skip
    sim = Simulator(model, classifier, GaussianField(), DT, backend="auto")
    assert sim.backend == "torch" and "decision.mode=lookup" in sim.backend_note
    ssa = EcoliModel(motor_sampler="ssa")
    assert (
        Simulator(ssa, FullDecision(ssa.internal), GaussianField(), DT, backend="auto").backend
        == "torch"
    )
    assert (
        Simulator(model, FullDecision(model.internal), GaussianField(), DT, backend="auto").backend
        == "numba"
    )
    with pytest.raises(KernelUnsupported, match="_UserField.*backend=torch"):
        Simulator(model, FullDecision(model.internal), _UserField(), DT, backend="numba")
    with pytest.raises(ConfigError, match="backend must be one of"):
        Simulator(model, FullDecision(model.internal), GaussianField(), DT, backend="numpy")


def test_kernel_leaves_the_callers_tensors_and_warm_up_changes_nothing() -> None:
    model = EcoliModel()
    torch.manual_seed(0)
    sim = Simulator(model, FullDecision(model.internal), GaussianField(), DT, backend="numba")
    state = sim.initial_state(20, (2.0, 0.0))
    held = {k: v.clone() for k, v in state.body.items()}
    views = dict(state.body)
    motors = sim.decision.fused_state()[0].clone()
    sim.warm_up(state)
    assert torch.equal(sim.decision.fused_state()[0], motors) and state.step == 0
    sim.advance(state, 5)
    assert state.step == 5
    for k in held:
        assert torch.equal(views[k], held[k]), k  # the caller's tensors are untouched
    assert not torch.equal(state.body["m"], held["m"])
    assert math.isfinite(float(state.body["position"].sum()))


@pytest.mark.parametrize("kind", ["full", "dG"])
def test_nan_in_the_state_survives_the_kernel_as_in_the_torch_step(kind) -> None:
    """A NaN methylation stays NaN (clamps let it through, as torch.clamp does), so the
    simulator's check at the next record time finds it."""
    from surrogate.errors import NumericalError

    model = EcoliModel()
    for backend in ("torch", "numba"):
        torch.manual_seed(0)
        sim = Simulator(model, _decision(kind, model), GaussianField(), DT, backend=backend)
        state = sim.initial_state(10, (2.0, 0.0))
        state.body["m"][3] = float("nan")
        sim.advance(state, 5)
        assert torch.isnan(state.body["m"][3]) and torch.isfinite(state.body["m"][:3]).all()
        with pytest.raises(NumericalError, match="NaN"):
            sim.check_state(state)


@pytest.mark.parametrize("kind", ["classes", "classes_mL"])
def test_a_nan_input_draws_the_same_classes_in_the_kernel_and_the_torch_step(kind) -> None:
    """K lumps with a NaN methylation (so a NaN table input, dG or m): both loops draw from
    the axis's first node, the same classes step by step (the torch step used to index outside
    the table), and the NaN reaches the simulator's check at the next record time."""
    from surrogate.errors import NumericalError

    model = EcoliModel()
    classes = {}
    for backend in ("torch", "numba"):
        torch.manual_seed(0)
        decision = _decision(kind, model)
        sim = Simulator(model, decision, GaussianField(), DT, backend=backend)
        assert sim.backend == backend
        state = sim.initial_state(N, (2.0, 0.0))
        state.body["m"][::4] = float("nan")
        out = []
        for _ in range(10):
            sim.advance(state, 3)
            out.append(decision.fused_state()[0].clone())
        classes[backend] = torch.stack(out)
        with pytest.raises(NumericalError, match="NaN"):
            sim.check_state(state)
    a, b = classes["torch"], classes["numba"]
    assert torch.equal(a, b), f"{int((a != b).any(0).sum())} cells diverged"
    assert bool((a[1:, ::4] != a[:-1, ::4]).any())  # the NaN cells still change class


def test_kernel_at_the_clamps() -> None:
    """Methylation at its upper bound (m_max just above the adapted level) and cells on the
    linear field's floor (beyond 10 mm along x)."""
    model = EcoliModel(m_max=2.21)
    field = LinearField()
    for kind in ("full", "dG"):
        a = _run(model, kind, field, "torch", start=(10.5, 0.0))
        b = _run(model, kind, field, "numba", start=(10.5, 0.0))
        _assert_same_trajectories(a, b)
        assert (a[0].body["m"] == 2.21).sum() > 10  # the clamp was hit
        assert (a[0].inputs[:, 1] == field.floor).sum() > 10  # and the floor


def test_the_kernel_refuses_what_it_does_not_transcribe() -> None:
    """Subclasses (which may override a formula), other internal models, feature maps other
    than the model's, and a table over more axes than features: torch for auto, an error
    naming it for numba."""
    from surrogate.models.base import FeatureMap

    model = EcoliModel()
    internal = model.internal

    class Tempered(AbstractDecision):
        def probability(self, phi, x):
            return 0.5 * super().probability(phi, x)

    class Scaled(FeatureMap):
        def __call__(self, x):
            return 2 * super().__call__(x)

    table = _table(model, ("dG",))
    cases = {
        "Tempered": Tempered(table, internal, model.featurizer(["dG"])),
        "another internal model": FullDecision(EcoliModel(n_motors=5).internal),
        "feature map": AbstractDecision(table, internal, Scaled(internal, ["dG"])),
        "1 features for a lookup table over 2 axes": AbstractDecision(
            _table(model, ("m", "L")), internal, model.featurizer(["dG"])
        ),
    }
    # another instance with the same constants is the same motors (a batch's runs each build
    # their own model object)
    twin = FullDecision(EcoliModel().internal)
    assert Simulator(model, twin, GaussianField(), DT, backend="auto").backend == "numba"
    for what, decision in cases.items():
        sim = Simulator(model, decision, GaussianField(), DT, backend="auto")
        assert sim.backend == "torch" and what in sim.backend_note, (what, sim.backend_note)
        with pytest.raises(KernelUnsupported, match=what):
            Simulator(model, decision, GaussianField(), DT, backend="numba")


def test_a_lone_stacked_table_must_cover_the_population() -> None:
    from surrogate.gp import StackedPsiLookup

    model = EcoliModel()
    tables = [_table(model, ("dG",)), _table(model, ("dG",))]
    decision = AbstractDecision(StackedPsiLookup(tables, [10, 10]), model.internal,
                                model.featurizer(["dG"]))  # fmt: skip
    sim = Simulator(model, decision, GaussianField(), DT, backend="numba")
    sim.advance(sim.initial_state(20, (2.0, 0.0)), 3)
    with pytest.raises(ValueError, match="cover 20 cells, not 30"):
        sim.advance(sim.initial_state(30, (2.0, 0.0)), 3)


def test_advance_leaves_a_held_motor_state_alone() -> None:
    model = EcoliModel()
    torch.manual_seed(1)
    sim = Simulator(model, FullDecision(model.internal), GaussianField(), DT, backend="numba")
    state = sim.initial_state(50, (2.0, 0.0))
    held = sim.decision.fused_state()[0]
    before = held.clone()
    sim.advance(state, 10)
    assert torch.equal(held, before)
    assert not torch.equal(sim.decision.fused_state()[0], before)  # the layer's own copy moved


# -- ecoli_phospho: the same body, its abstraction over the MWC activity ------------------------
def _phospho_model():
    from surrogate.models.ecoli_phospho import EcoliPhosphoModel

    # burn_in=0: the cells' first phi from the network's file state (no SSA; not under test)
    return EcoliPhosphoModel(burn_in=0.0)


def _phospho_decision(model, names: tuple[str, ...] = ("activity",)) -> AbstractDecision:
    """A two-state chain over a smooth psi of the activity (and F): runs end and tumbles start
    at rates that vary across the activity cells live at (a ~ 0.45 adapted)."""
    bounds = {"activity": (0.0, 1.0), "F": (-6.0, 6.0)}

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        a = z[:, 0] if len(names) == 1 else z[:, 1] - 0.02 * z[:, 0]
        return torch.where(phi > 0, torch.sigmoid(3.0 - 4.0 * a), torch.sigmoid(4.0 * a - 2.5))

    size = {1: (512,), 2: (48, 64)}[len(names)]
    table = PsiLookupTable.from_function(psi, [bounds[n] for n in names], names, size)
    return AbstractDecision(table, model.internal, model.featurizer(list(names)))


@pytest.mark.parametrize("names", [("activity",), ("F", "activity")], ids=["a", "Fa"])
@pytest.mark.parametrize("field", ["gaussian", "linear"])
def test_kernel_follows_the_torch_step_on_the_phospho_abstraction(field, names) -> None:
    """From one seed the phospho abstraction (a lookup over the activity) on the kernel
    follows the torch step over 300 steps: positions, phi, m, segment lengths."""
    model = _phospho_model()
    decision = _phospho_decision(model, names)
    f = {"gaussian": GaussianField(), "linear": LinearField()}[field]
    runs = []
    for backend in ("torch", "numba"):
        torch.manual_seed(5)
        sim = Simulator(model, decision, f, DT, backend=backend)
        assert sim.backend == backend
        with torch.inference_mode():
            state = sim.initial_state(N, (2.0, 0.0), equilibration_time=1.0)
            sim.warm_up(state)
            ended = torch.cat([sim.advance(state, k) for k in (7, 20, 273)])
        runs.append((state, ended))
    _assert_same_trajectories(*runs)
    a = runs[0][0]
    assert a.phi.float().mean() > 0.2 and (1 - a.phi.float()).mean() > 0.2  # both states live


def test_auto_runs_the_phospho_abstraction_on_the_kernel_and_its_full_model_on_torch() -> None:
    """backend=auto: numba for the chain over a lookup table, torch for the SSA network (the
    kernel refuses it, naming why); backend=numba on the full model is an error."""
    from surrogate.simulate.loop import resolve_backend

    model = _phospho_model()
    abstract = _phospho_decision(model)
    sim = Simulator(model, abstract, GaussianField(), DT, backend="auto")
    assert sim.backend == "numba" and sim.backend_note is None
    assert resolve_backend("auto", model, abstract, LinearField(), DT) == "numba"
    full = FullDecision(model.internal)
    sim = Simulator(model, full, GaussianField(), DT, backend="auto")
    assert sim.backend == "torch" and "FullDecision over PhosphoInternalModel" in sim.backend_note
    assert resolve_backend("auto", model, full, GaussianField(), DT) == "torch"
    with pytest.raises(KernelUnsupported, match="FullDecision over PhosphoInternalModel"):
        Simulator(model, full, GaussianField(), DT, backend="numba")
    # compile=true asks for the torch step; the classifier has no table
    assert Simulator(model, abstract, GaussianField(), DT, compile=True).backend == "torch"
    classifier = AbstractDecision(lambda phi, z: torch.full_like(z[:, 0], 0.5), model.internal,
                                  model.featurizer(["activity"]))  # fmt: skip
    assert Simulator(model, classifier, GaussianField(), DT, backend="auto").backend == "torch"
    # one compiled kernel serves both models
    assert model.kernel_precompiler() == EcoliModel().kernel_precompiler()


def test_the_kernel_refuses_what_it_does_not_transcribe_for_the_phospho_model() -> None:
    """An exact chain over the network (no motors), a feature the network does not compute
    (dG: torch would fail on it too), a layer over the other model's internal model, and
    E. coli's kernel for a phospho layer."""
    from surrogate.models.base import FeatureMap

    model = _phospho_model()
    internal = model.internal
    table = _phospho_decision(model).run_probability
    dg = _table(EcoliModel(), ("dG",))
    cases = {
        "ExactDecision over PhosphoInternalModel": ExactDecision(internal, DT, table),
        "features \\['dG'\\]": AbstractDecision(dg, internal, FeatureMap(internal, ["dG"])),
        "another internal model": AbstractDecision(table, _phospho_model().internal,
                                                   _phospho_model().featurizer(["activity"])),
    }  # fmt: skip
    for what, decision in cases.items():
        sim = Simulator(model, decision, GaussianField(), DT, backend="auto")
        assert sim.backend == "torch", what
        with pytest.raises(KernelUnsupported, match=what):
            Simulator(model, decision, GaussianField(), DT, backend="numba")
    ecoli = EcoliModel()
    with pytest.raises(KernelUnsupported, match="another internal model"):
        ecoli.cell_kernel(pack_decision(_phospho_decision(model), DT), GaussianField(), DT)


def test_activity_feature_code_is_the_phospho_networks_activity_in_float32() -> None:
    """The kernel's ``activity`` (code 5) is torch.sigmoid(-F) within 2 float32 ulps at the
    same F (exp differs by an ulp between torch's vector code and libm), and from (m, L) it is
    PhosphoInternalModel.features' activity up to F's rounding (the terms are summed in
    another order)."""
    import numpy as np

    from surrogate.models.ecoli import kernel

    model = _phospho_model()
    p32, _ = kernel.pack_parameters(model.params, DT)
    g = torch.Generator().manual_seed(0)
    n = 1500
    x = torch.stack([0.5 + 3.0 * torch.rand(n, generator=g), torch.rand(n, generator=g) ** 3], 1)
    x[:4, 1] = torch.tensor([0.0, 1e-4, 10.0, 1e3])
    ref = model.internal.features(x, ("F", "activity"))
    code = kernel.FEATURE_CODES["activity"]
    assert code == 5 and set(model.internal.feature_names) <= set(kernel.FEATURE_CODES)
    # the formula alone, at torch's F
    energy = ref[:, 0].numpy()
    act = np.array([kernel._activity(e) for e in energy], dtype=np.float32)  # float32 inside
    expected = torch.sigmoid(-ref[:, 0]).numpy()
    ulps = np.abs(act - expected) / np.spacing(expected)
    assert ulps.max() <= 2, ulps.max()
    # the kernel's path from (m, L): its signal, then the feature code
    got = np.empty((n, 2), dtype=np.float32)
    for i, (m, ligand) in enumerate(x.numpy()):
        e, a, yp, dg = kernel._signal(m, kernel._log_receptor_terms(ligand, p32), p32)
        values = kernel._features(m, ligand, e, a, yp, dg)
        got[i] = (values[kernel.FEATURE_CODES["F"]], values[code])
    torch.testing.assert_close(torch.from_numpy(got), ref, atol=1e-5, rtol=1e-6)
    assert np.abs(got[:, 1] - ref[:, 1].numpy()).max() < 5e-7


def test_the_per_cell_loop_compiles_without_reference_counts() -> None:
    """The loop hands its packs to inlined decision steps; with reference counts numba counts
    every array of a pack each time (half the speed, measured). ``_nrt`` is a private numba
    option: a numba that drops it must fail here, not silently run at half speed."""
    from surrogate.models.ecoli import kernel

    assert kernel._NO_REFCOUNTS == {"_nrt": False}

"""A population coupled to a grid field: the order of a step, mass conserved over a whole run
for every decision layer, replicates with their own fields, and what is refused by name."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.fields import ConstantField, FieldBatch
from surrogate.grid import MOLECULES_PER_NMOL, GridField
from surrogate.kinds.layers import exact_decision
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision, FullDecision, Simulator
from surrogate.simulate.batch import BatchSimulator, Replicate
from surrogate.simulate.classes import ClassDecision, exact_class_table
from surrogate.simulate.coupling import coupled_blocks

MODEL = EcoliModel()
DT = 0.05
EPS = float(np.finfo(np.float64).eps)


def channel(diffusion: float = 8e-4, rate_on: float = 2e5) -> GridField:
    """A 4 mm x 0.5 mm channel: a consumed attractant (what the cells read) and a signal they
    secrete while running."""
    return GridField(
        [[0.0, 4.0], [-0.25, 0.25]], [64, 8],
        {"attractant": {"diffusion": diffusion, "initial": 0.1,
                        "uptake": {"vmax": 1e8, "km": 0.01}},
         "signal": {"diffusion": diffusion, "decay": 0.01,
                    "secretion": {"rate_on": rate_on, "rate_off": 0.0}}},
        depth=0.1,
    )  # fmt: skip


def flipping(model: EcoliModel) -> AbstractDecision:
    """A fused two-state chain whose phi flips every step (so phi before and after differ)."""

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return torch.where(phi.reshape(-1) > 0, 0.0, 1.0).to(torch.float32)

    return AbstractDecision(psi, model.internal)


@pytest.mark.parametrize("decision", ["full", "abstract"])
def test_mass_is_conserved_over_a_whole_coupled_run(decision: str) -> None:
    """field + taken + decayed - secreted - supplied = initial, per species, to float64
    rounding (a few ulps of the mass per step), whatever decides phi."""
    torch.manual_seed(0)
    field = channel()
    layer = FullDecision(MODEL.internal) if decision == "full" else flipping(MODEL)
    sim = Simulator(MODEL, layer, field, DT)
    state = sim.initial_state(200, (1.0, 0.0))
    steps = 200
    sim.advance(state, steps)
    sim.check_state(state)
    ledger = field.state
    assert ledger.steps == steps and state.fields == (ledger,)
    assert float(ledger.taken[0]) > 0.01 * float(ledger.initial[0])  # the cells consumed
    assert float(ledger.secreted[1]) > 0 and float(ledger.decayed[1]) > 0
    scale = ledger.initial + ledger.secreted + ledger.supplied
    assert bool((field.balance().abs() <= steps * 64 * EPS * scale).all()), field.balance()


def test_a_step_reads_the_field_then_the_field_takes_the_cells_exchange() -> None:
    """The order of a step: the cells read the field as it was (their inputs), move, then the
    field takes their secretion at their new positions with their phi after the window."""
    torch.manual_seed(1)
    field = channel(diffusion=0.0, rate_on=1e6)  # no diffusion: the deposit stays put
    sim = Simulator(MODEL, flipping(MODEL), field, DT)
    state = sim.initial_state(100, (1.0, 0.0))
    before = field(state.body["position"], 0.0)
    signal_before = field.concentration("signal").clone()
    record = sim.step(state)
    assert torch.equal(record.inputs[:, 1], before)  # L read before the field changed
    assert not torch.equal(record.phi_after, record.phi_before)
    on = state.phi.to(torch.float64)  # phi after the window
    assert float(field.state.secreted[1]) == pytest.approx(
        float(on.sum()) * 1e6 * DT / MOLECULES_PER_NMOL, rel=1e-14)  # fmt: skip
    # where it went: the deposit at the positions after the move (decayed for one step)
    amounts = on * (1e6 * DT / MOLECULES_PER_NMOL)
    added = field.grid.stencil(state.body["position"]).deposit(amounts) / field.grid.cell_volume
    got = field.concentration("signal") - signal_before
    assert torch.allclose(got, added * np.exp(-0.01 * DT), rtol=1e-12, atol=1e-20)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_batched_replicates_each_advance_their_own_field_bit_for_bit(backend: str) -> None:
    """Two replicates given one field object: each gets its own state, and each replicate
    (cells and field) is its standalone run exactly (eager CPU; the per-cell kernel too, its
    fields' rows read outside block by block)."""

    def layer():  # the kernel runs no Python psi: the full model there
        return flipping(MODEL) if backend == "torch" else FullDecision(MODEL.internal)

    shared = channel()
    reps = [Replicate(layer(), shared, 60, seed=s, start=(1.0, 0.0)) for s in (3, 4)]
    batch = BatchSimulator(MODEL, reps, DT, backend=backend)
    assert batch.backend == backend
    assert batch.replicates[0].field is shared and batch.replicates[1].field is not shared
    state = batch.initial_state()
    batch.advance(state, 40)
    for rep, cells in zip(batch.replicates, batch.slices, strict=True):
        torch.manual_seed(rep.seed)
        alone_field = channel()
        alone = Simulator(MODEL, layer(), alone_field, DT, backend=backend)
        solo = alone.initial_state(rep.n_cells, rep.start)
        alone.advance(solo, 40)
        assert torch.equal(state.body["position"][cells], solo.body["position"])
        assert torch.equal(rep.field.state.concentration, alone_field.state.concentration)


def _kernel_run(decision: str, backend: str, threads: int = 1, n: int = 200, steps: int = 60):
    torch.manual_seed(5)
    field = channel()
    layer = FullDecision(MODEL.internal) if decision == "full" else ClassDecision(
        exact_class_table(MODEL.internal, DT, size=64), MODEL.internal,
        MODEL.featurizer(["dG"]))  # fmt: skip
    sim = Simulator(MODEL, layer, field, DT, backend=backend)
    assert sim.backend == backend
    state = sim.initial_state(n, (1.0, 0.0))
    sim.warm_up(state)
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)  # the kernel runs on as many threads as torch
    try:
        ends = torch.cat([sim.advance(state, k) for k in (7, steps - 7)])
    finally:
        torch.set_num_threads(previous)
    sim.check_state(state)
    return state, ends, field


@pytest.mark.parametrize("decision", ["full", "classes"])
def test_the_kernel_runs_a_coupled_field_as_the_torch_step(decision: str) -> None:
    """backend=numba: one kernel step per call, the field read before it and stepped after
    it, as the torch step does. The kernel rounds an elementary function's last bit now and
    then (tests/models/test_kernel.py), so: every cell's segments and phi the same, positions
    within float32 rounding at their scale (1e-6 mm; 3e-9 measured), concentrations to 1e-8
    of the largest (3e-10 measured), the mass balance to float64 rounding; the kernel's own
    bytes independent of its thread count."""
    state, ends, field = _kernel_run(decision, "torch")
    state_k, ends_k, field_k = _kernel_run(decision, "numba")
    same = (ends == ends_k).all(0) & (state.phi == state_k.phi)
    assert bool(same.all()) and int((ends != 0).sum()) > 200  # segments ended
    torch.testing.assert_close(state_k.body["position"], state.body["position"], atol=1e-6,
                               rtol=0)  # fmt: skip
    c, c_k = field.state.concentration, field_k.state.concentration
    assert torch.allclose(c_k, c, rtol=0.0, atol=1e-8 * float(c.max()))
    scale = field_k.state.initial + field_k.state.secreted + field_k.state.supplied
    assert bool((field_k.balance().abs() <= 60 * 64 * EPS * scale).all())
    state_2, ends_2, field_2 = _kernel_run(decision, "numba", threads=2)
    assert torch.equal(ends_2, ends_k) and torch.equal(state_2.body["position"],
                                                       state_k.body["position"])  # fmt: skip
    assert torch.equal(field_2.state.concentration, field_k.state.concentration)


def test_auto_runs_a_coupled_field_on_the_kernel() -> None:
    auto = Simulator(MODEL, FullDecision(MODEL.internal), channel(), DT, backend="auto")
    assert auto.backend == "numba" and auto.backend_note is None


def _coupled_run(decision: str, compile: bool, n: int = 200, steps: int = 30):
    torch.manual_seed(5)
    field = channel()
    # the exact chain as decision=exact builds it by default (a table over the signal); its
    # direct mode traces exp(Q dt) into ~20 graphs, ~20 s of cold compilation for nothing the
    # coupling does differently
    layer = FullDecision(MODEL.internal) if decision == "full" else exact_decision(
        MODEL, DT, "lookup", None, torch.device("cpu"))[0]  # fmt: skip
    sim = Simulator(MODEL, layer, field, DT, compile=compile, compile_fallback=False)
    state = sim.initial_state(n, (1.0, 0.0))
    sim.warm_up(state)
    ends = sim.advance(state, steps)
    sim.check_state(state)
    assert sim.compiled is compile
    return state.body["position"], ends, field


@pytest.mark.parametrize("decision", ["full", "exact"])
def test_the_compiled_step_runs_a_coupled_field_as_the_eager_one(decision: str) -> None:
    """compile=true: the field is read before the compiled kernel and stepped after it, both
    eagerly, so only the agents' step is compiled and it rounds a few last bits differently,
    as for a given field (tests/simulate/test_batch.py): the same segments, positions and
    concentrations to float32 rounding (one flipped draw would move one cell: 1% allowed), and
    the mass balance to float64 rounding; two compiled runs with one seed, the same bytes."""
    position, ends, field = _coupled_run(decision, compile=False)
    position_c, ends_c, field_c = _coupled_run(decision, compile=True)
    moved = ((position - position_c).abs() > 1e-5).any(-1)
    assert float(moved.float().mean()) <= 0.01
    assert float((ends != ends_c).any(0).float().mean()) <= 0.01
    c, c_c = field.state.concentration, field_c.state.concentration
    assert torch.allclose(c, c_c, rtol=0.0, atol=1e-6 * float(c.max()))
    steps = field_c.state.steps
    scale = field_c.state.initial + field_c.state.secreted + field_c.state.supplied
    assert bool((field_c.balance().abs() <= steps * 64 * EPS * scale).all()), field_c.balance()
    assert float(field_c.state.taken[0]) > 0
    if decision == "full":  # the compiled loop is reproducible: one seed, the same bytes
        position_again, ends_again, field_again = _coupled_run(decision, compile=True)
        assert torch.equal(position_again, position_c) and torch.equal(ends_again, ends_c)
        assert torch.equal(field_again.state.concentration, c_c)


def test_one_coupled_field_in_two_blocks_apart_is_refused() -> None:
    shared = channel()
    batch = FieldBatch([shared, ConstantField(0.1), shared], [10, 10, 10])
    with pytest.raises(ConfigError, match="one coupled field object serves two blocks"):
        coupled_blocks(batch)
    assert [c for _, c in coupled_blocks(FieldBatch([ConstantField(), channel()], [5, 7]))] == [
        slice(5, 12)
    ]


def test_a_body_without_positions_is_refused_by_name() -> None:
    class NoPosition:
        def __init__(self, body):
            self.inner = body

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def move(self, state, *args):
            moved = self.inner.move({**state, "position": state["where"]}, *args)
            return {"where": moved.pop("position"), **moved}

        def initial_state(self, *args):
            state = self.inner.initial_state(*args)
            return {"where": state.pop("position"), **state}

        def inputs(self, state, field, t):
            return self.inner.inputs({**state, "position": state["where"]}, field, t)

    model = EcoliModel()
    model.body = NoPosition(model.body)  # type: ignore[assignment]
    sim = Simulator(model, FullDecision(model.internal), channel(), DT)
    state = sim.initial_state(5, (1.0, 0.0))
    with pytest.raises(ConfigError, match="needs a body whose state has a 'position'"):
        sim.step(state)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_coupled_run_on_cuda_conserves_mass_and_steps_the_field_as_the_cpu() -> None:
    """device=cuda: the cells and the grid on the GPU (the dense step, index_add_'s deposit):
    mass balance to float64 rounding over a run; one field step from the same state and
    positions equals the CPU's (transforms or dense, compiled exchange) to float64 rounding of
    the sums (atomics add in another order)."""
    torch.manual_seed(0)
    field = channel()
    sim = Simulator(MODEL, flipping(MODEL), field, DT, device="cuda")
    state = sim.initial_state(500, (1.0, 0.0))
    steps = 100
    sim.advance(state, steps)
    sim.check_state(state)
    ledger = field.state
    assert ledger.concentration.is_cuda and float(ledger.taken[0]) > 0
    scale = ledger.initial + ledger.secreted + ledger.supplied
    assert bool((field.balance().abs() <= steps * 64 * EPS * scale).all()), field.balance()
    on_cpu = channel()
    on_cpu.start_from(ledger.concentration.cpu())
    field.start_from(ledger.concentration)
    position, phi = state.body["position"], state.phi
    after = field.step(position, phi, DT).concentration.cpu()
    want = on_cpu.step(position.cpu(), phi.cpu(), DT).concentration
    assert field._solver.dense
    assert torch.allclose(after, want, rtol=0.0, atol=64 * 64 * EPS * float(want.abs().max()))

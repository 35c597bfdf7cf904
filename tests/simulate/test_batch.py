"""Replicates in one batch: every replicate is the run it would be alone.

Eager: bit for bit (each replicate draws its own random numbers, in its standalone layout, from
its own generator). Compiled: compiled kernels round a few last bits differently, so the test is
in distribution (two-sample KS at alpha = 0.001 on 2,000 cells, and mean durations).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from surrogate.fields import DynamicGaussianField, FieldBatch, GaussianField, LinearField
from surrogate.gp import PsiLookupTable, StackedPsiLookup
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision, ExactDecision, FullDecision, Simulator
from surrogate.simulate.batch import BatchSimulator, DecisionBatch, Replicate
from surrogate.simulate.memory import AGE, MemoryDecision

MODEL = EcoliModel()
DT = 0.05


def _table(lo: float = -3.0, hi: float = 10.0) -> PsiLookupTable:
    dg = torch.linspace(lo, hi, 256)
    return PsiLookupTable(torch.stack([torch.sigmoid(dg - 1.0), torch.sigmoid(dg + 2.0)]),
                          [(lo, hi)], ("dG",))  # fmt: skip


def _decisions():
    abstract = AbstractDecision(_table(), MODEL.internal, MODEL.featurizer(["dG"]))
    # another table over the same feature and grid size, on another box: stacked with the
    # abstract layer's in a batch (per-cell boxes)
    exact = ExactDecision(MODEL.internal, DT, _table(-4.0, 12.5))
    return {"full": lambda: FullDecision(MODEL.internal), "abstract": lambda: abstract,
            "exact": lambda: exact}  # fmt: skip


SPEC = [
    ("full", GaussianField(), 100, 0),
    ("full", LinearField(), 120, 1),
    ("abstract", GaussianField(), 50, 2),
    ("abstract", DynamicGaussianField(), 60, 3),
    ("exact", LinearField(), 80, 4),
]


# a replicate large enough that its blocks of random numbers cover fewer steps (16 MiB cap)
UNEQUAL = [("abstract", GaussianField(), 30_000, 5), ("full", LinearField(), 40, 6)]


@pytest.mark.parametrize("spec", [SPEC, UNEQUAL], ids=["equal_blocks", "unequal_blocks"])
def test_eager_replicates_are_their_standalone_runs_bit_for_bit(spec) -> None:
    make = _decisions()
    alone = []
    for kind, field, n, seed in spec:
        torch.manual_seed(seed)
        sim = Simulator(MODEL, make[kind](), field, DT)
        state = sim.initial_state(n, (2.0, 0.0), equilibration_time=1.0)
        for _ in range(150):  # more than two blocks of random numbers (64 steps each)
            sim.step(state)
        alone.append(state)
    reps = [Replicate(make[k](), f, n, s) for k, f, n, s in spec]
    batch = BatchSimulator(MODEL, reps, DT)
    if spec is SPEC:
        # same-kind neighbours share one layer; chains over equal-shape tables of the same
        # feature share one stacked table
        assert batch.groups == [[0, 1], [2, 3, 4]]
        stacked = batch.decision.members[1]
        assert isinstance(stacked.run_probability, StackedPsiLookup)
        assert stacked.name == "abstract+exact"
    state = batch.initial_state(equilibration_time=1.0)
    torch.manual_seed(99)  # the global stream does not matter any more
    for _ in range(150):
        batch.step(state)
    for i, cells in enumerate(batch.slices):
        for key in ("position", "heading", "m"):
            assert torch.equal(state.body[key][cells], alone[i].body[key]), (i, key)
        assert torch.equal(state.phi[cells], alone[i].phi)
        assert torch.equal(state.segment_steps[cells], alone[i].segment_steps)


class _Eager(AbstractDecision):
    """The abstract layer with its fused step switched off: it steps eagerly, drawing from
    the global generator (as every layer does in a batch with a network whose full model is
    not fusable)."""

    fusable = False


class _EagerClock(MemoryDecision):
    """A switch clock (a per-cell state) stepped eagerly."""

    fusable = False


def _clock() -> _EagerClock:
    table = PsiLookupTable.from_function(
        lambda phi, z: torch.sigmoid(z[:, 0] - 2.0 * z[:, 1] - phi.float()),
        [(-3.0, 10.0), (0.0, 2.0)], ("dG", AGE), (64, 9))  # fmt: skip
    return _EagerClock(table, MODEL.internal, MODEL.featurizer(["dG"]), max_age=2.0)


@pytest.mark.parametrize("kind", ["two-state", "clock"])
def test_eager_layers_draw_from_their_replicates_own_streams(kind: str) -> None:
    """A batch that is not fusable steps each layer eagerly: each draws from its replicate's
    own generator, so a replicate is its standalone run bit for bit whatever runs beside it
    (before, every layer drew from the one global stream: a chain's run moved when repeats
    of it joined the batch)."""
    spec = [(GaussianField(), 80, 7), (LinearField(), 60, 8), (GaussianField(), 70, 9)]

    def layer() -> AbstractDecision:
        if kind == "clock":  # its clocks: one per cell, each replicate's its own
            return _clock()
        return _Eager(_table(), MODEL.internal, MODEL.featurizer(["dG"]))

    alone = []
    for field, n, seed in spec:
        torch.manual_seed(seed)
        sim = Simulator(MODEL, layer(), field, DT)
        state = sim.initial_state(n, (2.0, 0.0), equilibration_time=1.0)
        for _ in range(150):
            sim.step(state)
        alone.append(state)
    shared = layer()  # one layer object for several replicates (a chain's repeats) too
    for picked, make in (([0, 1, 2], layer), ([2, 0], layer), ([1], layer),
                         ([0, 2], lambda: shared)):  # fmt: skip
        batch = BatchSimulator(MODEL, [Replicate(make(), *spec[i]) for i in picked], DT)
        assert batch.groups == [[k] for k in range(len(picked))]  # one layer per replicate
        state = batch.initial_state(equilibration_time=1.0)
        assert batch.decision.generators is not None  # one per layer, each its replicate's
        torch.manual_seed(99)
        for _ in range(150):
            batch.step(state)
        for cells, i in zip(batch.slices, picked, strict=True):
            assert torch.equal(state.phi[cells], alone[i].phi), (picked, i)
            assert torch.equal(state.body["position"][cells], alone[i].body["position"])


def test_field_and_decision_batches_split_by_block() -> None:
    fields = FieldBatch([GaussianField(), LinearField()], [2, 3])
    x = torch.tensor([[1.0, 0.0]] * 5)
    expected = torch.cat([GaussianField()(x[:2], 0.0), LinearField()(x[2:], 0.0)])
    assert torch.equal(fields(x, 0.0), expected)
    with pytest.raises(ValueError, match="one size per"):
        DecisionBatch([FullDecision(MODEL.internal)], [1, 2])


def test_field_batch_evaluates_a_shared_field_once_over_its_blocks() -> None:
    """Blocks G, L, G (one GaussianField object twice): the same values as block by block, with
    one call per distinct field."""
    gauss, linear = GaussianField(), DynamicGaussianField()
    calls: list[int] = []

    class Counting(LinearField):
        def __call__(self, position, t):
            calls.append(len(position))
            return super().__call__(position, t)

    counted = Counting()
    sizes = [2, 3, 4, 1]
    fields = FieldBatch([gauss, counted, gauss, counted], sizes)
    x = torch.randn(10, 2, generator=torch.Generator().manual_seed(0))
    parts = torch.split(x, sizes)
    for t in (0.0, 30.0):
        expected = torch.cat([gauss(parts[0], t), LinearField()(parts[1], t),
                              gauss(parts[2], t), LinearField()(parts[3], t)])  # fmt: skip
        assert torch.equal(fields(x, t), expected)
    assert calls == [4, 4]  # both of its blocks in one call, per evaluation
    peaks = FieldBatch([linear, GaussianField(peak=(1.0, 1.0)), linear], [2, 2, 2])
    y = torch.zeros(6, 2)
    np.testing.assert_allclose(peaks.distance_from_peak(y), [0, 0, 2**0.5, 2**0.5, 0, 0])


def test_compiled_batch_is_identical_in_distribution(tmp_path) -> None:
    """Two compiled replicates (L1 and L2) against the same runs simulated alone, eagerly:
    distances after 60 s and mean run/tumble durations agree (KS at alpha = 0.001; means
    within 4.5 combined standard errors)."""
    n, steps = 2000, 1200
    fields = [GaussianField(), LinearField()]
    alone = []
    for seed, field in enumerate(fields):
        torch.manual_seed(seed + 10)
        sim = Simulator(MODEL, FullDecision(MODEL.internal), field, DT)
        state = sim.initial_state(n, (2.0, 0.0))
        ends = []
        for _ in range(steps):
            ends.append(sim.step(state).ended_length)
        alone.append((field.distance_from_peak(state.body["position"]), torch.stack(ends)))
    reps = [Replicate(FullDecision(MODEL.internal), f, n, s + 20) for s, f in enumerate(fields)]
    batch = BatchSimulator(MODEL, reps, DT, compile=True)
    state = batch.initial_state()
    batch.warm_up(state)
    ends = torch.stack([batch.step(state).ended_length for _ in range(steps)])
    assert batch.compile_error is None
    distance = batch.field.distance_from_peak(state.body["position"])
    crit = 1.949 * math.sqrt(2 / n)  # two-sample KS critical value at alpha = 0.001
    for i, cells in enumerate(batch.slices):
        ks = stats.ks_2samp(distance[cells].numpy(), alone[i][0].numpy()).statistic
        assert ks < crit, (i, ks, crit)
        for sign in (1, -1):  # runs, then tumbles
            a = _durations(ends[:, cells], sign)
            b = _durations(alone[i][1], sign)
            se = math.sqrt(a.var() / len(a) + b.var() / len(b))
            assert abs(a.mean() - b.mean()) < 4.5 * se


def _durations(ended: torch.Tensor, sign: int) -> np.ndarray:
    values = ended[ended * sign > 0].abs().double().numpy() * DT
    assert len(values) > 1000
    return values


def test_replicates_sharing_a_matmul_psi_keep_their_own_blocks() -> None:
    """A closed-form GP psi (matmuls, another code path from 4,096 rows on) is not ``rowwise``:
    two runs sharing it stay two blocks, so each is still its standalone run bit for bit (one
    call over 6,000 rows gave some probabilities other last bits than two calls over 3,000, on
    the CPU where this was found; a flipped draw is rare, so the grouping is what is asserted).
    """
    import numpy as np
    import pandas as pd

    from surrogate.gp import GPSettings, fit_psi
    from surrogate.gp.fast import CachedPsi

    rng = np.random.default_rng(0)
    dg = rng.uniform(-3.0, 10.0, 1200)
    phi = rng.integers(0, 2, dg.size)
    switch = rng.random(dg.size) < 1.0 / (1.0 + np.exp(-(dg - 1.0)))
    data = pd.DataFrame({"dG": dg, "phi": phi, "phi_next": switch.astype(np.int8)})
    torch.manual_seed(0)
    psi = fit_psi(data, ("dG",), GPSettings(n_inducing=20, epochs=3, batch_size=400),
                  progress=False)  # fmt: skip
    fast = CachedPsi.from_classifier(psi)
    assert not getattr(fast, "rowwise", False) and _table().rowwise
    shared = AbstractDecision(fast, MODEL.internal, MODEL.featurizer(["dG"]))
    spec = [(GaussianField(), 3000, 0), (GaussianField(), 3000, 1)]
    alone = []
    for field, n, seed in spec:
        torch.manual_seed(seed)
        sim = Simulator(MODEL, shared, field, DT)
        state = sim.initial_state(n, (2.0, 0.0))
        for _ in range(40):
            sim.step(state)
        alone.append(state)
    batch = BatchSimulator(MODEL, [Replicate(shared, f, n, s) for f, n, s in spec], DT)
    assert batch.groups == [[0], [1]]
    state = batch.initial_state()
    for _ in range(40):
        batch.step(state)
    for i, cells in enumerate(batch.slices):
        assert torch.equal(state.phi[cells], alone[i].phi), i
        assert torch.equal(state.body["position"][cells], alone[i].body["position"]), i
    # a shared lookup table is rowwise: one block
    table = AbstractDecision(_table(), MODEL.internal, MODEL.featurizer(["dG"]))
    reps = [Replicate(table, f, 10, s) for f, _, s in spec]
    assert BatchSimulator(MODEL, reps, DT).groups == [[0, 1]]

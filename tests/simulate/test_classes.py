"""K lumps (gp.lumps=classes): the class table's draw samples its law, the decision layer's
eager and fused steps agree and check what they are given, and a model whose switch out of a
lump depends on a hidden sub-state fails with the two-state chain and passes with the exact
class chain, at the two-sample KS critical value of its dwell times.

The draw test: at inputs between grid nodes the drawn class has the multilinear interpolation
of the nodes' laws (:meth:`ClassTable.law`); a chi-square goodness-of-fit test at alpha = 1e-3
per (origin, input) case, with 20,000 draws each (the same counts reject the law of the nearest
node, so the test has power). Because that test reads the grid positions through the law
itself, a separate test places the nodes from the bounds alone (a wrong spacing fails it).
"""

from __future__ import annotations

import pytest
import torch
from scipy.stats import chisquare

from surrogate.ctmc.lumped import lumped_class_step
from surrogate.models import NetworkInternalModel
from surrogate.models.base import InternalState
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate.classes import ClassDecision, ClassTable, exact_class_table
from surrogate.simulate.decision import AbstractDecision, FullDecision
from tests.simulate.test_memory import DT, RATES, dwells, erlang_model, ks, run

ALPHA = 1e-3
DRAWS = 20_000  # per (origin, input) case


def _toy_table(n_classes: int, shape: tuple[int, ...], seed: int) -> ClassTable:
    """A table of random laws (exponential weights, i.e. Dirichlet(1) rows): neighbouring nodes differ by O(0.1) per class."""
    g = torch.Generator().manual_seed(seed)
    p = -torch.log(torch.rand(n_classes, *shape, n_classes, generator=g, dtype=torch.float64))
    bounds = [(-1.0, 2.0), (0.0, 0.5)][: len(shape)]
    names = ("a", "b")[: len(shape)]
    lumps = [k % 2 for k in range(n_classes)]
    return ClassTable(p, bounds, names, [f"c{k}" for k in range(n_classes)], lumps, DT)


#: inputs between nodes (and one beyond the box: clamped to its edge)
POINTS = {1: [[0.37], [1.1], [2.6]], 2: [[0.37, 0.21], [-0.55, 0.04], [1.9, 0.61]]}


@pytest.mark.parametrize("n_classes", [2, 3])
@pytest.mark.parametrize("shape", [(5,), (4, 3)])
def test_draw_samples_the_interpolated_law(n_classes: int, shape: tuple[int, ...]) -> None:
    table = _toy_table(n_classes, shape, seed=n_classes * 10 + len(shape))
    g = torch.Generator().manual_seed(1)
    d = len(shape)
    rejected_nearest = 0
    for origin in range(n_classes):
        for point in POINTS[d]:
            z = torch.tensor(point).expand(DRAWS, d)
            a = torch.full((DRAWS,), origin, dtype=torch.int64)
            u = torch.rand(d + 1, DRAWS, generator=g)
            nxt = table.draw(a, z, u)
            counts = torch.bincount(nxt, minlength=n_classes).double()
            law = table.law(a[:1], z[:1])[0].double()
            assert float(law.sum()) == pytest.approx(1.0, abs=1e-6)
            p = chisquare(counts.numpy(), (DRAWS * law / law.sum()).numpy()).pvalue
            assert p > ALPHA, (origin, point, counts.tolist(), law.tolist())
            # the law at the lower node (no interpolation): the counts reject it
            node = torch.tensor([table.bounds[j][0] + (table.bounds[j][1] - table.bounds[j][0])
                                 * int(table._positions(z[:1])[j][0]) / (table.shape[j] - 1)
                                 for j in range(d)]).unsqueeze(0)  # fmt: skip
            lower = table.law(a[:1], node)[0].double()
            if chisquare(counts.numpy(), (DRAWS * lower / lower.sum()).numpy()).pvalue < ALPHA:
                rejected_nearest += 1
    assert rejected_nearest >= n_classes * len(POINTS[d]) - 1  # the test sees the difference


def test_a_table_reads_back_its_probabilities_and_state() -> None:
    table = _toy_table(3, (4, 3), seed=0)
    p = table.probabilities()
    torch.testing.assert_close(p.sum(-1), torch.ones(3, 4, 3), rtol=0, atol=1e-6)
    back = ClassTable.from_state(table.to_state())
    assert torch.equal(back.cdf, table.cdf) and back.class_lumps == table.class_lumps
    # at a node the law is the node's row
    z = torch.tensor([[table.bounds[0][0], table.bounds[1][1]]])
    torch.testing.assert_close(table.law(torch.tensor([2]), z)[0], p[2, 0, 2])


@pytest.mark.parametrize("shape", [(5,), (4, 3)])
def test_the_grid_puts_node_k_at_lo_plus_k_spacings(shape: tuple[int, ...]) -> None:
    """The nodes are evenly spaced from lo to hi, node k at lo + k (hi - lo) / (n - 1),
    computed here from the bounds alone: at every node the law and the draw are that node's
    row, and halfway between two nodes the law is their mean (the draw test compares the draw
    with :meth:`ClassTable.law`, which reads the same positions, so it cannot see a wrong grid)."""
    table = _toy_table(3, shape, seed=4)
    p = table.probabilities()
    axes = [torch.linspace(lo, hi, n, dtype=torch.float64)
            for (lo, hi), n in zip(table.bounds, shape, strict=True)]  # fmt: skip
    nodes = torch.cartesian_prod(*[torch.arange(n) for n in shape]).reshape(-1, len(shape))
    z = torch.stack([axes[j][nodes[:, j]] for j in range(len(shape))], 1).float()
    g = torch.Generator().manual_seed(5)
    for origin in range(3):
        a = torch.full((len(nodes),), origin)
        rows = p[(origin, *nodes.T)]
        torch.testing.assert_close(table.law(a, z), rows, rtol=0, atol=1e-6)
        # at a node no uniform rounds up: the draw is the categorical draw from its row
        u = torch.rand(len(shape) + 1, len(nodes), generator=g)
        cdf = table.cdf.reshape(3, *shape, 3)[(origin, *nodes.T)]
        expected = (u[-1].unsqueeze(1) >= cdf[:, :-1]).sum(1)
        assert torch.equal(table.draw(a, z, u), expected)
    # halfway along the first axis between nodes 1 and 2 (the other axes at their node 0)
    half = torch.tensor([[0.5 * float(axes[0][1] + axes[0][2]), *[float(x[0]) for x in axes[1:]]]])
    mean = 0.5 * (p[(1, 1, *[0] * (len(shape) - 1))] + p[(1, 2, *[0] * (len(shape) - 1))])
    torch.testing.assert_close(table.law(torch.tensor([1]), half)[0], mean, rtol=0, atol=1e-6)


def test_a_nan_input_draws_from_the_first_node_as_the_kernel_does() -> None:
    """A NaN input (on any axis) is node 0 of that axis, never rounded up: the draw is the
    draw at the axis's lower bound with the same uniforms (the compiled kernel's rule), where
    it used to index far outside the table; the law there is NaN (it says nothing)."""
    table = _toy_table(3, (4, 3), seed=2)
    n = 4000
    g = torch.Generator().manual_seed(3)
    origin = torch.randint(0, 3, (n,), generator=g)
    z = torch.stack([torch.rand(n, generator=g) * 3 - 1, torch.rand(n, generator=g) * 0.5], 1)
    u = torch.rand(3, n, generator=g)
    for axis in (0, 1):
        nan, low = z.clone(), z.clone()
        nan[:, axis] = float("nan")
        low[:, axis] = table.bounds[axis][0]
        assert torch.equal(table.draw(origin, nan, u), table.draw(origin, low, u)), axis
        assert table.law(origin[:2], nan[:2]).isnan().all()
    # the lower bound's draw differs from the original inputs' (the comparison has teeth)
    assert not torch.equal(table.draw(origin, low, u), table.draw(origin, z, u))


def _ecoli_layer(size: int = 64) -> tuple[EcoliModel, ClassDecision]:
    model = EcoliModel()
    table = exact_class_table(model.internal, DT, size=size)
    return model, ClassDecision(table, model.internal, model.featurizer(["dG"]))


def _inputs(n: int, seed: int) -> torch.Tensor:
    """(m, L) spread over adapted and perturbed cells."""
    g = torch.Generator().manual_seed(seed)
    m = 1.8 + 0.8 * torch.rand(n, generator=g)
    ligand = 0.05 * torch.rand(n, generator=g)
    return torch.stack([m, ligand], 1)


def test_eager_and_fused_steps_draw_the_same_classes() -> None:
    _, eager = _ecoli_layer()
    _, fused = _ecoli_layer()
    n = 2000
    x = _inputs(n, 0)
    torch.manual_seed(5)
    phi = eager.initialize(x)
    torch.manual_seed(5)
    assert torch.equal(fused.initialize(x), phi)
    state: InternalState = fused.fused_state()
    moved = 0
    for k in range(20):
        before = state[0]
        torch.manual_seed(100 + k)
        phi_eager = eager.step(phi, x, DT)
        torch.manual_seed(100 + k)
        u = torch.rand(len(fused.table.input_names) + 1, n)
        phi_fused, state, aux = fused.fused_step(phi.float(), x, DT, u, None, state)
        assert aux == ()
        assert torch.equal(state[0], eager.cls), k
        assert torch.equal(phi_fused > 0, phi_eager), k
        phi = phi_eager
        moved += int((state[0] != before).sum())
    assert moved > n // 4  # classes moved (~2 % of the cells per step)


def test_ecoli_classes_sit_in_their_lumps() -> None:
    internal = EcoliModel().internal
    torch.manual_seed(0)
    state = internal.initial_state(_inputs(5000, 1))
    classes = internal.classes(state)
    lumps = torch.tensor(internal.class_lumps)
    assert torch.equal(lumps[classes].float(), internal.phi(state).float())
    assert len(set(classes.tolist())) >= 6  # the comparison covers most classes
    assert len(internal.class_names) == 7 and sorted(set(internal.class_lumps)) == [0, 1]


def test_the_stationary_law_of_each_node_solves_pi_p_equals_pi() -> None:
    """Each node's stationary law is the left fixed point of its law (and, for two classes, the
    closed form b / (a + b), a / (a + b)), also for a chain that keeps its class ~3e4 windows."""
    table = _toy_table(3, (4, 3), seed=5)
    pi = table.stationary()
    p = table.probabilities().double()
    for i in range(4):
        for j in range(3):
            assert float(pi[i, j].sum()) == pytest.approx(1.0, abs=1e-12)
            assert torch.allclose(pi[i, j] @ p[:, i, j, :], pi[i, j], atol=1e-6)
    a = torch.tensor([3e-5, 1e-3, 0.2], dtype=torch.float64)  # leaving class 0 per window
    b = torch.tensor([1e-5, 4e-3, 0.5], dtype=torch.float64)  # leaving class 1
    law = torch.stack([torch.stack([1 - a, a], -1), torch.stack([b, 1 - b], -1)])  # 2 x 3 x 2
    slow = ClassTable(law, [(0.0, 1.0)], ("z",), ("off", "on"), (0, 1), DT)
    want = torch.stack([b / (a + b), a / (a + b)], -1)
    assert torch.allclose(slow.stationary(), want, atol=2e-3)  # float32 table: rates to ~1e-3


@pytest.mark.parametrize("shape", [(5,), (4, 3)])
def test_cells_start_from_the_interpolated_stationary_law(shape: tuple[int, ...]) -> None:
    """``draw_start``: at inputs between nodes the classes follow the multilinear interpolation
    of the nodes' stationary laws (a chi-square test at ALPHA, DRAWS cells per point)."""
    table = _toy_table(3, shape, seed=7)
    pi = table.stationary().reshape(-1, 3)
    g = torch.Generator().manual_seed(2)
    d = len(shape)
    for point in POINTS[d]:
        z = torch.tensor(point).expand(DRAWS, d)
        counts = torch.bincount(table.draw_start(z, torch.rand(d + 1, DRAWS, generator=g)),
                                minlength=3).double()  # fmt: skip
        want = torch.zeros(3, dtype=torch.float64)
        positions = table._positions(z[:1])
        for corner in range(2**d):
            index, weight = 0, 1.0
            for j, (node, frac) in enumerate(positions):
                up = (corner >> j) & 1
                index += (int(node[0]) + up) * table.strides[j]
                weight *= float(frac[0]) if up else 1.0 - float(frac[0])
            want += weight * pi[index]
        assert chisquare(counts.numpy(), (DRAWS * want / want.sum()).numpy()).pvalue > ALPHA


def test_a_chain_started_stationary_simulates_no_internal_state() -> None:
    """``start=stationary`` never asks the internal model for a state (a network's burn-in),
    and its classes at the start are the stationary law's (ALPHA); other starts are refused."""
    model, exact = _ecoli_layer(size=8)

    class NoStates:
        def __getattr__(self, name: str):
            if name == "initial_state":
                raise AssertionError("the internal model's initial state was simulated")
            return getattr(model.internal, name)

    layer = ClassDecision(exact.table, NoStates(), model.featurizer(["dG"]), start="stationary")  # type: ignore[arg-type]
    x = _inputs(1, 0).expand(DRAWS, 2)
    phi = layer.initialize(x)
    assert torch.equal(phi, layer.table.lumps[layer.cls] > 0)
    z = model.featurizer(["dG"])(x[:1])
    pi = layer.table.stationary().reshape(-1, 7)
    node, frac = layer.table._positions(z)[0]
    want = (1 - float(frac[0])) * pi[int(node[0])] + float(frac[0]) * pi[int(node[0]) + 1]
    counts = torch.bincount(layer.cls, minlength=7).double()
    keep = want > 1e-9
    assert counts[~keep].sum() == 0
    assert (
        chisquare(counts[keep].numpy(), (DRAWS * want[keep] / want[keep].sum()).numpy()).pvalue
        > ALPHA
    )
    with pytest.raises(ValueError, match="start must be one of"):
        ClassDecision(exact.table, model.internal, None, start="burned")


def test_the_layer_refuses_another_models_classes_and_another_dt() -> None:
    model, layer = _ecoli_layer(size=8)
    t = layer.table
    other = ClassTable(t.probabilities(), t.bounds, t.input_names,
                       tuple(f"x{k}" for k in range(7)), t.class_lumps, DT)  # fmt: skip
    with pytest.raises(ValueError, match="classes"):
        ClassDecision(other, model.internal, model.featurizer(["dG"]))
    with pytest.raises(ValueError, match="declares no classes"):
        ClassDecision(t, erlang_model(), None)
    x = _inputs(10, 0)
    phi = layer.initialize(x)
    with pytest.raises(ValueError, match="dt"):
        layer.step(phi, x, 2 * DT)
    with pytest.raises(ValueError, match="class table"):
        ClassTable(torch.ones(7, 8, 6), t.bounds, t.input_names, t.class_names, t.class_lumps,
                   DT)  # fmt: skip


# -- a model that needs classes -------------------------------------------------------------------
class ClassedErlang(NetworkInternalModel):
    """The Erlang cycle A0 -> A1 -> B -> A0 (phi = [B >= 1]) with its molecule's place as the
    class: a stay in phi = 0 ends only from the hidden sub-state A1."""

    class_names = ("A0", "A1", "B")
    class_lumps = (0, 0, 1)

    def classes(self, state: InternalState) -> torch.Tensor:
        return state[0].argmax(1)  # one molecule: the species holding it

    def exact_class_step(self, signal: torch.Tensor, dt: float) -> torch.Tensor:
        space = self.state_space
        rates = torch.tensor(RATES, dtype=torch.float64).expand(signal.shape[0], 3)
        q = space.generator(rates)
        return lumped_class_step(q, self.classes((space.states,)), 3, dt)


@pytest.fixture(scope="module")
def classed():
    internal = erlang_model(ClassedErlang)
    phis = run(FullDecision(internal), seed=0)
    return internal, dwells(phis, 0), dwells(phis, 1)


def test_a_hidden_sub_state_defeats_the_two_state_chain_and_not_the_class_chain(classed):
    internal, off, on = classed
    assert off.size > 5000 and on.size > 5000
    psi = internal.exact_psi

    def lumped(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        p = psi(z.double(), DT)
        return p.gather(1, phi.long().unsqueeze(1)).squeeze(1).float()

    d, critical = ks(off, dwells(run(AbstractDecision(lumped, internal), seed=1), 0))
    assert d > 3 * critical, (d, critical)
    chain = ClassDecision(exact_class_table(internal, DT, size=8), internal)
    phis = run(chain, seed=1)
    for full, chained in ((off, dwells(phis, 0)), (on, dwells(phis, 1))):
        d, critical = ks(full, chained)
        assert d < critical, (d, critical)

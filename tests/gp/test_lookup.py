"""PsiLookupTable: multilinear interpolation error, exactness at nodes, clamping, export, over
one, two and three input axes."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
import torch
from torch import Tensor

from surrogate.errors import ArtefactError, ConfigError, NumericalError
from surrogate.gp import (
    GPSettings,
    PsiClassifier,
    PsiLookupTable,
    StackedPsiLookup,
    fit_classifier,
)
from surrogate.gp import fast as fast_module
from surrogate.gp.fast import CachedPsi
from surrogate.gp.lookup import grid_nodes

W = 0.1
M_BOX = (1.0, 3.5)
L_BOX = (0.0, 0.1)
BOX = [M_BOX, L_BOX]
NAMES = ("m", "L")
MAX_S2 = 1.0 / (6.0 * math.sqrt(3.0))  # max |sigmoid''|


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def analytic(phi: Tensor, z: Tensor) -> Tensor:
    """A psi-like surface over z = (m, L) with known curvature: s = sigmoid((2.2 + 10 L - m) / w)."""
    z = z.double()
    s = torch.sigmoid((2.2 + 10.0 * z[:, 1] - z[:, 0]) / W)
    return torch.where(phi.bool(), 0.05 + 0.9 * s, 0.3 * s)


def bilinear_bound(n: int) -> float:
    """Max bilinear error at a cell centre: (h^2 |f_mm| + k^2 |f_LL|) / 8.

    f = 0.9 s((m0(L) - m)/w) has f_mm = 0.9 s''/w^2 and f_LL = 0.9 * 100 s''/w^2 (dm0/dL = 10);
    both peak together, so the leading-order worst case is their sum at max |s''|.
    """
    h = (M_BOX[1] - M_BOX[0]) / (n - 1)
    k = (L_BOX[1] - L_BOX[0]) / (n - 1)
    return 0.9 * (h * h + 100.0 * k * k) / 8.0 * MAX_S2 / W**2


def mL(m: Tensor, L: Tensor) -> Tensor:
    return torch.stack([m, L], 1)


def test_deviation_matches_theory_and_shrinks() -> None:
    devs = {}
    for n in (33, 65, 129):
        table = PsiLookupTable.from_function(analytic, BOX, NAMES, (n, n))
        devs[n] = table.max_deviation(analytic)
        # Upper: the bound plus float32 rounding of table and arithmetic (~1e-7).
        assert devs[n] <= bilinear_bound(n) + 1e-6
        # Lower: cell centres fall within h/2 of the curvature peak, where |s''| is within a few
        # per cent of its max; 0.9 leaves room for that and O(h^4) terms.
        assert devs[n] >= 0.9 * bilinear_bound(n)
    # Second-order method: halving h divides the error by ~4 (3.5..4.5 allows O(h^4) terms).
    for coarse, fine in ((33, 65), (65, 129)):
        assert 3.5 < devs[coarse] / devs[fine] < 4.5


def test_deviation_subset_is_at_most_full() -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (40, 30))
    full = table.max_deviation(analytic, n_check=None)
    assert table.max_deviation(analytic, n_check=10**9) == full  # more than there are: all
    part = table.max_deviation(analytic, n_check=200, seed=1)
    assert 0 < part <= full
    assert part != table.max_deviation(analytic, n_check=200, seed=2)  # another subset
    with pytest.raises(ConfigError, match="n_check"):
        table.max_deviation(analytic, n_check=0)


def test_full_deviation_is_over_every_cell_centre() -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (12, 9))
    m_nodes, L_nodes = table.nodes()
    m_mid = 0.5 * (m_nodes[:-1] + m_nodes[1:])
    L_mid = 0.5 * (L_nodes[:-1] + L_nodes[1:])
    mm, ll = torch.meshgrid(m_mid, L_mid, indexing="ij")
    z = mL(mm.reshape(-1), ll.reshape(-1)).float()
    worst = 0.0
    for value in (0, 1):
        phi = torch.full((z.shape[0],), value)
        err = (table(phi, z).double() - analytic(phi, z)).abs().max().item()
        worst = max(worst, err)
    assert table.max_deviation(analytic, n_check=None) == pytest.approx(worst, rel=0, abs=1e-12)


def test_exact_at_nodes_on_binary_grid() -> None:
    # Node spacings 2^-6 in m and 2^-10 in L are exact in float32, so the fractional offsets
    # are exactly 0 and interpolation must return the stored node value bit for bit.
    table = PsiLookupTable.from_function(analytic, [(0.0, 4.0), (0.0, 0.125)], NAMES, (257, 129))
    assert table.shape == (257, 129)
    m_nodes, L_nodes = table.nodes()
    gen = torch.Generator().manual_seed(0)
    i = torch.randint(0, 257, (5000,), generator=gen)
    j = torch.randint(0, 129, (5000,), generator=gen)
    phi = torch.randint(0, 2, (5000,), generator=gen)
    # Include the four corners (upper edges use the last cell with fraction 1).
    i[:4] = torch.tensor([0, 0, 256, 256])
    j[:4] = torch.tensor([0, 128, 0, 128])
    got = table(phi, mL(m_nodes[i], L_nodes[j]).float())
    assert torch.equal(got, table.table[phi, i, j])


def test_nodes_on_generic_grid() -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (256, 256))
    m_nodes, L_nodes = table.nodes()
    gen = torch.Generator().manual_seed(1)
    i = torch.randint(0, 256, (5000,), generator=gen)
    j = torch.randint(0, 256, (5000,), generator=gen)
    phi = torch.randint(0, 2, (5000,), generator=gen)
    got = table(phi, mL(m_nodes[i], L_nodes[j]))
    # Off-binary nodes carry float32 rounding in the index, |du| <= ~2e-5 cells (m ~ 3.5 with
    # relative error 6e-8, times 102 cells per unit m); times a neighbour difference <= 0.3
    # this is < 1e-5.
    torch.testing.assert_close(got, table.table[phi, i, j], atol=1e-5, rtol=0)


def test_matches_manual_bilinear_between_nodes() -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (11, 6))
    # Point at 30% of the way in m and 75% in L inside cell (i=4, j=2), phi = 1.
    h, k = 0.25, 0.02
    m = torch.tensor([M_BOX[0] + (4 + 0.3) * h])
    L = torch.tensor([L_BOX[0] + (2 + 0.75) * k])
    t = table.table[1].double()
    expected = (
        0.7 * 0.25 * t[4, 2] + 0.7 * 0.75 * t[4, 3] + 0.3 * 0.25 * t[5, 2] + 0.3 * 0.75 * t[5, 3]
    )
    got = table(torch.tensor([1]), mL(m, L))
    assert got.item() == pytest.approx(expected.item(), abs=1e-6)  # float32 arithmetic


def test_clamps_outside_the_box() -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (64, 32))
    table.check_finite = False  # inf is clamped like any out-of-box value when unchecked
    phi = torch.tensor([0, 1, 1, 0, 1])
    m = torch.tensor([-10.0, 99.0, 2.0, 0.0, 2.5])
    L = torch.tensor([0.05, 0.05, -1.0, 5.0, float("inf")])
    inside_m = torch.tensor([M_BOX[0], M_BOX[1], 2.0, M_BOX[0], 2.5])
    inside_L = torch.tensor([0.05, 0.05, L_BOX[0], L_BOX[1], L_BOX[1]])
    assert torch.equal(table(phi, mL(m, L)), table(phi, mL(inside_m, inside_L)))


def test_nan_propagates_without_bad_index() -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (16, 16))
    z = torch.tensor([[float("nan"), 0.0], [2.0, 0.05], [2.0, float("nan")]])
    with pytest.raises(NumericalError, match="NaN"):
        table(torch.tensor([1, 0, 1]), z)
    out = table.evaluate(torch.tensor([1, 0, 1]), z)  # the unchecked form
    assert math.isnan(out[0].item()) and math.isfinite(out[1].item())
    assert math.isnan(out[2].item())
    table.check_finite = False
    assert torch.equal(table(torch.tensor([1, 0, 1]), z).isnan(), out.isnan())


def test_nan_propagates_through_the_compiled_interpolation() -> None:
    """Compiled, a NaN input's node index is whatever the C++ conversion gives (clamped into
    range); its output must still be NaN and its neighbours' values unchanged."""
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (16, 16))
    z = torch.tensor([[float("nan"), 0.0], [2.0, 0.05], [2.0, float("nan")], [2.5, 0.02]])
    phi = torch.tensor([1, 0, 1, 0])
    compiled = torch.compile(table.evaluate)
    out = compiled(phi, z)
    assert out.isnan().tolist() == [True, False, True, False]
    eager = table.evaluate(phi, z)
    torch.testing.assert_close(out[~out.isnan()], eager[~eager.isnan()], rtol=0, atol=1e-6)


def test_phi_selects_layer() -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (32, 32))
    z = mL(torch.full((3,), 1.2), torch.full((3,), 0.05))
    # Far below m0: phi = 1 layer ~ 0.95, phi = 0 layer ~ 0.3 (the analytic caps).
    one = table(torch.ones(3, dtype=torch.long), z)
    zero = table(torch.zeros(3, dtype=torch.bool), z)
    assert bool((one > 0.9).all()) and bool((zero < 0.31).all())


def test_state_round_trip(tmp_path: Path) -> None:
    table = PsiLookupTable.from_function(analytic, BOX, NAMES, (20, 10))
    state = table.to_state()
    assert state["format"] == "surrogate.gp.lookup/2"
    assert state["input_names"] == list(NAMES) and state["ranges"] == [list(M_BOX), list(L_BOX)]
    torch.save(state, tmp_path / "t.pt")
    loaded = PsiLookupTable.from_state(torch.load(tmp_path / "t.pt", weights_only=True))
    assert torch.equal(loaded.table, table.table)
    assert loaded.input_names == NAMES and loaded.domain == {"m": M_BOX, "L": L_BOX}
    gen = torch.Generator().manual_seed(2)
    m = 1.0 + 2.5 * torch.rand(1000, generator=gen)
    L = 0.1 * torch.rand(1000, generator=gen)
    phi = torch.randint(0, 2, (1000,), generator=gen)
    assert torch.equal(loaded(phi, mL(m, L)), table(phi, mL(m, L)))
    with pytest.raises(ArtefactError):
        PsiLookupTable.from_state({"table": table.table})
    with pytest.raises(ArtefactError, match="lookup/2"):  # the old (m, L)-only format
        PsiLookupTable.from_state({**state, "format": "surrogate.gp.lookup/1"})


def test_bad_sizes() -> None:
    with pytest.raises(ConfigError, match="size"):
        PsiLookupTable.from_function(analytic, BOX, NAMES, (1, 10))
    with pytest.raises(ConfigError, match="size"):  # one size per axis
        PsiLookupTable.from_function(analytic, BOX, NAMES, (10,))
    with pytest.raises(ConfigError, match="lo < hi"):
        PsiLookupTable.from_function(analytic, [(3.0, 1.0), L_BOX], NAMES, (8, 8))
    with pytest.raises(ConfigError, match="lo < hi"):
        PsiLookupTable(torch.zeros(2, 4), [(1.0, 1.0)])


def test_bad_shapes() -> None:
    with pytest.raises(ConfigError, match="shape"):  # four axes: beyond the supported three
        PsiLookupTable(torch.zeros(2, 2, 2, 2, 2), [(0.0, 1.0)] * 4)
    with pytest.raises(ConfigError, match="shape"):  # no input axis
        PsiLookupTable(torch.zeros(2), [])
    with pytest.raises(ConfigError, match="shape"):  # not two phi layers
        PsiLookupTable(torch.zeros(3, 4), [(0.0, 1.0)])
    with pytest.raises(ConfigError, match="shape"):  # a single node on an axis
        PsiLookupTable(torch.zeros(2, 4, 1), [(0.0, 1.0), (0.0, 1.0)])
    with pytest.raises(ConfigError, match="ranges"):
        PsiLookupTable(torch.zeros(2, 4, 4), [(0.0, 1.0)])
    with pytest.raises(ConfigError, match="names"):
        PsiLookupTable(torch.zeros(2, 4, 4), BOX, ("m",))


def test_default_sizes_and_names() -> None:
    one = PsiLookupTable.from_function(lambda phi, z: z[:, 0].sigmoid(), [(-5.0, 5.0)])
    assert one.shape == (4096,) and one.input_names == ("x0",)
    two = PsiLookupTable.from_function(analytic, BOX)
    assert two.shape == (256, 256) and two.input_names == ("x0", "x1")
    assert two.domain == {"x0": M_BOX, "x1": L_BOX}


def test_from_gp_classifier() -> None:
    gen = torch.Generator().manual_seed(3)
    x = mL(1.0 + 2.5 * torch.rand(600, generator=gen), 0.1 * torch.rand(600, generator=gen))
    y = torch.bernoulli(analytic(torch.ones(600), x), generator=gen)
    settings = GPSettings(n_inducing=10, epochs=3, batch_size=200)
    fitted = fit_classifier(x, y, settings, progress=False)
    psi = PsiClassifier(fitted, fitted, NAMES)
    coarse = PsiLookupTable.from_function(psi, BOX, NAMES, (16, 16)).max_deviation(psi)
    fine = PsiLookupTable.from_function(psi, BOX, NAMES, (128, 128)).max_deviation(psi)
    # h shrinks 8.5x, so a second-order error should shrink ~70x; ask for 8x.
    assert fine < coarse / 8
    # Table values on both layers come from the classifier.
    table = PsiLookupTable.from_function(psi, BOX, NAMES, (16, 16))
    assert table.table.dtype == torch.float32 and table.table.shape == (2, 16, 16)
    m_nodes, L_nodes = table.nodes()
    z = mL(m_nodes[[0, 5, 15]], L_nodes[[3, 9, 15]]).float()
    expected = psi(torch.tensor([0, 1, 1]), z)
    torch.testing.assert_close(table.table[[0, 1, 1], [0, 5, 15], [3, 9, 15]], expected)


def _two_classifiers(d: int) -> PsiClassifier:
    """psi_0 and psi_1 fitted on different data over (m[, L]): the layers differ."""
    gen = torch.Generator().manual_seed(4)
    x = mL(1.0 + 2.5 * torch.rand(600, generator=gen), 0.1 * torch.rand(600, generator=gen))
    x = x[:, :d].contiguous()
    settings = GPSettings(kernel="matern52", n_inducing=12, epochs=3, batch_size=200)
    logit = 4.0 * (x[:, 0] - 2.2 - (10.0 * x[:, 1] if d > 1 else 0.5))
    fitted = []
    for phi in (0, 1):  # the origin shifts the surface
        y = torch.bernoulli(torch.sigmoid(logit + 2.0 * phi - 1.0), generator=gen)
        fitted.append(fit_classifier(x, y, settings, progress=False))
    return PsiClassifier(fitted[0], fitted[1], NAMES[:d])


@pytest.mark.parametrize("d", [1, 2])
def test_gp_table_is_tabulated_in_closed_form(d: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """A classifier's table comes from its tabulator (CachedPsi.tabulate, ~10x faster than
    gpytorch on a table's grid), in several chunks, and equals the classifier at every node
    of both layers to 2e-5: both evaluate one predictive in float32, rounded in another
    order, and gpytorch's own float32 round-off on such models is ~1e-5 (tests/gp/test_fast.py).
    """
    psi = _two_classifiers(d)
    calls = []
    tabulate = CachedPsi.tabulate

    def counting(self: CachedPsi, phi: Tensor, z: Tensor) -> Tensor:
        calls.append(z.shape[0])
        return tabulate(self, phi, z)

    monkeypatch.setattr(CachedPsi, "tabulate", counting)
    monkeypatch.setattr(fast_module, "TABULATE_ROWS", 128)  # several chunks per layer
    size = (300,) if d == 1 else (24, 17)
    table = PsiLookupTable.from_function(psi, BOX[:d], NAMES[:d], size)
    grid = grid_nodes(BOX[:d], size).float()
    assert calls == [grid.shape[0]] * 2  # one call per layer, through the tabulator
    for phi in (0, 1):
        expected = psi(torch.full((grid.shape[0],), phi), grid).reshape(size)
        assert (expected.max() - expected.min()).item() > 0.1  # a surface that varies
        assert (table.table[phi] - expected).abs().max().item() < 2e-5
    assert (table.table[1] - table.table[0]).abs().max().item() > 0.1  # layers differ


def test_gp_table_without_closed_form_uses_the_classifier(monkeypatch: pytest.MonkeyPatch) -> None:
    """A model CachedPsi does not cover (TypeError) is tabulated by the classifier itself."""
    psi = _two_classifiers(2)

    def refuse(*args: object, **kwargs: object) -> CachedPsi:
        raise TypeError("not covered")

    monkeypatch.setattr(CachedPsi, "from_classifier", refuse)
    assert psi.tabulator() is psi
    table = PsiLookupTable.from_function(psi, BOX, NAMES, (9, 7))
    grid = grid_nodes(BOX, (9, 7)).float()
    for phi in (0, 1):
        expected = psi(torch.full((63,), phi), grid).reshape(9, 7)
        assert torch.equal(table.table[phi], expected)


# ----------------------------------------------------------------------------------------------
# one axis


def sig1(phi: Tensor, z: Tensor) -> Tensor:
    """A 1-D psi with known curvature: 0.3 s or 0.05 + 0.9 s, s = sigmoid((x - 0.5) / w)."""
    s = torch.sigmoid((z.double().reshape(-1) - 0.5) / W)
    return torch.where(phi.bool(), 0.05 + 0.9 * s, 0.3 * s)


def test_one_axis_linear_error_matches_theory() -> None:
    devs = {}
    for n in (33, 65, 129):
        table = PsiLookupTable.from_function(sig1, [(0.0, 1.0)], ("dG",), (n,))
        assert table.table.shape == (2, n)
        devs[n] = table.max_deviation(sig1, n_check=None)
        bound = 0.9 * (1.0 / (n - 1)) ** 2 / 8.0 * MAX_S2 / W**2  # h^2 max|f''| / 8
        assert 0.9 * bound <= devs[n] <= bound + 1e-6
    for coarse, fine in ((33, 65), (65, 129)):
        assert 3.5 < devs[coarse] / devs[fine] < 4.5


def test_one_axis_nodes_between_and_outside() -> None:
    # 17 nodes on [0, 2]: spacing 1/8, exact in float32
    table = PsiLookupTable.from_function(sig1, [(0.0, 2.0)], ("dG",), (17,))
    (nodes,) = table.nodes()
    assert nodes.shape == (17,) and table.domain == {"dG": (0.0, 2.0)}
    phi = torch.tensor([0, 1, 1, 0, 1, 0, 1])
    # nodes (as n x 1 and as a flat vector), 40 % into cell 3, and clamped outside the box
    z = torch.tensor([[0.0], [0.125], [2.0], [0.375 + 0.4 * 0.125], [-7.0], [9.0], [2.0]])
    got = table(phi, z)
    assert torch.equal(table(phi, z.reshape(-1)), got)
    t = table.table
    assert got[0].item() == t[0, 0].item() and got[1].item() == t[1, 1].item()
    assert got[2].item() == t[1, 16].item()
    assert got[3].item() == pytest.approx((0.6 * t[0, 3] + 0.4 * t[0, 4]).item(), abs=1e-7)
    assert got[4].item() == t[1, 0].item() and got[5].item() == t[0, 16].item()
    assert got[6].item() == t[1, 16].item()
    out = table.evaluate(torch.tensor([1, 0]), torch.tensor([[float("nan")], [1.0]]))
    assert math.isnan(out[0].item()) and math.isfinite(out[1].item())


# ----------------------------------------------------------------------------------------------
# three axes

RANGES3 = [(-1.0, 2.0), (0.0, 0.5), (10.0, 30.0)]
SHAPE3 = (5, 7, 4)


def multilinear(phi: Tensor, z: Tensor) -> Tensor:
    """A function that is linear in each input separately, different per layer: multilinear
    interpolation must reproduce it everywhere in the box, whatever the grid."""
    z = z.double()
    x, y, w = z[:, 0], z[:, 1], (z[:, 2] - 20.0) / 10.0
    base = 0.3 + 0.1 * x - 0.4 * y + 0.2 * w + 0.05 * x * y - 0.1 * x * w + 0.3 * y * w
    f1 = base + 0.2 * x * y * w
    f0 = 0.5 - 0.1 * x + 0.6 * y * w - 0.07 * x * y * w
    return torch.where(phi.bool(), f1, f0)


def _uniform_in(ranges: list[tuple[float, float]], n: int, seed: int) -> Tensor:
    gen = torch.Generator().manual_seed(seed)
    cols = [lo + (hi - lo) * torch.rand(n, generator=gen) for lo, hi in ranges]
    return torch.stack(cols, 1)


def test_three_axes_reproduce_multilinear_functions() -> None:
    table = PsiLookupTable.from_function(multilinear, RANGES3, ("a", "b", "c"), SHAPE3)
    assert table.shape == SHAPE3 and table.table.shape == (2, *SHAPE3)
    z = _uniform_in(RANGES3, 5000, seed=0)
    phi = torch.randint(0, 2, (5000,), generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(table(phi, z).double(), multilinear(phi, z), atol=2e-6, rtol=0)
    assert table.max_deviation(multilinear, n_check=None) < 2e-6


def test_three_axes_interpolate_nonlinear_functions_by_hand() -> None:
    """Against an explicit trilinear sum over the 8 corners of a random table (a function no
    lower-order scheme could match); a mixed-up axis or stride would pick other corners."""
    gen = torch.Generator().manual_seed(4)
    values = torch.rand(2, *SHAPE3, generator=gen)
    table = PsiLookupTable(values, RANGES3, ("a", "b", "c"))
    z = _uniform_in(RANGES3, 300, seed=5)
    phi = torch.randint(0, 2, (300,), generator=gen)
    got = table(phi, z).double()
    expected = torch.empty(300, dtype=torch.float64)
    for r in range(300):
        idx, frac = [], []
        for a, (n, (lo, hi)) in enumerate(zip(SHAPE3, RANGES3, strict=True)):
            u = (z[r, a].double().item() - lo) / (hi - lo) * (n - 1)
            i = min(math.floor(u), n - 2)
            idx.append(i)
            frac.append(u - i)
        total = 0.0
        for bits in itertools.product((0, 1), repeat=3):
            weight = math.prod(f if b else 1.0 - f for f, b in zip(frac, bits, strict=True))
            corner = [i + b for i, b in zip(idx, bits, strict=True)]
            total += weight * values[int(phi[r]), corner[0], corner[1], corner[2]].item()
        expected[r] = total
    torch.testing.assert_close(got, expected, atol=2e-6, rtol=0)


def test_three_axes_nodes_clamp_and_round_trip(tmp_path: Path) -> None:
    gen = torch.Generator().manual_seed(6)
    values = torch.rand(2, *SHAPE3, generator=gen)
    table = PsiLookupTable(values, RANGES3, ("a", "b", "c"))
    nodes = table.nodes()
    assert [len(g) for g in nodes] == list(SHAPE3)
    i, j, k = (torch.randint(0, n, (500,), generator=gen) for n in SHAPE3)
    phi = torch.randint(0, 2, (500,), generator=gen)
    z = torch.stack([nodes[0][i], nodes[1][j], nodes[2][k]], 1).float()
    torch.testing.assert_close(table(phi, z), values[phi, i, j, k], atol=1e-6, rtol=0)
    # outside the box on every axis at once: the nearest corner
    far = torch.tensor([[-9.0, 9.0, -99.0], [9.0, -9.0, 99.0]])
    assert torch.equal(table(torch.tensor([0, 1]), far), values[[0, 1], [0, 4], [6, 0], [0, 3]])
    torch.save(table.to_state(), tmp_path / "t3.pt")
    loaded = PsiLookupTable.from_state(torch.load(tmp_path / "t3.pt", weights_only=True))
    assert loaded.input_names == ("a", "b", "c") and loaded.ranges == RANGES3
    z = _uniform_in(RANGES3, 1000, seed=7)
    phi = torch.randint(0, 2, (1000,), generator=gen)
    assert torch.equal(loaded(phi, z), table(phi, z))


def test_stacked_tables_give_each_block_its_own_table_bit_for_bit() -> None:
    """Blocks of cells in one stacked interpolation: each block's values are exactly its own
    table's (own box, clamping and NaN included); tables of other shapes are refused."""
    gen = torch.Generator().manual_seed(0)
    tables = [
        PsiLookupTable(torch.rand(2, 17, 9, generator=gen), [(-1.0, 2.0), (0.0, 5.0)], ("a", "b")),
        PsiLookupTable(torch.rand(2, 17, 9, generator=gen), [(-3.0, 1.5), (1.0, 2.0)], ("a", "b")),
        PsiLookupTable(torch.rand(2, 17, 9, generator=gen), [(0.0, 9.0), (-2.0, 7.0)], ("a", "b")),
    ]
    sizes = [5, 7, 6]
    z = torch.rand(sum(sizes), 2, generator=gen) * 14.0 - 5.0  # inside and outside the boxes
    z[3, 0] = float("nan")
    phi = torch.randint(0, 2, (sum(sizes),), generator=gen)
    stacked = StackedPsiLookup(tables, sizes)
    out = stacked(phi, z)
    parts = [t.evaluate(p, q) for t, p, q in
             zip(tables, phi.split(sizes), z.split(sizes), strict=True)]  # fmt: skip
    assert torch.equal(out.isnan(), torch.cat(parts).isnan()) and bool(out[3].isnan())
    assert torch.equal(out.nan_to_num(-1.0), torch.cat(parts).nan_to_num(-1.0))
    other = PsiLookupTable(torch.rand(2, 17, 8), [(0.0, 1.0), (0.0, 1.0)], ("a", "b"))
    with pytest.raises(ValueError, match="one shape"):
        StackedPsiLookup([tables[0], other], [1, 1])
    with pytest.raises(ValueError, match="one size per table"):
        StackedPsiLookup(tables, [1, 2])

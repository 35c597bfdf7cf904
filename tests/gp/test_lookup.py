"""PsiLookupTable: bilinear interpolation error, exactness at nodes, clamping, export."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from torch import Tensor

from surrogate.errors import ArtefactError, ConfigError
from surrogate.gp import GPSettings, PsiClassifier, PsiLookupTable, fit_classifier

W = 0.1
M_BOX = (1.0, 3.5)
L_BOX = (0.0, 0.1)
MAX_S2 = 1.0 / (6.0 * math.sqrt(3.0))  # max |sigmoid''|


@pytest.fixture(autouse=True, scope="module")
def _one_thread() -> Iterator[None]:
    # Shared 2-core machine: avoid OpenMP oversubscription with other test processes.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def analytic(phi: Tensor, m: Tensor, L: Tensor) -> Tensor:
    """A psi-like surface with known curvature: s = sigmoid((2.2 + 10 L - m) / w)."""
    s = torch.sigmoid((2.2 + 10.0 * L.double() - m.double()) / W)
    return torch.where(phi.bool(), 0.05 + 0.9 * s, 0.3 * s)


def bilinear_bound(n: int) -> float:
    """Max bilinear error at a cell centre: (h^2 |f_mm| + k^2 |f_LL|) / 8.

    f = 0.9 s((m0(L) - m)/w) has f_mm = 0.9 s''/w^2 and f_LL = 0.9 * 100 s''/w^2 (dm0/dL = 10);
    both peak together, so the leading-order worst case is their sum at max |s''|.
    """
    h = (M_BOX[1] - M_BOX[0]) / (n - 1)
    k = (L_BOX[1] - L_BOX[0]) / (n - 1)
    return 0.9 * (h * h + 100.0 * k * k) / 8.0 * MAX_S2 / W**2


def test_deviation_matches_theory_and_shrinks() -> None:
    devs = {}
    for n in (33, 65, 129):
        table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (n, n))
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
    table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (40, 30))
    full = table.max_deviation(analytic)
    part = table.max_deviation(analytic, n_check=200, seed=1)
    assert 0 < part <= full


def test_exact_at_nodes_on_binary_grid() -> None:
    # Node spacings 2^-6 in m and 2^-10 in L are exact in float32, so the fractional offsets
    # are exactly 0 and interpolation must return the stored node value bit for bit.
    table = PsiLookupTable.from_classifier(analytic, (0.0, 4.0), (0.0, 0.125), (257, 129))
    m_nodes, L_nodes = table.grid()
    gen = torch.Generator().manual_seed(0)
    i = torch.randint(0, 257, (5000,), generator=gen)
    j = torch.randint(0, 129, (5000,), generator=gen)
    phi = torch.randint(0, 2, (5000,), generator=gen)
    # Include the four corners (upper edges use the last cell with fraction 1).
    i[:4] = torch.tensor([0, 0, 256, 256])
    j[:4] = torch.tensor([0, 128, 0, 128])
    got = table(phi, m_nodes[i].float(), L_nodes[j].float())
    assert torch.equal(got, table.table[phi, i, j])


def test_nodes_on_generic_grid() -> None:
    table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (256, 256))
    m_nodes, L_nodes = table.grid()
    gen = torch.Generator().manual_seed(1)
    i = torch.randint(0, 256, (5000,), generator=gen)
    j = torch.randint(0, 256, (5000,), generator=gen)
    phi = torch.randint(0, 2, (5000,), generator=gen)
    got = table(phi, m_nodes[i], L_nodes[j])
    # Off-binary nodes carry float32 rounding in the index, |du| <= ~2e-5 cells (m ~ 3.5 with
    # relative error 6e-8, times 102 cells per unit m); times a neighbour difference <= 0.3
    # this is < 1e-5.
    torch.testing.assert_close(got, table.table[phi, i, j], atol=1e-5, rtol=0)


def test_matches_manual_bilinear_between_nodes() -> None:
    table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (11, 6))
    # Point at 30% of the way in m and 75% in L inside cell (i=4, j=2), phi = RUN.
    h, k = 0.25, 0.02
    m = torch.tensor([M_BOX[0] + (4 + 0.3) * h])
    L = torch.tensor([L_BOX[0] + (2 + 0.75) * k])
    t = table.table[1].double()
    expected = (
        0.7 * 0.25 * t[4, 2] + 0.7 * 0.75 * t[4, 3] + 0.3 * 0.25 * t[5, 2] + 0.3 * 0.75 * t[5, 3]
    )
    got = table(torch.tensor([1]), m, L)
    assert got.item() == pytest.approx(expected.item(), abs=1e-6)  # float32 arithmetic


def test_clamps_outside_the_box() -> None:
    table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (64, 32))
    table.check_finite = False  # inf is clamped like any out-of-box value when unchecked
    phi = torch.tensor([0, 1, 1, 0, 1])
    m = torch.tensor([-10.0, 99.0, 2.0, 0.0, 2.5])
    L = torch.tensor([0.05, 0.05, -1.0, 5.0, float("inf")])
    inside_m = torch.tensor([M_BOX[0], M_BOX[1], 2.0, M_BOX[0], 2.5])
    inside_L = torch.tensor([0.05, 0.05, L_BOX[0], L_BOX[1], L_BOX[1]])
    assert torch.equal(table(phi, m, L), table(phi, inside_m, inside_L))


def test_nan_propagates_without_bad_index() -> None:
    table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (16, 16))
    table.check_finite = False
    out = table(torch.tensor([1, 0]), torch.tensor([float("nan"), 2.0]), torch.tensor([0.0, 0.05]))
    assert math.isnan(out[0].item()) and math.isfinite(out[1].item())


def test_phi_selects_layer() -> None:
    table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (32, 32))
    m = torch.full((3,), 1.2)
    L = torch.full((3,), 0.05)
    # Far below m0: RUN layer ~ 0.95, TUMBLE layer ~ 0.3 (the analytic caps).
    run = table(torch.ones(3, dtype=torch.long), m, L)
    tumble = table(torch.zeros(3, dtype=torch.bool), m, L)
    assert bool((run > 0.9).all()) and bool((tumble < 0.31).all())


def test_state_round_trip(tmp_path: Path) -> None:
    table = PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (20, 10))
    torch.save(table.to_state(), tmp_path / "t.pt")
    loaded = PsiLookupTable.from_state(torch.load(tmp_path / "t.pt", weights_only=True))
    assert torch.equal(loaded.table, table.table)
    gen = torch.Generator().manual_seed(2)
    m = 1.0 + 2.5 * torch.rand(1000, generator=gen)
    L = 0.1 * torch.rand(1000, generator=gen)
    phi = torch.randint(0, 2, (1000,), generator=gen)
    assert torch.equal(loaded(phi, m, L), table(phi, m, L))
    with pytest.raises(ArtefactError):
        PsiLookupTable.from_state({"table": table.table})


def test_bad_sizes() -> None:
    with pytest.raises(ConfigError, match="size"):
        PsiLookupTable.from_classifier(analytic, M_BOX, L_BOX, (1, 10))
    with pytest.raises(ConfigError, match="m_range"):
        PsiLookupTable.from_classifier(analytic, (3.0, 1.0), L_BOX, (8, 8))


def test_from_gp_classifier() -> None:
    gen = torch.Generator().manual_seed(3)
    x = torch.stack(
        [1.0 + 2.5 * torch.rand(600, generator=gen), 0.1 * torch.rand(600, generator=gen)], 1
    )
    y = torch.bernoulli(analytic(torch.ones(600), x[:, 0], x[:, 1]), generator=gen)
    settings = GPSettings(n_inducing=10, epochs=3, batch_size=200)
    fitted = fit_classifier(x, y, settings, progress=False)
    psi = PsiClassifier(fitted, fitted)
    coarse = PsiLookupTable.from_classifier(psi, M_BOX, L_BOX, (16, 16)).max_deviation(psi)
    fine = PsiLookupTable.from_classifier(psi, M_BOX, L_BOX, (128, 128)).max_deviation(psi)
    # h shrinks 8.5x, so a second-order error should shrink ~70x; ask for 8x.
    assert fine < coarse / 8
    # Table values on both layers come from the classifier.
    table = PsiLookupTable.from_classifier(psi, M_BOX, L_BOX, (16, 16))
    assert table.table.dtype == torch.float32 and table.table.shape == (2, 16, 16)

"""The engine's per-cell decision steps (surrogate.models.decision_kernel) against the torch layers,
without a model: psi's lookup against PsiLookupTable.evaluate (1-3 axes, inputs outside the
box and NaN; within an ulp, mostly equal), the K-lumps draw against ClassTable.draw (the same
uniforms: the same classes), the switch clock against memory.tick, and the segment
bookkeeping on a hand-made sequence."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import surrogate.models.decision_kernel as kd
from surrogate.errors import KernelUnsupported
from surrogate.gp import PsiLookupTable
from surrogate.models.packed import CHAIN, PackedBlock, PackedClock
from surrogate.simulate.classes import ClassTable
from surrogate.simulate.kernel_pack import pack_class_table, pack_tables
from surrogate.simulate.memory import tick

N = 400


def _table(d: int) -> PsiLookupTable:
    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        s = z.sum(1)
        return torch.where(phi > 0, torch.sigmoid(s - 1.0), torch.sigmoid(0.5 - s))

    bounds = [(-1.0, 2.0), (0.0, 0.5), (1.0, 4.0)][:d]
    size = {1: (64,), 2: (16, 12), 3: (8, 6, 5)}[d]
    return PsiLookupTable.from_function(psi, bounds, ("a", "b", "c")[:d], size)


def _inputs(d: int, seed: int) -> torch.Tensor:
    """Inputs over and beyond each box, a few NaN."""
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(N, d, generator=g) * 6.0 - 2.0
    z[:5, 0] = float("nan")
    return z


@pytest.mark.parametrize("d", [1, 2, 3])
def test_lookup_is_the_tables_interpolation(d: int) -> None:
    table = _table(d)
    packed, why = pack_tables(table, None)
    assert packed is not None and why is None
    # the features come in the kernel's own order: reversed here, mapped back by the indices
    pack = kd.chain_pack(packed, np.arange(d)[::-1].copy(), 0, packed.table_of_cell(N))
    z = _inputs(d, seed=d)
    phi = (torch.arange(N) % 2).float()
    expected = table.evaluate(phi, z).numpy()
    got = [kd.lookup(np.float32(phi[i]), 0, tuple(np.float32(v) for v in z[i].flip(0)),
                     np.float32(0.0), pack) for i in range(N)]  # fmt: skip
    # a float32 result comes back as a Python float (exact): compare in float32; torch's
    # vectorised lerp may fuse a multiply-add (an ulp now and then), numba's does not
    got32 = np.array(got, dtype=np.float32)
    assert np.isnan(got32[:5]).all() and np.isnan(expected[:5]).all()
    np.testing.assert_array_max_ulp(got32[5:], expected[5:], maxulp=1)
    assert (got32[5:] == expected[5:]).mean() > 0.95


def test_a_chains_clock_is_psis_last_input_and_ticks_as_memory_tick() -> None:
    """The clock in steps, read as min(age * unit, cap) (CLOCK), restarts when phi changes."""
    table = _table(2)
    packed, _ = pack_tables(table, None)
    assert packed is not None
    clock = PackedClock(cap=0.4, unit=0.05)
    pack = kd.chain_pack(packed, np.array([0, kd.CLOCK]), 0, packed.table_of_cell(N), clock,
                         np.zeros(N, np.float32))  # fmt: skip
    g = torch.Generator().manual_seed(1)
    z, age = _inputs(1, seed=4), torch.randint(0, 20, (N,), generator=g).float()
    phi, u = (torch.rand(N, generator=g) < 0.5).float(), torch.rand(N, generator=g)
    read = torch.clamp(age * 0.05, max=0.4).float()
    p = table.evaluate(phi, torch.cat([z, read[:, None]], 1))
    phi_next = (u < p).float()
    for i in range(N):
        got = kd.chain_step(np.float32(phi[i]), np.float32(age[i]), 0, (np.float32(z[i, 0]),),
                            np.float32(u[i]), pack)  # fmt: skip
        assert got == (phi_next[i].item(), tick(age, phi, phi_next)[i].item())


@pytest.mark.parametrize("shape", [(9,), (7, 5)])
def test_class_step_is_class_table_draw_with_the_same_uniforms(shape: tuple[int, ...]) -> None:
    n_classes, d = 4, len(shape)
    g = torch.Generator().manual_seed(d)
    p = -torch.log(torch.rand(n_classes, *shape, n_classes, generator=g, dtype=torch.float64))
    table = ClassTable(p, [(-1.0, 2.0), (0.0, 0.5)][:d], ("a", "b")[:d],
                       [f"c{k}" for k in range(n_classes)], [k % 2 for k in range(n_classes)],
                       0.05)  # fmt: skip
    law, why = pack_class_table(table)
    assert law is not None and why is None
    z = _inputs(d, seed=7)
    origin = torch.randint(0, n_classes, (N,), generator=g)
    u = torch.rand(d + 1, N, generator=g)
    expected = table.draw(origin, z, u).numpy()
    pack = kd.class_pack(law, np.arange(d), 0, np.zeros(N, np.int64))
    u3 = u.numpy()[None]  # (steps, rows, n)
    got = [kd.class_step(int(origin[i]), tuple(np.float32(v) for v in z[i]), u3, 0, i, pack)
           for i in range(N)]  # fmt: skip
    np.testing.assert_array_equal(got, expected)


def test_account_ends_segments_when_phi_switches_the_first_left_censored() -> None:
    phis = [1, 1, 0, 0, 0, 1, 1, 0]
    cells = kd.Cells(np.zeros(1, np.uint8), np.zeros(1, np.int32), np.zeros(1, np.uint8),
                     np.zeros((len(phis), 1), np.int32))  # fmt: skip
    before = np.float32(1.0)
    for s, phi in enumerate(phis):
        kd.account(cells, 0, s, before, np.float32(phi))
        before = np.float32(phi)
    # the first run segment (censored) is not reported; then 3 tumble steps, 2 run steps
    assert cells.ended[:, 0].tolist() == [0, 0, 0, 0, 0, -3, 0, 2]
    assert int(cells.seg[0]) == 0 and int(cells.complete[0]) == 1


def test_feature_axes_append_the_clock_and_check_the_tables_axes() -> None:
    packed, _ = pack_tables(_table(2), None)
    block = PackedBlock(CHAIN, "MemoryDecision", 0, None, None, True, tables=packed,
                        clock=PackedClock(cap=1.0, unit=0.05))  # fmt: skip
    assert kd.feature_axes(block, [3]).tolist() == [3, kd.CLOCK]
    with pytest.raises(KernelUnsupported, match="3 features for a lookup table over 2 axes"):
        kd.feature_axes(block, [3, 4])  # two features and the clock

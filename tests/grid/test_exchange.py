"""Agents and the grid: bilinear reading, its adjoint deposit, Michaelis-Menten uptake (capped by
what a cell holds) and phi-dependent secretion, with exact accounting."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from surrogate.grid import MOLECULES_PER_NMOL, Grid, GridField, geometry, kernels

EPS = float(np.finfo(np.float64).eps)


def _grid(boundary) -> Grid:
    return Grid.from_config([[-1.0, 2.0], [0.0, 1.0]], [12, 8], boundary, depth=0.1)


def _inside(grid: Grid, n: int, seed: int) -> torch.Tensor:
    """Positions between the first and the last cell centre of each axis (float32)."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(grid.lower) + torch.tensor(grid.spacing) / 2
    hi = torch.tensor(grid.upper) - torch.tensor(grid.spacing) / 2
    return (lo + (hi - lo) * torch.rand(n, 2, generator=g, dtype=torch.float64)).float()


#: both implementations of the exchange (surrogate.grid.kernels on the CPU, torch's ops)
PATHS = pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])


@PATHS
@pytest.mark.parametrize("boundary", ["no_flux", "periodic"])
def test_bilinear_reading_is_exact_for_linear_fields(boundary: str, compiled: bool) -> None:
    grid = _grid(boundary)
    centres = grid.centres()
    f = 0.3 + 1.7 * centres[..., 0] - 0.4 * centres[..., 1]
    p = _inside(grid, 500, 0)
    p64 = p.double()
    want = 0.3 + 1.7 * p64[:, 0] - 0.4 * p64[:, 1]
    got = grid.stencil(p, compiled).interpolate(f)
    assert torch.allclose(got, want, rtol=0, atol=16 * EPS * float(want.abs().max()))


@PATHS
def test_a_no_flux_wall_reads_the_first_cell_and_a_periodic_edge_wraps(compiled: bool) -> None:
    wall, ring = _grid("no_flux"), _grid("periodic")
    f = torch.arange(96, dtype=torch.float64).reshape(12, 8)
    hx, hy = wall.spacing
    near_wall = torch.tensor([[-1.0 + hx / 4, 0.5 * hy], [-5.0, -3.0]])  # inside and beyond
    assert wall.stencil(near_wall, compiled).interpolate(f).tolist() == [0.0, 0.0]
    p = _inside(ring, 50, 1)
    shifted = p + torch.tensor([3.0, -2.0])  # whole periods
    got, want = ring.stencil(shifted, compiled).interpolate(f), ring.stencil(p).interpolate(f)
    assert torch.allclose(got, want, rtol=0, atol=1e-5 * float(f.max()))  # float32 positions


@PATHS
@pytest.mark.parametrize("boundary", ["no_flux", "periodic", ["periodic", "no_flux"]])
def test_the_deposit_is_the_adjoint_of_the_reading(boundary, compiled: bool) -> None:
    """<interpolate(f), w> = <f, deposit(w)> for any f and w, agents anywhere (also outside)."""
    grid = _grid(boundary)
    g = torch.Generator().manual_seed(2)
    p = (torch.rand(300, 2, generator=g) * 6 - 2).float()  # many outside the domain
    f = torch.rand(2, *grid.shape, generator=g, dtype=torch.float64)
    w = torch.rand(2, 300, generator=g, dtype=torch.float64)
    stencil = grid.stencil(p, compiled)
    lhs = (stencil.interpolate(f) * w).sum()
    rhs = (f * stencil.deposit(w)).sum()
    assert abs(float(lhs - rhs)) <= 8 * EPS * float((f.abs().max() * w.abs()).sum())
    # each agent's weights sum to one: the grid gets exactly what the agents give
    assert torch.allclose(stencil.deposit(w).sum((-2, -1)), w.sum(-1), rtol=4 * EPS, atol=0)


@pytest.mark.parametrize("boundary", ["no_flux", "periodic", ["no_flux", "periodic"]])
def test_the_compiled_exchange_is_torchs(boundary) -> None:
    """The compiled kernels read the same bytes as torch's ops (the same arithmetic per agent)
    and deposit the same amounts to float64 rounding (summed in another order), agents inside
    and outside the domain; the fused uptake deposit is the read, then the deposit. (A cell
    beyond a corner gathers ~5e4 agents, here of equal demand: summed in another order, the
    sums differ within the bound of a sequential sum's rounding, n eps relative.)"""
    grid = _grid(boundary)
    g = torch.Generator().manual_seed(4)
    p = (torch.rand(200_000, 2, generator=g) * 6 - 2).float()
    f = torch.rand(grid.shape, generator=g, dtype=torch.float64) - 0.2
    fast, slow = grid.stencil(p, compiled=True), grid.stencil(p, compiled=False)
    assert torch.equal(fast.interpolate(f), slow.interpolate(f))
    assert torch.equal(fast.read(f), slow.read(f)) and fast.read(f).dtype == torch.float32
    w = torch.rand(len(p), generator=g, dtype=torch.float64)
    bound = len(p) * EPS
    assert torch.allclose(fast.deposit(w), slow.deposit(w), rtol=bound, atol=0)
    got, want = fast.saturating_deposit(f, 3.0, 0.2), slow.saturating_deposit(f, 3.0, 0.2)
    assert torch.allclose(got, want, rtol=bound, atol=0)


@pytest.mark.parametrize("lanes", [2, 128])
def test_a_deposit_into_private_copies_is_the_one_copy_deposit(lanes, monkeypatch) -> None:
    """The GPU's deposit (agent a adds into copy a % lanes, the copies then summed, against
    atomics that serialise on crowded cells) gives the one-copy deposit to float64 rounding,
    species by species; forced on the CPU's torch path here (tests/simulate/test_coupling.py
    runs it on CUDA)."""
    grid = _grid("no_flux")
    g = torch.Generator().manual_seed(6)
    p = (torch.rand(5_000, 2, generator=g) * 0.3).float()  # crowded: ~40 agents per cell
    w = torch.rand(2, len(p), generator=g, dtype=torch.float64)
    want = grid.stencil(p, compiled=False).deposit(w)
    assert geometry.deposit_lanes(len(p), grid.n_cells, torch.device("cpu")) == 1
    monkeypatch.setattr(geometry, "deposit_lanes", lambda agents, cells, device: lanes)
    stencil = grid.stencil(p, compiled=False)
    assert stencil._lanes[0] == lanes
    got = stencil.deposit(w)
    assert torch.allclose(got, want, rtol=len(p) * EPS, atol=0)
    assert not torch.equal(got, torch.zeros_like(got))


def test_gpu_deposit_lanes_stay_within_their_memory() -> None:
    cuda = torch.device("cuda")
    assert geometry.deposit_lanes(10**6, 512 * 64, cuda) == 128
    assert geometry.deposit_lanes(10**6, 2048 * 2048, cuda) == 1  # 4M values: one copy
    assert geometry.deposit_lanes(10**6, 2**18, cuda) == 16  # 16 x 2^18 = LANE_VALUES
    assert geometry.deposit_lanes(3, 100, cuda) == 2  # no more copies than agents


def test_the_compiled_deposit_is_the_same_bytes_on_any_number_of_threads() -> None:
    """The deposit adds in pieces fixed by the sizes alone (kernels.deposit_pieces), not by the
    threads: the same bytes on one thread as on two (CPU runs are reproducible to the byte)."""
    grid = _grid("periodic")
    g = torch.Generator().manual_seed(5)
    p = (torch.rand(300_000, 2, generator=g) * 3).float()
    w = torch.rand(len(p), generator=g, dtype=torch.float64)
    f = torch.rand(grid.shape, generator=g, dtype=torch.float64)
    assert kernels.deposit_pieces(len(p), grid.n_cells) > 1
    before = torch.get_num_threads()
    try:
        out = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            stencil = grid.stencil(p)
            out.append((stencil.deposit(w), stencil.saturating_deposit(f, 1.0, 0.5)))
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(a, b) for a, b in zip(*out, strict=True))


def test_a_stencil_on_the_cpu_is_compiled_unless_asked_not_to() -> None:
    grid = _grid("no_flux")
    p = torch.zeros(3, 2)
    assert grid.stencil(p).compiled and not grid.stencil(p, compiled=False).compiled


def _uniform_population(per_cell: int, vmax: float, km: float, c0: float):
    field = GridField([[0, 1], [0, 1]], [8, 8], {"a": {"diffusion": 1e-3, "initial": c0,
                      "uptake": {"vmax": vmax, "km": km}}}, depth=0.1, boundary="periodic")  # fmt: skip
    centres = field.grid.centres().reshape(-1, 2).float()
    position = centres.repeat_interleave(per_cell, 0)
    return field, position, per_cell / field.grid.cell_volume  # agents per mm^3


def test_a_uniform_populations_uptake_follows_the_ode() -> None:
    """Agents on every cell centre deplete a uniform field as dc/dt = -rho vmax c / (K + c)
    (rho agents per mm^3, vmax in nmol/s): forward Euler's global error is at most
    t dt / 2 max|c''| (the ODE contracts: dt |f'| < 2), and halves with dt."""
    vmax, km, c0, t = 1.2e9, 0.05, 0.1, 40.0
    errors = []
    for dt in (0.1, 0.05):
        field, position, rho = _uniform_population(4, vmax, km, c0)
        field.reset()
        phi = torch.zeros(len(position), dtype=torch.bool)
        for _ in range(round(t / dt)):
            field.step(position, phi, dt)
        a = rho * vmax / MOLECULES_PER_NMOL  # mM/s at saturation

        def rate(_, c, a=a):
            return -a * c / (km + c)

        exact = solve_ivp(rate, (0, t), [c0], rtol=1e-12, atol=1e-15, dense_output=True)
        grid_c = field.state.concentration[0]
        assert float(grid_c.max() - grid_c.min()) <= 64 * EPS * c0  # stays uniform
        c_path = exact.sol(np.linspace(0, t, 2001))[0]
        second = (a * km / (km + c_path) ** 2) * (a * c_path / (km + c_path))  # |c''| = f' f
        bound = t * dt / 2 * second.max()
        error = abs(float(grid_c.mean()) - exact.sol(t)[0])
        assert error <= bound, (dt, error, bound)
        assert float(field.state.taken[0]) == pytest.approx(
            float(field.state.initial[0] - field.mass()[0]), rel=1e-12)  # fmt: skip
        errors.append(error)
    assert 1.8 < errors[0] / errors[1] < 2.2, errors  # first order: the scheme's, not noise


def test_uptake_never_takes_more_than_a_cell_holds() -> None:
    """Agents demanding far more than their cells hold empty those cells exactly (never below
    zero) and take what they held, no more."""
    field = GridField([[0, 1], [0, 1]], [8, 8], {"a": {"diffusion": 0.0, "initial": 0.1,
                      "uptake": {"vmax": 1e15, "km": 1e-3}}}, depth=0.1)  # fmt: skip
    field.reset()
    g = torch.Generator().manual_seed(3)
    position = torch.rand(50, 2, generator=g) * 0.4 + 0.05  # the lower-left quarter
    touched = field.grid.stencil(position).deposit(torch.ones(2, 50, dtype=torch.float64))[0] > 0
    held = 0.1 * field.grid.cell_volume * int(touched.sum())
    field.step(position, torch.zeros(50), dt=0.1)
    c = field.state.concentration[0]
    assert float(c[touched].abs().max()) <= 64 * EPS * 0.1
    assert float((c[~touched] - 0.1).abs().max()) <= 64 * EPS * 0.1  # the transforms' rounding
    assert float(field.state.taken[0]) == pytest.approx(held, rel=64 * EPS * 50)
    assert abs(float(field.balance()[0])) <= 64 * EPS * float(field.state.initial[0])


def test_secretion_follows_phi() -> None:
    field = GridField([[0, 1], [0, 1]], [4, 4], {"s": {"diffusion": 1e-3, "initial": 0.0,
                      "secretion": {"rate_on": 1e6, "rate_off": 1e5}}}, depth=0.1)  # fmt: skip
    field.reset()
    position = torch.rand(10, 2)
    phi = torch.tensor([True] * 3 + [False] * 7)
    field.step(position, phi, dt=0.5)
    want = (3 * 1e6 + 7 * 1e5) * 0.5 / MOLECULES_PER_NMOL
    assert float(field.state.secreted[0]) == pytest.approx(want, rel=1e-14)
    assert float(field.mass()[0]) == pytest.approx(want, rel=1e-12)


def test_the_torch_path_reads_through_the_steps_stencil(monkeypatch) -> None:
    """On torch's path (CUDA) the agents' read after a step shares the step's stencil where the
    positions are equal, and makes its own where they are not: the same values either way."""
    made = []
    stencil = Grid.stencil

    def torch_stencil(grid, position, compiled=None):
        made.append(stencil(grid, position, compiled=False))
        return made[-1]

    monkeypatch.setattr(Grid, "stencil", torch_stencil)
    field, position, _ = _uniform_population(2, 1e7, 0.05, 0.1)
    field.reset()
    field.step(position, torch.zeros(len(position)), dt=0.1)
    assert len(made) == 1
    got = field(position.clone(), 0.0)
    assert len(made) == 1  # shared
    c = field.state.concentration[0]
    assert torch.equal(got, stencil(field.grid, position, compiled=True).read(c))
    moved = position + 0.01
    assert torch.equal(field(moved, 0.0), stencil(field.grid, moved).read(c)) and len(made) == 2


@pytest.mark.parametrize("boundary", ["no_flux", "periodic"])
def test_a_diverged_agent_reads_nan_and_breaks_nothing(boundary) -> None:
    """NaN or infinite positions (a diverged cell) index the grid safely in the compiled
    kernels: NaN read and deposited where the position is NaN (the field's check names it),
    the other agents unchanged."""
    grid = _grid(boundary)
    p = torch.tensor([[0.5, 0.5], [float("nan"), 0.5], [float("inf"), -float("inf")]])
    f = torch.rand(grid.shape, dtype=torch.float64)
    fast = grid.stencil(p, compiled=True)
    got = fast.interpolate(f)
    assert got[0] == grid.stencil(p[:1], compiled=False).interpolate(f)[0] and got[1].isnan()
    assert fast.deposit(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)).isnan().any()

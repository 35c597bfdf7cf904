"""Diffusion, decay and sources on the grid against closed forms, at the accuracy each scheme
predicts.

Both solvers advance the five-point finite-volume equation; the spectral step integrates it
exactly in time. A Gaussian's error against the continuous closed form (periodic images, or
the method of images for no-flux walls) is then that of the finite-volume eigenvalues
``(4/h^2) sin^2(kh/2)`` against the continuous ``k^2``, mode by mode: the tests bound it by
``max|psi| * sum_m |c_m| |exp(-D lambda_m t) - exp(-D k_m^2 t)|`` over the initial data's
coefficients ``c_m`` (an orthonormal basis, each basis vector at most ``max|psi|`` in any
cell), computed independently with numpy. The explicit step's distance from the exact one is
bounded the same way with its amplification factor ``(1 - D lambda dt)^n``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.grid import GridField, solvers
from surrogate.grid.geometry import Grid
from surrogate.grid.solvers import SERIAL_VALUES, SpectralSolver

EPS = float(np.finfo(np.float64).eps)
D = 1.0e-3  # mm^2/s
AMPLITUDE = 0.1  # mM


def _basis(n: int, length: float, boundary: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An orthonormal basis of one axis (rows: modes), its continuous k^2 and the
    finite-volume eigenvalues, for cell-centred samples."""
    h = length / n
    i = np.arange(n) + 0.5
    m = np.arange(n)
    if boundary == "no_flux":
        psi = np.sqrt(2.0 / n) * np.cos(np.pi * np.outer(m, i) / n)
        psi[0] /= np.sqrt(2.0)
        k2 = (np.pi * m / length) ** 2
        lam = (4 / h**2) * np.sin(np.pi * m / (2 * n)) ** 2
    else:
        psi = np.exp(-2j * np.pi * np.outer(m, i - 0.5) / n) / np.sqrt(n)
        freq = np.fft.fftfreq(n, d=1.0 / n)
        k2 = (2 * np.pi * freq / length) ** 2
        lam = (4 / h**2) * np.sin(np.pi * m / n) ** 2
    return psi, k2, lam


def _images(x0: float, lo: float, hi: float, boundary: str, k: int = 6) -> list[float]:
    length = hi - lo
    if boundary == "periodic":
        return [x0 + j * length for j in range(-k, k + 1)]
    # zero-flux walls at lo and hi: reflections, all with the same sign
    mirrored = 2 * lo - x0
    return [p + 2 * j * length for j in range(-k, k + 1) for p in (x0, mirrored)]


def _gaussian(grid: Grid, centre: tuple[float, float], var0: float, t: float) -> np.ndarray:
    """The closed form at the cell centres: the Gaussian of variance var0 + 2 D t per axis,
    summed over the boundary's images."""
    var = var0 + 2 * D * t
    xs = grid.centres().numpy()
    out = np.ones(grid.shape)
    for axis in range(2):
        images = _images(centre[axis], grid.lower[axis], grid.upper[axis], grid.boundary[axis])
        u = xs[..., axis]
        out = out * sum(np.exp(-((u - p) ** 2) / (2 * var)) for p in images)
    return AMPLITUDE * (var0 / var) * out


def _field(boundary, solver: str = "spectral", shape=(64, 32)) -> GridField:
    return GridField([[0.0, 2.0], [0.0, 1.0]], list(shape), {"a": {"diffusion": D}},
                     depth=0.1, boundary=boundary, solver=solver)  # fmt: skip


def _run(field: GridField, initial: np.ndarray, dt: float, steps: int) -> np.ndarray:
    field.start_from(torch.from_numpy(initial)[None])
    no_agents = torch.zeros(0, 2)
    for _ in range(steps):
        field.step(no_agents, torch.zeros(0, dtype=torch.bool), dt)
    return field.state.concentration[0].numpy()


def _bound(grid: Grid, initial: np.ndarray, t: float, factor) -> float:
    """max|psi| * sum_m |c_m| |factor(lambda_m) - exp(-D k_m^2 t)| over the 2-D modes."""
    (px, kx, lx), (py, ky, ly) = (_basis(grid.shape[a], grid.upper[a] - grid.lower[a],
                                         grid.boundary[a]) for a in (0, 1))  # fmt: skip
    coeff = px @ initial @ py.T
    lam = lx[:, None] + ly[None, :]
    k2 = kx[:, None] + ky[None, :]
    gap = np.abs(factor(lam) - np.exp(-D * k2 * t))
    top = np.abs(px).max() * np.abs(py).max()
    return float(top * (np.abs(coeff) * gap).sum())


BOUNDARIES = ["no_flux", "periodic", ["periodic", "no_flux"]]


@pytest.fixture(params=["transforms", "dense"])
def spectral_path(request, monkeypatch) -> str:
    """Each spectral test for both forms of the step: the transforms, and the same flow as two
    dense per-axis matrices (chosen by grid size: forced here)."""
    monkeypatch.setattr(solvers, "DENSE_MAX_MACS", -1 if request.param == "transforms" else 2**62)
    return request.param


@pytest.mark.parametrize("boundary", BOUNDARIES)
def test_spectral_step_diffuses_a_gaussian_as_the_closed_form(boundary, spectral_path) -> None:
    field = _field(boundary)
    grid = field.grid
    centre, var0, t = (0.3, 0.2), 0.15**2, 20.0  # near two walls: the images matter
    initial = _gaussian(grid, centre, var0, 0.0)
    got = _run(field, initial, dt=0.5, steps=40)
    want = _gaussian(grid, centre, var0, t)
    bound = _bound(grid, initial, t, lambda lam: np.exp(-D * lam * t))
    error = np.abs(got - want).max()
    # the scheme's own error, plus the transforms' rounding over the steps
    assert error <= bound + 40 * 64 * EPS * AMPLITUDE, (error, bound)
    assert bound < 0.01 * AMPLITUDE  # the test would see an O(1) error (e.g. wrong eigenvalues)


@pytest.mark.parametrize("boundary", BOUNDARIES)
def test_spectral_step_is_exact_in_time(boundary, spectral_path) -> None:
    """One step of 20 s equals 40 of 0.5 s (the flow of a linear ODE, to rounding)."""
    field = _field(boundary)
    initial = _gaussian(field.grid, (0.7, 0.4), 0.1**2, 0.0)
    one = _run(field, initial, dt=20.0, steps=1)
    many = _run(field, initial, dt=0.5, steps=40)
    assert np.abs(one - many).max() <= 40 * 64 * EPS * AMPLITUDE


@pytest.mark.parametrize("boundary", BOUNDARIES)
def test_explicit_step_converges_to_the_exact_one_at_first_order(boundary) -> None:
    grid_field = _field(boundary)
    initial = _gaussian(grid_field.grid, (0.5, 0.5), 0.1**2, 0.0)
    t = 10.0
    exact = _run(grid_field, initial, dt=t, steps=1)
    gaps = []
    for dt in (0.1, 0.05):
        n = round(t / dt)
        got = _run(_field(boundary, "explicit"), initial, dt=dt, steps=n)
        # the explicit step's distance from the exact flow, mode by mode
        (px, _, lx), (py, _, ly) = (_basis(grid_field.grid.shape[a], [2.0, 1.0][a],
                                           grid_field.grid.boundary[a]) for a in (0, 1))  # fmt: skip
        coeff = px @ initial @ py.T
        lam = lx[:, None] + ly[None, :]
        gap = np.abs((1 - D * lam * dt) ** n - np.exp(-D * lam * t))
        bound = float(np.abs(px).max() * np.abs(py).max() * (np.abs(coeff) * gap).sum())
        error = np.abs(got - exact).max()
        assert error <= bound + n * 64 * EPS * AMPLITUDE, (dt, error, bound)
        gaps.append(error)
    # first order in dt: halving dt halves the error (its leading term)
    assert 1.8 < gaps[0] / gaps[1] < 2.2, gaps


@pytest.mark.parametrize("solver", ["spectral", "explicit"])
def test_decay_and_a_constant_source_follow_the_mass_ode(solver: str, spectral_path) -> None:
    """No agents: dM/dt = -k M + S, M(t) = M0 e^{-kt} + S (1 - e^{-kt}) / k (exact for the
    spectral step's mean mode; forward Euler's (1 - k dt)^n for the explicit one)."""
    k, s, c0 = 0.05, 2e-4, 0.1  # 1/s, mM/s, mM
    field = GridField([[0, 1], [0, 1]], [16, 8], {"a": {"diffusion": D, "decay": k,
                      "source": s, "initial": "0.1 * (1 + 0.5 * cos(6.283185307179586 * x))"}},
                      depth=0.1, boundary="periodic", solver=solver)  # fmt: skip
    state = field.reset()
    volume_total = 1.0 * 1.0 * 0.1
    m0 = float(state.initial[0])
    assert m0 == pytest.approx(c0 * volume_total, rel=1e-6)  # the cosine integrates to zero
    dt, steps = 0.5, 40
    for _ in range(steps):
        field.step(torch.zeros(0, 2), torch.zeros(0), dt)
    t = dt * steps
    supply = s * volume_total
    if solver == "spectral":
        want = m0 * math.exp(-k * t) + supply * (1 - math.exp(-k * t)) / k
    else:
        g = 1 - k * dt
        want = m0 * g**steps + supply * dt * sum(g**j for j in range(steps))
    assert float(field.mass()[0]) == pytest.approx(want, rel=steps * 64 * EPS)
    # the ledger closes: mass + decayed - supplied = initial
    assert abs(float(field.balance()[0])) <= steps * 64 * EPS * m0


def test_spectral_step_keeps_a_point_deposit_non_negative(spectral_path) -> None:
    """The finite-volume flow has a non-negative kernel: a one-cell spike spreads without
    undershoot (the exact flow of the spectral Laplacian, k^2, rings to -2 % of the peak here)."""
    field = _field("no_flux")
    spike = np.zeros(field.grid.shape)
    spike[10, 5] = 1.0
    got = _run(field, spike, dt=0.05, steps=3)
    assert got.min() >= -64 * EPS * got.max()


def test_explicit_dt_beyond_its_limit_is_refused_naming_dt_and_the_grid() -> None:
    field = _field("no_flux", "explicit")
    hx, hy = field.grid.spacing
    limit = 1 / (2 * D * (1 / hx**2 + 1 / hy**2))
    assert field.max_dt() == pytest.approx(limit)
    field.validate(0.99 * limit)
    with pytest.raises(ConfigError, match=r"dt=.*beyond field.solver=explicit.*h_x=0.03125"):
        field.validate(1.01 * limit)
    with pytest.raises(ConfigError, match="field.solver=explicit"):
        _run(field, np.zeros(field.grid.shape), dt=1.01 * limit, steps=1)


def test_a_small_grid_transforms_on_one_thread_and_restores_the_count(monkeypatch) -> None:
    """The spectral step of a grid below SERIAL_VALUES runs on one CPU thread (waking a second
    one cost more than the transform on loaded cores) and leaves torch's thread count as it
    was; the step is the same bytes whatever the count."""
    monkeypatch.setattr(solvers, "DENSE_MAX_MACS", -1)  # the transforms' path
    field = _field("no_flux")
    assert field.grid.n_cells <= SERIAL_VALUES
    initial = np.random.default_rng(0).random(field.grid.shape)
    seen = []
    forward = SpectralSolver.forward

    def spy(self, c):
        seen.append(torch.get_num_threads())
        return forward(self, c)

    monkeypatch.setattr(SpectralSolver, "forward", spy)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (2, 1):
            torch.set_num_threads(threads)
            out.append(_run(field, initial, dt=0.1, steps=3))
            assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(before)
    assert set(seen) == {1} and np.array_equal(out[0], out[1])


@pytest.mark.parametrize("boundary", BOUNDARIES)
def test_the_dense_step_is_the_transforms_step_to_rounding(boundary, monkeypatch) -> None:
    """Two forms of one linear map (diffusion, decay and a source): the same values to float64
    rounding of the sums (a few ulps of the largest value per step), and the grid size picks
    the form (DENSE_MAX_MACS)."""
    species = {"a": {"diffusion": D, "decay": 0.02, "source": "1e-3 * x", "initial": 0.1},
               "b": {"diffusion": 0.1 * D, "initial": "0.1 * y"}}  # fmt: skip
    out = {}
    for limit in (-1, 2**62):
        monkeypatch.setattr(solvers, "DENSE_MAX_MACS", limit)
        field = GridField([[0.0, 2.0], [0.0, 1.0]], [48, 20], species, depth=0.1,
                          boundary=boundary)  # fmt: skip
        state = field.reset()
        assert field._solver.dense is (limit > 0)
        for _ in range(20):
            state = field.step(torch.zeros(0, 2), torch.zeros(0), 0.5)
        out[limit] = state.concentration
    scale = float(out[-1].abs().max())
    assert float((out[-1] - out[2**62]).abs().max()) <= 20 * 64 * EPS * scale

"""One time step of diffusion, first-order decay and constant sources on a :class:`Grid`.

Both solvers advance ``dc/dt = D L c - k c + s`` per species, with ``L`` the five-point
finite-volume Laplacian of the grid (``(c_{i+1} - 2 c_i + c_{i-1}) / h^2`` per axis; at a
no-flux wall the ghost cell mirrors its neighbour, at a periodic edge the index wraps). That
semi-discretisation conserves mass exactly (a flux leaving one cell enters its neighbour), is
second order in ``h``, and its generator ``D L - k`` has non-negative off-diagonal entries, so
its exact flow keeps concentrations non-negative: the property the agents' point-like uptake and
secretion need (the flow of a spectrally exact Laplacian rings below zero around them: to -2 %
of the peak around a one-cell deposit in ``tests/grid/test_solvers.py``).

* :class:`SpectralSolver` (``solver: spectral``, the default) integrates it *exactly* over dt:
  ``L`` is diagonal in the cosine basis of a no-flux axis (the DCT-II,
  :mod:`surrogate.grid.transforms`) and in the Fourier basis of a periodic one (``rfft``),
  with eigenvalues ``-(4 / h^2) sin^2(pi m / (2 n))`` and ``-(4 / h^2) sin^2(pi m / n)``; each
  mode is multiplied by ``exp(-(D lambda + k) dt)`` and gains its share of the source,
  ``s_m (1 - exp(-(D lambda + k) dt)) / (D lambda + k)``. Unconditionally stable, no error in
  time at all, cost two transforms per step (``O(N log N)`` for N cells: a 512 x 64 grid is
  ~3e5 complex flops per transform, negligible beside a population's step). The same linear
  map is separable, ``c -> e^{-k dt} A_x c A_y^T + G`` with ``A`` the exact 1-D flow of each
  axis (the transforms applied to the identity, once per dt) and ``G`` the sources' constant
  share; where the grid is small (:data:`DENSE_MAX_MACS`) or on a GPU (two matrix products
  against ~30 small kernels; on an H200 either is < 0.1 ms on 512 x 64) the step is those two
  products.
* :class:`ExplicitSolver` (``solver: explicit``) is forward Euler on the same equation: cheaper
  per step (a few element-wise passes, no transform), first order in time, and positive and
  stable only while ``dt <= 1 / (2 D (1/h_x^2 + 1/h_y^2) + k)`` (:func:`explicit_max_dt`);
  a longer dt is refused naming dt, the grid spacing and the limit.

So the spectral step is exact where the explicit one has an O(dt) error and a step limit; the
explicit one is there as a cross-check of the spectral step (both converge to the same
semi-discrete solution as dt -> 0, tested) and for kernels without an FFT.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from contextlib import AbstractContextManager

import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.grid.geometry import Grid
from surrogate.grid.transforms import dct, idct
from surrogate.threads import one_thread

__all__ = [
    "SOLVERS",
    "ExplicitSolver",
    "SpectralSolver",
    "euler_decay_loss",
    "exact_decay_loss",
    "explicit_max_dt",
    "make_solver",
]

#: the grid's x and y dimensions in a ``(species, n_x, n_y)`` tensor
_DIMS = (-2, -1)
#: multiply-adds per species (``n_x^2 n_y + n_x n_y^2``) up to which the CPU step is two dense
#: matrix products rather than transforms. Measured one thread, a 2-core EPYC, ms per step
#: transforms / dense: 64 x 32 0.89 / 0.18, 350 x 4 (channel_band) 1.06 / 0.91, 128 x 64
#: 1.57 / 0.70, 256 x 32 1.72 / 1.08, 512 x 32 2.64 / 5.84, 512 x 64 4.22 / 6.97
DENSE_MAX_MACS = 2**22
#: the longest axis for the dense step on a GPU (its matrices: ``n^2`` float64 per species)
DENSE_MAX_SIDE = 4096
#: grid values (species x cells) up to which the spectral step runs its transforms on one CPU
#: thread: on a 512 x 64 grid with 2 threads on 2 loaded cores each FFT waited ~17 ms for its
#: second thread, the step 51 ms (median) against 4 ms on one thread
SERIAL_VALUES = 2**18


def serial_below(values: int, device: torch.device) -> AbstractContextManager[None]:
    """torch on one CPU thread inside, where ``values`` <= :data:`SERIAL_VALUES` on the CPU
    (small transforms cost less than waking a second thread); the thread count is restored."""
    return one_thread(device.type == "cpu" and values <= SERIAL_VALUES)


def _eigenvalues(grid: Grid, axis: int, length: int, dtype: torch.dtype,
                 device: torch.device) -> Tensor:  # fmt: skip
    """``-lambda`` of the 1-D second difference for the first ``length`` modes of ``axis``:
    ``(4 / h^2) sin^2(pi m / (2n))`` (no-flux, cosine modes) or ``(4 / h^2) sin^2(pi m / n)``
    (periodic, Fourier modes; modes m and n - m share it)."""
    n, h = grid.shape[axis], grid.spacing[axis]
    m = torch.arange(length, dtype=dtype, device=device)
    period = 2 * n if grid.boundary[axis] == "no_flux" else n
    return (4.0 / h**2) * torch.sin(math.pi * m / period) ** 2


class SpectralSolver:
    """The exact step of the finite-volume diffusion-decay-source equation (module docstring).

    Args:
        grid: the grid.
        diffusion: ``(S,)`` diffusion constants (mm^2/s), float64.
        decay: ``(S,)`` first-order decay rates (1/s), float64.
        source: ``(S, n_x, n_y)`` constant source rates (mM/s), float64, or None (none).
    """

    name = "spectral"

    def __init__(
        self,
        grid: Grid,
        diffusion: Tensor,
        decay: Tensor,
        source: Tensor | None,
        dense: bool | None = None,
    ) -> None:
        self.grid = grid
        self.diffusion = diffusion
        self.decay = decay
        nx, ny = grid.shape
        if dense is None:  # by measurement (module docstring)
            on_gpu = decay.device.type != "cpu"
            dense = (max(nx, ny) <= DENSE_MAX_SIDE if on_gpu
                     else nx * nx * ny + nx * ny * ny <= DENSE_MAX_MACS)  # fmt: skip
        #: whether :meth:`step` applies the flow as dense per-axis matrices
        self.dense = bool(dense)
        self._periodic = [d for d, b in zip(_DIMS, grid.boundary, strict=True) if b == "periodic"]
        self._no_flux = [d for d, b in zip(_DIMS, grid.boundary, strict=True) if b == "no_flux"]
        # the transformed layout: rfft halves the last periodic dimension
        lengths = list(grid.shape)
        if self._periodic:
            last = self._periodic[-1] + 2
            lengths[last] = grid.shape[last] // 2 + 1
        ex, ey = (_eigenvalues(grid, a, lengths[a], decay.dtype, decay.device) for a in (0, 1))
        self._rate = diffusion[:, None, None] * (ex[:, None] + ey[None, :]) + decay[:, None, None]
        self._source = None if source is None else self.forward(source)
        self._dt: float | None = None
        self._factor: Tensor | None = None
        self._gain: Tensor | None = None
        self._axes: tuple[Tensor, Tensor] | None = None  # dense: (S, n_x, n_x), (S, n_y, n_y)
        self._kept: Tensor | None = None  # dense: e^{-k dt}, (S, 1, 1)
        self._added: Tensor | None = None  # dense: the sources' share of a step, (S, n_x, n_y)

    def forward(self, c: Tensor) -> Tensor:
        """``(S, n_x, n_y)`` values -> their coefficients in the modes of the step."""
        for d in self._no_flux:
            c = dct(c, d)
        if self._periodic:
            c = torch.fft.rfftn(c, dim=self._periodic)
        return c

    def inverse(self, coeff: Tensor) -> Tensor:
        """Coefficients -> ``(S, n_x, n_y)`` values (the inverse of :meth:`forward`)."""
        if self._periodic:
            sizes = [self.grid.shape[d + 2] for d in self._periodic]
            coeff = torch.fft.irfftn(coeff, s=sizes, dim=self._periodic)
        for d in self._no_flux:
            coeff = idct(coeff, d)
        return coeff

    def _prepare(self, dt: float) -> None:
        rate = self._rate
        self._factor = torch.exp(-rate * dt)
        if self._source is not None:
            # (1 - exp(-rate dt)) / rate, dt where rate = 0 (a conserved mode gains s dt)
            safe = torch.where(rate > 0, rate, torch.ones_like(rate))
            gain = torch.where(rate > 0, -torch.expm1(-rate * dt) / safe, torch.full_like(rate, dt))
            self._gain = self._source * gain
        if self.dense:
            self._axes = (self._axis_flow(0, dt), self._axis_flow(1, dt))
            self._kept = torch.exp(-self.decay * dt)[:, None, None]
            self._added = None if self._gain is None else self.inverse(self._gain)
        self._dt = dt

    def _axis_flow(self, axis: int, dt: float) -> Tensor:
        """The exact flow of diffusion along ``axis`` over ``dt``, ``(S, n, n)``: the
        transforms of :meth:`forward` applied to the identity (column j: the flow of a unit
        in cell j), each mode scaled by ``exp(-D lambda dt)``, transformed back."""
        n = self.grid.shape[axis]
        eye = torch.eye(n, dtype=self.decay.dtype, device=self.decay.device)
        lam = _eigenvalues(self.grid, axis, n, eye.dtype, eye.device)
        factor = torch.exp(-self.diffusion[:, None] * lam * dt)[:, :, None]  # (S, modes, 1)
        if self.grid.boundary[axis] == "no_flux":
            return idct(factor * dct(eye, -2), -2)
        modes = torch.fft.fft(eye, dim=-2)  # every Fourier mode: m and n - m share lambda
        return torch.fft.ifft(factor * modes, dim=-2).real

    def flow(self, dt: float) -> tuple[Tensor, Tensor, Tensor, Tensor | None] | None:
        """The dense step's ``(A_x, A_y, e^{-k dt}, G or None)`` for ``dt`` (what :meth:`step`
        applies: ``c -> A_x c A_y^T e^{-k dt} + G``), or None where the step is not dense;
        for :func:`~surrogate.grid.fused.fused_step`."""
        if not self.dense:
            return None
        if dt != self._dt:
            with serial_below(0, self.decay.device):
                self._prepare(dt)
        assert self._axes is not None and self._kept is not None
        return self._axes[0], self._axes[1], self._kept, self._added

    def step(self, c: Tensor, dt: float) -> Tensor:
        """``c`` (``(S, n_x, n_y)``, mM) advanced by ``dt`` seconds."""
        if dt != self._dt:
            with serial_below(0, c.device):  # the same factors, to the byte, for any count
                self._prepare(dt)
        assert self._factor is not None  # set by _prepare
        if self.dense:  # one thread on the CPU (the grid is small): BLAS's blocking, and so
            # its rounding, may change with the thread count; the bytes must not
            assert self._axes is not None and self._kept is not None
            ax, ay = self._axes
            with serial_below(0, c.device):
                out = torch.matmul(torch.matmul(ax, c), ay.transpose(-2, -1)) * self._kept
            return out if self._added is None else out + self._added
        with serial_below(c.numel(), c.device):
            coeff = self.forward(c) * self._factor
            if self._gain is not None:
                coeff = coeff + self._gain
            return self.inverse(coeff)

    def decay_loss(self, mass: Tensor, supply: Tensor, dt: float) -> Tensor:
        """The amount each species loses to decay over the step, from its mass at the step's
        start and its supply rate (diffusion conserves mass; the mean mode is exact):
        ``M + S dt - (M e^{-k dt} + S (1 - e^{-k dt}) / k)``."""
        return exact_decay_loss(self.decay, mass, supply, dt)


def explicit_max_dt(grid: Grid, diffusion: Sequence[float], decay: Sequence[float]) -> float:
    """The longest step the explicit solver takes stably and keeping concentrations
    non-negative, ``1 / max_s(2 D_s (1/h_x^2 + 1/h_y^2) + k_s)`` (inf where nothing changes)."""
    hx, hy = grid.spacing
    top = max(2.0 * d * (1.0 / hx**2 + 1.0 / hy**2) + k for d, k in zip(diffusion, decay,
                                                                         strict=True))  # fmt: skip
    return math.inf if top <= 0 else 1.0 / top


class ExplicitSolver:
    """Forward Euler on the finite-volume equation (module docstring), for dt up to
    :func:`explicit_max_dt`.

    Args:
        grid, diffusion, decay, source: as for :class:`SpectralSolver`.
    """

    name = "explicit"

    def __init__(self, grid: Grid, diffusion: Tensor, decay: Tensor, source: Tensor | None) -> None:
        self.grid = grid
        self.diffusion = diffusion
        self.decay = decay
        self.source = source

    def _laplacian(self, c: Tensor) -> Tensor:
        out = torch.zeros_like(c)
        for axis, d in enumerate(_DIMS):
            n, h = self.grid.shape[axis], self.grid.spacing[axis]
            if self.grid.boundary[axis] == "periodic":
                up, down = torch.roll(c, -1, d), torch.roll(c, 1, d)
            else:  # mirrored ghost cells
                up = torch.cat([c.narrow(d, 1, n - 1), c.narrow(d, n - 1, 1)], d)
                down = torch.cat([c.narrow(d, 0, 1), c.narrow(d, 0, n - 1)], d)
            out = out + (up - 2.0 * c + down) / h**2
        return out

    def step(self, c: Tensor, dt: float) -> Tensor:
        """``c`` advanced by ``dt`` seconds (``dt`` <= :func:`explicit_max_dt`, checked by the
        field)."""
        change = self.diffusion[:, None, None] * self._laplacian(c) - self.decay[:, None, None] * c
        if self.source is not None:
            change = change + self.source
        return c + dt * change

    def decay_loss(self, mass: Tensor, supply: Tensor, dt: float) -> Tensor:
        """The amount each species loses to decay over the step: ``k M dt``."""
        return euler_decay_loss(self.decay, mass, supply, dt)


def exact_decay_loss(decay: Tensor, mass: Tensor, supply: Tensor, dt: float) -> Tensor:
    """:meth:`SpectralSolver.decay_loss` with the decay rates ``decay`` (``(S,)``, 1/s)."""
    k = decay
    e = torch.exp(-k * dt)
    gain = torch.where(k > 0, -torch.expm1(-k * dt) / torch.where(k > 0, k, 1.0), dt)
    return mass + supply * dt - (mass * e + supply * gain)


def euler_decay_loss(decay: Tensor, mass: Tensor, supply: Tensor, dt: float) -> Tensor:
    """:meth:`ExplicitSolver.decay_loss` with the decay rates ``decay`` (``(S,)``, 1/s)."""
    return decay * mass * dt


SOLVERS: dict[str, type[SpectralSolver] | type[ExplicitSolver]] = {
    "spectral": SpectralSolver,
    "explicit": ExplicitSolver,
}


def make_solver(
    name: str, grid: Grid, diffusion: Tensor, decay: Tensor, source: Tensor | None
) -> SpectralSolver | ExplicitSolver:
    """The solver called ``name`` (:data:`SOLVERS`)."""
    if name not in SOLVERS:
        raise ConfigError(f"field.solver must be one of {list(SOLVERS)}, got {name!r}")
    return SOLVERS[name](grid, diffusion, decay, source)

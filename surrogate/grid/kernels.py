"""The agents' exchange with a grid on the CPU, compiled (numba): one pass over the agents each.

At 1e6 agents the exchange is memory-bound: torch's eager ops make a float64 ``(n, 4)`` index
and weight (64 bytes per agent, ~25 passes over the agents) and then gather and scatter through
them. Here each pass recomputes an agent's stencil from its position (8 bytes read, a few
flops: :func:`_axis` is the arithmetic of :meth:`~surrogate.grid.Grid.stencil`, in the same
order, so the indices and weights are the same numbers) and does all its work with it:

* :func:`interpolate_kernel`: the grid at the agents (the bilinear read; optionally clamped at
  zero and stored as float32: the field the agents sense),
* :func:`deposit_kernel`: the adjoint, each agent's amount spread over its four cells,
* :func:`uptake_kernel`: the read and the deposit fused, for the Michaelis-Menten demand
  ``coef l / (km + l)`` of each agent at ``l``, the grid interpolated there (so the demand is
  never stored).

The reads are parallel over agents (each agent's result is its own: the same bytes on any
number of threads). A deposit adds in a fixed number of pieces (:func:`deposit_pieces`: a
function of the population and the grid only), each into its own copy of the grid in agent
order, then sums the copies in piece order: the same bytes on any number of threads, and
memory bounded by :data:`PIECE_BYTES`. The torch step (:class:`~surrogate.grid.Stencil` on
CUDA, or ``compiled=False``) computes the same sums in another order: results agree to float64
rounding, not to the byte.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from surrogate.ctmc.compiled import match_torch_threads

__all__ = ["PIECE_BYTES", "deposit", "deposit_pieces", "interpolate", "uptake_deposit"]

_JIT: dict[str, Any] = {"nogil": True, "cache": True, "fastmath": False, "error_model": "numpy"}
#: agents per piece of a deposit, at least (fewer pieces for fewer agents)
PIECE_AGENTS = 65536
#: pieces of a deposit, at most
MAX_PIECES = 16
#: the bytes a deposit's private grids may take together (fewer pieces on a large grid)
PIECE_BYTES = 64 * 2**20


def deposit_pieces(n: int, cells: int) -> int:
    """The pieces a deposit of ``n`` agents on ``cells`` grid cells adds in (each its own copy
    of the grid): a function of the sizes only, so the sums' order is the same on any
    number of threads."""
    return max(1, min(MAX_PIECES, n // PIECE_AGENTS, PIECE_BYTES // (8 * cells)))


@numba.njit(inline="always", **_JIT)
def _axis(p, lo, h, n, periodic):
    """One axis of an agent's stencil, as :meth:`Grid.stencil`: the two cells and weights."""
    g = (np.float64(p) - lo) / h - 0.5
    if not periodic:  # beyond a wall: the nearest point inside (torch.clamp)
        g = min(max(g, -0.5), n - 0.5)
    first = np.floor(g)
    frac = g - first
    if not abs(first) < 2.0**62:  # NaN or beyond int64 (a diverged agent): a valid index, and
        first = 0.0  # NaN weights where NaN came in (the field's check names it)
    i0 = int(first)
    i1 = i0 + 1
    if periodic:
        i0, i1 = i0 % n, i1 % n  # Python's (and torch.remainder's) sign: in [0, n)
    else:
        i0, i1 = min(max(i0, 0), n - 1), min(max(i1, 0), n - 1)
    return i0, i1, 1.0 - frac, frac


@numba.njit(inline="always", **_JIT)
def _stencil(position, a, geometry):
    """Agent ``a``'s four flat cell indices and weights (in :meth:`Grid.stencil`'s order)."""
    ny = np.int64(geometry[5])
    x0, x1, wx0, wx1 = _axis(position[a, 0], geometry[0], geometry[2], np.int64(geometry[4]),
                             geometry[6] != 0.0)  # fmt: skip
    y0, y1, wy0, wy1 = _axis(position[a, 1], geometry[1], geometry[3], ny, geometry[7] != 0.0)
    return (x0 * ny + y0, x0 * ny + y1, x1 * ny + y0, x1 * ny + y1,
            wx0 * wy0, wx0 * wy1, wx1 * wy0, wx1 * wy1)  # fmt: skip


@numba.njit(inline="always", **_JIT)
def _read(values, k0, k1, k2, k3, w0, w1, w2, w3):
    """The bilinear read of ``values`` (flat) through one agent's stencil."""
    return values[k0] * w0 + values[k1] * w1 + values[k2] * w2 + values[k3] * w3


@numba.njit(parallel=True, **_JIT)
def interpolate_kernel(position, geometry, values, out, clamp, pieces):
    """``out[a]`` = the bilinear read of ``values`` (flat float64) at agent ``a``; clamped at
    zero where ``clamp``; in ``out``'s dtype."""
    n = position.shape[0]
    for k in prange(pieces):
        for a in range(n * k // pieces, n * (k + 1) // pieces):
            k0, k1, k2, k3, w0, w1, w2, w3 = _stencil(position, a, geometry)
            v = _read(values, k0, k1, k2, k3, w0, w1, w2, w3)
            if clamp:
                v = max(v, 0.0)
            out[a] = v


@numba.njit(inline="always", **_JIT)
def _spread(buf, q, k0, k1, k2, k3, w0, w1, w2, w3):
    """Add ``q`` to one agent's four cells of ``buf`` by its weights: the read's adjoint."""
    buf[k0] += q * w0
    buf[k1] += q * w1
    buf[k2] += q * w2
    buf[k3] += q * w3


@numba.njit(inline="always", **_JIT)
def _reduce(buffers, out):
    """``out`` = the sum of the pieces' grids, in piece order (parallel over cells)."""
    pieces, cells = buffers.shape
    for j in prange(cells):
        s = buffers[0, j]
        for k in range(1, pieces):
            s += buffers[k, j]
        out[j] = s


@numba.njit(parallel=True, **_JIT)
def deposit_kernel(position, geometry, amounts, buffers, out):
    """``out`` (flat) = every agent's ``amounts[a]`` spread over its four cells (the adjoint of
    the read), summed in ``buffers.shape[0]`` pieces (module docstring)."""
    n = position.shape[0]
    pieces = buffers.shape[0]
    for k in prange(pieces):
        buf = buffers[k]
        buf[:] = 0.0
        for a in range(n * k // pieces, n * (k + 1) // pieces):
            k0, k1, k2, k3, w0, w1, w2, w3 = _stencil(position, a, geometry)
            q = amounts[a]
            _spread(buf, q, k0, k1, k2, k3, w0, w1, w2, w3)
    _reduce(buffers, out)


@numba.njit(parallel=True, **_JIT)
def uptake_kernel(position, geometry, values, coef, km, buffers, out):
    """``out`` (flat) = the deposit of each agent's demand ``coef l / (km + l)``, ``l`` the
    grid ``values`` at the agent clamped at zero (:func:`deposit_kernel`'s pieces)."""
    n = position.shape[0]
    pieces = buffers.shape[0]
    for k in prange(pieces):
        buf = buffers[k]
        buf[:] = 0.0
        for a in range(n * k // pieces, n * (k + 1) // pieces):
            k0, k1, k2, k3, w0, w1, w2, w3 = _stencil(position, a, geometry)
            local = max(_read(values, k0, k1, k2, k3, w0, w1, w2, w3), 0.0)
            q = coef * local / (km + local)
            _spread(buf, q, k0, k1, k2, k3, w0, w1, w2, w3)
    _reduce(buffers, out)


# -- the adaptor: tensors in, tensors out ---------------------------------------------------------
def _geometry(grid: Any) -> np.ndarray:
    """The grid as the kernels take it: lower x, y, spacing x, y, cells x, y, periodic x, y."""
    periodic = [float(b == "periodic") for b in grid.boundary]
    return np.array([*grid.lower, *grid.spacing, *grid.shape, *periodic], dtype=np.float64)


def _agents(position: Tensor) -> np.ndarray:
    return position.detach().numpy()


def interpolate(grid: Any, position: Tensor, values: Tensor, clamp: bool = False,
                dtype: torch.dtype = torch.float64) -> Tensor:  # fmt: skip
    """The grid ``values`` (``(..., n_x, n_y)`` float64, CPU) at ``position`` (``(n, 2)``):
    ``(..., n)`` in ``dtype``, clamped at zero where ``clamp``."""
    threads = match_torch_threads()
    n = position.shape[0]
    lead = values.shape[:-2]
    flat = values.to(torch.float64).reshape(-1, grid.n_cells).contiguous()
    out = torch.empty((flat.shape[0], n), dtype=dtype)
    p, geometry = _agents(position), _geometry(grid)
    pieces = max(1, min(n, 4 * threads))
    for row in range(flat.shape[0]):
        interpolate_kernel(p, geometry, flat[row].numpy(), out[row].numpy(), clamp, pieces)
    return out.reshape(*lead, n)


def deposit(grid: Any, position: Tensor, amounts: Tensor) -> Tensor:
    """Each agent's ``amounts`` (``(..., n)`` float64, CPU) spread over its four cells:
    ``(..., n_x, n_y)``."""
    match_torch_threads()
    n = position.shape[0]
    lead = amounts.shape[:-1]
    rows = amounts.to(torch.float64).reshape(-1, n).contiguous()
    out = torch.empty((rows.shape[0], grid.n_cells), dtype=torch.float64)
    buffers = np.empty((deposit_pieces(n, grid.n_cells), grid.n_cells), dtype=np.float64)
    p, geometry = _agents(position), _geometry(grid)
    for row in range(rows.shape[0]):
        deposit_kernel(p, geometry, rows[row].numpy(), buffers, out[row].numpy())
    return out.reshape(*lead, *grid.shape)


def uptake_deposit(grid: Any, position: Tensor, values: Tensor, coef: float, km: float) -> Tensor:
    """The deposit of each agent's demand ``coef l / (km + l)`` with ``l`` = ``values``
    (``(n_x, n_y)`` float64, CPU) at the agent, clamped at zero: ``(n_x, n_y)``."""
    match_torch_threads()
    n = position.shape[0]
    flat = values.to(torch.float64).reshape(-1).contiguous()
    out = torch.empty(grid.n_cells, dtype=torch.float64)
    buffers = np.empty((deposit_pieces(n, grid.n_cells), grid.n_cells), dtype=np.float64)
    uptake_kernel(_agents(position), _geometry(grid), flat.numpy(), float(coef), float(km),
                  buffers, out.numpy())  # fmt: skip
    return out.reshape(grid.shape)

"""A regular 2-D grid of cells (finite volumes) and the bilinear stencil that couples agents to it.

Cell ``(i, j)`` is the rectangle of width ``h_x``, ``h_y`` whose centre is
``lower + (i + 1/2, j + 1/2) * h``; a concentration is one value per cell (its mean), an amount
is concentration times the cell's volume ``h_x h_y depth`` (the grid is a thin layer of depth
``depth``: a channel's cross-section is ``h_y x depth`` per row of cells).

Agents read the grid by bilinear interpolation between the four cell centres around them
(:meth:`Stencil.interpolate`) and write to it by the adjoint of that interpolation
(:meth:`Stencil.deposit`: the same four cells, the same weights, ``index_add_``), so for any
grid function ``f`` and agent amounts ``w``, ``<interpolate(f), w> = <f, deposit(w)>``, and the
weights of each agent sum to one: what an agent gives or takes is exactly what the grid gets or
loses (to float64 rounding). Weights are computed in float64 from the float32 positions.

Two implementations do that arithmetic (:meth:`Grid.stencil` picks): on the CPU the compiled
kernels of :mod:`surrogate.grid.kernels` (one pass over the agents per read or deposit, each
agent's stencil recomputed from its position: the same indices and weights, reads to the byte),
elsewhere torch's ops on an ``(n, 4)`` index and weight computed once per stencil
(:meth:`Grid.weights`) and shared by its reads and deposits.

Boundaries, per axis: ``periodic`` (indices wrap; positions are read modulo the domain) or
``no_flux`` (a wall at the domain's edge: between the wall and the first cell centre the value
is the first cell's, the interpolant of a zero-gradient wall; an agent beyond the wall
exchanges with the nearest point inside, so nothing leaves the grid).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from surrogate.errors import ConfigError

__all__ = ["BOUNDARIES", "Grid", "Stencil"]

#: the boundary conditions an axis may have
BOUNDARIES = ("periodic", "no_flux")


@dataclass(frozen=True)
class Grid:
    """The geometry of a field's grid (see the module docstring).

    Attributes:
        lower: the domain's lower corner (mm).
        upper: the domain's upper corner (mm).
        shape: cells along x and y.
        boundary: each axis's boundary condition (:data:`BOUNDARIES`).
        depth: the layer's depth (mm): a cell holds ``h_x h_y depth`` mm^3.
    """

    lower: tuple[float, float]
    upper: tuple[float, float]
    shape: tuple[int, int]
    boundary: tuple[str, str]
    depth: float

    @classmethod
    def from_config(
        cls,
        domain: Sequence[Sequence[float]],
        shape: Sequence[int],
        boundary: str | Sequence[str],
        depth: float,
        where: str = "field",
    ) -> Grid:
        """A checked grid: ``domain`` ``[[x_lo, x_hi], [y_lo, y_hi]]`` (mm), ``shape``
        ``[n_x, n_y]`` (integers >= 2), ``boundary`` one name or one per axis, ``depth`` > 0.

        Raises:
            ConfigError: naming ``<where>.domain``, ``.shape``, ``.boundary`` or ``.depth``.
        """
        try:
            bounds = [(float(a), float(b)) for a, b in domain]
        except (TypeError, ValueError):
            bounds = []
        if len(bounds) != 2 or not all(
            math.isfinite(a) and math.isfinite(b) and a < b for a, b in bounds
        ):
            raise ConfigError(
                f"{where}.domain must be [[x_lo, x_hi], [y_lo, y_hi]] in mm with lo < hi, "
                f"got {domain!r}"
            )
        if (
            isinstance(shape, str | bytes)
            or len(shape) != 2
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 2 for n in shape)
        ):
            raise ConfigError(f"{where}.shape must be two integers >= 2 (cells along x, y), "
                              f"got {shape!r}")  # fmt: skip
        names = (boundary, boundary) if isinstance(boundary, str) else tuple(boundary)
        if len(names) != 2 or any(b not in BOUNDARIES for b in names):
            raise ConfigError(f"{where}.boundary must be one of {list(BOUNDARIES)} or one per "
                              f"axis [x, y], got {boundary!r}")  # fmt: skip
        try:  # what float() refuses (and a bool) is refused by name, as the other keys are
            value = math.nan if isinstance(depth, bool) else float(depth)
        except (TypeError, ValueError):
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{where}.depth must be a positive number (mm), got {depth!r}")
        lower = (bounds[0][0], bounds[1][0])
        upper = (bounds[0][1], bounds[1][1])
        return cls(lower, upper, (int(shape[0]), int(shape[1])), names, value)

    @property
    def spacing(self) -> tuple[float, float]:
        """Cell widths ``(h_x, h_y)`` (mm)."""
        # spelt out, no zip(strict=True): torch.compile traces it (surrogate/grid/fused.py)
        return ((self.upper[0] - self.lower[0]) / self.shape[0],
                (self.upper[1] - self.lower[1]) / self.shape[1])  # fmt: skip

    @property
    def cell_volume(self) -> float:
        """Volume of one cell (mm^3)."""
        hx, hy = self.spacing
        return hx * hy * self.depth

    @property
    def n_cells(self) -> int:
        """Cells of the grid."""
        return self.shape[0] * self.shape[1]

    def centres(self, device: torch.device | str = "cpu") -> Tensor:
        """Every cell's centre, ``(n_x, n_y, 2)`` float64 (mm)."""
        axes = [
            lo + (torch.arange(n, dtype=torch.float64, device=device) + 0.5) * h
            for lo, n, h in zip(self.lower, self.shape, self.spacing, strict=True)
        ]
        gx, gy = torch.meshgrid(*axes, indexing="ij")
        return torch.stack([gx, gy], -1)

    def stencil(self, position: Tensor, compiled: bool | None = None) -> Stencil:
        """The bilinear stencil of agents at ``position`` (``(n, 2)``, mm).

        Args:
            position: ``(n, 2)`` the agents' positions (mm), float32 or float64.
            compiled: exchange through the compiled kernels (:mod:`surrogate.grid.kernels`:
                one pass over the agents per read or deposit, the stencil recomputed in it)
                rather than torch's ops on a stored ``(n, 4)`` index and weight; default: on
                the CPU, where they are ~10x faster at 1e6 agents. Always torch on CUDA.
        """
        on_cpu = position.device.type == "cpu"
        if compiled and not on_cpu:
            raise ValueError(f"the compiled exchange runs on the CPU; position is on "
                             f"{position.device}")  # fmt: skip
        return Stencil(self, position, on_cpu if compiled is None else compiled)

    def weights(self, position: Tensor) -> tuple[Tensor, Tensor]:
        """Each agent's four flat cell indices (int64 ``(n, 4)``, ``i * n_y + j``) and bilinear
        weights (float64 ``(n, 4)``, each row summing to one), computed in float64 from
        ``position`` (``(n, 2)``, mm) with torch's ops (:mod:`surrogate.grid.kernels` repeats
        this arithmetic per agent)."""
        p = position.to(torch.float64)
        idx, wts = [], []
        for axis in range(2):
            n, h = self.shape[axis], self.spacing[axis]
            g = (p[:, axis] - self.lower[axis]) / h - 0.5  # in units of cells, from centre 0
            if self.boundary[axis] == "no_flux":
                g = g.clamp(-0.5, n - 0.5)  # beyond a wall: the nearest point inside
            first = torch.floor(g)
            frac = g - first
            i0 = first.to(torch.int64)
            i1 = i0 + 1
            if self.boundary[axis] == "periodic":
                i0, i1 = i0.remainder(n), i1.remainder(n)
            else:  # mirrored ghost cells: a zero-gradient wall
                i0, i1 = i0.clamp(0, n - 1), i1.clamp(0, n - 1)
            idx.append((i0, i1))
            wts.append((1.0 - frac, frac))
        ny = self.shape[1]
        index = torch.stack([ix * ny + iy for ix in idx[0] for iy in idx[1]], -1)
        weight = torch.stack([wx * wy for wx in wts[0] for wy in wts[1]], -1)
        return index, weight


#: the most private copies of the grid a GPU deposit adds into (:attr:`Stencil._lanes`)
DEPOSIT_LANES = 128
#: and the most values they may hold together (float64: 32 MiB)
LANE_VALUES = 2**22


def deposit_lanes(agents: int, cells: int, device: torch.device) -> int:
    """Private copies of a grid of ``cells`` values that a torch deposit of ``agents`` adds
    into on ``device``: on a GPU the largest power of two up to :data:`DEPOSIT_LANES`, at
    most ``agents`` and with at most :data:`LANE_VALUES` values in all; 1 on the CPU."""
    lanes = 1
    if device.type != "cpu":
        while lanes < DEPOSIT_LANES and 2 * lanes <= agents and 2 * lanes * cells <= LANE_VALUES:
            lanes *= 2
    return lanes


@dataclass(frozen=True)
class Stencil:
    """Agents at their positions on a grid: four cells and their bilinear weights each, through
    which they read the grid (:meth:`interpolate`) and write to it (:meth:`deposit`, the
    adjoint). Made by :meth:`Grid.stencil`; the torch path computes :attr:`index` and
    :attr:`weight` once, at first use, and shares them between its reads and deposits.

    Attributes:
        grid: the grid.
        position: ``(n, 2)`` the agents' positions (mm).
        compiled: whether the compiled kernels do the work (:meth:`Grid.stencil`).
    """

    grid: Grid
    position: Tensor
    compiled: bool

    @cached_property
    def _torch(self) -> tuple[Tensor, Tensor]:
        return self.grid.weights(self.position)

    @property
    def index(self) -> Tensor:
        """int64 ``(n, 4)``, flat cell indices (``i * n_y + j``)."""
        return self._torch[0]

    @property
    def weight(self) -> Tensor:
        """float64 ``(n, 4)``, the weights (each row sums to one)."""
        return self._torch[1]

    @property
    def shape(self) -> tuple[int, int]:
        """The grid's ``(n_x, n_y)``."""
        return self.grid.shape

    def interpolate(self, values: Tensor) -> Tensor:
        """The grid's values at the agents.

        Args:
            values: ``(..., n_x, n_y)`` per cell.

        Returns:
            ``(..., n)`` at the agents, in ``values``' dtype (the weights are float64).
        """
        if self.compiled:
            from surrogate.grid import kernels

            out = kernels.interpolate(self.grid, self.position, values.to(torch.float64))
            return out.to(values.dtype)
        flat = values.reshape(*values.shape[:-2], -1)
        picked = flat[..., self.index]  # (..., n, 4)
        return (picked * self.weight.to(values.dtype)).sum(-1)

    def read(self, values: Tensor) -> Tensor:
        """What the agents sense: ``values`` (``(n_x, n_y)`` float64) at the agents, clamped at
        zero, as float32 ``(n,)``."""
        if self.compiled:
            from surrogate.grid import kernels

            return kernels.interpolate(self.grid, self.position, values, clamp=True,
                                       dtype=torch.float32)  # fmt: skip
        return self.interpolate(values).clamp_min(0.0).to(torch.float32)

    def deposit(self, amounts: Tensor) -> Tensor:
        """The adjoint of :meth:`interpolate`: each agent's amount spread over its four cells.

        Args:
            amounts: ``(..., n)`` per agent (float64 for exact accounting).

        Returns:
            ``(..., n_x, n_y)`` per cell; its sum is ``amounts``' sum (to rounding).
        """
        if self.compiled:
            from surrogate.grid import kernels

            return kernels.deposit(self.grid, self.position, amounts.to(torch.float64)).to(
                amounts.dtype)  # fmt: skip
        lead = amounts.shape[:-1]
        spread = (amounts[..., None] * self.weight.to(amounts.dtype)).reshape(*lead, -1)
        lanes, index = self._lanes
        cells = self.shape[0] * self.shape[1]
        out = amounts.new_zeros(*lead, lanes * cells)
        out.index_add_(-1, index, spread)
        if lanes > 1:
            out = out.reshape(*lead, lanes, cells).sum(-2)
        return out.reshape(*lead, *self.shape)

    @cached_property
    def _lanes(self) -> tuple[int, Tensor]:
        """The deposit's private copies of the grid and each weight's flat index into them.

        On a GPU every agent's four weights are atomic adds, and a band puts most agents in a
        few grid cells (1e6 agents in 8 cells after 2 s of the band): the adds to one address
        serialise (2.5 ms of a 3.1 ms field step on an H200). Agent ``a`` adds into copy
        ``a % lanes`` and the copies are summed: 0.18 ms with 128 copies, measured. The CPU's
        torch path keeps one copy (its adds are not atomic; the compiled exchange has its own
        pieces, :func:`~surrogate.grid.kernels.deposit_pieces`)."""
        index = self.index
        n, cells = index.shape[0], self.shape[0] * self.shape[1]
        lanes = deposit_lanes(n, cells, index.device)
        if lanes == 1:
            return 1, index.reshape(-1)
        lane = torch.arange(n, device=index.device).remainder(lanes) * cells
        return lanes, (index + lane[:, None]).reshape(-1)

    def saturating_deposit(self, values: Tensor, coef: float, km: float) -> Tensor:
        """The deposit of each agent's ``coef l / (km + l)``, ``l`` the grid ``values``
        (``(n_x, n_y)`` float64) at the agent clamped at zero: Michaelis-Menten demand
        (:class:`~surrogate.grid.Uptake`), fused into one pass where compiled.

        Returns:
            ``(n_x, n_y)`` float64 per cell.
        """
        if self.compiled:
            from surrogate.grid import kernels

            return kernels.uptake_deposit(self.grid, self.position, values, coef, km)
        local = self.interpolate(values).clamp_min(0.0)
        return self.deposit(coef * local / (km + local))

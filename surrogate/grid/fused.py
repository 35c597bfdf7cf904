"""The grid field's step as one pure function of tensors, for ``torch.compile`` on a GPU.

On a GPU the eager step (:meth:`GridField.step <surrogate.grid.GridField.step>`) is ~90 small
kernels per step: the torch stencil's index and weights (~36 element-wise ops over the agents),
the demand's read and deposit into the private copies (~15), the uptake's cap (~10), the
ledger's bookkeeping on ``(S,)`` tensors (~25) and the dense flow (3). Each costs a launch of
~10 us on the host while its arithmetic (32,768 grid values, or 1e6 agents at memory speed)
takes a few: at 1e6 agents on a 512 x 64 grid the eager step was 1.2-1.3 ms on an H200, 87-93 %
of the agents' step. :func:`fused_step` is the same arithmetic, in the same order, as one
function with no host sync, so ``torch.compile`` (inductor: Triton on CUDA) fuses the
element-wise chains into a few kernels and launches those from one wrapper.

Results: the eager step's to float64 rounding (a fused kernel may contract ``a * b + c`` into an
FMA or sum in another order; the deposit's atomics already add in any order on a GPU), tested
against the eager step (``tests/grid/test_fused.py``): the field's float64 values to 1e-12
relative, the agents' float32 reads to one float32 rounding (a 1e-16 difference in float64 may
cross a float32 rounding edge).

Which step runs is the field's ``fuse`` setting (:data:`FUSE_MODES`): ``auto`` (the default)
compiles on CUDA, where the eager step is launch bound, and keeps the eager step elsewhere (the
CPU's exchange is numba's, :mod:`surrogate.grid.kernels`: its bytes do not change); ``eager``
is the eager step on every device (the path before this module, and the reference);
``compile`` compiles on any device (on the CPU the exchange is then torch's, not numba's).
"""

from __future__ import annotations

import types
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from surrogate.grid.geometry import Grid
from surrogate.grid.species import MOLECULES_PER_NMOL, Species, cap_uptake

__all__ = ["FUSE_MODES", "FusedStep", "fused_step"]

#: the field's ``fuse`` setting: ``auto`` (compiled on CUDA, eager elsewhere), ``eager``,
#: ``compile``
FUSE_MODES = ("auto", "eager", "compile")

#: the outputs of :func:`fused_step`: concentration, taken, secreted, supplied, decayed, and
#: the stencil's index and weight (for the agents' next read)
Outputs = tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]


def fused_step(  # noqa: PLR0913  # torch.compile(fullgraph): its tensors are graph inputs
    grid: Grid,
    species: Sequence[Species],
    decay_loss: Callable[[Tensor, Tensor, Tensor, float], Tensor],
    decay: Tensor,
    lanes: int,
    dt: float,
    position: Tensor,
    phi: Tensor,
    concentration: Tensor,
    supply: Tensor,
    ledger: tuple[Tensor, Tensor, Tensor, Tensor],
    flow: tuple[Tensor, Tensor, Tensor, Tensor | None] | None,
) -> Outputs:
    """One field step, as :meth:`GridField.step <surrogate.grid.GridField.step>` with the torch
    stencil (the same ops in the same order; see the module docstring).

    Args:
        grid: the field's grid.
        species: its species, in order.
        decay_loss: its solver's decay loss
            (:func:`~surrogate.grid.solvers.exact_decay_loss` or ``euler_decay_loss``).
        decay: ``(S,)`` the species' decay rates (1/s).
        lanes: the deposit's private copies of the grid
            (:func:`~surrogate.grid.geometry.deposit_lanes`).
        dt: the step (s).
        position: ``(n, 2)`` the agents' positions (mm).
        phi: ``(n,)`` their phi after the window.
        concentration: ``(S, n_x, n_y)`` float64, the state's.
        supply: ``(S,)`` the sources' supply rate (nmol/s).
        ledger: the state's taken, secreted, supplied and decayed, ``(S,)`` each.
        flow: the dense spectral step's ``(A_x, A_y, e^{-k dt}, G or None)``
            (:meth:`SpectralSolver.flow <surrogate.grid.solvers.SpectralSolver.flow>`), or
            None: the concentration is returned before the flow, for the caller's solver.

    Returns:
        The new concentration, taken, secreted, supplied and decayed, and the stencil's
        ``(n, 4)`` index and weight (:meth:`Grid.weights`).
    """
    volume = grid.cell_volume
    cells = grid.n_cells
    index, weight = grid.weights(position)
    n = index.shape[0]
    if lanes > 1:  # as Stencil._lanes
        lane = torch.arange(n, device=index.device).remainder(lanes) * cells
        flat_index = (index + lane[:, None]).reshape(-1)
    else:
        flat_index = index.reshape(-1)

    def interpolate(values: Tensor) -> Tensor:  # as Stencil.interpolate, (n_x, n_y) float64
        return (values.reshape(-1)[index] * weight).sum(-1)

    def deposit(amounts: Tensor) -> Tensor:  # as Stencil.deposit, (n,) float64
        spread = (amounts[:, None] * weight).reshape(-1)
        out = amounts.new_zeros(lanes * cells)
        out = out.index_add(0, flat_index, spread)
        if lanes > 1:
            out = out.reshape(lanes, cells).sum(-2)
        return out.reshape(grid.shape)

    zero = concentration.new_zeros(())
    rows, taken, given = [], [], []
    for k, s in enumerate(species):
        c, took, gave = concentration[k], zero, zero
        if s.uptake is not None:  # Uptake.take through Stencil.saturating_deposit
            coef = s.uptake.vmax / MOLECULES_PER_NMOL * dt
            local = interpolate(c).clamp_min(0.0)
            wanted = deposit(coef * local / (s.uptake.km + local))
            loss, took = cap_uptake(wanted, c, volume)
            c = c - loss
        if s.secretion is not None:
            amounts = s.secretion.give(phi, dt)
            c, gave = c + deposit(amounts) / volume, amounts.sum()
        rows.append(c)
        taken.append(took)
        given.append(gave)
    c = torch.stack(rows)
    decayed = decay_loss(decay, c.sum((-2, -1)) * volume, supply, dt)
    if flow is not None:  # SpectralSolver.step's dense branch
        ax, ay, kept, added = flow
        c = torch.matmul(torch.matmul(ax, c), ay.transpose(-2, -1)) * kept
        if added is not None:
            c = c + added
    t, s_, sup, dec = ledger
    return (c, t + torch.stack(taken), s_ + torch.stack(given), sup + supply * dt,
            dec + decayed, index, weight)  # fmt: skip


def _private_function(func: Callable[..., Any]) -> Callable[..., Any]:
    """A copy of ``func`` with its own code object: ``torch.compile`` keeps its cache and its
    recompile limit per code object, so each field compiles its own (as the simulator's step,
    :func:`surrogate.simulate.loop._private_copy`)."""
    return types.FunctionType(func.__code__.replace(), func.__globals__, func.__name__,
                              func.__defaults__, func.__closure__)  # fmt: skip


class FusedStep:
    """:func:`fused_step` through ``torch.compile`` for one field (its own compiled code).

    Args:
        backend: ``torch.compile``'s backend (``inductor``; tests trace with ``aot_eager``).
        fallback: where a compiled call fails, warn and run :func:`fused_step`
            eagerly from then on (the ``auto`` setting); else raise.
    """

    def __init__(
        self, backend: str | Callable[..., Any] = "inductor", fallback: bool = True
    ) -> None:
        self.backend = backend
        self.fallback = fallback
        #: why compiling failed (then the step runs eagerly), or None
        self.error: str | None = None
        self._eager = _private_function(fused_step)
        self._compiled = torch.compile(self._eager, backend=backend, fullgraph=True)

    def __deepcopy__(self, memo: dict[int, Any]) -> FusedStep:
        """A fresh one (its own code object and compiled cache): a replicate's deep copy of
        a field (:mod:`surrogate.simulate.batch`) compiles its own, as a new field does."""
        return FusedStep(self.backend, self.fallback)

    def __call__(self, *args: Any) -> Outputs:
        """:func:`fused_step` (``args`` as its), compiled unless compiling failed."""
        if self.error is None:
            try:
                return self._compiled(*args)
            except Exception as exc:  # a compiler/backend failure: the same function, eagerly
                if not self.fallback:
                    raise
                self.error = f"{type(exc).__name__}: {exc}"
                warnings.warn(f"torch.compile of the grid field's step failed ({self.error}); "
                              "running it eagerly", stacklevel=3)  # fmt: skip
        return self._eager(*args)

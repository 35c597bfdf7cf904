"""A field that is state: concentrations on a regular 2-D grid that the agents consume and secrete.

Every step the simulator lets the agents read the grid (bilinear interpolation, through
``__call__`` as any field), advances them, then calls :meth:`GridField.step`, which in order

1. takes each species' uptake from the grid and adds its secretion, at the agents' positions
   after their step and with their phi after the step's window (the adjoint deposit of
   :mod:`surrogate.grid.geometry`, the exchange of :mod:`surrogate.grid.species`), then
2. advances every species by dt of diffusion, decay and sources (:mod:`surrogate.grid.solvers`:
   the exact spectral step by default).

So the agents of step n read the field of step n and their exchange enters the field of step
n + 1: the same order whatever decides phi (full model, abstraction, exact chain). The state
(:class:`GridState`) carries a ledger per species (nmol, float64: taken up, secreted, supplied
by the sources, lost to decay), so ``mass + taken + decayed - secreted - supplied`` stays the
initial mass to float64 rounding over a whole run (:meth:`GridField.balance`).

Example (yaml, ``conf/field/channel_consumed.yaml``)::

    _target_: surrogate.grid.GridField
    domain: [[0.0, 20.0], [-0.5, 0.5]]   # mm
    shape: [512, 32]
    boundary: no_flux
    depth: 0.1                            # mm
    species:
      serine: {diffusion: 8.0e-4, initial: 0.1, uptake: {vmax: 1.6e5, km: 0.01}}
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from surrogate.errors import ConfigError
from surrogate.grid.coupled import CoupledField
from surrogate.grid.fused import FUSE_MODES, FusedStep
from surrogate.grid.geometry import Grid, Stencil, deposit_lanes
from surrogate.grid.solvers import (
    SOLVERS,
    ExplicitSolver,
    SpectralSolver,
    euler_decay_loss,
    exact_decay_loss,
    explicit_max_dt,
    make_solver,
)
from surrogate.grid.species import Species

__all__ = ["GridField", "GridState"]

#: float64 copies of the grid a step holds at once (state, transforms, factors, exchange)
WORKING_COPIES = 10


@dataclass(frozen=True)
class GridState:
    """A grid field's state after ``steps`` steps; the ledger is per species, nmol, float64.

    Attributes:
        concentration: ``(S, n_x, n_y)`` float64, mM.
        initial: ``(S,)`` the mass at reset.
        taken: ``(S,)`` taken up by the agents so far.
        secreted: ``(S,)`` secreted by the agents so far.
        supplied: ``(S,)`` added by the sources so far.
        decayed: ``(S,)`` lost to first-order decay so far.
        steps: steps taken since reset.
    """

    concentration: Tensor
    initial: Tensor
    taken: Tensor
    secreted: Tensor
    supplied: Tensor
    decayed: Tensor
    steps: int = 0


class GridField(CoupledField):
    """Concentrations on a grid, advanced by diffusion, decay, sources and the agents.

    Args:
        domain: ``[[x_lo, x_hi], [y_lo, y_hi]]`` (mm).
        shape: cells ``[n_x, n_y]``.
        species: name -> its settings (:class:`~surrogate.grid.species.Species`), in order.
        depth: the layer's depth (mm): a cell holds ``h_x h_y depth`` mm^3.
        boundary: ``no_flux`` or ``periodic``, or one per axis ``[x, y]``.
        read: the species the agents read as their field (default: the first).
        solver: ``spectral`` (exact in time, any dt) or ``explicit`` (forward Euler, dt
            limited; :mod:`surrogate.grid.solvers`).
        peak: where distances are measured from (default: the middle of the domain's left
            edge, a channel's inlet).
        fuse: how the step runs (:data:`~surrogate.grid.fused.FUSE_MODES`): ``auto`` (one
            ``torch.compile``'d function on CUDA, where the eager step is ~90 kernel launches;
            the eager step elsewhere), ``eager`` (the eager step on every device: the
            reference) or ``compile`` (compiled on any device, failures raised);
            :mod:`surrogate.grid.fused`. Results agree to float64 rounding.

    Raises:
        ConfigError: a bad geometry, species, rate or solver, named (``field.<key>``).

    Example:
        >>> field = GridField([[0, 1], [0, 1]], [8, 8], {"a": {"diffusion": 1e-3,
        ...                   "initial": 0.1}}, depth=0.1)
        >>> field(torch.tensor([[0.5, 0.5]]), 0.0)
        tensor([0.1000])
    """

    name = "grid"

    def __init__(  # noqa: PLR0913  # built from the field config's keys (hydra)
        self,
        domain: Sequence[Sequence[float]],
        shape: Sequence[int],
        species: Mapping[str, Mapping[str, Any]],
        depth: float,
        boundary: str | Sequence[str] = "no_flux",
        read: str | None = None,
        solver: str = "spectral",
        peak: Sequence[float] | None = None,
        fuse: str = "auto",
    ) -> None:
        self.grid = Grid.from_config(domain, shape, boundary, depth)
        if not isinstance(species, Mapping) or not species:
            raise ConfigError("field.species must declare at least one species by name, e.g. "
                              "{serine: {diffusion: 8.0e-4, initial: 0.1}}")  # fmt: skip
        self.species = [Species.from_config(str(k), v) for k, v in species.items()]
        for s in self.species:
            s.check_formulas(self.grid)
        names = [s.name for s in self.species]
        self.read = names[0] if read is None else str(read)
        if self.read not in names:
            raise ConfigError(f"field.read={read!r} is not a declared species; declared: {names}")
        if solver not in SOLVERS:
            raise ConfigError(f"field.solver must be one of {list(SOLVERS)}, got {solver!r}")
        self.solver_name = solver
        if fuse not in FUSE_MODES:
            raise ConfigError(f"field.fuse must be one of {list(FUSE_MODES)}, got {fuse!r}")
        self.fuse = fuse
        self._fused: FusedStep | None = None
        g = self.grid
        inlet = (g.lower[0], (g.lower[1] + g.upper[1]) / 2)
        super().__init__(inlet if peak is None else peak)
        self._read_index = names.index(self.read)
        self._state: GridState | None = None
        self._solver: SpectralSolver | ExplicitSolver | None = None
        self._supply: Tensor | None = None
        # the torch path's last exchange stencil and a copy of its positions: the agents read
        # the next step's field at the very positions they deposited at (_stencil_at)
        self._shared: tuple[Tensor, Stencil] | None = None

    # --------------------------------------------------------------------------------------
    @property
    def species_names(self) -> list[str]:
        """The declared species, in order."""
        return [s.name for s in self.species]

    @property
    def state(self) -> GridState:
        """The current state (after :meth:`reset`)."""
        if self._state is None:
            raise RuntimeError("the grid field has no state yet: call reset(device) first")
        return self._state

    def max_dt(self) -> float:
        """The longest time step the solver takes (inf for the spectral step)."""
        if self.solver_name != "explicit":
            return float("inf")
        return explicit_max_dt(self.grid, [s.diffusion for s in self.species],
                               [s.decay for s in self.species])  # fmt: skip

    def validate(self, dt: float) -> None:
        """Refuse a dt beyond the explicit scheme's limit, naming dt, the grid and the limit."""
        limit = self.max_dt()
        if dt > limit:
            hx, hy = self.grid.spacing
            raise ConfigError(
                f"dt={dt:g} s is beyond field.solver=explicit's limit {limit:.4g} s on this grid "
                f"(h_x={hx:.4g} mm, h_y={hy:.4g} mm; dt <= 1 / (2 D (1/h_x^2 + 1/h_y^2) + k) "
                f"for the fastest species): use field.solver=spectral (exact for any dt), a "
                f"smaller dt or a coarser field.shape"
            )

    def memory_bytes(self) -> int:
        """Memory of the state and one step's working copies (bytes), and the most that a
        compiled deposit's private copies of the grid take
        (:func:`~surrogate.grid.kernels.deposit_pieces`)."""
        from surrogate.grid.kernels import deposit_pieces

        cells = self.grid.n_cells
        pieces = deposit_pieces(2**62, cells)  # as many as any population gets
        return WORKING_COPIES * 8 * len(self.species) * cells + 8 * pieces * cells

    # --------------------------------------------------------------------------------------
    def reset(self, device: torch.device | str = "cpu") -> GridState:
        """The initial profiles on ``device``, an empty ledger; returns the state."""
        g = self.grid
        c0 = torch.stack([s.profile("initial", g, device) for s in self.species])
        any_source = any(isinstance(s.source, str) or s.source > 0 for s in self.species)
        source = (torch.stack([s.profile("source", g, device) for s in self.species])
                  if any_source else None)  # fmt: skip
        diffusion = c0.new_tensor([s.diffusion for s in self.species])
        decay = c0.new_tensor([s.decay for s in self.species])
        self._solver = make_solver(self.solver_name, g, diffusion, decay, source)
        self._shared = None
        volume = g.cell_volume
        self._supply = (c0.new_zeros(len(self.species)) if source is None
                        else source.sum((-2, -1)) * volume)  # fmt: skip
        # four zero ledgers, not one shared: a compiled step recompiles where inputs alias
        taken, secreted, supplied, decayed = (c0.new_zeros(len(self.species)) for _ in range(4))
        self._state = GridState(c0, c0.sum((-2, -1)) * volume, taken, secreted, supplied,
                                decayed, 0)  # fmt: skip
        return self._state

    def start_from(self, concentration: Tensor) -> GridState:
        """Reset, then start from ``concentration`` (``(S, n_x, n_y)`` mM, on the device the
        state is to live on) instead of the initial profiles: a saved state, or a test's."""
        want = (len(self.species), *self.grid.shape)
        if tuple(concentration.shape) != want:
            raise ValueError(f"concentration must be {want}, got {tuple(concentration.shape)}")
        c = concentration.to(torch.float64).clone()
        self.reset(c.device)
        taken, secreted, supplied, decayed = (c.new_zeros(len(self.species)) for _ in range(4))
        mass = c.sum((-2, -1)) * self.grid.cell_volume
        self._state = GridState(c, mass, taken, secreted, supplied, decayed, 0)
        return self._state

    def _current(self, device: torch.device) -> GridState:
        """The state, made on ``device`` at first use; the agents must live where it does."""
        if self._state is None:
            return self.reset(device)
        if self._state.concentration.device != device:
            raise ValueError(f"the grid field's state is on {self._state.concentration.device} "
                             f"but the agents are on {device}: reset it on their device")  # fmt: skip
        return self._state

    def __call__(self, position: Tensor, t: float) -> Tensor:
        """The read species' concentration at ``position`` (``(n, 2)``), float32 ``(n,)``
        (clamped at zero: transforms may leave -1e-20 where a species ran out)."""
        c = self._current(position.device).concentration[self._read_index]
        return self._stencil_at(position).read(c)

    def _stencil_at(self, position: Tensor) -> Stencil:
        """The stencil at ``position``: the last step's where it was made (by torch's ops) at
        equal positions, so the agents' read after a step shares the index and weights of the
        step's deposit; a fresh one otherwise (the compiled kernels recompute it per agent,
        cheaper than storing it, :mod:`surrogate.grid.kernels`)."""
        if self._shared is not None:
            before, stencil = self._shared
            same = (before.shape, before.dtype, before.device) == (
                position.shape, position.dtype, position.device)  # fmt: skip
            if same and bool(torch.equal(before, position)):
                return stencil
        return self.grid.stencil(position)

    def sample(self, position: Tensor) -> Tensor:
        """Every species at ``position``: ``(S, n)`` float64 (mM)."""
        state = self._current(position.device)
        return self.grid.stencil(position).interpolate(state.concentration)

    def concentration(self, name: str) -> Tensor:
        """Species ``name`` on the grid, ``(n_x, n_y)`` float64 (mM)."""
        if name not in self.species_names:
            raise ConfigError(f"unknown species {name!r}; declared: {self.species_names}")
        return self.state.concentration[self.species_names.index(name)]

    def mass(self) -> Tensor:
        """Each species' amount on the grid, ``(S,)`` nmol."""
        return self.state.concentration.sum((-2, -1)) * self.grid.cell_volume

    def balance(self) -> Tensor:
        """``mass + taken + decayed - secreted - supplied - initial`` per species (nmol): zero
        up to float64 rounding."""
        s = self.state
        return self.mass() + s.taken + s.decayed - s.secreted - s.supplied - s.initial

    def check(self) -> str | None:
        """``NaN/inf in the grid field`` where the concentrations are not finite."""
        if self._state is None:
            return None
        if not bool(torch.isfinite(self._state.concentration).all()):
            return "NaN/inf in the grid field's concentrations"
        return None

    # --------------------------------------------------------------------------------------
    def step(self, position: Tensor, phi: Tensor, dt: float) -> GridState:
        """The agents' exchange at ``position`` (``(n, 2)``, after their step) with phi
        (``(n,)``, after the window), then dt of diffusion, decay and sources (module
        docstring); returns the new state.

        Args:
            position: ``(n, 2)`` the agents' positions (mm).
            phi: ``(n,)`` bool or 0/1, their phi after the step's window.
            dt: the step (s).
        """
        state = self._current(position.device)
        if dt > self.max_dt():
            self.validate(dt)
        fused = self._fused_step(position.device)
        if fused is not None:
            return self._step_fused(fused, state, position, phi, dt)
        volume = self.grid.cell_volume
        stencil = self.grid.stencil(position)
        self._shared = None if stencil.compiled else (position.clone(), stencil)
        zero = state.concentration.new_zeros(())
        rows, taken, given = [], [], []
        for k, species in enumerate(self.species):
            c, took, gave = state.concentration[k], zero, zero
            if species.uptake is not None:
                loss, took = species.uptake.take(c, stencil, dt, volume)
                c = c - loss
            if species.secretion is not None:
                amounts = species.secretion.give(phi, dt)
                c, gave = c + stencil.deposit(amounts) / volume, amounts.sum()
            rows.append(c)
            taken.append(took)
            given.append(gave)
        c = torch.stack(rows)
        assert self._solver is not None and self._supply is not None
        decayed = self._solver.decay_loss(c.sum((-2, -1)) * volume, self._supply, dt)
        c = self._solver.step(c, dt)
        self._state = replace(
            state,
            concentration=c,
            taken=state.taken + torch.stack(taken),
            secreted=state.secreted + torch.stack(given),
            supplied=state.supplied + self._supply * dt,
            decayed=state.decayed + decayed,
            steps=state.steps + 1,
        )
        return self._state

    @property
    def step_path(self) -> str:
        """How the steps on the state's device run: ``compiled``, ``eager``, or ``eager
        (torch.compile failed: ...)`` (the ``fuse`` setting, :mod:`surrogate.grid.fused`)."""
        state = self._state
        if state is None or self._fused is None or not self._compiles(state.concentration.device):
            return "eager"
        if self._fused.error is None:
            return "compiled"
        return f"eager (torch.compile failed: {self._fused.error})"

    def _compiles(self, device: torch.device) -> bool:
        """Whether the ``fuse`` setting compiles the step on ``device``."""
        return self.fuse == "compile" or (self.fuse == "auto" and _compiles_on(device))

    def _fused_step(self, device: torch.device) -> FusedStep | None:
        """The compiled step where ``fuse`` asks for it on ``device`` (made at first use and
        kept, so resets reuse its compiled code), else None: the eager step."""
        if not self._compiles(device):
            return None
        if self._fused is None:
            self._fused = FusedStep(fallback=self.fuse == "auto")
        return self._fused

    def _step_fused(self, fused: FusedStep, state: GridState, position: Tensor, phi: Tensor,
                    dt: float) -> GridState:  # fmt: skip
        """:meth:`step` through :func:`~surrogate.grid.fused.fused_step`; the stencil it
        computed is kept for the agents' next read, as the eager torch path keeps its own."""
        assert self._solver is not None and self._supply is not None
        if isinstance(self._solver, SpectralSolver):  # flow: None where its step is not dense
            flow, loss = self._solver.flow(dt), exact_decay_loss
        else:
            flow, loss = None, euler_decay_loss
        lanes = deposit_lanes(position.shape[0], self.grid.n_cells, position.device)
        ledger = (state.taken, state.secreted, state.supplied, state.decayed)
        # the solver's tensors enter as arguments, not the solver: each reset makes a new
        # solver, and torch.compile would recompile for a new object
        c, taken, secreted, supplied, decayed, index, weight = fused(
            self.grid, tuple(self.species), loss, self._solver.decay, lanes, dt, position, phi,
            state.concentration, self._supply, ledger, flow)  # fmt: skip
        if flow is None:
            c = self._solver.step(c, dt)
        stencil = Stencil(self.grid, position, False)
        stencil.__dict__["_torch"] = (index, weight)  # its cached_property, computed
        self._shared = (position.clone(), stencil)
        self._state = replace(state, concentration=c, taken=taken, secreted=secreted,
                              supplied=supplied, decayed=decayed, steps=state.steps + 1)  # fmt: skip
        return self._state


def _compiles_on(device: torch.device) -> bool:
    """Whether ``fuse=auto`` compiles the step on ``device``: CUDA with Triton."""
    if device.type != "cuda":
        return False
    try:
        from torch.utils._triton import has_triton
    except ImportError:  # pragma: no cover - every torch this project supports has it
        return False
    return bool(has_triton())

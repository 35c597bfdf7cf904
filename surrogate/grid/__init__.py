"""Fields that are state: concentrations on a grid that the agents consume and secrete
(docs/fields.md)."""

from __future__ import annotations

from surrogate.grid.coupled import CoupledField, is_coupled
from surrogate.grid.field import GridField, GridState
from surrogate.grid.geometry import BOUNDARIES, Grid, Stencil
from surrogate.grid.solvers import SOLVERS, ExplicitSolver, SpectralSolver
from surrogate.grid.species import MOLECULES_PER_NMOL, Secretion, Species, Uptake
from surrogate.grid.transforms import dct, idct

__all__ = [
    "BOUNDARIES",
    "MOLECULES_PER_NMOL",
    "SOLVERS",
    "CoupledField",
    "ExplicitSolver",
    "Grid",
    "GridField",
    "GridState",
    "Secretion",
    "Species",
    "SpectralSolver",
    "Stencil",
    "Uptake",
    "dct",
    "idct",
    "is_coupled",
]

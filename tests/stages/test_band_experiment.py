"""experiment=band (issue 39): the config composes into a band channel whose mass balance gives
a band of a few um/s at a realistic density, and a small run of it (the same cells per unit
cross-section, fewer cells in a shallower channel) grows a front that travels forward at the
speed the mass balance gives."""

from __future__ import annotations

import pytest

from surrogate.grid import MOLECULES_PER_NMOL, GridField
from surrogate.io import read_manifest
from surrogate.simulate.profiles import read_profiles
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.settings import SimulateSettings

#: the share of the cells the config's design counts in the band (docs/fields.md)
IN_BAND = 0.75


def test_the_band_experiment_composes_into_a_consumed_channel(compose_cfg) -> None:
    settings = SimulateSettings.from_config(compose_cfg("simulate", ["experiment=band"]))
    field = settings.setup.field
    assert isinstance(field, GridField) and field.read == "serine"
    grid = field.grid
    assert grid.boundary == ("no_flux", "periodic")  # closed ends; y without walls (bodies)
    assert settings.n_cells == 5000 and settings.backend == "auto"
    assert settings.t_end * settings.setup.dt > 0 and settings.start == (0.0, 0.0)
    # the serine fills x > 0 only; the cells start where it begins, well inside the grid
    serine = field.species[0]
    c0 = serine.parameters["c0"]
    c = field.reset().concentration[0]
    centres = grid.centres()[..., 0]
    inside = c[centres > 0]  # the formula is evaluated in float32
    assert float((inside - c0).abs().max()) <= 1e-7 * c0 and bool((c[centres < 0] == 0).all())
    assert grid.lower[0] < settings.start[0] < grid.upper[0] - 2.0 - 1.0  # 2 mm ahead, and more
    # the design: v = q N_band / (A c0) a few um/s, at a few 1e9 cells/ml in a ~0.5 mm band
    area = (grid.upper[1] - grid.lower[1]) * grid.depth  # mm^2
    assert serine.uptake is not None
    q = serine.uptake.vmax / MOLECULES_PER_NMOL  # nmol/s per cell
    speed = q * IN_BAND * settings.n_cells / (area * c0)  # mm/s
    assert 2e-3 < speed < 6e-3
    per_ml = IN_BAND * settings.n_cells / (area * 0.5) * 1e3  # cells/mm^3 -> cells/ml
    assert 1e9 <= per_ml <= 5e9


N_SMALL = 600  # cells: the config's N/A in a channel 600/5,000 as deep


def test_a_small_band_travels_at_its_mass_balance(compose_cfg) -> None:
    """The first minute of a band at the config's density (a shallower channel for fewer
    cells): the depletion front forms and moves forward, at the speed the cells' uptake gives
    by mass balance (within the spread of a few hundred cells' band)."""
    full = compose_cfg("simulate", ["experiment=band"])
    depth = full.field.depth * N_SMALL / full.n_cells
    cfg = compose_cfg("simulate", ["experiment=band", f"n_cells={N_SMALL}",
                                   f"field.depth={depth}", "t_end=80.0",
                                   "record_interval=10.0", "equilibration_time=2.0",
                                   "record_durations=false"])  # fmt: skip
    out = simulate_stage.run(cfg)
    band = read_manifest(out)["band"]
    front, balance = band["front"], band["mass_balance"]
    assert front["n"] >= 5 and front["last"] - front["first"] > 0.1  # mm
    assert front["speed"] > 0 and balance["speed"] > 0
    assert front["speed"] == pytest.approx(balance["speed"], rel=0.5)
    profiles = read_profiles(out)
    assert profiles.counts.sum(1)[-1] + profiles.below[-1] + profiles.above[-1] == N_SMALL

"""ProfileRecorder: the cells' x histogram on the grid's columns and the y-averaged
concentrations, bins x record times whatever the number of cells; written by a run (alone or in
a batch) in a grid field only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from surrogate.errors import ArtefactError
from surrogate.fields import ConstantField
from surrogate.grid import GridField
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import AbstractDecision, Simulator, simulate_population
from surrogate.simulate.batch import BatchSimulator, Replicate, simulate_batch
from surrogate.simulate.profiles import PROFILES, ProfileRecorder, read_profiles

MODEL = EcoliModel()
DT = 0.05


def channel(boundary: str = "no_flux") -> GridField:
    """A 4 mm x 0.5 mm channel of 16 x 4 cells: a consumed attractant (read) and a signal."""
    return GridField(
        [[0.0, 4.0], [-0.25, 0.25]], [16, 4],
        {"attractant": {"diffusion": 8e-4, "initial": 0.1, "uptake": {"vmax": 1e8, "km": 0.01}},
         "signal": {"diffusion": 8e-4, "secretion": {"rate_on": 1e5, "rate_off": 0.0}}},
        depth=0.1, boundary=boundary, read="attractant",
    )  # fmt: skip


def flipping() -> AbstractDecision:
    """A cheap two-state chain whose phi flips every step."""

    def psi(phi: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return torch.where(phi.reshape(-1) > 0, 0.0, 1.0).to(torch.float32)

    return AbstractDecision(psi, MODEL.internal)


def test_counts_every_cell_on_the_columns_and_averages_the_field_over_y(tmp_path: Path) -> None:
    """Counts are the histogram of x on the grid's columns (cells beyond either end in their
    own bins, none lost); concentrations are the grid's column means, per species."""
    field = channel()
    rng = np.random.default_rng(0)
    c = torch.as_tensor(rng.uniform(0.0, 0.2, (2, 16, 4)))
    field.start_from(c)
    rec = ProfileRecorder(tmp_path, field, n_cells=500)
    xs = []
    for t in (0.0, 1.0):
        x = rng.uniform(-1.0, 5.0, 500)  # some beyond both ends of [0, 4]
        xs.append(x)
        rec.record(
            t, torch.as_tensor(np.stack([x, rng.uniform(-1, 1, 500)], 1), dtype=torch.float32)
        )
    assert not (tmp_path / PROFILES).exists()  # only once committed
    facts = rec.commit()
    assert facts["n_records"] == 2 and facts["read"] == "attractant" and facts["n_x"] == 16
    p = read_profiles(tmp_path)
    edges = np.linspace(0.0, 4.0, 17)
    assert np.allclose(p.edges, edges) and p.width == pytest.approx(0.25)
    for k, x in enumerate(np.asarray(xs, dtype=np.float32).astype(np.float64)):
        assert np.array_equal(p.counts[k], np.histogram(x, edges)[0])
        assert p.below[k] == (x < 0).sum() and p.above[k] == (x >= 4).sum()
        assert p.counts[k].sum() + p.below[k] + p.above[k] == 500
    for s, name in enumerate(("attractant", "signal")):
        assert np.array_equal(p.concentration[name], np.tile(c[s].mean(-1).numpy(), (2, 1)))
    assert np.array_equal(p.read_concentration(), p.concentration["attractant"])
    assert np.allclose(p.density.sum(1) * p.width, p.counts.sum(1) / 500)
    assert np.array_equal(p.t, [0.0, 1.0]) and p.cross_section == pytest.approx(0.05)


def test_a_periodic_x_axis_wraps_positions_into_the_columns(tmp_path: Path) -> None:
    field = channel("periodic")
    field.reset()
    rec = ProfileRecorder(tmp_path, field, n_cells=3)
    rec.record(0.0, torch.tensor([[-0.1, 0.0], [4.1, 0.0], [8.3, 0.0]]))
    rec.commit()
    p = read_profiles(tmp_path)
    assert p.below[0] == 0 and p.above[0] == 0
    assert np.flatnonzero(p.counts[0]).tolist() == [0, 1, 15]  # 3.9 -> 15, 0.1 and 0.3 -> 0, 1


def test_what_is_kept_is_bins_by_records_whatever_the_cells(tmp_path: Path) -> None:
    """1e6 cells keep exactly as many numbers as 10 (and are all counted)."""
    field = channel()
    field.reset()
    rows = {}
    for n in (10, 1_000_000):
        rec = ProfileRecorder(tmp_path / str(n), field, n_cells=n)
        gen = torch.Generator().manual_seed(n)
        for t in range(3):
            rec.record(float(t), torch.rand(n, 2, generator=gen) * 4.0)
        rec.commit()
        p = read_profiles(tmp_path / str(n))
        assert p.counts.sum() == 3 * n
        rows[n] = (p.counts.shape, {k: v.shape for k, v in p.concentration.items()})
    assert rows[10] == rows[1_000_000] == ((3, 16), {"attractant": (3, 16), "signal": (3, 16)})


def test_abort_leaves_nothing_and_a_missing_table_is_named(tmp_path: Path) -> None:
    field = channel()
    field.reset()
    rec = ProfileRecorder(tmp_path, field, n_cells=1)
    rec.record(0.0, torch.zeros(1, 2))
    rec.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ArtefactError, match="coupled grid field"):
        read_profiles(tmp_path)
    assert ProfileRecorder.of(tmp_path, ConstantField(0.1), 1) is None


def test_a_run_in_a_grid_field_writes_its_profiles_and_one_in_a_given_field_none(
    tmp_path: Path,
) -> None:
    """The run's records: t = 0 the initial field, every record all its cells, the last the
    field's final state; a run in a given field writes no profiles."""
    torch.manual_seed(0)
    field = channel()
    sim = Simulator(MODEL, flipping(), field, DT)
    summary = simulate_population(sim, 50, 1.0, tmp_path / "grid", record_interval=0.5,
                                  start=(1.0, 0.0), progress=False)  # fmt: skip
    assert summary.profiles is not None and summary.profiles["n_records"] == 3
    p = read_profiles(tmp_path / "grid")
    assert np.array_equal(p.t, [0.0, 0.5, 1.0])
    assert (p.counts.sum(1) + p.below + p.above == 50).all()
    assert np.array_equal(p.counts[0], np.eye(16, dtype=np.int64)[4] * 50)  # all at x = 1
    assert np.allclose(p.concentration["attractant"][0], 0.1)
    final = field.state.concentration.mean(-1).numpy()
    assert np.array_equal(p.concentration["attractant"][-1], final[0])
    assert p.concentration["signal"][-1].max() > 0  # the cells secreted
    torch.manual_seed(0)
    given = Simulator(MODEL, flipping(), ConstantField(0.1), DT)
    plain = simulate_population(given, 10, 0.5, tmp_path / "given", record_interval=0.5,
                                start=(1.0, 0.0), progress=False)  # fmt: skip
    assert plain.profiles is None and not (tmp_path / "given" / PROFILES).exists()


def test_each_replicate_of_a_batch_writes_its_standalone_runs_profiles(tmp_path: Path) -> None:
    """Two replicates given one field object: each records its own field and cells, the very
    profiles of the run it would be alone (eager CPU: bit for bit)."""
    shared = channel()
    reps = [Replicate(flipping(), shared, n, seed=s, start=(1.0, 0.0))
            for n, s in ((30, 3), (40, 4))]  # fmt: skip
    batch = BatchSimulator(MODEL, reps, DT)
    dirs = [tmp_path / "a", tmp_path / "b"]
    summaries = simulate_batch(batch, 1.0, dirs, record_interval=0.5, progress=False)
    for rep, out, summary in zip(reps, dirs, summaries, strict=True):
        assert summary.profiles is not None
        torch.manual_seed(rep.seed)
        alone = Simulator(MODEL, flipping(), channel(), DT)
        simulate_population(alone, rep.n_cells, 1.0, tmp_path / f"alone{rep.seed}",
                            record_interval=0.5, start=(1.0, 0.0), progress=False)  # fmt: skip
        got, want = read_profiles(out), read_profiles(tmp_path / f"alone{rep.seed}")
        assert got.n_cells == rep.n_cells
        assert np.array_equal(got.counts, want.counts)
        for name in ("attractant", "signal"):
            assert np.array_equal(got.concentration[name], want.concentration[name])

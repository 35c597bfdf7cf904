"""Recorded transitions and occupancy: the kernel and the torch step record the same rows."""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from surrogate.fields import GaussianField
from surrogate.models.ecoli import EcoliModel
from surrogate.simulate import FullDecision, Simulator
from surrogate.simulate.transitions import (
    CollectOptions,
    collect_transitions,
    record_occupancy,
)


def _simulator(backend: str) -> Simulator:
    model = EcoliModel()
    return Simulator(model, FullDecision(model.internal), GaussianField(), 0.05, backend=backend)


def _same_rows(a, b) -> None:
    assert len(a) == len(b) > 0
    for column in ("cell", "t", "phi"):
        np.testing.assert_array_equal(a[column], b[column])
    # one u < p may flip at float rounding; such rows must stay rare
    assert (a["phi_next"] != b["phi_next"]).mean() < 1e-3
    np.testing.assert_allclose(a["m"], b["m"], atol=1e-4)
    np.testing.assert_allclose(a["L"], b["L"], rtol=1e-4, atol=1e-7)


def test_occupancy_recorded_by_the_kernel_is_the_torch_steps() -> None:
    """Recorded steps go through the kernel too (phi before copied, inputs from the state):
    from one seed both backends record the same rows."""
    tables = []
    for backend in ("torch", "numba"):
        torch.manual_seed(4)
        tables.append(record_occupancy(_simulator(backend), 300, 20.0, (2.0, 0.0), 7, 1.0))
    _same_rows(*tables)
    assert {0, 1} <= set(tables[0]["phi_next"].unique())


def test_collected_transitions_by_the_kernel_are_the_torch_steps() -> None:
    """With perturbations every step is one kernel call after the jumps: the same rows."""
    tables = []
    model = EcoliModel()
    for backend in ("torch", "numba"):
        torch.manual_seed(5)
        sim = _simulator(backend)
        perturbation = model.body.perturbation(sim.field, model.perturbation_options)
        tables.append(collect_transitions(sim, perturbation, n_cells=300, n_per_state=500,
                                          perturb_rate=0.5, progress=False,
                                          options=CollectOptions(record_every=3,
                                                                 equilibration_time=1.0,
                                                                 blackout=4)))  # fmt: skip
    _same_rows(*tables)
    np.testing.assert_array_equal(tables[0]["since_jump"], tables[1]["since_jump"])


def test_expected_labels_average_to_the_switching_frequency() -> None:
    """Collected with expected labels (kernel loop), the same rows as without (they draw no
    random numbers), and per origin the expected labels average to the outcomes' frequency
    within 4 standard errors of the difference (outcome minus expected label per row)."""
    from surrogate.simulate.transitions import EXPECTED

    model = EcoliModel()
    tables = []
    for expected in (False, True):
        torch.manual_seed(6)
        sim = _simulator("numba")
        perturbation = model.body.perturbation(sim.field, model.perturbation_options)
        tables.append(collect_transitions(sim, perturbation, n_cells=1000, n_per_state=20000,
                                          perturb_rate=0.1, progress=False,
                                          options=CollectOptions(record_every=5,
                                                                 equilibration_time=1.0,
                                                                 blackout=20,
                                                                 expected=expected)))  # fmt: skip
    plain, table = tables
    assert EXPECTED not in plain.columns
    for column in plain.columns:
        np.testing.assert_array_equal(plain[column], table[column])
    for origin in (0, 1):
        rows = table[table["phi"] == origin]
        diff = rows["phi_next"].to_numpy(float) - rows[EXPECTED].to_numpy(float)
        se = diff.std(ddof=1) / np.sqrt(len(diff))
        assert abs(diff.mean()) < 4 * se, (origin, diff.mean(), se)
        # lower variance than the outcomes (the point of them)
        assert rows[EXPECTED].var() < 0.5 * rows["phi_next"].var()


def test_recorded_switch_clocks_follow_each_cells_phi() -> None:
    """With clocks, each row's phi_age is the time since the cell's phi last changed, seen
    from its rows (every step recorded): 0 after a window that changed phi, else the previous
    row's clock + dt; censored until the cell's first switch (then its clock counts from the
    start of recording), and the rows without clocks carry no clock columns."""
    from surrogate.simulate.memory import AGE, CENSORED

    torch.manual_seed(6)
    table = record_occupancy(_simulator("torch"), 200, 10.0, (2.0, 0.0), 1, 1.0, clock=True)
    table = table.sort_values(["cell", "t"])
    prev = table.groupby("cell").shift(1)
    inside = prev["t"].notna()
    changed = (prev["phi_next"] != prev["phi"]) & inside
    kept = ~changed & inside
    assert changed.sum() > 500 and kept.sum() > 500
    np.testing.assert_allclose(table.loc[changed, AGE], 0.0)
    np.testing.assert_allclose(table.loc[kept, AGE], prev.loc[kept, AGE] + 0.05, atol=1e-5)
    first = ~inside
    assert table.loc[first, CENSORED].all() and np.allclose(table.loc[first, AGE], 0.0)
    switched = table.groupby("cell")["phi"].transform(lambda p: (p != p.iloc[0]).cummax())
    assert not table.loc[switched.astype(bool), CENSORED].any()
    torch.manual_seed(6)
    plain = record_occupancy(_simulator("torch"), 20, 1.0, (2.0, 0.0), 1, 1.0)
    assert AGE not in plain and CENSORED not in plain


def test_keeping_switches_records_every_switch_and_the_thinned_rows_weighted() -> None:
    """collect.keep_switches with record_every=4 records, from one seed, exactly the windows
    of an every-window collection that fall on the thinned steps or changed phi or (E. coli
    declares classes: phi x CCW motors) the class (recording draws no random numbers), each
    carrying the windows it stands for: 4 where both held, 1 where either changed."""
    from surrogate.gp.windows import WINDOWS
    from surrogate.simulate.transitions import _Jumps, _rows

    model = EcoliModel()
    tables = []
    for options in (CollectOptions(record_every=1, equilibration_time=1.0, blackout=4),
                    CollectOptions(record_every=4, equilibration_time=1.0, blackout=4,
                                   keep_switches=True)):  # fmt: skip
        torch.manual_seed(7)
        sim = _simulator("torch")
        perturbation = model.body.perturbation(sim.field, model.perturbation_options)
        start = perturbation.start(200, sim.device)
        chunks = list(_rows(sim, 200, start, options, 200, _Jumps(perturbation, 0.5)))
        tables.append(pd.DataFrame({k: np.concatenate([c[k] for c in chunks])
                                    for k in chunks[0]}))  # fmt: skip
    every, kept = tables
    assert WINDOWS not in every.columns
    step = np.rint(every["t"].to_numpy() / 0.05).astype(np.int64) + 1  # the step k recorded
    switched = every["phi"] != every["phi_next"]
    moved = (every["phi_class"] != every["phi_class_next"]) & ~switched  # within a lump
    expected = every[(step % 4 == 0) | switched | moved]
    assert switched.sum() > 200 and moved.sum() > 200
    assert (~switched & ~moved & (step % 4 != 0)).sum() > 1000
    for column in ("cell", "t", "phi", "phi_next", "since_jump", "phi_class", "phi_class_next"):
        np.testing.assert_array_equal(kept[column].to_numpy(), expected[column].to_numpy())
    changed = kept["phi_class"] != kept["phi_class_next"]
    np.testing.assert_array_equal(kept[WINDOWS].to_numpy(), np.where(changed, 1.0, 4.0))


def test_a_take_that_keeps_switches_counts_thinned_rows() -> None:
    """collect_transitions keeping switches stops when each origin's rows, counted as a
    thinned collection counts them (windows / record_every), reach n_per_state, and keeps the
    same share of switches and held rows: the windows kept per origin are n_per_state x
    record_every within 3 windows (half a held row and half a switch)."""
    from surrogate.gp.windows import WINDOWS, origin_rows

    model = EcoliModel()
    torch.manual_seed(8)
    sim = _simulator("torch")
    perturbation = model.body.perturbation(sim.field, model.perturbation_options)
    table = collect_transitions(sim, perturbation, n_cells=300, n_per_state=2000,
                                perturb_rate=0.1, progress=False,
                                options=CollectOptions(record_every=5, equilibration_time=1.0,
                                                       keep_switches=True))  # fmt: skip
    assert WINDOWS in table.columns
    np.testing.assert_allclose(origin_rows(table, 5), [2000, 2000], atol=0.6)
    changed = table["phi_class"] != table["phi_class_next"]  # every switch changes the class
    assert (table.loc[changed, WINDOWS] == 1.0).all() and (table.loc[~changed, WINDOWS] == 5).all()

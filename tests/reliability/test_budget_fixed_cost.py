"""The cost estimate's fixed part per step (surrogate/diagnosis/cost.py): measured once per
process, part of every stage's estimate, so a small population's long run is not estimated at
nearly nothing. Structure and monotonicity only: no wall-clock value is asserted."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import torch
import yaml

from surrogate.diagnosis import cost
from surrogate.fields import ConstantField, GaussianField
from surrogate.models.network import NetworkInternalModel
from surrogate.models.sbml_agent import SbmlAgentModel
from surrogate.stages import budget
from surrogate.stages.settings import SimulateSettings
from tests.reliability.conftest import compose_in
from tests.sbml.builder import Reaction, Species, build

ROOT = Path(__file__).resolve().parents[2]
GENE = ["model=sbml", f"model.spec={ROOT / 'examples/gene_switch/model.yaml'}"]


def test_cost_formula() -> None:
    """steps x (fixed per step + cells x per cell-step), and a Work's seconds are it."""
    assert cost.cost_seconds(100, 0, 1e-3, 1e-6) == pytest.approx(0.1)
    assert cost.cost_seconds(100, 1000, 1e-3, 1e-6) == pytest.approx(0.2)
    assert cost.cost_seconds(200, 1000, 1e-3, 1e-6) == pytest.approx(0.4)
    work = cost.Work("w", 10, 50.0, 2e-6, "n_cells=10", "m", step_seconds=3e-3)
    assert work.seconds == pytest.approx(50 * (3e-3 + 10 * 2e-6))
    assert "~0.003 s per step + ~2e-06 s per cell-step of model 'm'" in work.describe()
    # without a measured figure: the documented constant
    assert cost.Work("w", 1, 1.0, 0.0, "", "m").step_seconds == cost.STEP_SECONDS


def test_step_seconds_measured_cached_and_leaves_the_random_state() -> None:
    model = SbmlAgentModel(spec=str(ROOT / "examples/gene_switch/model.yaml"))
    field = GaussianField()
    torch.manual_seed(7)
    before = torch.get_rng_state()
    full = cost.step_seconds(model, field, 0.05, "full")
    chain = cost.step_seconds(model, field, 0.05, "abstract")
    assert torch.equal(torch.get_rng_state(), before)
    assert full > 0 and chain > 0
    assert cost.step_seconds(model, field, 0.05, "full") == full  # once per process


def test_step_seconds_falls_back_where_the_simulator_cannot_run() -> None:
    class Broken:
        name = "broken"
        internal = None
        body = None

    assert cost.step_seconds(Broken(), GaussianField(), 0.05) == cost.STEP_SECONDS


def test_estimate_grows_with_steps_even_at_one_cell(tmp_path: Path) -> None:
    """At 1 cell the per-cell part is ~nothing: the estimate still grows with the steps, by
    the fixed part per step."""
    seconds = []
    for t_end in (10, 100, 1000):
        cfg = compose_in(tmp_path / "data", "simulate", [*GENE, "n_cells=1", f"t_end={t_end}"])
        (work,) = budget.run_work(SimulateSettings.from_config(cfg))
        assert work.cells == 1 and work.step_seconds > 0
        assert work.seconds >= work.steps * work.step_seconds
        assert work.seconds > work.steps * work.cell_step_seconds  # the fixed part counts
        seconds.append(work.seconds)
    assert seconds[0] < seconds[1] < seconds[2]
    assert seconds[2] / seconds[0] == pytest.approx((1000 + 1) / (10 + 1), rel=1e-6)


def test_a_job_threads_survive_numba_pool() -> None:
    """Starting numba's pool resets the process's OpenMP count (torch's): a ``threads=1`` job
    then ran the SSA on every core, ~10 ms per window on a loaded box."""
    import numba

    from surrogate.ctmc.compiled import match_torch_threads, start_numba_pool

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        start_numba_pool()
        numba.get_num_threads()
        assert torch.get_num_threads() == 1
        assert match_torch_threads() == 1 and numba.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
        match_torch_threads()


def runaway(tmp_path: Path) -> SbmlAgentModel:
    """Autocatalysis A -> 2A at 50 A from A = 10, burned in for 1 s (A ~ 1e22: never done)."""
    (tmp_path / "runaway.xml").write_text(build("runaway", [Species("A", amount=10)],
                                                {"k": 50.0, "s": 1.0},
                                                [Reaction("grow", "k * s * A", {"A": 1},
                                                          {"A": 2})]))  # fmt: skip
    spec = tmp_path / "runaway.yaml"
    spec.write_text(yaml.safe_dump({"name": "runaway", "network": "runaway.xml",
                                    "inputs": {"s": "L"}, "lump": "A >= 20",
                                    "body": {"kind": "static"}, "burn_in": 1.0}))  # fmt: skip
    return SbmlAgentModel(str(spec))


def birth_death(tmp_path: Path, birth: float, start: int, burn_in: float) -> NetworkInternalModel:
    """The network of a bounded birth-death, X made at ``birth`` (the input) and lost at 1 x X
    (settling near ``birth``), from ``start`` molecules, with ``burn_in`` seconds of burn-in."""
    (tmp_path / "busy.xml").write_text(build("busy", [Species("X", amount=start)],
                                             {"b": birth, "d": 1.0},
                                             [Reaction("birth", "b", {}, {"X": 1}),
                                              Reaction("death", "d * X", {"X": 1}, {})]))  # fmt: skip
    spec = tmp_path / "busy.yaml"
    spec.write_text(yaml.safe_dump({"name": "busy", "network": "busy.xml", "inputs": {"b": "L"},
                                    "lump": f"X >= {birth:g}", "body": {"kind": "static"},
                                    "burn_in": burn_in}))  # fmt: skip
    return SbmlAgentModel(str(spec)).internal


def test_a_window_over_max_events_raises_naming_the_cell(tmp_path: Path) -> None:
    """``advance_at(..., max_events=...)`` caps each cell's events in the window; without it
    the window runs as before."""
    network = runaway(tmp_path).internal
    inputs = network.file_inputs().expand(2, -1).clone()
    torch.manual_seed(0)
    state = network.start_state(2, torch.device("cpu"), inputs)
    with pytest.raises(RuntimeError, match=r"cell \d .*exceeded max_events"):
        network.advance_at(state, inputs, 0.2, max_events=100)
    after = network.advance_at(state, inputs, 0.01)  # ~e^0.5 growth: a few events
    assert bool((after[0] >= 10).all())
    assert network.bounded(100, burn_in=0.0).max_events == 100 and network.max_events is None


def test_a_long_burn_in_of_a_busy_network_is_no_runaway(tmp_path: Path, monkeypatch) -> None:
    """A burn-in is one window of many seconds: its cap is the runaway cap per
    ``RUNAWAY_SPAN_SECONDS`` of it. A bounded birth-death making ~2,000 events a second passes a
    200-s burn-in that the window cap alone refused (the auto-regulatory network's 4,000-s
    burn-in passed 1e7 events in one cell of a stationary sample); a runaway still trips."""
    from surrogate.errors import RunawayError
    from surrogate.models import network as network_module

    busy = birth_death(tmp_path, birth=1000.0, start=0, burn_in=200.0)
    monkeypatch.setattr(network_module, "RUNAWAY_EVENTS", 50_000)  # ~4e5 events in the burn-in
    monkeypatch.setattr(network_module, "RUNAWAY_SPAN_SECONDS", 1.0)
    assert busy.burn_in_cap(200.0) == 10_000_000 and busy.burn_in_cap(0.5) == 50_000
    inputs = torch.full((3, 1), 1000.0, dtype=torch.float64)
    torch.manual_seed(0)
    counts = busy.burn_in_at(inputs)[0]
    assert bool(((counts > 800) & (counts < 1200)).all())  # settled near b / d = 1,000
    with pytest.raises(RunawayError):  # the window's own cap: 50,000 events within ~25 s
        state = busy.start_state(3, torch.device("cpu"), inputs)
        busy.advance_at(state, inputs, 200.0)
    grows = runaway(tmp_path).internal  # 1 s of e^(50 t): past any cap
    with pytest.raises(RunawayError):
        grows.burn_in_at(grows.file_inputs().expand(2, -1).clone())


def test_a_network_busy_from_its_counts_is_no_runaway_in_its_burn_in(
    tmp_path: Path, monkeypatch
) -> None:
    """A burn-in's cap is at least ``RUNAWAY_RATE_FACTOR`` times the events the file's counts
    imply over it: a birth-death busy from its start (~4,000 events a second, ~40,000 in a
    10-s burn-in), which the span's cap alone (scaled down here to 10,000) refused as a
    runaway, settles; a network that does run away still trips (StochSS's Brusselator:
    1.1e7 events in its 50-s burn-in against 1e7)."""
    from surrogate.errors import RunawayError
    from surrogate.models import network as network_module

    busy = birth_death(tmp_path, birth=2000.0, start=2000, burn_in=10.0)
    monkeypatch.setattr(network_module, "RUNAWAY_EVENTS", 1_000)
    monkeypatch.setattr(network_module, "RUNAWAY_SPAN_SECONDS", 1.0)
    expected = busy.events_per_window(10.0)  # b + d X = 4,000 a second from the file's counts
    assert expected == pytest.approx(40_000.0)
    assert busy.burn_in_cap(10.0) == int(network_module.RUNAWAY_RATE_FACTOR * expected)
    inputs = torch.full((2, 1), 2000.0, dtype=torch.float64)
    torch.manual_seed(0)
    counts = busy.burn_in_at(inputs)[0]
    assert bool(((counts > 1800) & (counts < 2200)).all())  # settled near b / d
    monkeypatch.setattr(network_module, "RUNAWAY_RATE_FACTOR", 0.0)  # the span's cap alone
    with pytest.raises(RunawayError):
        busy.burn_in_at(inputs)
    monkeypatch.setattr(network_module, "RUNAWAY_RATE_FACTOR", 10.0)
    grows = runaway(tmp_path).internal  # 1 s of e^(50 t): past any multiple of its start's
    with pytest.raises(RunawayError):
        grows.burn_in_at(grows.file_inputs().expand(2, -1).clone())


def test_step_seconds_does_not_pay_a_runaway_burn_in(tmp_path: Path) -> None:
    """The per-step probe starts from the file's counts with windows capped at
    ``PROBE_MAX_EVENTS`` per cell: a runaway network falls back to ``STEP_SECONDS`` in a second
    or two, not an endless burn-in (L = 1: e^(50 t))."""
    model = runaway(tmp_path)
    model.internal.prepare()  # the compile is not the probe's
    start = time.perf_counter()
    assert cost.step_seconds(model, ConstantField(1.0), 0.05) == cost.STEP_SECONDS
    assert time.perf_counter() - start < 3.0


def test_the_estimate_says_it_is_priced_for_a_quiet_machine(caplog) -> None:
    """Every logged estimate says it assumes a quiet machine (collect ran 3-4x past it at a
    load of 4.5 on 2 cores, issue 54), and names the load where it exceeds the cores."""
    assert budget.quiet_note(1.0, 2) == (
        "; priced for a quiet machine: other work beside it makes it longer"
    )
    assert budget.quiet_note(4.5, 2).endswith("; this one is busy now (load 4.5 on 2 cores)")
    work = cost.Work("the run", 10, 50.0, 2e-6, "n_cells=10", "m", step_seconds=3e-3)
    with caplog.at_level("INFO", logger="surrogate.stages.budget"):
        budget.log_estimate([work], "collect")
    [message] = [r.getMessage() for r in caplog.records]
    assert message.startswith("collect: estimated ~") and "priced for a quiet machine" in message

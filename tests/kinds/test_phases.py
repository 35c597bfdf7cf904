"""The hidden-phase kind (``gp=phases``): its settings are refused by name, it starts its
cells within their lump, it packs for the per-cell kernel as K lumps do, and train then
simulate run it end to end on a tiny E. coli run, on both loops."""

from __future__ import annotations

import json

import pandas as pd
import pytest
import torch

from surrogate.errors import ConfigError
from surrogate.evaluate.statistics import load_run
from surrogate.gp import load_psi
from surrogate.gp.phases import (
    InputBasis,
    PhaseLaw,
    PhaseLayout,
    grid_points,
    input_grid,
    stationary_leaving,
)
from surrogate.kinds.phases import (
    HiddenPhases,
    PhaseSettings,
    load_phase_chain,
    phase_table,
    psi_leaving,
)
from surrogate.models.base import Randoms
from surrogate.simulate.kernel_pack import Slot, pack_layer
from surrogate.simulate.phases import PhaseDecision
from surrogate.stages import collect, train
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.settings import SimulateSettings, TrainSettings
from tests.stages.test_stages import TINY

PHASES = ["gp=phases", "gp.phases.n_cells=40", "gp.phases.t_end=10.0",
          "gp.phases.max_per_lump=2", "gp.phases.max_iterations=30"]  # fmt: skip


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("gp.phases.max_per_lump=0", r"gp.phases.max_per_lump must be an integer >= 1, got 0"),
        ("gp.phases.max_per_lump=1.5", r"gp.phases.max_per_lump must be an integer >= 1"),
        ("gp.phases.per_lump=[0,2]", r"gp.phases.per_lump must be null or two integers >= 1"),
        ("gp.phases.per_lump=[1,2,3]", r"gp.phases.per_lump must be null or two integers"),
        ("gp.phases.structure=ring", r"gp.phases.structure must be one of \['series', 'full'\]"),
        ("gp.phases.held_out=0.0", r"gp.phases.held_out must be in \(0, 1\)"),
        ("gp.phases.held_out=1.0", r"gp.phases.held_out must be a number in \[0, 1\)"),
        ("gp.phases.penalty=-1.0", r"gp.phases.penalty must be a number in \[0, inf\)"),
        ("gp.phases.nodes=1", r"gp.phases.nodes must be an integer >= 2"),
        ("gp.phases.t_end=0.0", r"gp.phases.t_end must be positive"),
        ("+gp.phases.phases=3", r"gp.phases.*phases"),
        ("gp.phases.means=mine", r"gp.phases.means must be one of \['psi', 'sequences'\]"),
        ("gp.phases.counts=best", r"gp.phases.counts must be one of \['max', 'held_out'\]"),
        ("gp.history=age", r"gp.lumps=phases takes no switch clock"),
    ],
)  # fmt: skip
def test_bad_phase_settings_are_refused_by_name(compose_cfg, override, message) -> None:
    with pytest.raises(ConfigError, match=message):
        TrainSettings.from_config(compose_cfg("train", ["gp=phases", override]))


def test_the_kinds_identity_and_refusals(compose_cfg) -> None:
    settings = TrainSettings.from_config(compose_cfg("train", ["gp=phases"]))
    assert isinstance(settings.kind, HiddenPhases)
    gp = settings.fit_identity()["gp"]
    assert gp["lumps"] == "phases" and gp["phases"]["max_per_lump"] == 3
    assert gp["phase_law_version"] == 3 and "lumps=phases" in settings.fit_directory.name
    # the counts chosen by held-out likelihood (the default, its identity as before the key);
    # counts: max puts max_per_lump phases in every lump, its own identity; per_lump wins
    assert "counts" not in gp["phases"]
    assert PhaseSettings.from_config({**gp["phases"], "counts": "held_out"}).per_lump is None
    assert PhaseSettings.from_config({**gp["phases"], "counts": "max"}).per_lump == (3, 3)
    fixed = {**gp["phases"], "counts": "max", "per_lump": [1, 2]}
    assert PhaseSettings.from_config(fixed).per_lump == (1, 2)
    most = TrainSettings.from_config(compose_cfg("train", ["gp=phases", "gp.phases.counts=max"]))
    assert most.fit_identity()["gp"]["phases"]["counts"] == "max"
    assert most.fit_directory != settings.fit_directory
    with pytest.raises(ConfigError, match="gp.phases is required with gp.lumps=phases"):
        TrainSettings.from_config(compose_cfg("train", ["gp.lumps=phases"]))
    with pytest.raises(ConfigError, match="the hidden-phase chain is a table"):
        SimulateSettings.from_config(compose_cfg("simulate", [
            "gp=phases", "decision=abstract", "decision.mode=classifier"]))  # fmt: skip
    with pytest.raises(ConfigError, match="the hidden-phase chain is learned only"):
        SimulateSettings.from_config(compose_cfg("simulate", ["decision=exact",
                                                              "decision.lumps=phases"]))  # fmt: skip


def test_means_from_psi_need_psi(compose_cfg) -> None:
    """gp.phases.means=psi (the default) refuses a fit without psi before its sample."""
    settings = TrainSettings.from_config(compose_cfg("train", ["gp=phases"]))
    with pytest.raises(ConfigError, match="gp.phases.means=psi matches the chain's means"):
        settings.kind.fit(settings, pd.DataFrame(), {name: (0.0, 1.0) for name in settings.inputs})


class _Phi:
    """An internal model whose initial phi is given (the layer's start reads only this)."""

    def __init__(self, phi: torch.Tensor) -> None:
        self._phi = phi

    def initial_state(self, x: torch.Tensor) -> torch.Tensor:
        return self._phi

    def phi(self, state: torch.Tensor) -> torch.Tensor:
        return state


def _layer(start: str, phi: torch.Tensor) -> PhaseDecision:
    weights = torch.zeros(2, 4, 4, dtype=torch.float64)
    weights[0] = -2.0  # every move left with ~0.1 per window
    law = PhaseLaw(PhaseLayout((2, 2)), InputBasis(((0.0, 1.0),), 0), weights)
    table = phase_table(law, ("z",), ("off", "on"), 0.1, 8)
    return PhaseDecision(table, _Phi(phi), start=start)  # type: ignore[arg-type]


def test_cells_start_within_their_lump_and_pack_as_k_lumps() -> None:
    """``start=internal``: each cell's hidden state is in the lump of its internal phi, spread
    over the lump's phases (the stationary law within it); the kernel gets a K-lumps block."""
    torch.manual_seed(0)
    phi = torch.arange(4000) % 2
    layer = _layer("internal", phi)
    start = layer.initialize(torch.rand(4000, 1))
    assert torch.equal(start.long(), phi)
    assert set(layer.state.tolist()) == {0, 1, 2, 3}  # type: ignore[union-attr]
    nxt = layer.step(start, torch.rand(4000, 1), 0.1)
    assert nxt.dtype == torch.bool and layer.state.shape == (4000,)  # type: ignore[union-attr]
    with pytest.raises(ValueError, match="built for dt=0.1 stepped with dt=0.2"):
        layer.step(nxt, torch.rand(4000, 1), 0.2)
    block = pack_layer(layer, Slot(0, None, Randoms(uniform=2), 0.1))
    assert block.kind == "classes" and block.classes is not None
    assert block.classes.lumps.tolist() == [0, 0, 1, 1]


def test_train_then_simulate_on_both_loops(compose_cfg) -> None:
    """A tiny E. coli collect, train gp=phases and simulate decision=abstract on the per-cell
    kernel and on the torch loop: the same chain, so their mean run durations agree within
    their standard errors (5 of the difference's); the fit's metrics name the candidates."""
    tiny = [*TINY, *PHASES]
    cfg = compose_cfg("train", [o for o in tiny if o.split("=")[0].split(".")[0] in ("collect",
                                                                                     "gp")])  # fmt: skip
    collect.run(cfg)
    trained = train.run(cfg)
    metrics = json.loads((trained / "train_metrics.json").read_text())["phase_chain"]
    assert metrics["cells"] == 40 and metrics["windows"] == 200
    assert [c["per_lump"] for c in metrics["candidates"]][:3] == [[1, 1], [2, 1], [1, 2]]
    # the table's mean sojourns are psi's at every node (gp.phases.means=psi, the default)
    assert set(metrics["sequence_means_over_psi"]) == {"tumble", "run"}
    table = load_phase_chain(trained)
    points = grid_points(input_grid(table.bounds, table.shape[0]))
    s = len(table.class_names)
    moves = table.cdf.double().reshape(s, -1, s).movedim(0, 1).diff(dim=-1, prepend=torch.zeros(
        len(points), s, 1, dtype=torch.float64))  # fmt: skip
    lumps = torch.tensor(table.class_lumps)
    psi, _ = load_psi(trained / "psi.pt")
    torch.testing.assert_close(stationary_leaving(moves, lumps), psi_leaving(psi)(points),
                               rtol=1e-4, atol=0.0)  # fmt: skip
    runs = {}
    for backend in ("numba", "torch"):
        out = simulate_stage.run(compose_cfg("simulate", [*tiny, "decision=abstract",
                                                          f"backend={backend}",
                                                          "n_cells=200"]))  # fmt: skip
        manifest = json.loads((out / "manifest.json").read_text())
        assert manifest["loop_backend"] == backend
        runs[backend] = load_run(out)
    means = {b: (r.mean_duration("run"), r.mean_duration_se("run")) for b, r in runs.items()}
    (a, sa), (b, sb) = means["numba"], means["torch"]
    assert a and b and sa and sb
    assert abs(a - b) < 5 * (sa**2 + sb**2) ** 0.5, means


@pytest.mark.parametrize(
    ("overrides", "split", "fix"),
    [(["gp.phases.n_cells=4"], r"\(1, 3\)", 6),
     (["gp.phases.n_cells=10", "gp.phases.held_out=0.95"], r"\(9, 1\)", 30)],
)  # fmt: skip
def test_a_held_out_split_of_one_cell_is_refused(compose_cfg, overrides, split, fix) -> None:
    """One held-out cell gives the gain no SE (any gain added a phase); one fitted cell fits
    noise: refused with the cell count that passes."""
    with pytest.raises(ConfigError, match=rf"leaves {split} \(held-out, fitted\) cells.*"
                                          rf"gp\.phases\.n_cells={fix} or more"):  # fmt: skip
        TrainSettings.from_config(compose_cfg("train", ["gp=phases", *overrides]))
    passing = [o for o in overrides if "n_cells" not in o]
    TrainSettings.from_config(compose_cfg("train", ["gp=phases", f"gp.phases.n_cells={fix}",
                                                    *passing]))  # fmt: skip
    with pytest.raises(ConfigError, match="n_cells"):
        TrainSettings.from_config(compose_cfg("train", ["gp=phases", f"gp.phases.n_cells={fix - 1}",
                                                        *passing]))  # fmt: skip


def test_a_table_too_large_is_refused_before_the_sample(compose_cfg) -> None:
    """nodes^d x S^2 entries were tabulated after the sample and the fits: 1e5 nodes over E.
    coli's two raw inputs is 3.6e11 entries."""
    base = ["gp=phases", "gp.inputs=inputs"]
    with pytest.raises(ConfigError, match=r"gp\.phases\.nodes=100000 over 2 input\(s\).*"
                                          r"use gp\.phases\.nodes=2730 or fewer"):  # fmt: skip
        TrainSettings.from_config(compose_cfg("train", [*base, "gp.phases.nodes=100000"]))
    TrainSettings.from_config(compose_cfg("train", [*base, "gp.phases.nodes=2730"]))


def test_a_sample_shorter_than_two_windows_is_refused(compose_cfg) -> None:
    """t_end below one window was rounded up to one, and one window shows no memory."""
    with pytest.raises(ConfigError, match=r"gp\.phases\.t_end=0\.07 s is shorter than two "
                                          r"windows \(dt=0\.05 s\).*gp\.phases\.t_end=50"):  # fmt: skip
        train.validate(compose_cfg("train", ["gp=phases", "gp.phases.t_end=0.07"]))
    train.validate(compose_cfg("train", ["gp=phases", "gp.phases.t_end=50"]))


def test_the_phase_fit_shares_the_two_state_psi(compose_cfg, monkeypatch) -> None:
    """gp=phases' psi is gp=svgp's of the same settings: its identity is the two-state fit's
    (the same directory), and a phase fit where that fit exists fits no psi of its own."""
    data = [o for o in TINY if o.split("=")[0].split(".")[0] in ("collect", "gp")]
    phases = ["gp=phases", "gp.phases.n_cells=8", "gp.phases.t_end=2.0",
              "gp.phases.max_per_lump=1", "gp.phases.max_iterations=5"]  # fmt: skip
    two_state = TrainSettings.from_config(compose_cfg("train", [*data, "gp=svgp"]))
    settings = TrainSettings.from_config(compose_cfg("train", [*data, *phases]))
    shared = train.shared_psi_settings(settings)
    assert shared is not None and train.shared_psi_settings(two_state) is None
    assert shared.fit_identity() == two_state.fit_identity()
    assert shared.fit_directory == two_state.fit_directory
    collect.run(compose_cfg("train", data))
    table, source = train.load_transitions(two_state)
    psi_dir = train.fit(two_state, table, source)

    def refit(*args: object, **kwargs: object) -> None:
        raise AssertionError("the phase fit refitted psi")

    monkeypatch.setattr(train, "fit_psi", refit)
    out = train.fit(settings, table, source)
    assert out != psi_dir and "lumps=phases" in out.name
    mine, theirs = (torch.load(d / "psi.pt", weights_only=True)["psi"] for d in (out, psi_dir))
    assert _tensors(mine) and _tensors(mine) == _tensors(theirs)  # the same classifiers
    metrics = json.loads((out / "fit_metrics.json").read_text())
    assert metrics["psi_fit"] == str(psi_dir) and "phase_chain" in metrics


def _tensors(state: object) -> list[list[float]]:
    """Every tensor of a nested state, flattened to lists, in order."""
    if isinstance(state, torch.Tensor):
        return [state.flatten().tolist()]
    if isinstance(state, dict):
        return [t for k in sorted(state) for t in _tensors(state[k])]
    if isinstance(state, list | tuple):
        return [t for v in state for t in _tensors(v)]
    return []

"""The grid field from yaml: the shipped channel, a run through the simulate stage, and every bad
input refused up front with an error naming the setting."""

from __future__ import annotations

import json

import pytest
import torch

from surrogate.config import build_field, group_config
from surrogate.errors import ConfigError
from surrogate.grid import GridField
from surrogate.simulate import Simulator
from surrogate.stages import simulate
from surrogate.stages.settings import CollectSettings, SimulateSettings, TrainSettings

GOOD = {"diffusion": 8e-4, "initial": 0.1, "uptake": {"vmax": 1.6e5, "km": 0.01}}


def _field(**changes):
    args = {"domain": [[0, 20], [-0.5, 0.5]], "shape": [64, 8], "species": {"serine": GOOD},
            "depth": 0.1, **changes}  # fmt: skip
    return GridField(**args)


def test_the_shipped_channel_is_a_consumed_attractant_channel() -> None:
    field = build_field(group_config("field", "channel_consumed"))
    assert isinstance(field, GridField)
    assert field.grid.shape == (512, 32) and field.grid.boundary == ("no_flux", "no_flux")
    (serine,) = field.species
    assert serine.uptake is not None and serine.diffusion == pytest.approx(8e-4)
    assert field.read == "serine" and field.max_dt() == float("inf")
    value = field(torch.tensor([[2.0, 0.0]]), 0.0)
    assert value.dtype == torch.float32 and float(value) == pytest.approx(0.1)


def test_a_formula_profile_is_evaluated_at_the_cell_centres() -> None:
    field = _field(species={"a": {"diffusion": 1e-3, "initial": "c0 * x / 20",
                                  "parameters": {"c0": 0.2}}})  # fmt: skip
    field.reset()
    centres = field.grid.centres()
    want = 0.2 * centres[..., 0] / 20
    assert torch.allclose(field.concentration("a"), want, rtol=1e-6)  # float32 formulas


BAD = [
    (
        {"species": {"serine": {**GOOD, "diffusion": -1.0}}},
        r"field.species.serine.diffusion "
        r"must be a non-negative number",
    ),
    ({"species": {"serine": {**GOOD, "decay": -0.1}}}, r"field.species.serine.decay"),
    (
        {"species": {"serine": {**GOOD, "uptake": {"vmax": -5.0, "km": 0.01}}}},
        r"field.species.serine.uptake.vmax",
    ),
    (
        {"species": {"serine": {**GOOD, "uptake": {"vmax": 5.0, "km": 0.0}}}},
        r"field.species.serine.uptake.km must be a positive number",
    ),
    (
        {"species": {"s": {"diffusion": 1e-3, "secretion": {"rate_on": -1.0}}}},
        r"field.species.s.secretion.rate_on",
    ),
    (
        {"species": {"serine": {**GOOD, "difusion": 1e-3}}},
        r"unknown field.species.serine setting\(s\) \['difusion'\]",
    ),
    ({"species": {"serine": {"initial": 0.1}}}, r"field.species.serine.diffusion is required"),
    (
        {"species": {"serine": {**GOOD, "uptake": {"vmax": 5.0}}}},
        r"field.species.serine.uptake needs the setting\(s\) \['km'\]",
    ),
    ({"species": {"serine": {**GOOD, "initial": "foo * x"}}}, r"field.species.serine.initial.*foo"),
    ({"species": {}}, r"field.species must declare at least one species"),
    ({"read": "aspartate"}, r"field.read='aspartate' is not a declared species.*serine"),
    ({"boundary": "reflecting"}, r"field.boundary must be one of \['periodic', 'no_flux'\]"),
    ({"shape": [64, 1]}, r"field.shape must be two integers >= 2"),
    ({"domain": [[5, 0], [0, 1]]}, r"field.domain must be .* lo < hi"),
    ({"depth": 0.0}, r"field.depth must be a positive number"),
    ({"depth": "abc"}, r"field.depth must be a positive number \(mm\), got 'abc'"),
    ({"depth": None}, r"field.depth must be a positive number \(mm\), got None"),
    ({"depth": True}, r"field.depth must be a positive number \(mm\), got True"),
    ({"solver": "crank_nicolson"}, r"field.solver must be one of \['spectral', 'explicit'\]"),
]


@pytest.mark.parametrize(("changes", "message"), BAD, ids=[m.split()[0] for _, m in BAD])
def test_a_bad_field_setting_is_refused_by_name(changes, message) -> None:
    with pytest.raises(ConfigError, match=message):
        _field(**changes)


def test_a_negative_initial_formula_is_refused_when_evaluated() -> None:
    field = _field(species={"a": {"diffusion": 1e-3, "initial": "x - 10"}})
    with pytest.raises(ConfigError, match=r"field.species.a.initial.*non-negative"):
        field.reset()


CHANNEL = ["field=channel_consumed", "n_cells=20", "t_end=1.0", "equilibration_time=0.0"]
RUN_BAD = [
    (
        ["shard.count=2"],
        r"shard.count=2: a population in a coupled field \(GridField.* cannot "
        r"be split",
    ),
    (
        ["field.solver=explicit", "dt=0.5", "record_interval=0.5"],
        r"dt=0.5 s is beyond field.solver=explicit's limit 0.37.. s .*h_x=0.03906 mm",
    ),
    (
        ["field.shape=[200000,100000]"],
        r"field.shape=\[200000, 100000\]: the grid field needs "
        r"about .* GiB",
    ),
    (["field.read=aspartate"], r"field.read='aspartate' is not a declared species"),
]


@pytest.mark.parametrize(("overrides", "message"), RUN_BAD, ids=[o[0] for o, _ in RUN_BAD])
def test_a_coupled_run_the_loop_cannot_take_is_refused_before_it_starts(
    compose_cfg, overrides, message
) -> None:
    with pytest.raises(ConfigError, match=message):
        SimulateSettings.from_config(compose_cfg("simulate", [*CHANNEL, *overrides]))


@pytest.mark.parametrize(("loop", "backend", "compiled"),
                         [("compile=true", "torch", True), ("backend=numba", "numba", False)])  # fmt: skip
def test_every_loop_runs_a_coupled_field(compose_cfg, loop, backend, compiled) -> None:
    """compile=true (the compiled step is the agents'; the field is read and stepped eagerly)
    and the per-cell kernel (one step per call) run a coupled field: only shards are refused
    (above). The simulator the stage builds runs the loop asked for, over the coupled field
    (the stage test below runs the kernel; a run here would compile each loop, minutes)."""
    settings = SimulateSettings.from_config(compose_cfg("simulate", [*CHANNEL, loop]))
    decision, _ = simulate.build_decision(settings)
    setup = settings.setup
    simulator = Simulator(setup.model, decision, setup.field, setup.dt, settings.job.device,
                          compile=settings.compile, backend=settings.backend,
                          compile_fallback=False)  # fmt: skip
    assert isinstance(simulator.field, GridField) and simulator.field is setup.field
    assert (simulator.backend, simulator.compiled) == (backend, compiled)


def test_the_channel_runs_through_the_simulate_stage(compose_cfg) -> None:
    cfg = compose_cfg("simulate", [*CHANNEL, "threads=1"])
    out = simulate.run(cfg)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["loop_backend"] == "numba"  # backend=auto: the per-cell kernel
    assert (out / "observables.parquet").exists()


@pytest.mark.parametrize("stage", ["collect", "train"])
def test_collect_and_train_in_a_coupled_field_are_refused_naming_the_way(compose_cfg, stage):
    """The abstraction is collected and trained in a given field and run in the coupled one;
    a coupled training field is refused before any simulation (it ran, then blamed phi's
    occupancy)."""
    settings = {"collect": CollectSettings, "train": TrainSettings}[stage]
    with pytest.raises(ConfigError, match=r"collect runs in a given field; "
                       r"field=channel_consumed \(GridField\) is coupled.*field=gaussian"):  # fmt: skip
        settings.from_config(compose_cfg(stage, ["field=channel_consumed"]))

"""Bad inputs found by trying the package as a new user (issue 27), across every stage: each is
refused before any work with a message that names the setting.

* work that would take hours or years (``dt=1e-11``, absurd budgets) is estimated up front
  (steps x cells x the model's cost per cell-step) and refused above ``max_hours``;
* ``decision=exact`` on a model without an exact psi says so and what to use;
* a yaml model (``model=sbml``) with an unknown species, a missing parameter, a body parameter
  of the wrong type, ... is refused by name.

Each entry failed before the fix (a traceback, a silent hours-long run, or a run that started).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest
import torch

from surrogate.config import CONF_DIR
from surrogate.errors import ConfigError
from surrogate.stages import collect, reproduce, train
from surrogate.stages import evaluate as evaluate_stage
from surrogate.stages import simulate as simulate_stage
from surrogate.stages.settings import CollectSettings

from .conftest import compose_in

VALIDATORS = {
    "collect": collect.validate,
    "train": train.validate,
    "simulate": simulate_stage.validate,
    "evaluate": evaluate_stage.validate,
    "reproduce": reproduce.validate,
}
EXAMPLES = CONF_DIR.parent / "examples"
GENE = ["model=sbml", f"model.spec={EXAMPLES / 'gene_switch' / 'model.yaml'}"]
PHOSPHO_YAML = ["model=sbml", f"model.spec={EXAMPLES / 'ecoli_phospho' / 'model.yaml'}"]
RUN_MISSING = ["evaluate.run_missing=true"]

# (stage, overrides, text the message must contain: the setting's name and what is wrong)
BAD_INPUTS = [
    # time steps and budgets that would run for hours, days or years
    ("simulate", ["dt=1e-11"], "at dt=1e-11 s, n_cells=20"),
    ("collect", ["dt=1e-11"], "collect.equilibration_time=1 s, dt=1e-11 s"),
    ("train", ["dt=1e-11"], "dt=1e-11 s"),
    ("evaluate", ["dt=1e-11", *RUN_MISSING], "above max_hours=24"),
    ("reproduce", ["dt=1e-11"], "above max_hours=24"),
    ("simulate", ["n_cells=1000000", "t_end=100000"], "t_end=100000 s"),
    ("simulate", ["decision=abstract", "t_end=1e8"], "the abstraction's run"),
    (
        "collect",
        ["collect.n_per_state=100000000"],
        "collect.n_per_state=100000000: the transitions",
    ),
    (
        "collect",
        ["collect.n_per_state=10000000", "collect.record_every=10000"],
        "collect.record_every=10000th window",
    ),
    (
        "train",
        ["gp.diagnostic.n_cells=10000000", "gp.diagnostic.t_end=1000"],
        "gp.diagnostic.n_cells=10000000",
    ),
    (
        "evaluate",
        ["evaluate.full_n_cells=1000000", "t_end=100000", *RUN_MISSING],
        "n_cells=1000000",
    ),
    ("reproduce", ["t_end=1e7"], "t_end=1e+07 s"),
    (
        "collect",
        ["model=ecoli_phospho", "collect.n_per_state=30000000"],
        "collect.n_per_state=30000000",
    ),
    (
        "simulate",
        ["model=ecoli_phospho", "max_hours=0.0001"],
        "per cell-step of model 'ecoli_phospho'",
    ),
    ("simulate", ["max_hours=0"], "max_hours must be a positive number of hours, got 0"),
    ("collect", ["max_hours=soon"], "max_hours must be a positive number of hours, got 'soon'"),
    # no exact psi: what to use instead
    (
        "simulate",
        ["model=ecoli_phospho", "decision=exact"],
        "decision=exact: model 'ecoli_phospho' has no exact lumped psi",
    ),
    ("evaluate", ["model=ecoli_phospho", "decision=exact"], "use decision=full"),
    (
        "simulate",
        [*PHOSPHO_YAML, "decision=exact"],
        "model 'ecoli_phospho_yaml' has no exact lumped psi",
    ),
    # model=sbml: the yaml and its overrides
    ("simulate", ["model=sbml"], "model.network is required"),
    (
        "simulate",
        ["model=sbml", "model.spec=/nonexistent.yaml"],
        "model.spec=/nonexistent.yaml: no such file",
    ),
    ("collect", [*GENE, "+model.lump='Q >= 2'"], "model.lump: unknown species 'Q'"),
    ("train", [*GENE, "+model.inputs.inducr=L"], "input 'inducr' is not a global parameter"),
    (
        "collect",
        [*GENE, "+model.inputs.inducer=M"],
        "model.inputs.inducer: unknown body variable 'M'",
    ),
    ("simulate", [*GENE, "+model.inputs.inducer='L +'"], "model.inputs.inducer: cannot parse"),
    (
        "simulate",
        [*GENE, "+model.body.speed_on=fast"],
        "model.body.speed_on must be a finite number, got 'fast'",
    ),
    ("reproduce", [*GENE, "+model.body.kind=flyer"], "model.body.kind must be one of"),
    ("evaluate", [*GENE, "+model.lump_names=[a,a]"], "model.lump_names must be two different"),
    ("simulate", [*GENE, "+model.ssa=gpu"], "model.ssa must be one of"),
    ("train", [*GENE, "+model.network=missing.xml"], "model.network=missing.xml: no such SBML"),
    ("collect", [*GENE, "+model.collect.n_per_state=0"], "model.collect.n_per_state must be"),
    (
        "collect",
        [*GENE, "+model.body.perturbation.radius=-1"],
        "model.body.perturbation.radius must be a finite number > 0",
    ),
    ("collect", [*PHOSPHO_YAML, "dt=20.0"], "must be smaller than model.body.tau=15 s"),
    ("simulate", [*PHOSPHO_YAML, "+model.body.tau=slow"], "model.body.tau must be a finite"),
    ("simulate", [*GENE, "+model.wings=2"], "unknown model setting(s) ['wings']"),
]


@pytest.mark.parametrize(
    ("stage", "overrides", "message"),
    BAD_INPUTS,
    ids=[f"{s}:{' '.join(o)}" for s, o, _ in BAD_INPUTS],
)
def test_bad_input_is_refused_by_name(
    tmp_path: Path, stage: str, overrides: list[str], message: str
) -> None:
    cfg = compose_in(tmp_path / "data", stage, overrides)
    with pytest.raises(ConfigError) as info:
        VALIDATORS[stage](cfg)
    assert message in str(info.value)
    assert not (tmp_path / "data").exists()  # validation writes nothing


def test_the_table_covers_every_stage() -> None:
    assert len(BAD_INPUTS) >= 30
    assert {stage for stage, _, _ in BAD_INPUTS} == set(VALIDATORS)


def test_the_phospho_model_carries_a_budget_for_its_cost(tmp_path, caplog) -> None:
    """``reproduce.py model=ecoli_phospho`` collects the model's own budget (10,000 per origin
    from 500 cells), not the first model's 100,000, and says up front what it will cost."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="reproduce",
                      overrides=[f"data_dir={tmp_path / 'data'}", "model=ecoli_phospho"])  # fmt: skip
    with caplog.at_level(logging.INFO, logger="surrogate.stages.budget"):
        settings = reproduce.validate(cfg)
    options = settings.train.source.options
    assert (options["n_per_state"], options["n_cells"], options["record_every"]) == (10000, 500, 5)
    warning = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert warning and "reproduce: estimated ~" in warning[0].message
    assert "gp.diagnostic.n_cells=1000" in warning[0].message  # names what makes it long
    assert not (tmp_path / "data").exists()


def test_a_default_budget_is_the_same_artefact_as_the_same_budget_given(tmp_path) -> None:
    """The E. coli default (null -> the model's 100,000 / 2,000 / 10) and those numbers given
    explicitly make one artefact; the command does not repeat the defaults."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        default = compose(config_name="collect", overrides=[f"data_dir={tmp_path}"])
        given = compose(config_name="collect", overrides=[
            f"data_dir={tmp_path}", "collect.n_per_state=100000", "collect.n_cells=2000",
            "collect.record_every=10"])  # fmt: skip
    a, b = CollectSettings.from_config(default), CollectSettings.from_config(given)
    assert a.directory == b.directory
    assert "n_per_state" not in a.command() and "collect.n_per_state=100000" in b.command()


def test_the_cost_estimate_is_steps_x_cells_x_the_models_cell_step(tmp_path) -> None:
    """The estimate's formula, pinned with numbers computed here (its accuracy is measured,
    not guaranteed: docs/performance.md): a collection's steps are the equilibration's plus
    2 n_per_state record_every / n_cells over the share of windows outside the blackout after
    a jump, exp(-perturb_rate blackout_time) (0.1 per s and 1 s here, both models' default),
    each costing the loop's measured fixed cost per step
    (surrogate.diagnosis.cost.step_seconds, > 0) plus n_cells cell-steps;
    the gene switch's cell-step is the SSA overhead plus its expected events per window at the
    file's counts and inputs (8 inactive proteins, inducer 0.05: only activation fires, at
    k_act inducer I = 50 x 0.05 x 8 = 20 per s) times the compiled SSA's cost of an event;
    E. coli gives no estimate of its own (the base CELL_STEP_SECONDS)."""
    from surrogate.models.base import CELL_STEP_SECONDS
    from surrogate.models.network import COMPILED_EVENT_SECONDS, STEP_OVERHEAD_SECONDS
    from surrogate.stages.budget import collect_work

    # the per-cell part around the events, as measured (collect's loop on the gene switch:
    # 0.47 us per cell-step, surrogate/models/network.py), not the 3 us read before from a
    # whole collection's wall time with the fixed part per step in it
    assert 2e-7 <= STEP_OVERHEAD_SECONDS <= 1e-6

    sizes = ["collect.n_per_state=1000", "collect.n_cells=50", "collect.record_every=2",
             "collect.equilibration_time=1.0", "dt=0.05"]  # fmt: skip
    steps = 1.0 / 0.05 + 2 * 1000 * 2 / (50 * math.exp(-0.1 * 1.0))
    for model, cell_step in (
        (GENE, STEP_OVERHEAD_SECONDS + 20.0 * 0.05 * COMPILED_EVENT_SECONDS),
        (["model=ecoli"], CELL_STEP_SECONDS),
    ):
        [work] = collect_work(CollectSettings.from_config(
            compose_in(tmp_path / "data", "collect", [*model, *sizes])))  # fmt: skip
        assert work.cell_step_seconds == pytest.approx(cell_step, rel=1e-12), model
        assert work.steps == pytest.approx(steps, rel=1e-12)
        assert work.step_seconds > 0
        assert work.seconds == pytest.approx(steps * (work.step_seconds + 50 * cell_step),
                                             rel=1e-12)  # fmt: skip


def test_a_network_on_the_cuda_ssa_is_priced_at_the_gpus_event_cost(tmp_path, monkeypatch) -> None:
    """On ``device=cuda`` a network whose windows run on the CUDA SSA is priced at that SSA's
    measured cost of an event (an H200: 2.7e9 events/s), not the CPU's: priced as the
    compiled SSA, the phospho network's 10,000 cells x 11 s were estimated at 34 min and
    warned about where they ran in 22 s. Where no CUDA SSA runs, CUDA gets the torch SSA's."""
    from surrogate.models import network
    from surrogate.models.network import (
        BATCHED_EVENT_SECONDS,
        COMPILED_EVENT_SECONDS,
        CUDA_EVENT_SECONDS,
        STEP_OVERHEAD_SECONDS,
    )

    model = CollectSettings.from_config(
        compose_in(tmp_path / "data", "collect", [*GENE, "dt=0.05"])).setup.model  # fmt: skip
    events = 20.0 * 0.05  # the gene switch's events per window at its file's counts (above)
    on_cpu = model.cell_step_seconds(0.05)
    assert on_cpu == pytest.approx(STEP_OVERHEAD_SECONDS + events * COMPILED_EVENT_SECONDS)
    monkeypatch.setattr(network, "_cuda_ssa_available", lambda: True)
    assert model.internal.backend(torch.device("cuda")) == "cuda"
    assert model.cell_step_seconds(0.05, device="cuda") == pytest.approx(
        STEP_OVERHEAD_SECONDS + events * CUDA_EVENT_SECONDS)  # fmt: skip
    assert CUDA_EVENT_SECONDS < COMPILED_EVENT_SECONDS / 100
    monkeypatch.setattr(network, "_cuda_ssa_available", lambda: False)
    assert model.cell_step_seconds(0.05, device="cuda") == pytest.approx(
        STEP_OVERHEAD_SECONDS + events * BATCHED_EVENT_SECONDS)  # fmt: skip
    # a chain's cell-step is the same on any device (the base figure)
    assert model.cell_step_seconds(0.05, full=False, device="cuda") == model.cell_step_seconds(
        0.05, full=False)  # fmt: skip

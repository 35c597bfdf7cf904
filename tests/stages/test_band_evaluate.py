"""evaluate on experiment=band (issue 39, item 4): the full runs on fewer cells get a channel
scaled to the same cells per cross-section, missing runs are named up front with the commands
that make them, and a tiny evaluation writes the band's comparison (table, report, figure, the
summary's verdict) beside the usual one."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from surrogate.errors import MissingArtefactError
from surrogate.stages import evaluate as evaluate_stage
from surrogate.stages.artefacts import BAND_FIDELITY
from surrogate.stages.settings import EvaluateSettings

#: experiment=band's cells per cross-section (5,000 cells in 0.008 mm) at 240 cells, the full
#: model on half of them: a few seconds of band, the exact chain (no training) as the candidate
N, FULL_N = 240, 120
DEPTH = 0.008 * N / 5000
TINY = ["experiment=band", "decision=exact", f"n_cells={N}", f"field.depth={DEPTH}",
        "t_end=10.0", "record_interval=2.5", "equilibration_time=1.0",
        f"evaluate.full_n_cells={FULL_N}", "evaluate.times=[5,10]",
        "evaluate.subsample=100"]  # fmt: skip


def test_the_full_runs_keep_the_candidates_cells_per_cross_section(compose_cfg) -> None:
    settings = EvaluateSettings.from_config(compose_cfg("evaluate", TINY))
    assert settings.candidate.setup.field.grid.depth == pytest.approx(DEPTH)
    for full in (settings.full, settings.full_repeat):
        assert full is not None and full.n_cells == FULL_N
        assert full.setup.field_config["depth"] == pytest.approx(DEPTH * FULL_N / N, rel=1e-12)
    assert settings.full_repeat is not None and settings.full_repeat.setup.seed == 1000
    # candidates of another training seed against the same full runs
    other = EvaluateSettings.from_config(compose_cfg("evaluate", [*TINY, "seed=1",
                                                                  "evaluate.full_seed=0"]))  # fmt: skip
    assert other.candidate.setup.seed == 1
    assert other.full.directory == settings.full.directory
    assert other.full_repeat is not None
    assert other.full_repeat.directory == settings.full_repeat.directory


def test_evaluate_compares_the_band_with_the_floor(compose_cfg) -> None:
    cfg = compose_cfg("evaluate", TINY)
    with pytest.raises(
        MissingArtefactError, match=r"simulation\(s\) of this evaluation \(3 of 3\)"
    ) as missing:
        evaluate_stage.run(cfg)
    full_depth = f"field.depth={DEPTH * FULL_N / N:g}"
    assert str(missing.value).count(full_depth) == 2 and f"n_cells={FULL_N}" in str(missing.value)
    out = evaluate_stage.run(compose_cfg("evaluate", [*TINY, "evaluate.run_missing=true"]))
    table = pd.read_csv(out / f"{BAND_FIDELITY}.csv")
    assert table["run"].unique().tolist() == ["full_repeat", "exact"]
    assert table.groupby("run").size().tolist() == [5, 5]  # records 0, 2.5, ..., 10 s
    assert table["ks"].between(0, 1).all() and (table["n_reference"] == FULL_N).all()
    assert set(table.loc[table["run"] == "exact", "n_other"]) == {N}
    summary = json.loads((out / "summary.json").read_text())["band_fidelity"]
    assert summary["floor"] == "full_repeat" and isinstance(summary["passed"], bool)
    checks = summary["checks"]["exact"]
    assert [c["check"] for c in checks] == ["max_ks", "front_rms", "speed_diff"]
    ks = checks[0]
    assert ks["threshold"] == pytest.approx(max(1.5 * ks["floor"], ks["critical"]))
    report = (out / f"{BAND_FIDELITY}.md").read_text()
    assert "## The rule" in report and f"]({BAND_FIDELITY}.png)" in report
    assert (out / f"{BAND_FIDELITY}.png").read_bytes()[:4] == b"\x89PNG"


def test_reproduce_refuses_the_band_naming_the_evaluation_that_makes_it(compose_cfg) -> None:
    """reproduce's `fields` (L1-L3) once won silently over experiment=band's field: 700 s of
    given fields and a report with no band. A coupled field, given or listed, is refused before
    any work, naming the evaluate command of these settings that makes the band's report."""
    from surrogate.errors import ConfigError
    from surrogate.stages import reproduce

    with pytest.raises(ConfigError, match="field=channel_band is coupled") as given:
        reproduce.validate(compose_cfg("reproduce", ["experiment=band"]))
    command = str(given.value)
    assert "python scripts/evaluate.py decision=abstract" in command
    assert "field=channel_band" in command and "n_cells=5000" in command
    assert "evaluate.run_missing=true" in command and "experiment=band" in command
    with pytest.raises(ConfigError, match="fields: channel_band is coupled"):
        reproduce.validate(compose_cfg("reproduce", ["fields=[gaussian,channel_band]"]))


class _FirstSimulation(Exception):
    """Raised in place of the evaluation's first simulation."""


def test_run_missing_trains_the_abstraction_before_the_first_simulation(
    compose_cfg, monkeypatch
) -> None:
    """`evaluate.py experiment=band decision=abstract evaluate.run_missing=true` in a fresh
    data directory once simulated the full band for minutes, then stopped for want of a
    trained abstraction: run_missing collects and trains it first, as its estimate counts."""
    tiny_fit = ["gp=svgp", "collect.n_per_state=400", "collect.n_cells=100",
                "gp.n_inducing=16", "gp.epochs=8", "gp.batch_size=200", "gp.grid_size=[12]",
                "gp.diagnostic.n_cells=100", "gp.diagnostic.t_end=10.0"]  # fmt: skip
    band = [o.replace("decision=exact", "decision=abstract") for o in TINY]
    cfg = compose_cfg("evaluate", [*band, *tiny_fit, "evaluate.run_missing=true"])
    settings = evaluate_stage.validate(cfg)
    fit = settings.candidate.decision.train
    assert fit is not None and not (fit.fit_directory / "manifest.json").exists()

    def first_simulation(run) -> None:
        assert (fit.fit_directory / "manifest.json").exists(), "simulated before training"
        raise _FirstSimulation(run.directory)

    monkeypatch.setattr(evaluate_stage, "simulate", first_simulation)
    with pytest.raises(_FirstSimulation):
        evaluate_stage.evaluate(settings)

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

"""The coupled-field benchmark runs end to end and splits each step into the agents' part and
the field's (a smoke run: no timing asserts)."""

from __future__ import annotations

import json

import pytest

from surrogate.benchmarks.field import run_field_bench
from surrogate.errors import ConfigError


def test_the_field_bench_splits_the_step(compose_cfg, tmp_path) -> None:
    out = tmp_path / "field.json"
    cfg = compose_cfg("bench_field", [f"output={out}", "n_cells=300", "steps=2", "warm_up=1",
                                      "field.shape=[32,4]", "threads=1"])  # fmt: skip
    lines: list[str] = []
    r = run_field_bench(cfg, log=lines.append)
    assert json.loads(out.read_text())["n_cells"] == 300
    assert r["grid"] == [32, 4] and r["species"] == ["serine"]
    assert r["field_ms_per_step"] > 0 and r["agents_ms_per_step"] > 0
    assert 0 < r["field_share"] < 1
    assert r["field_over_agents"] == pytest.approx(
        r["field_ms_per_step"] / r["agents_ms_per_step"], rel=1e-9
    )
    assert "of the agents' cost" in lines[0]
    assert r["field_fuse"] == "auto" and r["field_step_path"] == "eager"  # the CPU's numba


def test_the_field_bench_takes_the_fields_fuse_setting(compose_cfg, tmp_path) -> None:
    """``++field.fuse=eager`` (the GPU's eager step, the reference of .devcheck timings)."""
    cfg = compose_cfg("bench_field", [f"output={tmp_path / 'f.json'}", "n_cells=100", "steps=1",
                                      "warm_up=0", "field.shape=[16,4]", "threads=1",
                                      "++field.fuse=eager"])  # fmt: skip
    r = run_field_bench(cfg, log=lambda line: None)
    assert r["field_fuse"] == "eager" and r["field_step_path"] == "eager"


def test_the_field_bench_needs_a_grid_field(compose_cfg, tmp_path) -> None:
    cfg = compose_cfg("bench_field", [f"output={tmp_path / 'f.json'}", "field=gaussian",
                                      "scale_depth=false", "n_cells=10", "steps=1"])  # fmt: skip
    with pytest.raises(ConfigError, match="needs a grid field"):
        run_field_bench(cfg)

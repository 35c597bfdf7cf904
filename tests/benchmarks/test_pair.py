"""The pair benchmark (surrogate/benchmarks/pair.py) runs and reports each set-up."""

from __future__ import annotations

import json
from pathlib import Path

from surrogate.benchmarks.pair import pair_data, run_bench


def test_the_pair_bench_times_both_ways_and_writes_them(tmp_path: Path) -> None:
    out = tmp_path / "pair.json"
    runs = run_bench(epochs=2, rows=500, busy=(0,), output=out)
    assert [(r["busy"], r["processes"]) for r in runs] == [(0, 1), (0, 2)]
    assert all(r["wall_s"] > 0 for r in runs)
    assert json.loads(out.read_text())["runs"] == runs
    a, b = pair_data(100)
    assert a[0].shape == (100, 2) and set(a[1].unique().tolist()) <= {0.0, 1.0}
    assert not bool((a[1] == b[1]).all())  # two surfaces

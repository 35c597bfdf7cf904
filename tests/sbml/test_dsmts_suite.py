"""The public SBML discrete stochastic test suite (DSMTS), a vendored subset (tests/data/dsmts,
LGPL, see its README): files read as the suite and common tools write them, simulated by the
compiled SSA and checked with the suite's own statistics and ranges (Z of the means within
(-3, 3), Y of the variances within (-5, 5), at every one of its 51 times and every output).

N_RUNS = 2,000 runs per case (the DSMTS guide: at least 1,000 for unit tests, 10,000 to see
small errors; scripts/dsmts.py runs the whole suite with 10,000). A case that fails once is
run again with the next seed, as the guide advises (a correct simulator fails a few of its
checks by chance); a real error fails both. Refused cases must name the construct. The cases
with a species assignment rule or events run on both SSAs (compiled and batched torch).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from surrogate.sbml import read_sbml, read_sbml_string
from surrogate.sbml.dsmts import DsmtsCase, run_case_twice, simulate_outputs, statistics

DATA = Path(__file__).resolve().parents[1] / "data" / "dsmts"
SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
N_RUNS = 2000
SEED = 1


@pytest.mark.parametrize("case", ["00001", "00011", "00024", "00030", "00037"])
def test_the_case_passes_the_suites_checks(case: str) -> None:
    result = run_case_twice(DsmtsCase.load(DATA / case), N_RUNS, SEED, parallel=False)
    assert result.status == "passed", (result.reason, result.retried)
    outputs = len(DsmtsCase.load(DATA / case).variables)
    assert result.checks >= 50  # every time but t = 0 of at least one output
    assert result.checks <= 50 * outputs


@pytest.mark.parametrize("ssa", ["compiled", "batched"])
@pytest.mark.parametrize("case", ["00019", "00028", "00029", "00033"])
def test_rules_and_events_pass_the_suites_checks(case: str, ssa: str) -> None:
    """A species assignment rule (00019), time events at a window's end (00028, where every run
    must equal the reset value) and inside a window (00029), a state event (00033)."""
    result = run_case_twice(DsmtsCase.load(DATA / case), N_RUNS, SEED, parallel=False, ssa=ssa)
    assert result.status == "passed", (result.reason, result.retried)
    assert result.checks >= 49


@pytest.mark.parametrize(
    ("case", "constructs"),
    [("00040", ["rate rule for 't'", "package 'distrib'"])],
)
def test_an_unsupported_case_is_refused_naming_every_construct(case, constructs) -> None:
    result = run_case_twice(DsmtsCase.load(DATA / case), N_RUNS, SEED)
    assert result.status == "refused"
    for construct in constructs:
        assert construct in result.reason


def test_a_compartment_without_a_size_is_read_where_nothing_needs_it() -> None:
    """DSMTS 001-01: the compartment has no size (legal in Level 3) and X is an amount; it is
    read (its size recorded as NaN), and needed nowhere."""
    model = read_sbml(DATA / "00001" / "00001-sbml-l3v1.xml")
    assert model.species == ("X",) and model.initial_state.tolist() == [100]
    assert model.constants["Cell"] != model.constants["Cell"]  # NaN


def test_a_wrong_simulator_fails_the_suites_checks() -> None:
    """The checks can fail: 00001 read with the birth rate halved (an error a reader could
    make, e.g. a stray concentration) misses the suite's means by far."""
    case = DsmtsCase.load(DATA / "00001")
    model = read_sbml_string(case.model_path.read_text().replace('value="0.1"', 'value="0.05"'))
    values = simulate_outputs(model, [0], case.times, N_RUNS, SEED, parallel=False)
    z, _, _, _ = statistics(values, case.mean.to_numpy(float), case.sd.to_numpy(float))
    assert np.nanmax(np.abs(z)) > 3


def test_the_script_replaces_only_the_rows_of_the_cases_it_ran() -> None:
    """``scripts/dsmts.py --cases``: the rows run replace theirs, the others stay, and the
    summary is recounted over every row."""
    spec = importlib.util.spec_from_file_location("dsmts_script", SCRIPTS / "dsmts.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    header = "| case | synopsis | result |\n|---|---|---|"
    old = (
        f"{script.BEGIN}\n`python3 scripts/dsmts.py --seed 1` (2026-01-02): 2 cases\n\n{header}\n"
        "| 00001 | a | passed | seed 1: 1 Z; seed 2: all within range |\n"
        f"| 00002 | b | refused | event |\n{script.END}\n"
    )
    new = f"`python3 scripts/dsmts.py --seed 1` (today)\n\n{header}\n| 00002 | b | passed |"
    merged = script.merge_rows(old, new, ["00002"])
    lines = merged.splitlines()
    assert lines[0].startswith("`python3 scripts/dsmts.py --seed 1` (2026-01-02; 1 case(s)")
    assert (
        "**2 passed**, 0 failed, 0 refused" in lines[0]
        and "1 case(s) run again with the next" in lines[0]
    )
    assert lines[4:] == ["| 00001 | a | passed | seed 1: 1 Z; seed 2: all within range |",
                         "| 00002 | b | passed |"]  # fmt: skip

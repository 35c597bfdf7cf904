"""scripts/dsmts.py: its arguments are checked before any case runs (each refusal names the
argument and what it must be), and the table it writes is headed by the command that ran."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "dsmts"


def _script():
    spec = importlib.util.spec_from_file_location("dsmts_script", REPO / "scripts" / "dsmts.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ([], "the following arguments are required: --suite"),
        (["--suite", "/nonexistent/cases"], "--suite /nonexistent/cases: no such directory"),
        (["--suite", str(DATA.parent)], "no case folders (NNNNN) in it"),
        (["--suite", str(DATA), "--runs", "1"], "--runs 1: the suite's checks need at least 1,000"),
        (["--suite", str(DATA), "--runs", "0"], "--runs 0: the suite's checks need at least 1,000"),
        (["--suite", str(DATA), "--cases", "99999"], "--cases: no case(s) ['99999'] in"),
        (["--suite", str(DATA), "--cases"], "--cases needs one or more case ids"),
    ],
)
def test_a_bad_argument_is_a_usage_error_before_any_case_runs(args, message, capsys, tmp_path):
    doc = tmp_path / "doc.md"
    with pytest.raises(SystemExit) as info:
        _script().main([*args, "--doc", str(doc)])
    assert info.value.code == 2
    assert message in capsys.readouterr().err
    assert not doc.exists()  # nothing written


def test_a_subsets_table_names_the_subset_it_ran(tmp_path, capsys) -> None:
    doc = tmp_path / "doc.md"
    _script().main(["--suite", str(DATA), "--runs", "1000", "--cases", "00001", "--doc", str(doc)])
    text = doc.read_text()
    command = ("`python3 scripts/dsmts.py --suite <sbml-test-suite>/cases/stochastic --runs 1000 "
               "--seed 1 --cases 00001`")  # fmt: skip
    assert command in text and "1 cases" in text and "| 00001 |" in text

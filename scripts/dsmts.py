"""Run the SBML discrete stochastic test suite (DSMTS) and write its table into docs/sbml.md.

python scripts/dsmts.py --suite <sbml-test-suite>/cases/stochastic [--runs 10000] [--seed 1]
                        [--cases 00001 00002 ...] [--doc docs/sbml.md]

The suite: git clone https://github.com/sbmlteam/sbml-test-suite (LGPL 2.1+). Every case is
read, simulated ``--runs`` times by the compiled SSA and checked with the suite's Z and Y at
its time points (surrogate/sbml/dsmts.py); a failing case is run again with the next seed.
``--runs`` must be at least 1,000, the suite's minimum: its checks read Z and Y against normal
ranges, which fewer runs do not justify (a "passed" would mean nothing). The table's header
names the command that made it (with ``--cases`` when a subset ran).
"""

from __future__ import annotations

import argparse
import re
import time
from collections.abc import Sequence
from pathlib import Path

from surrogate.sbml.dsmts import DsmtsCase, DsmtsResult, run_case_twice

BEGIN, END = "<!-- dsmts-table: begin -->", "<!-- dsmts-table: end -->"
#: the suite's minimum number of runs per case (DSMTS user guide 3.1)
MIN_RUNS = 1000


def _row(case: DsmtsCase, r: DsmtsResult) -> str:
    if r.status == "refused":
        return f"| {case.id} | {case.synopsis} | refused | | | | | {r.reason} |"
    note = r.reason
    if r.retried is not None:
        first = r.retried
        note = (f"seed {first.seed}: {first.reason}; seed {r.seed}: "
                f"{r.reason or 'all within range'}")  # fmt: skip
    return (f"| {case.id} | {case.synopsis} | {r.status} | {r.checks} | "
            f"{r.z_outside} / {r.y_outside} | {r.max_abs_z:.2f} / {r.max_abs_y:.2f} | "
            f"{r.seconds:.1f} | {note} |")  # fmt: skip


def command(runs: int, seed: int, cases: Sequence[str] | None = None) -> str:
    """The command line that runs ``cases`` (None: every case) as the table reports them."""
    subset = f" --cases {' '.join(cases)}" if cases else ""
    return (f"python3 scripts/dsmts.py --suite <sbml-test-suite>/cases/stochastic --runs {runs} "
            f"--seed {seed}{subset}")  # fmt: skip


def table(
    cases: list[DsmtsCase],
    results: list[DsmtsResult],
    runs: int,
    seed: int,
    subset: Sequence[str] | None = None,
) -> str:
    """The markdown table and its summary, headed by the command that ran (``subset``: the
    ``--cases`` given, None for the whole suite)."""
    counts = {s: sum(r.status == s for r in results) for s in ("passed", "failed", "refused")}
    retried = sum(r.retried is not None for r in results)
    lines = [
        f"`{command(runs, seed, subset)}` ({time.strftime('%Y-%m-%d')}): {len(results)} cases, "
        f"**{counts['passed']} passed**, {counts['failed']} failed, {counts['refused']} "
        f"refused (the reader names the construct); {runs} runs per case, seed {seed} "
        f"({retried} case(s) run again with the next seed after a first failure).",
        "",
        "| case | synopsis | result | checks | Z / Y outside | max abs Z / Y | s | note |",
        "|---|---|---|---:|---:|---:|---:|---|",
    ]
    lines += [_row(c, r) for c, r in zip(cases, results, strict=True)]
    return "\n".join(lines)


def write_table(doc: Path, text: str) -> None:
    """Replace the table between the markers in ``doc`` (appended when missing)."""
    content = doc.read_text() if doc.exists() else ""
    block = f"{BEGIN}\n{text}\n{END}"
    if BEGIN in content:
        content = re.sub(re.escape(BEGIN) + r".*?" + re.escape(END), lambda _: block, content,
                         flags=re.S)  # fmt: skip
    else:
        content = content.rstrip("\n") + "\n\n" + block + "\n"
    doc.write_text(content)


def parse(argv: Sequence[str] | None = None) -> tuple[argparse.Namespace, list[Path]]:
    """The arguments and the case folders to run, every one checked: a usage error (exit 2)
    names the argument and what it must be, before any case runs."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--suite", type=Path, required=True, help="cases/stochastic of the suite")
    parser.add_argument("--runs", type=int, default=10_000,
                        help=f"runs per case (>= {MIN_RUNS:,}, the suite's minimum)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cases", nargs="*", help="case ids (default: every folder)")
    parser.add_argument("--doc", type=Path, default=Path("docs/sbml.md"))
    args = parser.parse_args(argv)
    if args.runs < MIN_RUNS:
        parser.error(f"--runs {args.runs}: the suite's checks need at least {MIN_RUNS:,} runs "
                     f"per case (DSMTS user guide 3.1: Z and Y are read against normal ranges; "
                     f"10,000 to see small errors)")  # fmt: skip
    if not args.suite.is_dir():
        parser.error(f"--suite {args.suite}: no such directory (the cases/stochastic folder of "
                     f"a checkout of https://github.com/sbmlteam/sbml-test-suite)")  # fmt: skip
    folders = sorted(
        p for p in args.suite.iterdir() if p.is_dir() and re.fullmatch(r"\d{5}", p.name)
    )
    if not folders:
        parser.error(f"--suite {args.suite}: no case folders (NNNNN) in it; give the suite's "
                     f"cases/stochastic folder")  # fmt: skip
    if args.cases is not None:
        if not args.cases:
            parser.error("--cases needs one or more case ids (leave it out for every case)")
        unknown = [c for c in args.cases if c not in {f.name for f in folders}]
        if unknown:
            parser.error(f"--cases: no case(s) {unknown} in {args.suite} (it has "
                         f"{folders[0].name}..{folders[-1].name}, {len(folders)} cases)")  # fmt: skip
        folders = [f for f in folders if f.name in args.cases]
    return args, folders


def main(argv: Sequence[str] | None = None) -> None:
    """Parse arguments, run every case, print and write the table."""
    args, folders = parse(argv)
    cases, results = [], []
    for folder in folders:
        case = DsmtsCase.load(folder)
        result = run_case_twice(case, args.runs, args.seed)
        cases.append(case)
        results.append(result)
        print(_row(case, result), flush=True)
    subset = [f.name for f in folders] if args.cases else None
    text = table(cases, results, args.runs, args.seed, subset)
    write_table(args.doc, text)
    print(text)


if __name__ == "__main__":
    main()
